// The hanging experiment's forward model for tests and benchmarks: eq. 4-7 written out (first
// order or with finite rotations), from known leg parameters, with optional sensor noise.
#pragma once

#include <array>
#include <cmath>
#include <random>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"

namespace ftcal {
namespace hanging_testdata {

constexpr double kTwoPi = 2.0 * M_PI;

inline Mat3 Rot(const Vec3& axis, double angle) {
  return Eigen::AngleAxisd(angle, axis).toRotationMatrix();
}

// Rotation by rotation vector v, via Eigen (independent of ftcal::ExpSO3).
inline Mat3 RotVec(const Vec3& v) {
  if (v.norm() == 0.0) return Mat3::Identity();
  return Eigen::AngleAxisd(v.norm(), v.normalized()).toRotationMatrix();
}

// Nominal poses: left legs as designed, right legs mirrored three different ways so that each
// sign flip of the transducer x and z axes is exercised.
inline std::array<Pose3, kNumLegs> NominalPoses() {
  std::array<Pose3, kNumLegs> X;
  const double hip_x[3] = {-0.25, 0.0, 0.25};
  for (int i = 0; i < 3; ++i) {
    X[i] = Pose3(Mat3::Identity(), Vec3(hip_x[i], 0.15, 0.0));
  }
  X[3] = Pose3(Rot(Vec3::UnitZ(), M_PI), Vec3(hip_x[0], -0.15, 0.0));  // x flipped
  X[4] = Pose3(Rot(Vec3::UnitX(), M_PI), Vec3(hip_x[1], -0.15, 0.0));  // z flipped
  X[5] = Pose3(Rot(Vec3::UnitY(), M_PI), Vec3(hip_x[2], -0.15, 0.0));  // x and z flipped
  return X;
}

// Stated gravity per series: the body axis of the report's naming (left legs).
inline Vec3 SeriesGravityB(HangSeries s) {
  switch (s) {
    case HangSeries::kXPos:
      return Vec3::UnitX();
    case HangSeries::kXNeg:
      return -Vec3::UnitX();
    case HangSeries::kZPos:
      return Vec3::UnitZ();
    case HangSeries::kZNeg:
      return -Vec3::UnitZ();
  }
  return Vec3::Zero();
}

// Slot of a series for a leg: 0 +x, 1 -x, 2 +z, 3 -z of the transducer along gravity.
inline int SlotOf(const Pose3& X_B_ft, const Vec3& g_b) {
  const Vec3 g = X_B_ft.R.transpose() * g_b;
  if (std::abs(g.x()) > 0.5) return g.x() > 0 ? 0 : 1;
  return g.z() > 0 ? 2 : 3;
}

struct LegTruth {
  double weight_n = 0.0;
  Vec6 offset = Vec6::Zero();
  LegComModel com;
  std::array<Vec3, 4> s;  // per slot; no component about the slot's axis
};

inline std::array<LegTruth, kNumLegs> MakeTruth(double s_scale) {
  std::array<LegTruth, kNumLegs> t;
  for (int k = 0; k < kNumLegs; ++k) {
    LegTruth& l = t[k];
    l.weight_n = 5.8 + 0.15 * k;
    l.offset << 1.47 - 0.4 * k, -1.30 + 0.2 * k, -5.61 + 0.7 * k, 0.031 - 0.01 * k,
        -0.052 + 0.013 * k, 0.012 + 0.004 * k;
    l.com.x = {0.040 + 0.002 * k, 0.3 + 0.5 * k, 0.010 - 0.002 * k};
    l.com.y = 0.021 - 0.003 * k;
    l.com.z = {0.033 + 0.001 * k, 1.9 - 0.4 * k, -0.062 + 0.003 * k};
    const double a = s_scale * (1.0 + 0.1 * k);
    l.s[0] = Vec3(0.0, 0.7 * a, -0.5 * a);
    l.s[1] = Vec3(0.0, -0.3 * a, 0.9 * a);
    l.s[2] = Vec3(0.6 * a, 0.4 * a, 0.0);
    l.s[3] = Vec3(-0.2 * a, 0.8 * a, 0.0);
  }
  return t;
}

struct Motion {
  int bins = 200;  // aligned mode: one sample at each bin centre
  bool aligned = true;
  double cycles = 10.0;
  double start_phase = 0.0;
  double samples_per_cycle = 1000.0;  // unaligned mode (100 Hz, 10 s per cycle)
  double angle_quantum_rad = 0.0;
  double f_noise_n = 0.0, tau_noise_nm = 0.0;
  bool exact = false;  // finite rotations exp([s]) instead of I + [s]
};

// Shaft angles of one series, wrapped to (-pi, pi] as a servo reports them.
inline std::vector<double> Angles(const Motion& m, int direction) {
  std::vector<double> out;
  if (m.aligned) {
    const int n = static_cast<int>(std::lround(m.cycles * m.bins));
    const int start_bin = static_cast<int>(std::lround(m.start_phase * m.bins));
    for (int i = 0; i < n; ++i) {
      out.push_back(std::remainder(direction * kTwoPi * (start_bin + i + 0.5) / m.bins, kTwoPi));
    }
  } else {
    const int n = static_cast<int>(m.cycles * m.samples_per_cycle);
    for (int i = 0; i < n; ++i) {
      double th = direction * kTwoPi * (m.start_phase + i / m.samples_per_cycle);
      if (m.angle_quantum_rad > 0) th = m.angle_quantum_rad * std::round(th / m.angle_quantum_rad);
      out.push_back(std::remainder(th, kTwoPi));
    }
  }
  return out;
}

// Eq. 4-7 written out.
inline HangingRecording MakeSeries(HangSeries series, const std::array<Pose3, kNumLegs>& X,
                                   const std::array<LegTruth, kNumLegs>& truth, const Motion& m,
                                   std::mt19937* rng) {
  HangingRecording rec;
  rec.series = series;
  rec.gravity_b = SeriesGravityB(series);
  std::normal_distribution<double> nf(0.0, m.f_noise_n), nt(0.0, m.tau_noise_nm);
  for (int k = 0; k < kNumLegs; ++k) {
    const int slot = SlotOf(X[k], rec.gravity_b);
    const Vec3 axis = slot < 2 ? Vec3::UnitX() : Vec3::UnitZ();
    const double sign = slot % 2 == 0 ? 1.0 : -1.0;
    const LegTruth& t = truth[k];
    const Mat3 r = m.exact ? RotVec(t.s[slot]) : Mat3(Mat3::Identity() + Skew(t.s[slot]));
    const Vec3 f_leg = sign * t.weight_n * (r * axis);
    // Right legs turn the other way.
    const std::vector<double> angles = Angles(m, k < 3 ? 1 : -1);
    LegSamples& ls = rec.legs[k];
    for (size_t i = 0; i < angles.size(); ++i) {
      ls.t_s.push_back(0.01 * i);
      ls.angle_rad.push_back(angles[i]);
      const Vec3 com = t.com.At(LegPhase(angles[i]));
      Vec6 w;
      w << f_leg, com.cross(f_leg);
      w += t.offset;
      if (m.f_noise_n > 0) {
        for (int c = 0; c < 3; ++c) w(c) += nf(*rng);
        for (int c = 3; c < 6; ++c) w(c) += nt(*rng);
      }
      ls.wrench.push_back(w);
    }
  }
  return rec;
}

inline std::vector<HangingRecording> MakeRecordings(const std::array<Pose3, kNumLegs>& X,
                                                    const std::array<LegTruth, kNumLegs>& truth,
                                                    Motion m, std::mt19937* rng) {
  std::vector<HangingRecording> recs;
  for (int s = 0; s < kNumHangSeries; ++s) {
    m.start_phase += 0.137;  // each series starts elsewhere in the cycle
    recs.push_back(MakeSeries(static_cast<HangSeries>(s), X, truth, m, rng));
  }
  return recs;
}

}  // namespace hanging_testdata
}  // namespace ftcal
