#include "ftcal/segmenter.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace ftcal {
namespace {

TEST(SavitzkyGolay, FivePointQuadraticMatchesClosedForm) {
  // Textbook 5-point, 2nd-order first-derivative weights: (-2, -1, 0, 1, 2) / 10.
  const std::vector<double> c = SavitzkyGolayDerivative(5, 2);
  const double expected[5] = {-0.2, -0.1, 0.0, 0.1, 0.2};
  for (int i = 0; i < 5; ++i) EXPECT_NEAR(c[i], expected[i], 1e-14);
}

TEST(SavitzkyGolay, ExactOnPolynomialsOfItsOrder) {
  for (int order : {2, 3, 4}) {
    const int window = 41;
    const std::vector<double> c = SavitzkyGolayDerivative(window, order);
    // p(x) = 3 - 2x + 0.5x^2 (+ 0.01x^3 + ...): p'(0) = -2 whatever the higher terms.
    double d = 0.0;
    for (int i = 0; i < window; ++i) {
      const double x = i - window / 2;
      double p = 3 - 2 * x + 0.5 * x * x;
      if (order >= 3) p += 0.01 * x * x * x;
      if (order >= 4) p -= 0.001 * x * x * x * x;
      d += c[i] * p;
    }
    EXPECT_NEAR(d, -2.0, 1e-9) << "order " << order;
  }
}

TEST(SavitzkyGolay, RejectsBadWindow) {
  EXPECT_THROW(SavitzkyGolayDerivative(40, 2), std::invalid_argument);
  EXPECT_THROW(SavitzkyGolayDerivative(5, 5), std::invalid_argument);
}

// A synthetic standing session: plateaus of known wrenches joined by 0.5 s ramps with a damped
// oscillation after each change, 0.05 N noise, at 100 Hz.
struct Plateau {
  double duration_s;
  double level;         // force level added to every leg's fz
  bool marker_dropout;  // one sample with a marker missing in the middle
};

std::vector<SyncSample> MakeSession(const std::vector<Plateau>& plateaus, unsigned seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0.0, 0.05);
  std::vector<SyncSample> out;
  const double dt = 0.01;
  double t = 0.0, level = 0.0;
  for (const Plateau& p : plateaus) {
    const double from = level, to = p.level;
    const int ramp = 50;
    for (int i = 0; i < ramp; ++i, t += dt) {
      SyncSample s;
      s.utime = static_cast<int64_t>(std::llround(t * 1e6));
      const double u = (i + 1.0) / ramp;
      for (int k = 0; k < kNumLegs; ++k) {
        s.wrench[k] = Vec6::Zero();
        s.wrench[k][2] = from + (to - from) * u + noise(rng);
        s.angle_rad[k] = 0.1 * k;
      }
      s.attitude_ok = s.markers_ok = true;
      out.push_back(s);
    }
    const int n = static_cast<int>(std::lround(p.duration_s / dt));
    for (int i = 0; i < n; ++i, t += dt) {
      SyncSample s;
      s.utime = static_cast<int64_t>(std::llround(t * 1e6));
      const double tau = i * dt;
      // Damped oscillation: 4 Hz, 0.15 s decay, 3 N initial amplitude.
      const double osc = 3.0 * std::exp(-tau / 0.15) * std::sin(2 * M_PI * 4.0 * tau);
      for (int k = 0; k < kNumLegs; ++k) {
        s.wrench[k] = Vec6::Zero();
        s.wrench[k][2] = to + osc + noise(rng);
        s.wrench[k][3] = 0.01 * k + noise(rng) * 0.04;
        s.angle_rad[k] = 0.1 * k;
      }
      s.attitude_ok = true;
      s.markers_ok = !(p.marker_dropout && i == n / 2);
      out.push_back(s);
    }
    level = to;
  }
  return out;
}

TEST(PoseSegmenter, FindsEachSteadyPlateauWithItsMedian) {
  const std::vector<Plateau> plateaus = {{5.0, 10.0, false},
                                         {5.0, 14.0, false},
                                         {1.0, 18.0, false},  // too short
                                         {5.0, 12.0, true},   // marker dropout
                                         {5.0, 9.0, false}};
  const std::vector<SyncSample> session = MakeSession(plateaus, 7);
  std::vector<SteadyPoseOut> poses;
  PoseSegmenter seg(SegmenterOptions{}, [&](const SteadyPoseOut& p) { poses.push_back(p); });
  for (const SyncSample& s : session) seg.Add(s);
  seg.Flush();

  ASSERT_EQ(poses.size(), 3u);
  const double expected[3] = {10.0, 14.0, 9.0};
  for (int i = 0; i < 3; ++i) {
    for (int k = 0; k < kNumLegs; ++k) {
      // Median of >= 150 samples of 0.05 N noise: a few mN from the plateau.
      EXPECT_NEAR(poses[i].pose.wrench[k][2], expected[i], 0.015) << "pose " << i << " leg " << k;
      EXPECT_NEAR(poses[i].pose.wrench[k][3], 0.01 * k, 0.005);
      EXPECT_DOUBLE_EQ(poses[i].pose.angle_rad[k], 0.1 * k);
    }
    EXPECT_GE(poses[i].num_samples, 150);
    // Steady must not start before the oscillation has decayed below the threshold.
    EXPECT_GT(poses[i].num_samples * 0.01, 1.5);
  }
  EXPECT_EQ(seg.counters().dropped_markers, 1);
  EXPECT_GE(seg.counters().dropped_short, 1);
}

TEST(PoseSegmenter, NaNSampleEndsRunAndNeverEntersAMedian) {
  std::vector<SyncSample> session = MakeSession({{5.0, 10.0, false}, {5.0, 20.0, false}}, 3);
  // Poison one sample in the middle of the second plateau.
  session[session.size() - 250].wrench[2][0] = std::nan("");
  std::vector<SteadyPoseOut> poses;
  PoseSegmenter seg(SegmenterOptions{}, [&](const SteadyPoseOut& p) { poses.push_back(p); });
  for (const SyncSample& s : session) seg.Add(s);
  seg.Flush();
  EXPECT_EQ(seg.counters().rejected_samples, 1);
  for (const SteadyPoseOut& p : poses) {
    for (int k = 0; k < kNumLegs; ++k) EXPECT_TRUE(p.pose.wrench[k].allFinite());
  }
  // The first plateau survives; the second is split by the NaN into two runs of ~2.3 s each.
  ASSERT_GE(poses.size(), 1u);
  EXPECT_NEAR(poses[0].pose.wrench[0][2], 10.0, 0.015);
}

TEST(PoseSegmenter, StreamIsSplitAtTimeGaps) {
  std::vector<SyncSample> session = MakeSession({{6.0, 10.0, false}}, 5);
  // Drop 1 s of samples in the middle: the run must not bridge the gap.
  session.erase(session.begin() + 300, session.begin() + 400);
  std::vector<SteadyPoseOut> poses;
  PoseSegmenter seg(SegmenterOptions{}, [&](const SteadyPoseOut& p) { poses.push_back(p); });
  for (const SyncSample& s : session) seg.Add(s);
  seg.Flush();
  EXPECT_GE(seg.counters().window_resets, 1);
  for (const SteadyPoseOut& p : poses) {
    EXPECT_LT(p.end_utime - p.start_utime, 3'500'000);
  }
}

// Motion capture late or lost for a few samples (a machine stall): those samples have no
// attitude, the forces show the robot still, and the pose stays, its median over the rest.
TEST(PoseSegmenter, ALapseOfAttitudeLeavesTheMedianNotThePose) {
  std::vector<SyncSample> session = MakeSession({{5.0, 10.0, false}, {5.0, 20.0, false}}, 11);
  const Mat3 tilted = Eigen::AngleAxisd(0.3, Vec3::UnitX()).toRotationMatrix();
  const Mat3 held = Eigen::AngleAxisd(-0.2, Vec3::UnitY()).toRotationMatrix();
  for (SyncSample& s : session) s.R_WC = tilted;
  // Four samples mid-way through the first plateau, holding an attitude that is not the robot's.
  const size_t lapse = 50 + 250;
  for (size_t i = lapse; i < lapse + 4; ++i) {
    session[i].attitude_ok = session[i].markers_ok = false;
    session[i].R_WC = held;
  }
  std::vector<SteadyPoseOut> poses;
  PoseSegmenter seg(SegmenterOptions{}, [&](const SteadyPoseOut& p) { poses.push_back(p); });
  std::vector<SteadyPoseOut> whole;
  PoseSegmenter reference(SegmenterOptions{}, [&](const SteadyPoseOut& p) { whole.push_back(p); });
  std::vector<SyncSample> intact = session;
  for (size_t i = lapse; i < lapse + 4; ++i) {
    intact[i].attitude_ok = intact[i].markers_ok = true;
    intact[i].R_WC = tilted;
  }
  for (size_t i = 0; i < session.size(); ++i) {
    seg.Add(session[i]);
    reference.Add(intact[i]);
  }
  seg.Flush();
  reference.Flush();

  ASSERT_EQ(whole.size(), 2u);
  ASSERT_EQ(poses.size(), 2u);
  EXPECT_EQ(seg.counters().dropped_markers, 0);
  // The same steady run, four samples fewer in its median, none of them the held attitude.
  EXPECT_EQ(poses[0].num_samples, whole[0].num_samples - 4);
  EXPECT_EQ(poses[0].start_utime, whole[0].start_utime);
  EXPECT_EQ(poses[0].end_utime, whole[0].end_utime);
  EXPECT_LT(LogSO3(poses[0].pose.R_WC * tilted.transpose()).norm(), 1e-12);
  EXPECT_NEAR(poses[0].pose.wrench[0][2], 10.0, 0.015);
  EXPECT_EQ(poses[1].num_samples, whole[1].num_samples);
}

TEST(PoseSegmenter, AttitudeForUnderHalfTheRunDropsThePose) {
  std::vector<SyncSample> session = MakeSession({{5.0, 10.0, false}}, 13);
  // The plateau's samples are 50..549: attitude only in its first and last 100.
  for (size_t i = 150; i < 450; ++i) session[i].attitude_ok = session[i].markers_ok = false;
  std::vector<SteadyPoseOut> poses;
  PoseSegmenter seg(SegmenterOptions{}, [&](const SteadyPoseOut& p) { poses.push_back(p); });
  for (const SyncSample& s : session) seg.Add(s);
  seg.Flush();
  EXPECT_TRUE(poses.empty());
  EXPECT_EQ(seg.counters().dropped_markers, 1);
}

}  // namespace
}  // namespace ftcal
