// A calibration against another (the twin's truth, or a second run): the largest error of each
// parameter class over the six legs, and the bounds the live experiment is held to. The same
// measures and bounds as experiment_live_test's CheckRun (scripts/compare_calibration.py's
// whole-experiment bounds times a factor; p~' held to its own stated sigma).
#pragma once

#include <algorithm>
#include <cmath>
#include <iostream>
#include <string>

#include <gtest/gtest.h>

#include "ftcal/calibration_io.h"
#include "ftcal/geometry.h"
#include "ftcal/sensing_model.h"

namespace ftcal::calibration_errors {

inline double RotationDeg(const Mat3& a, const Mat3& b) {
  const double c = std::clamp(((a.transpose() * b).trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / M_PI;
}

struct Errors {
  double weight_n = 0, force_n = 0, torque_nm = 0, com_m = 0, rotation_deg = 0, p_tilde_m = 0;
};

inline Errors Compare(const RobotCalibration& a, const RobotCalibration& b) {
  Errors e;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& x = a.leg[k];
    const LegCalibration& y = b.leg[k];
    e.weight_n = std::max(e.weight_n, std::abs(x.weight_n - y.weight_n));
    e.force_n =
        std::max(e.force_n, (x.offset.head<3>() - y.offset.head<3>()).cwiseAbs().maxCoeff());
    e.torque_nm =
        std::max(e.torque_nm, (x.offset.tail<3>() - y.offset.tail<3>()).cwiseAbs().maxCoeff());
    e.com_m = std::max(e.com_m, MaxCurveDistance(x.com, y.com));
    e.rotation_deg = std::max(e.rotation_deg, RotationDeg(x.R_tilde, y.R_tilde));
    e.p_tilde_m = std::max(e.p_tilde_m, (x.p_tilde_prime - y.p_tilde_prime).norm());
  }
  return e;
}

// The whole experiment's recovery bounds (scripts/compare_calibration.py: 0.015 N, 0.02 N,
// 0.001 N*m, 0.2 mm, 0.15 deg) times `factor`; p~' is held to its sigmas (below).
inline void ExpectWithinBounds(const Errors& e, double factor, const std::string& what) {
  EXPECT_LE(e.weight_n, factor * 0.015) << what << ": leg weight";
  EXPECT_LE(e.force_n, factor * 0.02) << what << ": force offset";
  EXPECT_LE(e.torque_nm, factor * 0.001) << what << ": torque offset";
  EXPECT_LE(e.com_m, factor * 0.2e-3) << what << ": leg CoM";
  EXPECT_LE(e.rotation_deg, factor * 0.15) << what << ": mounting rotation";
}

// p~' against the truth: each component within `sigmas` of the sigma the calibration states
// (with ~40 standing poses its vertical component is known to 2-5 mm only). Not a fixed bound
// on the horizontal error (it was 1.5 mm, and a run missed it by 0.07 mm): the short plan
// states horizontal sigmas of 0.39-0.61 mm, so 1.5 mm is under 3 of them and six legs in two
// runs cross it by chance. What keeps the sigma check from passing anything is the precision
// itself: horizontal sigmas under `max_horizontal_sigma_m` (1 mm for the short plan's ~33
// poses). Returns the worst component in sigmas.
inline double ExpectPTildeWithinSigmas(const calibration::Calibration& proto,
                                       const RobotCalibration& cal, const RobotCalibration& truth,
                                       double sigmas, double max_horizontal_sigma_m = 1e-3) {
  double worst = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& e = proto.leg(k).mounting().p_tilde_prime_m();
    const Vec3 sigma(e.sigma_x(), e.sigma_y(), e.sigma_z());
    const Vec3 err = cal.leg[k].p_tilde_prime - truth.leg[k].p_tilde_prime;
    for (int i = 0; i < 3; ++i) {
      EXPECT_GT(sigma[i], 0.0) << "leg " << k << ": the calibration states no sigma for p~'";
      if (!(sigma[i] > 0.0)) continue;
      worst = std::max(worst, std::abs(err[i]) / sigma[i]);
      EXPECT_LE(std::abs(err[i]), sigmas * sigma[i])
          << "leg " << proto.leg(k).name() << " p~' component " << i << ": " << err[i] * 1e3
          << " mm off, sigma " << sigma[i] * 1e3 << " mm";
    }
    EXPECT_LE(sigma[0], max_horizontal_sigma_m)
        << "leg " << proto.leg(k).name() << ": p~' x known to no better";
    EXPECT_LE(sigma[1], max_horizontal_sigma_m)
        << "leg " << proto.leg(k).name() << ": p~' y known to no better";
  }
  return worst;
}

inline std::string Describe(const Errors& e) {
  return "leg weight " + std::to_string(e.weight_n) + " N, force offsets " +
         std::to_string(e.force_n) + " N, torque offsets " + std::to_string(e.torque_nm) +
         " N*m, leg CoM " + std::to_string(e.com_m * 1e3) + " mm, mounting rotations " +
         std::to_string(e.rotation_deg) + " deg, p~' " + std::to_string(e.p_tilde_m * 1e3) + " mm";
}

}  // namespace ftcal::calibration_errors
