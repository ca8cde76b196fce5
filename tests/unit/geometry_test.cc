#include "ftcal/geometry.h"

#include <gtest/gtest.h>

namespace ftcal {
namespace {

TEST(Geometry, SkewIsCrossProduct) {
  const Vec3 v(1, -2, 3), u(0.5, 4, -1);
  EXPECT_NEAR((Skew(v) * u - v.cross(u)).norm(), 0.0, 1e-15);
}

}  // namespace
}  // namespace ftcal
