// What the calibration consumes, independent of how it was recorded (log, live, twin).
#pragma once

#include <array>
#include <string>
#include <vector>

#include "ftcal/geometry.h"
#include "ftcal/legs.h"

namespace ftcal {

// The four hanging series of step 1. The name is the transducer axis along gravity as the
// report uses it; which transducer axis each leg actually has along gravity follows from
// gravity_b and the leg's nominal rotation (a mirrored leg gets the opposite sign).
enum class HangSeries { kXPos = 0, kXNeg = 1, kZPos = 2, kZNeg = 3 };
inline constexpr int kNumHangSeries = 4;

// One leg's samples in time order.
struct LegSamples {
  std::vector<double> t_s;        // sample time, s
  std::vector<double> angle_rad;  // shaft angle at that time
  std::vector<Vec6> wrench;       // reading [f; tau] in ft_k
};

struct HangingRecording {
  HangSeries series = HangSeries::kXPos;
  Vec3 gravity_b = Vec3::Zero();  // stated direction of gravity in body frame B (unit)
  std::array<LegSamples, kNumLegs> legs;
  // Attitude samples R^W_C (or the mocap's R^G_C) during the series, when motion capture ran:
  // used only to check the stated axis.
  std::vector<Mat3> attitude;
};

// One steady standing pose (the segmenter's STEADY_POSE).
struct StandingPose {
  std::array<Vec6, kNumLegs> wrench;       // median readings in ft_k
  std::array<double, kNumLegs> angle_rad;  // median shaft angles
  Mat3 R_WC = Mat3::Identity();            // median attitude
  double t_s = 0.0;
  // Within-pose scatter: the standard error of the medians above (readings per component;
  // attitude as a rotation vector about W's axes, rad), from the samples' robust spread. The
  // pose's noise floor (docs/method.md "Uncertainty"); valid only when samples > 0 (a
  // STEADY_POSE message carries none).
  int samples = 0;
  std::array<Vec6, kNumLegs> wrench_sem;
  Vec3 attitude_sem_rad = Vec3::Zero();
};

// A sample with some legs unloaded (tripod stance or swing), for offset re-estimation.
struct LoadSample {
  std::array<Vec6, kNumLegs> wrench;
  std::array<double, kNumLegs> angle_rad;
  std::array<bool, kNumLegs> unloaded{};  // leg k carries no ground load
  Mat3 R_WC = Mat3::Identity();
};

}  // namespace ftcal
