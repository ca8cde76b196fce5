// The offset tracker (issue #40) against the twin's drifted truth: the twin walks its tripod
// gait while its offsets step or ramp (RunOptions::offset_change), its frames go straight into
// the tracker as the devices would report them, and the tracked change is compared with the
// change the twin added, every second.
#include "ftcal/offset_tracker.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include "ftcal/config.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

config::Config SimConfig() { return LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt"); }

double Wrap(double a) { return a - 2.0 * M_PI * std::floor((a + M_PI) / (2.0 * M_PI)); }

// The bounds on the tracked error.
constexpr double kForceBoundN = 0.1;
constexpr double kTorqueBoundNm = 0.005;
// The report's gait: 0.08 Hz, so two cycles are 25 s.
constexpr double kTwoCyclesS = 2.0 / 0.08;

struct Sample {
  double t_s;
  std::array<Vec6, kNumLegs> error;  // tracked - true change
  std::array<Vec6, kNumLegs> sigma;
  std::array<int, kNumLegs> warn;
};

struct WalkRun {
  std::vector<Sample> samples;  // 1 Hz
  // At each window used: the leg's change then, against the truth at the window's mean time.
  std::vector<std::pair<Vec6, Vec6>> at_windows;  // error, sigma
  BalanceStats balance;
  OffsetTrackerCounters counters;
};

// Walks `walk_s` and feeds every frame to a tracker built on the truth calibration (the drift
// is then the whole change), as the bridges would stamp them: each transducer a little after
// the frame's instant, the servos 2 ms and motion capture 4 ms after. Servo angles are wrapped
// to (-pi, pi] as the Dynamixel bridge reports them.
WalkRun Walk(const BigAntTwin& twin, double walk_s, std::function<Vec6(int, double)> change,
             const OffsetTrackerOptions& options = OffsetTrackerOptions{}) {
  OffsetTracker tracker(options, twin.Truth());
  tracker.SetPhase(ExperimentPhase::kWalking);
  WalkRun run;
  RunOptions ro;
  ro.offset_change = change;
  std::array<Vec6, kNumLegs> truth_change{};
  double next_report = 1.0;
  const Vec6 calibration_sigma = (Vec6() << 0.02, 0.02, 0.02, 0.001, 0.001, 0.001).finished();
  const Vec6 min_change = (Vec6() << 0.2, 0.2, 0.2, 0.01, 0.01, 0.01).finished();
  auto report = [&](double t) {
    Sample s;
    s.t_s = t;
    const auto utime = static_cast<int64_t>(std::llround(t * 1e6));
    for (int k = 0; k < kNumLegs; ++k) {
      const LegDrift d = tracker.Drift(k, utime);
      s.error[k] = d.change - truth_change[k];
      s.sigma[k] = d.sigma;
      s.warn[k] = DriftBeyondCalibration(d, calibration_sigma, 3.0, min_change);
    }
    run.samples.push_back(s);
  };
  twin.TripodWalk(walk_s, ro, [&](const TwinFrame& f) {
    const auto t = static_cast<int64_t>(std::llround(f.t_s * 1e6));
    if (f.t_s >= next_report) {
      report(f.t_s);
      next_report += 1.0;
    }
    for (int k = 0; k < kNumLegs; ++k) {
      FtInput in;
      in.utime = t + 500 + 100 * k;
      in.leg = k;
      in.wrench = f.reading[k];
      ASSERT_TRUE(tracker.AddFt(in));
    }
    truth_change = f.offset_change;
    ServoInput servo;
    servo.utime = t + 2000;
    for (int k = 0; k < kNumLegs; ++k) servo.angle_rad[k] = Wrap(f.angle_rad[k]);
    ASSERT_TRUE(tracker.AddServo(servo));
    MocapInput mocap;
    mocap.utime = t + 4000;
    mocap.tracked = true;
    mocap.markers_ok = true;
    mocap.R_WC = RemoveHeading(f.R_GC);
    ASSERT_TRUE(tracker.AddMocap(mocap));
    for (const DriftWindow& w : tracker.TakeWindows()) {
      const LegDrift d = tracker.Drift(w.leg, w.utime);
      const Vec6 truth = change ? change(w.leg, 1e-6 * static_cast<double>(w.utime)) : Vec6::Zero();
      run.at_windows.emplace_back(d.change - truth, d.sigma);
    }
  });
  tracker.Finish();
  run.balance = tracker.balance_total();
  run.counters = tracker.counters();
  return run;
}

// The largest |error| per axis class over the samples from `from_s` on, every leg.
struct Worst {
  double force_n = 0.0, torque_nm = 0.0;
};
Worst WorstFrom(const WalkRun& run, double from_s) {
  Worst w;
  for (const Sample& s : run.samples) {
    if (s.t_s < from_s) continue;
    for (int k = 0; k < kNumLegs; ++k) {
      w.force_n = std::max(w.force_n, s.error[k].head<3>().cwiseAbs().maxCoeff());
      w.torque_nm = std::max(w.torque_nm, s.error[k].tail<3>().cwiseAbs().maxCoeff());
    }
  }
  return w;
}

TwinOptions Seeded(uint64_t seed) {
  TwinOptions o;
  o.seed = seed;
  return o;
}

TEST(OffsetTracker, UnloadedReadingIsTheForwardModelWithNoGroundWrench) {
  const BigAntTwin twin(SimConfig(), Seeded(3));
  const RobotCalibration& cal = twin.Truth();
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int i = 0; i < 200; ++i) {
    const int k = i % kNumLegs;
    const double angle = 7.0 * u(rng);
    const Mat3 R_WC = ExpSO3(Vec3(0.3 * u(rng), 0.3 * u(rng), 3.0 * u(rng)));
    const Vec6 expected = TransducerReading(cal, k, Vec6::Zero(), angle, R_WC) - cal.leg[k].offset;
    const Vec6 got = UnloadedReading(cal, k, angle, R_WC);
    ASSERT_LT((got - expected).cwiseAbs().maxCoeff(), 1e-12) << "leg " << k << " angle " << angle;
  }
}

TEST(OffsetTracker, StepOnOneLegWhileWalkingIsTrackedWithinTwoCycles) {
  const BigAntTwin twin(SimConfig(), Seeded(5));
  const double step_at_s = 40.0;
  const Vec6 step = (Vec6() << 2.0, -2.0, 2.0, 0.05, -0.05, 0.05).finished();
  const int knocked = 1;  // ML
  const WalkRun run = Walk(twin, 100.0, [&](int k, double t) {
    return k == knocked && t >= step_at_s ? step : Vec6::Zero();
  });
  // Before the step (after the first cycle) and from two cycles after it.
  const Worst before = WorstFrom(run, kTwoCyclesS);
  Worst after = WorstFrom(run, step_at_s + kTwoCyclesS);
  std::printf("step: worst error from two cycles after it %.4f N %.5f N*m (windows %lld)\n",
              after.force_n, after.torque_nm, static_cast<long long>(run.counters.windows_used));
  EXPECT_LE(after.force_n, kForceBoundN);
  EXPECT_LE(after.torque_nm, kTorqueBoundNm);
  // Until the step the error is the noise's: the window means of a few hundred samples.
  double worst_before_step = 0.0;
  for (const Sample& s : run.samples) {
    if (s.t_s < kTwoCyclesS || s.t_s >= step_at_s) continue;
    for (int k = 0; k < kNumLegs; ++k)
      worst_before_step = std::max(worst_before_step, s.error[k].head<3>().cwiseAbs().maxCoeff());
  }
  EXPECT_LE(worst_before_step, kForceBoundN);
  (void)before;
}

TEST(OffsetTracker, RampOverTenMinutesOfWalkingIsTrackedAfterTwoCycles) {
  const BigAntTwin twin(SimConfig(), Seeded(6));
  const Vec6 total = (Vec6() << 1.0, -1.0, 1.0, 0.03, -0.03, 0.03).finished();
  const double walk_s = 600.0;
  const WalkRun run =
      Walk(twin, walk_s, [&](int, double t) { return Vec6(total * std::min(1.0, t / walk_s)); });
  const Worst w = WorstFrom(run, kTwoCyclesS);
  std::printf("ramp: worst error after two cycles %.4f N %.5f N*m\n", w.force_n, w.torque_nm);
  EXPECT_LE(w.force_n, kForceBoundN);
  EXPECT_LE(w.torque_nm, kTorqueBoundNm);
  // The balance of the six corrected wrenches with the tracked offsets is as good as the same
  // walk's without any drift (the issue: within 1.2 x).
  const WalkRun still = Walk(twin, walk_s, {});
  std::printf(
      "balance rms with tracking %.4f N %.5f N*m; without drift %.4f N %.5f N*m; "
      "drifting, untracked %.4f N %.5f N*m\n",
      run.balance.ForceRmsN(1), run.balance.TorqueRmsNm(1), still.balance.ForceRmsN(1),
      still.balance.TorqueRmsNm(1), run.balance.ForceRmsN(0), run.balance.TorqueRmsNm(0));
  ASSERT_GT(run.balance.count, 1000);
  EXPECT_LE(run.balance.ForceRmsN(1), 1.2 * still.balance.ForceRmsN(1));
  EXPECT_LE(run.balance.TorqueRmsNm(1), 1.2 * still.balance.TorqueRmsNm(1));
  // And untracked the drift shows in it.
  EXPECT_GT(run.balance.ForceRmsN(0), 1.5 * still.balance.ForceRmsN(0));
}

TEST(OffsetTracker, NoDriftNoWarningAndAStepWarns) {
  const BigAntTwin twin(SimConfig(), Seeded(8));
  const WalkRun still = Walk(twin, 300.0, {});
  int warnings = 0;
  for (const Sample& s : still.samples)
    for (int k = 0; k < kNumLegs; ++k) warnings += s.warn[k] != 0;
  EXPECT_EQ(warnings, 0);
  const Vec6 step = (Vec6() << 2.0, 0.0, 0.0, 0.0, 0.0, 0.05).finished();
  const WalkRun knocked =
      Walk(twin, 100.0, [&](int k, double t) { return k == 4 && t >= 30.0 ? step : Vec6::Zero(); });
  const Sample& last = knocked.samples.back();
  EXPECT_EQ(last.warn[4], 1 | 1 << 5);  // MR fx and tz, nothing else
  for (int k = 0; k < kNumLegs; ++k) {
    if (k != 4) {
      EXPECT_EQ(last.warn[k], 0) << "leg " << k;
    }
  }
}

// The issue: +-2 sigma of the tracked offset covers the drifted truth 85-99 % of the time, over
// at least ten seeds. Taken where the tracker estimates (each window it uses, against the truth
// at the window's mean time); between windows its sigma is a prediction of how far the offsets
// may have wandered, not an estimate.
TEST(OffsetTracker, TwoSigmaCoversTheDriftingTruthOverTenSeeds) {
  int covered[2] = {0, 0}, total[2] = {0, 0};
  const Vec6 ramp = (Vec6() << 1.0, -1.0, 1.0, 0.03, -0.03, 0.03).finished();
  for (uint64_t seed = 1; seed <= 10; ++seed) {
    const BigAntTwin twin(SimConfig(), Seeded(100 + seed));
    const WalkRun run = Walk(twin, 150.0, [&](int, double t) { return Vec6(ramp * t / 600.0); });
    for (const auto& [e, sigma] : run.at_windows) {
      for (int i = 0; i < 6; ++i) {
        ++total[i / 3];
        covered[i / 3] += std::abs(e[i]) <= 2.0 * sigma[i];
      }
    }
  }
  const double force = 100.0 * covered[0] / total[0], torque = 100.0 * covered[1] / total[1];
  std::printf("+-2 sigma coverage over 10 seeds: force %.1f %% torque %.1f %% (%d windows)\n",
              force, torque, total[0] / 3);
  EXPECT_GE(force, 85.0);
  EXPECT_LE(force, 99.0);
  EXPECT_GE(torque, 85.0);
  EXPECT_LE(torque, 99.0);
}

// The leg's inertia must not be taken for an offset: a lifted leg that speeds up (4 rad/s^2,
// twice the default limit) while its transducer also feels the torque and force that takes
// (J alpha about the shaft, m r alpha along the foot's path), runs, and slows down with its foot
// on the ground, is tracked at zero change; with the acceleration gate opened the same data pull
// the estimate off.
TEST(OffsetTracker, ShaftAccelerationIsNotTakenForAnOffset) {
  TwinOptions o = Seeded(9);
  const BigAntTwin twin(SimConfig(), o);
  const RobotCalibration& cal = twin.Truth();
  const int k = 2;  // FL
  constexpr double kAlpha = 4.0, kInertia = 0.05, kMassLever = 0.03;
  // Per 4 s: 0.5 s speeding up, 2 s at 2 rad/s, 0.5 s slowing down and 1 s still on the ground.
  auto profile = [&](double t, double* angle, double* alpha) {
    const double period = 4.0, w = kAlpha * 0.5;
    const double n = std::floor(t / period), u = t - n * period;
    const double per_period = 0.5 * kAlpha * 0.25 * 2 + w * 2.0;
    double a = n * per_period;
    if (u < 0.5) {
      a += 0.5 * kAlpha * u * u;
      *alpha = kAlpha;
    } else if (u < 2.5) {
      a += 0.5 * kAlpha * 0.25 + w * (u - 0.5);
      *alpha = 0.0;
    } else if (u < 3.0) {
      const double v = u - 2.5;
      a += 0.5 * kAlpha * 0.25 + w * 2.0 + w * v - 0.5 * kAlpha * v * v;
      *alpha = -kAlpha;
    } else {
      a += per_period;
      *alpha = 0.0;
    }
    *angle = a;
  };
  auto run = [&](double accel_limit) {
    OffsetTrackerOptions options;
    options.max_shaft_accel_rad_s2 = accel_limit;
    OffsetTracker tracker(options, cal);
    std::mt19937_64 rng(3);
    std::normal_distribution<double> noise(0.0, 1.0);
    for (int i = 0; i < 6000; ++i) {
      const double t = 0.01 * i;
      double angle = 0.0, alpha = 0.0;
      profile(t, &angle, &alpha);
      const auto utime = static_cast<int64_t>(std::llround(t * 1e6)) + 1'000'000;
      ServoInput servo;
      servo.utime = utime + 2000;
      servo.angle_rad[k] = Wrap(angle);
      tracker.AddServo(servo);
      MocapInput mocap;
      mocap.utime = utime + 4000;
      mocap.tracked = true;
      tracker.AddMocap(mocap);
      FtInput in;
      in.utime = utime;
      in.leg = k;
      in.wrench = UnloadedReading(cal, k, angle, Mat3::Identity()) + cal.leg[k].offset;
      in.wrench[0] += kMassLever * alpha;                  // tangential: m r alpha
      in.wrench[4] += kInertia * alpha;                    // about the shaft (ft_k's y)
      if (std::fmod(t, 4.0) >= 2.5) in.wrench[2] += 20.0;  // the foot on the ground
      for (int c = 0; c < 6; ++c) in.wrench[c] += (c < 3 ? 0.05 : 0.002) * noise(rng);
      tracker.AddFt(in);
    }
    tracker.Finish();
    return tracker.Drift(k, tracker.newest_utime());
  };
  const LegDrift gated = run(2.0);
  const LegDrift open = run(1e6);
  std::printf("accelerating leg: gated ty %.5f N*m fx %.4f N; ungated ty %.5f fx %.4f\n",
              gated.change[4], gated.change[0], open.change[4], open.change[0]);
  ASSERT_GT(gated.windows, 5);
  EXPECT_LE(gated.change.head<3>().cwiseAbs().maxCoeff(), kForceBoundN / 4);
  EXPECT_LE(gated.change.tail<3>().cwiseAbs().maxCoeff(), kTorqueBoundNm);
  // Opened, the accelerating bins enter the windows: the estimate is pulled far off.
  EXPECT_GT(std::abs(open.change[4]), 4 * kTorqueBoundNm);
}

// --apply's policy on hand-made drifts: a change is applied only when the tracker is sure of it
// (factor x its sigma) and it is beyond the calibration's own sigma and the floor.
TEST(DriftApply, OnlyASureChangeBeyondTheCalibrationIsSignificant) {
  const Vec6 min_change = (Vec6() << 0.2, 0.2, 0.2, 0.01, 0.01, 0.01).finished();
  const Vec6 cal_sigma = (Vec6() << 0.5, 0.0, 0.0, 0.0, 0.0, 0.0).finished();
  LegDrift d;
  d.windows = 3;
  d.sigma = Vec6::Constant(0.05);
  d.change << 0.4, 0.3, -0.24, 0.009, 0.0, 0.0;
  // fx: 0.4 < the calibration's 0.5; fy: 0.3 > 5 x 0.05 and > 0.2; fz: |-0.24| < 5 x 0.05;
  // tx: 0.009 < its floor 0.01 (and < 5 x 0.05).
  EXPECT_EQ(DriftSignificant(d, cal_sigma, 5.0, min_change), 1 << 1);
  d.change[0] = 0.6;  // beyond the calibration's 0.5 and 5 x 0.05
  EXPECT_EQ(DriftSignificant(d, cal_sigma, 5.0, min_change), (1 << 0) | (1 << 1));
  // A tracker that is not sure (its prior's sigma) finds nothing significant.
  d.sigma = Vec6::Constant(5.0);
  EXPECT_EQ(DriftSignificant(d, cal_sigma, 5.0, min_change), 0);
}

TEST(DriftApply, LegsWithASignificantChangeAtMostOncePerInterval) {
  DriftApplyPolicy policy;
  policy.factor = 5.0;
  policy.min_change = (Vec6() << 0.2, 0.2, 0.2, 0.01, 0.01, 0.01).finished();
  policy.min_interval_s = 30.0;
  std::array<Vec6, kNumLegs> cal_sigma;
  cal_sigma.fill(Vec6::Zero());  // the twin's truth: no sigma, the floor decides
  std::array<LegDrift, kNumLegs> drift{};
  const int mr = *LegIndex("MR"), hl = *LegIndex("HL");
  for (LegDrift& d : drift) {
    d.windows = 4;
    d.sigma = Vec6::Constant(0.02);
    d.change = Vec6::Constant(0.05);  // sure, but within the floor: not worth a calibration
  }
  const int64_t t0 = 1'000'000'000;
  EXPECT_EQ(LegsToApply(drift, cal_sigma, policy, t0, 0), 0);
  drift[mr].change[2] = 2.0;
  EXPECT_EQ(LegsToApply(drift, cal_sigma, policy, t0, 0), 1 << mr);
  // A leg without a window is never applied, whatever its numbers.
  drift[hl].change[2] = 2.0;
  drift[hl].windows = 0;
  EXPECT_EQ(LegsToApply(drift, cal_sigma, policy, t0, 0), 1 << mr);
  // Applied at t0: nothing until 30 s later, then again.
  EXPECT_EQ(LegsToApply(drift, cal_sigma, policy, t0 + 29'999'999, t0), 0);
  EXPECT_EQ(LegsToApply(drift, cal_sigma, policy, t0 + 30'000'000, t0), 1 << mr);
}

}  // namespace
}  // namespace ftcal
