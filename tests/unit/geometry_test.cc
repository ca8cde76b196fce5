// Property tests of the geometry core over many random cases (fixed seed), the hard cases
// (angles near 0 and near pi), and a few hand-computed values.
#include "ftcal/geometry.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <stdexcept>

namespace ftcal {
namespace {

constexpr int kTrials = 2000;

class Random {
 public:
  explicit Random(unsigned seed) : rng_(seed) {}
  double Uniform(double lo, double hi) {
    return std::uniform_real_distribution<double>(lo, hi)(rng_);
  }
  Vec3 UnitVector() {
    std::normal_distribution<double> n;
    Vec3 v;
    do v = Vec3(n(rng_), n(rng_), n(rng_));
    while (v.norm() < 1e-3);
    return v.normalized();
  }
  // A rotation about a random axis by an angle in [lo, hi] rad, built with Eigen (independent
  // of the code under test).
  Mat3 Rotation(double lo = 0.0, double hi = M_PI) {
    return Eigen::AngleAxisd(Uniform(lo, hi), UnitVector()).toRotationMatrix();
  }
  Pose3 PoseSample() {
    return Pose3(Rotation(), Vec3(Uniform(-2, 2), Uniform(-2, 2), Uniform(-2, 2)));
  }
  Vec6 Vector6() {
    Vec6 v;
    for (int i = 0; i < 6; ++i) v[i] = Uniform(-10, 10);
    return v;
  }

 private:
  std::mt19937 rng_;
};

double MaxAbs(const Eigen::MatrixXd& m) { return m.cwiseAbs().maxCoeff(); }

TEST(Geometry, SkewIsCrossProduct) {
  const Vec3 v(1, -2, 3), u(0.5, 4, -1);
  EXPECT_NEAR((Skew(v) * u - v.cross(u)).norm(), 0.0, 1e-15);
  EXPECT_EQ(Unskew(Skew(v)), v);
}

TEST(Geometry, WrenchTransformIsAHomomorphism) {
  Random r(1);
  for (int i = 0; i < kTrials; ++i) {
    const Pose3 X_AB = r.PoseSample(), X_BC = r.PoseSample();
    EXPECT_LT(MaxAbs(WrenchTransform(X_AB * X_BC) - WrenchTransform(X_AB) * WrenchTransform(X_BC)),
              1e-12);
  }
}

TEST(Geometry, WrenchTransformOfInverseIsInverse) {
  Random r(2);
  for (int i = 0; i < kTrials; ++i) {
    const Pose3 X = r.PoseSample();
    EXPECT_LT(MaxAbs(WrenchTransform(X.Inverse()) * WrenchTransform(X) - Mat6::Identity()), 1e-12);
    EXPECT_LT(MaxAbs(WrenchTransform(X.Inverse()) - WrenchTransform(X).inverse()), 1e-12);
  }
}

TEST(Geometry, TransformWrenchMatchesMatrix) {
  Random r(3);
  for (int i = 0; i < kTrials; ++i) {
    const Pose3 X = r.PoseSample();
    const Vec6 w = r.Vector6();
    EXPECT_LT(MaxAbs(TransformWrench(X, w) - WrenchTransform(X) * w), 1e-12);
  }
}

// Power w^T t is frame-independent: X(T)^T Ad(T) = I.
TEST(Geometry, PowerIsInvariant) {
  Random r(4);
  for (int i = 0; i < kTrials; ++i) {
    const Pose3 X_AB = r.PoseSample();
    const Vec6 w_B = r.Vector6(), t_B = r.Vector6();
    const double power_B = w_B.dot(t_B);
    const double power_A = (WrenchTransform(X_AB) * w_B).dot(TwistTransform(X_AB) * t_B);
    EXPECT_NEAR(power_A, power_B, 1e-10 * (1.0 + std::abs(power_B)));
    // Ad is a homomorphism too (the velocity of a point composes like the pose).
    const Pose3 X_BC = r.PoseSample();
    EXPECT_LT(MaxAbs(TwistTransform(X_AB * X_BC) - TwistTransform(X_AB) * TwistTransform(X_BC)),
              1e-12);
  }
}

// Hand-computed: frame B turned 90 deg about z and offset 1 m along A's x. A force of 1 N
// along B's x is along A's y, applied at (1, 0, 0): its torque about A's origin is
// (1, 0, 0) x (0, 1, 0) = (0, 0, 1). A pure torque only rotates.
TEST(Geometry, HandComputedWrenchTransform) {
  const Pose3 X_AB(Eigen::AngleAxisd(M_PI / 2, Vec3::UnitZ()).toRotationMatrix(), Vec3(1, 0, 0));
  Vec6 w_B, expected;
  w_B << 1, 0, 0, 0, 0, 0;
  expected << 0, 1, 0, 0, 0, 1;
  EXPECT_LT(MaxAbs(TransformWrench(X_AB, w_B) - expected), 1e-15);
  w_B << 0, 0, 0, 2, 0, 0;
  expected << 0, 0, 0, 0, 2, 0;
  EXPECT_LT(MaxAbs(TransformWrench(X_AB, w_B) - expected), 1e-15);
  // A vertical force under a lever: 10 N down at 0.2 m along x gives -2 N*m about y.
  const Pose3 lever(Mat3::Identity(), Vec3(0.2, 0, 0));
  w_B << 0, 0, -10, 0, 0, 0;
  expected << 0, 0, -10, 0, 2, 0;
  EXPECT_LT(MaxAbs(TransformWrench(lever, w_B) - expected), 1e-15);
}

TEST(Geometry, PoseGroupLaws) {
  Random r(5);
  for (int i = 0; i < kTrials; ++i) {
    const Pose3 a = r.PoseSample(), b = r.PoseSample(), c = r.PoseSample();
    const Vec3 x(r.Uniform(-1, 1), r.Uniform(-1, 1), r.Uniform(-1, 1));
    EXPECT_LT(MaxAbs(((a * b) * c).Matrix() - (a * (b * c)).Matrix()), 1e-12);
    EXPECT_LT(MaxAbs((a * a.Inverse()).Matrix() - Eigen::Matrix4d::Identity()), 1e-12);
    EXPECT_LT(((a * b) * x - a * (b * x)).norm(), 1e-12);
    EXPECT_LT(MaxAbs((a * b).Matrix() - a.Matrix() * b.Matrix()), 1e-12);
  }
}

// R = (I - [q])(I + [q])^-1 turns by -2 atan|q| about q (to first order R = I - 2[q]).
TEST(Geometry, CayleyMatchesAngleAxis) {
  Random r(6);
  for (int i = 0; i < kTrials; ++i) {
    const Vec3 axis = r.UnitVector();
    const double angle = r.Uniform(0.0, 170.0 * M_PI / 180.0);
    const Vec3 q = std::tan(angle / 2) * axis;
    const Mat3 expected = Eigen::AngleAxisd(-angle, axis).toRotationMatrix();
    const Mat3 R = CayleyToRotation(q);
    EXPECT_LT(MaxAbs(R - expected), 1e-12);
    EXPECT_LT(OrthonormalityError(R), 1e-12);
  }
}

TEST(Geometry, CayleyRoundTripsUpTo170Degrees) {
  Random r(7);
  for (int i = 0; i < kTrials; ++i) {
    const Mat3 R = r.Rotation(0.0, 170.0 * M_PI / 180.0);
    EXPECT_LT(MaxAbs(CayleyToRotation(RotationToCayley(R)) - R), 1e-12);
    // The other direction: |q| up to tan(85 deg) ~ 11.4, relative accuracy.
    const Vec3 q = std::tan(r.Uniform(0.0, 85.0 * M_PI / 180.0)) * r.UnitVector();
    EXPECT_LT((RotationToCayley(CayleyToRotation(q)) - q).norm(), 1e-12 * (1.0 + q.norm()));
  }
  EXPECT_EQ(RotationToCayley(Mat3::Identity()), Vec3::Zero());
}

TEST(Geometry, CayleyThrowsNearPi) {
  Random r(8);
  for (int i = 0; i < 100; ++i) {
    const Vec3 axis = r.UnitVector();
    EXPECT_THROW(RotationToCayley(Eigen::AngleAxisd(M_PI, axis).toRotationMatrix()),
                 std::domain_error);
    EXPECT_THROW(RotationToCayley(Eigen::AngleAxisd(M_PI - 1e-8, axis).toRotationMatrix()),
                 std::domain_error);
  }
}

TEST(Geometry, ExpMatchesAngleAxis) {
  Random r(9);
  for (int i = 0; i < kTrials; ++i) {
    const Vec3 axis = r.UnitVector();
    const double angle = r.Uniform(0.0, M_PI);
    EXPECT_LT(MaxAbs(ExpSO3(angle * axis) - Eigen::AngleAxisd(angle, axis).toRotationMatrix()),
              1e-14);
  }
  // Series branch: exact to double precision for tiny angles.
  const Vec3 tiny(1e-9, -2e-9, 3e-9);
  EXPECT_LT(MaxAbs(ExpSO3(tiny) - (Mat3::Identity() + Skew(tiny))), 1e-17);
  EXPECT_EQ(ExpSO3(Vec3::Zero()), Mat3::Identity());
}

TEST(Geometry, LogExpRoundTrip) {
  Random r(10);
  for (int i = 0; i < kTrials; ++i) {
    const Vec3 w = r.Uniform(0.0, M_PI - 1e-6) * r.UnitVector();
    EXPECT_LT((LogSO3(ExpSO3(w)) - w).norm(), 1e-12);
    const Mat3 R = r.Rotation();
    EXPECT_LT(MaxAbs(ExpSO3(LogSO3(R)) - R), 1e-12);
    EXPECT_LE(LogSO3(R).norm(), M_PI + 1e-12);
  }
}

TEST(Geometry, LogExpTinyAngles) {
  Random r(11);
  for (int i = 0; i < 200; ++i) {
    const Vec3 w = r.Uniform(1e-12, 1e-9) * r.UnitVector();
    // Relative accuracy: an absolute tolerance would pass trivially at this scale.
    EXPECT_LT((LogSO3(ExpSO3(w)) - w).norm(), 1e-6 * w.norm());
  }
}

TEST(Geometry, LogExpNearPi) {
  Random r(12);
  for (int i = 0; i < 200; ++i) {
    const Vec3 axis = r.UnitVector();
    const double angle = M_PI - r.Uniform(1e-9, 1e-6);
    const Vec3 w = LogSO3(ExpSO3(angle * axis));
    EXPECT_NEAR(w.norm(), angle, 1e-9);
    EXPECT_LT((w - angle * axis).norm(), 1e-6);
    // At exactly pi the axis sign is arbitrary; either one must reproduce the rotation.
    const Mat3 half_turn = ExpSO3(M_PI * axis);
    const Vec3 v = LogSO3(half_turn);
    EXPECT_NEAR(v.norm(), M_PI, 1e-9);
    EXPECT_NEAR(std::abs(v.normalized().dot(axis)), 1.0, 1e-9);
    EXPECT_LT(MaxAbs(ExpSO3(v) - half_turn), 1e-12);
  }
}

TEST(Geometry, QuaternionRoundTrip) {
  Random r(13);
  for (int i = 0; i < kTrials; ++i) {
    const Mat3 R = r.Rotation();
    const Eigen::Vector4d q = RotationToQuaternion(R);
    EXPECT_NEAR(q.norm(), 1.0, 1e-14);
    EXPECT_GE(q[0], 0.0);
    EXPECT_LT(MaxAbs(QuaternionToRotation(q) - R), 1e-13);
    // q and -q are the same rotation; the output is the one with w >= 0.
    EXPECT_LT((RotationToQuaternion(QuaternionToRotation(-q)) - q).norm(), 1e-13);
  }
  // Hand-computed: 90 deg about z is (cos 45, 0, 0, sin 45) in (w, x, y, z).
  const Eigen::Vector4d q = RotationToQuaternion(ExpSO3(Vec3(0, 0, M_PI / 2)));
  EXPECT_LT((q - Eigen::Vector4d(std::sqrt(0.5), 0, 0, std::sqrt(0.5))).norm(), 1e-15);
  EXPECT_LT(MaxAbs(QuaternionToRotation(q) * Vec3::UnitX() - Vec3::UnitY()), 1e-15);
}

TEST(Geometry, RollPitchYawOrder) {
  // R = Rz(yaw) Ry(pitch) Rx(roll): roll acts first.
  const Mat3 R = RotationFromRollPitchYaw(M_PI / 2, 0, M_PI / 2);
  // y --roll 90--> z --yaw 90--> z;  z --roll--> -y --yaw--> x.
  EXPECT_LT((R * Vec3::UnitY() - Vec3::UnitZ()).norm(), 1e-15);
  EXPECT_LT((R * Vec3::UnitZ() - Vec3::UnitX()).norm(), 1e-15);
}

TEST(Geometry, RemoveHeadingKeepsTiltAndZeroesYaw) {
  Random r(14);
  for (int i = 0; i < kTrials; ++i) {
    const double roll = r.Uniform(-1.2, 1.2), pitch = r.Uniform(-1.2, 1.2);
    const double yaw = r.Uniform(-M_PI, M_PI);
    const Mat3 R_GC = RotationFromRollPitchYaw(roll, pitch, yaw);
    const Mat3 R_WC = RemoveHeading(R_GC);
    EXPECT_NEAR(HeadingYaw(R_GC), yaw, 1e-12);
    EXPECT_NEAR(HeadingYaw(R_WC), 0.0, 1e-12);
    // Gravity seen from the body (the z row) is untouched: only the heading went.
    EXPECT_LT((R_WC.row(2) - R_GC.row(2)).norm(), 1e-12);
    EXPECT_LT(MaxAbs(R_WC - RotationFromRollPitchYaw(roll, pitch, 0.0)), 1e-12);
    EXPECT_LT(OrthonormalityError(R_WC), 1e-12);
  }
}

TEST(Geometry, ProjectToSO3) {
  Random r(15);
  for (int i = 0; i < 200; ++i) {
    const Mat3 R = r.Rotation();
    Mat3 noisy = R;
    for (int k = 0; k < 9; ++k) noisy(k / 3, k % 3) += r.Uniform(-1e-4, 1e-4);
    const Mat3 P = ProjectToSO3(noisy);
    EXPECT_LT(OrthonormalityError(P), 1e-12);
    EXPECT_LT(MaxAbs(P - R), 1e-3);
    EXPECT_LT(MaxAbs(ProjectToSO3(R) - R), 1e-12);  // a rotation is its own projection
  }
  // A reflection is far from SO(3), and projects to a proper rotation.
  const Mat3 reflection = Eigen::Vector3d(1, 1, -1).asDiagonal();
  EXPECT_NEAR(OrthonormalityError(reflection), 2.0, 1e-15);
  EXPECT_NEAR(ProjectToSO3(reflection).determinant(), 1.0, 1e-12);
}

}  // namespace
}  // namespace ftcal
