// Standing data generated from known parameters (shared by standing_test,
// offset_reestimation_test and, for its calibration, corrector_test): the sensing model's forward
// direction (TransducerReading) with physically consistent ground wrenches. Independent of the twin
// in services/sim on purpose.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <random>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/sensing_model.h"

namespace ftcal {
namespace testdata {

constexpr double kDeg = M_PI / 180.0;
constexpr double kLegLength = 0.25;  // hip to foot, m (only shapes the chassis tilt)

enum class Mounting { kNone, kFull, kRotationsOnly, kTranslationsOnly };

// A BigAnt-like robot: hips 0.2 m apart along x, 0.15 m either side; right transducers mirrored
// by a half turn about z so the same leg design serves both sides.
inline RobotCalibration MakeTruth(uint64_t seed, Mounting mounting) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  RobotCalibration cal;
  cal.total_mass_kg = 8.18;
  const double hip_x[kNumLegs] = {-0.2, 0.0, 0.2, -0.2, 0.0, 0.2};
  cal.p_C_B = Vec3(0.01 * u(rng), 0.01 * u(rng), 0.01 * u(rng));
  for (int k = 0; k < kNumLegs; ++k) {
    const bool left = k < 3;
    cal.X_B_ft[k] = Pose3(left ? Mat3::Identity() : RotationFromRollPitchYaw(0, 0, M_PI),
                          Vec3(hip_x[k], left ? 0.15 : -0.15, -0.03));
    LegCalibration& l = cal.leg[k];
    l.offset << 8 * u(rng), 8 * u(rng), 8 * u(rng), 0.36 * u(rng), 0.36 * u(rng), 0.36 * u(rng);
    l.weight_n = 6.2 + 0.3 * u(rng);
    l.com.x = {0.015 + 0.005 * u(rng), M_PI * u(rng), 0.01 * u(rng)};
    l.com.y = 0.005 * u(rng);
    l.com.z = {0.015 + 0.005 * u(rng), M_PI * u(rng), -0.06 + 0.02 * u(rng)};
    Mat3 R_tilde = Mat3::Identity();
    Vec3 p_tilde = Vec3::Zero();
    if (mounting == Mounting::kFull || mounting == Mounting::kRotationsOnly) {
      // A tilt of 1-3 degrees about the transducer's own origin ...
      const Vec3 axis = Vec3(u(rng), u(rng), u(rng)).normalized();
      R_tilde = ExpSO3(axis * (2.0 + u(rng)) * kDeg);
      p_tilde = (Mat3::Identity() - R_tilde) * cal.X_B_ft[k].p;
    }
    if (mounting == Mounting::kFull || mounting == Mounting::kTranslationsOnly) {
      // ... plus a shift of 2-8 mm (p~ acts about the body origin, docs/method.md).
      const Vec3 d = Vec3(u(rng), u(rng), u(rng)).normalized() * (0.005 + 0.003 * u(rng));
      p_tilde += d;
    }
    if (mounting == Mounting::kRotationsOnly) p_tilde.setZero();  // model 2's assumption
    l.R_tilde = R_tilde;
    l.p_tilde_prime = R_tilde.transpose() * (p_tilde + cal.p_C_B);
  }
  return cal;
}

// What step 1 hands to step 2: the same offsets, weights and CoM curves, no mounting errors.
inline RobotCalibration Step1Of(const RobotCalibration& truth) {
  RobotCalibration cal = truth;
  for (LegCalibration& l : cal.leg) {
    l.R_tilde = Mat3::Identity();
    l.p_tilde_prime = Vec3::Zero();
  }
  cal.p_C_B = Vec3::Zero();
  return cal;
}

inline std::vector<std::array<double, kNumLegs>> Grid() {
  std::vector<std::array<double, kNumLegs>> out;
  for (int i = 0; i < 729; ++i) {
    std::array<double, kNumLegs> a;
    int n = i;
    for (int k = 0; k < kNumLegs; ++k, n /= 3) a[k] = (n % 3 - 1) * 36.0 * kDeg;
    out.push_back(a);
  }
  return out;
}

inline std::vector<std::array<double, kNumLegs>> GridSubset(size_t count, uint64_t seed) {
  auto grid = Grid();
  std::mt19937_64 rng(seed);
  std::shuffle(grid.begin(), grid.end(), rng);
  grid.resize(count);
  return grid;
}

struct Noise {
  double force_n = 0.0;       // per sample
  double torque_nm = 0.0;     // per sample
  int samples = 150;          // per pose, median taken
  double attitude_deg = 0.0;  // per sample, per axis (rotation vector)
};

inline double Median(std::vector<double>& v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// Standing poses: the chassis tilts with the leg lengths (legs at +-36 deg are shorter), the
// ground wrenches are random foot loads corrected by the minimum-norm change (equal share
// per foot) so their sum at the CoM in W is exactly the target: (0,0,G,0,0,0), or with
// moving_com the torque delta_W x (0,0,G) of the shifted whole-robot CoM.
inline std::vector<StandingPose> MakePoses(const RobotCalibration& truth,
                                           const std::vector<std::array<double, kNumLegs>>& angles,
                                           const Noise& noise, bool moving_com, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const double G = truth.TotalWeightN();
  std::vector<StandingPose> poses;
  std::vector<double> buf(std::max(1, noise.samples));
  for (const auto& a : angles) {
    // Plane through the hip heights h_k = L cos(theta_k) gives roll and pitch.
    Eigen::Matrix<double, kNumLegs, 3> A;
    Eigen::Matrix<double, kNumLegs, 1> h;
    for (int k = 0; k < kNumLegs; ++k) {
      A.row(k) << 1.0, truth.X_B_ft[k].p.x(), truth.X_B_ft[k].p.y();
      h[k] = kLegLength * std::cos(a[k]);
    }
    const Vec3 plane = A.colPivHouseholderQr().solve(h);
    const Mat3 R_WC = RotationFromRollPitchYaw(std::atan(plane[2]) + 0.5 * kDeg * u(rng),
                                               -std::atan(plane[1]) + 0.5 * kDeg * u(rng), 0.0);
    std::array<Vec6, kNumLegs> w_W;
    Vec6 sum = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec3 foot_C = truth.X_B_ft[k].p + kLegLength * Vec3(std::sin(a[k]), 0, -std::cos(a[k]));
      const Vec3 f(2.0 * n01(rng), 2.0 * n01(rng), G / 6.0 + 4.0 * n01(rng));
      const Vec3 tau = (R_WC * foot_C).cross(f) + 0.02 * Vec3(n01(rng), n01(rng), n01(rng));
      w_W[k] << f, tau;
      sum += w_W[k];
    }
    Vec6 target;
    target << 0, 0, G, 0, 0, 0;
    if (moving_com) target.tail<3>() = (R_WC * ComShiftC(truth, a)).cross(Vec3(0, 0, G));
    StandingPose pose;
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 w = w_W[k] + (target - sum) / kNumLegs;
      const Vec6 w_C = TransformWrench(Pose3(R_WC.transpose(), Vec3::Zero()), w);
      const Vec6 clean = TransducerReading(truth, k, w_C, a[k], R_WC);
      for (int i = 0; i < 6; ++i) {
        const double sigma = i < 3 ? noise.force_n : noise.torque_nm;
        if (sigma == 0.0) {
          pose.wrench[k][i] = clean[i];
          continue;
        }
        for (double& s : buf) s = clean[i] + sigma * n01(rng);
        pose.wrench[k][i] = Median(buf);
      }
      pose.angle_rad[k] = a[k];
    }
    // The segmenter represents a pose by medians of its steady samples, attitude included.
    Vec3 att_err = Vec3::Zero();
    if (noise.attitude_deg > 0.0) {
      for (int i = 0; i < 3; ++i) {
        for (double& s : buf) s = noise.attitude_deg * kDeg * n01(rng);
        att_err[i] = Median(buf);
      }
    }
    pose.R_WC = ExpSO3(att_err) * R_WC;
    poses.push_back(pose);
  }
  return poses;
}

inline const Noise kReportNoise{0.05, 0.002, 150, 0.2};

}  // namespace testdata
}  // namespace ftcal
