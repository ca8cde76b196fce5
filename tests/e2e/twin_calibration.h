// Shared by the recovery test (tests/unit) and the coverage test (tests/e2e): the twin's data
// through Calibrate(), and the comparison of every estimate with the twin's truth.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <string>
#include <vector>

#include "ftcal/calibrate.h"
#include "ftcal/config.h"
#include "sim/twin.h"

namespace ftcal {
namespace testing_twin {

constexpr double kDegree = M_PI / 180.0;

inline config::Config SimConfig() { return LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt"); }

inline std::vector<HangingRecording> HangingOf(const BigAntTwin& twin) {
  std::vector<HangingRecording> out;
  for (int s = 0; s < kNumHangSeries; ++s)
    out.push_back(twin.MakeHangingRecording(static_cast<HangSeries>(s)));
  return out;
}

// The rotation error as the left perturbation the covariance describes:
// R_true = Exp(e) R_est, e in degrees.
inline Vec3 RotationErrorDeg(const Mat3& R_est, const Mat3& R_true) {
  return LogSO3(R_true * R_est.transpose()) / kDegree;
}

}  // namespace testing_twin
}  // namespace ftcal
