// The corrector engine: readings made by the forward model (TransducerReading) from known
// ground wrenches come back as those wrenches; stale inputs are flagged; no calibration, no
// output; a new calibration replaces the old.
#include "ftcal/corrector.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "standing_test_data.h"

namespace ftcal {
namespace {

using testdata::kDeg;

// A BigAnt-like calibration with every parameter away from its trivial value (standing_test's
// truth, with a full mounting error).
RobotCalibration MakeCalibration(uint64_t seed) {
  RobotCalibration cal = testdata::MakeTruth(seed, testdata::Mounting::kFull);
  cal.g0 = 9.80665;
  return cal;
}

Vec6 RandomGroundWrenchC(std::mt19937_64& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  Vec6 w;
  w << 3 * n(rng), 3 * n(rng), 13 + 4 * n(rng), 2 * n(rng), 2 * n(rng), 0.1 * n(rng);
  return w;
}

Vec6 ToW(const Mat3& R_WC, const Vec6& w_C) {
  return TransformWrench(Pose3(R_WC, Vec3::Zero()), w_C);
}

std::array<double, kNumLegs> Fill(double a) {
  std::array<double, kNumLegs> x;
  x.fill(a);
  return x;
}

TEST(Corrector, NoiseFreeReadingsReproduceTheTrueGroundWrenches) {
  const RobotCalibration cal = MakeCalibration(3);
  Corrector c({});
  c.SetCalibration(cal, 42);
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::array<Vec6, kNumLegs> truth_W;
  for (int frame = 0; frame < 200; ++frame) {
    const int64_t t = 5'000'000 + 10'000 * static_cast<int64_t>(frame);
    // Angles over several turns (the phase wraps), attitude tilted up to ~10 deg.
    std::array<double, kNumLegs> angle;
    for (int k = 0; k < kNumLegs; ++k) angle[k] = 8.0 * u(rng);
    const Mat3 R_WC = RotationFromRollPitchYaw(0.15 * u(rng), 0.15 * u(rng), 0.0);
    c.AddServo({t, angle});
    c.AddMocap({t, true, R_WC, true});
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 w_C = RandomGroundWrenchC(rng);
      truth_W[k] = ToW(R_WC, w_C);
      const Vec6 reading = TransducerReading(cal, k, w_C, angle[k], R_WC);
      const auto out = c.AddFt({t, k, reading, 0}, false);
      ASSERT_TRUE(out);
      EXPECT_EQ(out->updated_leg, k);
      EXPECT_EQ(out->utime, t);
      EXPECT_EQ(out->calibration_version, 42);
      EXPECT_LT((out->wrench_W[k] - truth_W[k]).cwiseAbs().maxCoeff(), 1e-9)
          << "frame " << frame << " leg " << k;
      if (k == kNumLegs - 1) {  // all six legs of this frame are in
        Vec6 sum = Vec6::Zero();
        for (const Vec6& w : truth_W) sum += w;
        EXPECT_LT((out->total_W - sum).cwiseAbs().maxCoeff(), 1e-9);
        Vec6 expect_residual = sum;
        expect_residual[2] -= cal.TotalWeightN();
        EXPECT_LT((out->residual_W - expect_residual).cwiseAbs().maxCoeff(), 1e-9);
        EXPECT_EQ(out->flags, 0);
      }
    }
  }
}

// The precomputed form the calibrator's walking figures use: the same bits as GroundWrenchW,
// and the ground's wrench the forward model was given.
TEST(GroundWrenchModel, IsGroundWrenchWBitForBitAndInvertsTheForwardModel) {
  std::mt19937_64 rng(23);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (uint64_t seed : {1, 4, 9}) {
    const RobotCalibration cal = MakeCalibration(seed);
    const GroundWrenchModel model(cal);
    for (int i = 0; i < 50; ++i) {
      const Mat3 R_WC = RotationFromRollPitchYaw(0.2 * u(rng), 0.2 * u(rng), 3.0 * u(rng));
      for (int k = 0; k < kNumLegs; ++k) {
        const double angle = 8.0 * u(rng);
        const Vec6 w_C = RandomGroundWrenchC(rng);
        const Vec6 reading = TransducerReading(cal, k, w_C, angle, R_WC);
        const Vec6 got = model.W(k, reading, angle, R_WC);
        const Vec6 expect = GroundWrenchW(cal, k, reading, angle, R_WC);
        for (int c = 0; c < 6; ++c) EXPECT_EQ(got[c], expect[c]) << "leg " << k << " comp " << c;
        EXPECT_LT((got - ToW(R_WC, w_C)).cwiseAbs().maxCoeff(), 1e-9) << "leg " << k;
      }
    }
  }
}

TEST(Corrector, AgreesWithGroundWrenchWOnTheInterpolatedAngle) {
  const RobotCalibration cal = MakeCalibration(5);
  Corrector c({});
  c.SetCalibration(cal, 1);
  const Mat3 R_WC = RotationFromRollPitchYaw(0.05, -0.08, 0.0);
  c.AddMocap({1'000'000, true, R_WC, true});
  c.AddServo({1'000'000, Fill(0.2)});
  c.AddServo({1'010'000, Fill(0.6)});
  Vec6 w_m;
  w_m << 1, -2, 30, 0.4, -0.3, 0.05;
  const auto out = c.AddFt({1'002'500, 4, w_m, 0}, false);  // alpha 0.25: angle 0.3
  ASSERT_TRUE(out);
  const Vec6 expect = GroundWrenchW(cal, 4, w_m, 0.3, R_WC);
  EXPECT_LT((out->wrench_W[4] - expect).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_NEAR(out->servo_age_s, 0.0025, 1e-12);
  EXPECT_NEAR(out->mocap_age_s, 0.0025, 1e-12);
}

TEST(Corrector, PublishesNothingWithoutACalibration) {
  Corrector c({});
  c.AddServo({0, Fill(0.0)});
  EXPECT_FALSE(c.AddFt({1000, 0, Vec6::Ones(), 0}, false));
  EXPECT_FALSE(c.has_calibration());
  EXPECT_EQ(c.counters().no_calibration, 1);
  c.SetCalibration(MakeCalibration(1), 7);
  EXPECT_TRUE(c.AddFt({2000, 0, Vec6::Ones(), 0}, false));
}

TEST(Corrector, FlagsStaleInputsAndMissingLegsAndAssumesLevelWithoutFreshMocap) {
  const RobotCalibration cal = MakeCalibration(2);
  CorrectorOptions opt;
  opt.max_ft_age_s = 0.05;
  opt.max_servo_age_s = 0.05;
  opt.max_mocap_age_s = 0.05;
  Corrector c(opt);
  c.SetCalibration(cal, 1);
  Vec6 w;
  w << 0.5, 0.2, 20, 0.1, 0.1, 0.0;

  // No servo state, no mocap, one leg only.
  auto out = c.AddFt({1'000'000, 0, w, 0}, false);
  ASSERT_TRUE(out);
  EXPECT_EQ(out->flags, kFlagStaleFt | kFlagStaleServo | kFlagStaleMocap);
  EXPECT_TRUE(out->wrench_W[0].array().isNaN().all()) << "no phase: no number";
  EXPECT_TRUE(out->wrench_W[1].array().isNaN().all());
  EXPECT_EQ(out->ft_age_s[1], -1.0);
  EXPECT_EQ(out->servo_age_s, -1.0);
  EXPECT_EQ(out->mocap_age_s, -1.0);

  // Everything fresh for every leg: no flags.
  const Mat3 tilt = RotationFromRollPitchYaw(0.1, 0, 0);
  c.AddServo({1'100'000, Fill(0.3)});
  c.AddMocap({1'100'000, true, tilt, true});
  for (int k = 0; k < kNumLegs; ++k) out = c.AddFt({1'100'000 + k, k, w, 0}, false);
  ASSERT_TRUE(out);
  EXPECT_EQ(out->flags, 0);
  EXPECT_LT((out->wrench_W[2] - GroundWrenchW(cal, 2, w, 0.3, tilt)).cwiseAbs().maxCoeff(), 1e-12);

  // 80 ms later, only leg 2 reports: the other legs, the servo state and the mocap are stale;
  // the attitude is taken level.
  out = c.AddFt({1'180'000, 2, w, 0}, false);
  ASSERT_TRUE(out);
  EXPECT_EQ(out->flags, kFlagStaleFt | kFlagStaleServo | kFlagStaleMocap);
  EXPECT_NEAR(out->ft_age_s[0], 0.08, 1e-9);
  EXPECT_NEAR(out->servo_age_s, 0.08, 1e-9);
  EXPECT_NEAR(out->mocap_age_s, 0.08, 1e-9);
  EXPECT_LT(
      (out->wrench_W[2] - GroundWrenchW(cal, 2, w, 0.3, Mat3::Identity())).cwiseAbs().maxCoeff(),
      1e-12);

  // An untracked frame is no attitude either, however fresh.
  c.AddMocap({1'190'000, false, Mat3::Identity(), false});
  c.AddServo({1'190'000, Fill(0.3)});
  out = c.AddFt({1'190'000, 2, w, 0}, true);
  ASSERT_TRUE(out);
  EXPECT_TRUE(out->flags & kFlagStaleMocap);
  EXPECT_FALSE(out->flags & kFlagStaleServo);
  EXPECT_TRUE(out->flags & kFlagSaturated);
}

TEST(Corrector, DropsOutOfOrderAndNonFiniteSamples) {
  Corrector c({});
  c.SetCalibration(MakeCalibration(4), 1);
  c.AddServo({0, Fill(0.0)});
  EXPECT_TRUE(c.AddFt({1000, 1, Vec6::Ones(), 0}, false));
  EXPECT_FALSE(c.AddFt({1000, 1, Vec6::Ones(), 0}, false));
  Vec6 nan = Vec6::Ones();
  nan[2] = std::nan("");
  EXPECT_FALSE(c.AddFt({2000, 1, nan, 0}, false));
  EXPECT_FALSE(c.AddServo({0, Fill(1.0)}));
  EXPECT_FALSE(c.AddServo({5, Fill(std::nan(""))}));
  EXPECT_EQ(c.counters().out_of_order, 2);
  EXPECT_EQ(c.counters().non_finite, 2);
}

TEST(Corrector, ANewCalibrationReplacesTheOldAndForgetsWrenchesCorrectedWithIt) {
  const RobotCalibration a = MakeCalibration(8), b = MakeCalibration(9);
  Corrector c({});
  c.SetCalibration(a, 1);
  c.AddServo({0, Fill(0.1)});
  c.AddMocap({0, true, Mat3::Identity(), true});
  Vec6 w;
  w << 1, 1, 25, 0, 0, 0;
  for (int k = 0; k < kNumLegs; ++k) c.AddFt({1000, k, w, 0}, false);
  c.SetCalibration(b, 2);
  const auto out = c.AddFt({2000, 0, w, 0}, false);
  EXPECT_EQ(out->calibration_version, 2);
  EXPECT_LT(
      (out->wrench_W[0] - GroundWrenchW(b, 0, w, 0.1, Mat3::Identity())).cwiseAbs().maxCoeff(),
      1e-12);
  EXPECT_TRUE(out->wrench_W[1].array().isNaN().all());
  EXPECT_TRUE(out->flags & kFlagStaleFt);
}

// The sums are of one instant: each leg's samples come a datagram (7) at a time and the legs'
// clocks are apart by up to 60 us of a 143 us period; a sum at each of leg 0's sample times
// takes every leg's sample of that instant, whatever order the legs' batches arrive in. Each
// sample's wrench differs, so a sum mixing instants would show. Its views carry each sample's
// own flags (LegWrenchOf) and every summed sample's (the sum's).
TEST(Corrector, SumsAreOfOneInstantWhicheverOrderTheLegsBatchesArriveIn) {
  const RobotCalibration cal = MakeCalibration(10);
  constexpr int kBatch = 7, kBatches = 6, kSamples = kBatch * kBatches;
  constexpr int64_t kPeriodUs = 143, kT0 = 1'000'000;
  auto sample = [](int k, int j) {
    Vec6 w;
    w << 1 + j, 2 - 0.5 * j, 25 + 0.25 * j * k, 0.1 * k, 0.2, 0.3 + 0.01 * j;
    return FtInput{kT0 + j * kPeriodUs + 10 * k, k, w, 0};
  };
  for (const bool reverse : {false, true}) {
    SCOPED_TRACE(reverse ? "legs' batches in reverse order" : "legs' batches in leg order");
    Corrector c({});
    c.SetCalibration(cal, 3);
    c.AddServo({kT0 - 1000, Fill(0.2)});
    c.AddServo({kT0 + 100'000, Fill(0.2)});
    c.AddMocap({kT0 - 1000, true, Mat3::Identity(), true});
    std::array<std::array<Vec6, kSamples>, kNumLegs> corrected;
    std::vector<WrenchSum> sums;
    for (int b = 0; b < kBatches; ++b) {
      for (int i = 0; i < kNumLegs; ++i) {
        const int k = reverse ? kNumLegs - 1 - i : i;
        for (int j = b * kBatch; j < (b + 1) * kBatch; ++j) {
          const auto out = c.AddFt(sample(k, j), k == 2 && j == 9);
          ASSERT_TRUE(out);
          const LegWrench leg = LegWrenchOf(*out);
          EXPECT_EQ(leg.leg, k);
          EXPECT_EQ(leg.utime, sample(k, j).utime);
          EXPECT_EQ(leg.flags, k == 2 && j == 9 ? kFlagSaturated : 0);
          corrected[k][j] = leg.wrench_W;
          WrenchSum sum;
          while (c.NextSum(&sum)) sums.push_back(sum);
        }
      }
    }
    // Every instant of leg 0 whose six samples are in: all of them.
    ASSERT_EQ(sums.size(), static_cast<size_t>(kSamples));
    for (int j = 0; j < kSamples; ++j) {
      const WrenchSum& sum = sums[static_cast<size_t>(j)];
      Vec6 total = Vec6::Zero();
      for (int k = 0; k < kNumLegs; ++k) total += corrected[k][j];
      EXPECT_EQ(sum.utime, sample(0, j).utime);
      EXPECT_EQ(sum.total_W, total) << "instant " << j;
      EXPECT_EQ(sum.residual_W[2], total[2] - cal.TotalWeightN());
      EXPECT_EQ(sum.calibration_version, 3);
      EXPECT_NEAR(sum.oldest_ft_age_s, 50e-6, 1e-12);  // leg 5, 50 us after leg 0
      EXPECT_EQ(sum.flags, j == 9 ? kFlagSaturated : 0) << "instant " << j;
    }
  }
}

// At the end of the input the instants still waiting are summed: here leg 3 samples 20 us before
// the pace leg, so the pace leg's last instant waits for a leg-3 sample that never comes (a
// replay's last sums were lost so). With input_ended it is made from leg 3's last sample, once.
TEST(Corrector, TheLastInstantsAreSummedWhenTheInputEnds) {
  const RobotCalibration cal = MakeCalibration(10);
  constexpr int kSamples = 20;
  constexpr int64_t kPeriodUs = 1000, kT0 = 1'000'000;
  auto sample = [](int k, int j) {
    Vec6 w;
    w << 1 + j, 2, 25 + k, 0.1 * k, 0.2, 0.3;
    return FtInput{kT0 + j * kPeriodUs + (k == 3 ? -20 : 10 * k), k, w, 0};
  };
  Corrector c({});
  c.SetCalibration(cal, 3);
  c.AddServo({kT0 - 1000, Fill(0.2)});
  c.AddMocap({kT0 - 1000, true, Mat3::Identity(), true});
  std::array<std::array<Vec6, kSamples>, kNumLegs> corrected;
  std::vector<WrenchSum> sums;
  WrenchSum sum;
  for (int j = 0; j < kSamples; ++j) {
    for (int k = 0; k < kNumLegs; ++k) {
      const auto out = c.AddFt(sample(k, j), false);
      ASSERT_TRUE(out);
      corrected[k][j] = LegWrenchOf(*out).wrench_W;
      while (c.NextSum(&sum)) sums.push_back(sum);
    }
  }
  ASSERT_EQ(sums.size(), static_cast<size_t>(kSamples - 1)) << "the last instant waits for leg 3";
  while (c.NextSum(&sum, /*input_ended=*/true)) sums.push_back(sum);
  ASSERT_EQ(sums.size(), static_cast<size_t>(kSamples));
  const WrenchSum& last = sums.back();
  EXPECT_EQ(last.utime, sample(0, kSamples - 1).utime);
  Vec6 total = Vec6::Zero();
  for (int k = 0; k < kNumLegs; ++k) total += corrected[k][kSamples - 1];
  EXPECT_EQ(last.total_W, total);
  EXPECT_NEAR(last.oldest_ft_age_s, 50e-6, 1e-12);  // leg 5, 50 us after leg 0
  EXPECT_EQ(last.flags, 0);
  EXPECT_FALSE(c.NextSum(&sum, /*input_ended=*/true)) << "each instant is summed once";
}

// A silent leg is not waited for: once its latest sample is max_ft_age_s older than the newest,
// the sums go on without it, flagged stale; when leg 0 is the silent one, the next leg sets
// the pace. Before that, no sum is made past the silent leg's last sample.
TEST(Corrector, ASilentLegIsNotWaitedForAndItsSumsAreFlaggedStale) {
  const RobotCalibration cal = MakeCalibration(10);
  CorrectorOptions opt;
  opt.max_ft_age_s = 0.05;
  for (const int silent : {0, 3}) {
    SCOPED_TRACE("leg " + std::to_string(silent) + " falls silent");
    Corrector c(opt);
    c.SetCalibration(cal, 3);
    Vec6 w;
    w << 1, 2, 25, 0.1, 0.2, 0.3;
    std::vector<WrenchSum> sums;
    const int64_t t0 = 1'000'000, period = 1000, stop = t0 + 10 * period;
    for (int64_t t = t0; t < t0 + 100 * period; t += period) {
      c.AddServo({t, Fill(0.2)});
      c.AddMocap({t, true, Mat3::Identity(), true});
      for (int k = 0; k < kNumLegs; ++k) {
        if (k == silent && t > stop) continue;
        ASSERT_TRUE(c.AddFt({t + k, k, w, 0}, false));
        WrenchSum sum;
        while (c.NextSum(&sum)) sums.push_back(sum);
      }
    }
    ASSERT_FALSE(sums.empty());
    const int pace = silent == 0 ? 1 : 0;
    bool resumed = false;
    for (size_t i = 0; i < sums.size(); ++i) {
      const WrenchSum& s = sums[i];
      if (i > 0) {
        EXPECT_GT(s.utime, sums[i - 1].utime);
      }
      if (s.utime <= stop + silent) {
        EXPECT_EQ(s.flags & kFlagStaleFt, 0) << "at " << s.utime;
        continue;
      }
      // Past the silent leg's last sample: made once it counts as silent, from its last
      // sample, flagged when that is more than max_ft_age_s from the instant.
      EXPECT_EQ((s.utime - t0 - pace) % period, 0) << "an instant of the pace leg " << pace;
      const bool stale = 1e-6 * static_cast<double>(s.utime - stop - silent) > opt.max_ft_age_s;
      EXPECT_EQ((s.flags & kFlagStaleFt) != 0, stale) << "at " << s.utime;
      resumed = true;
    }
    EXPECT_TRUE(resumed) << "no sum after leg " << silent << " fell silent";
    EXPECT_GT(sums.back().oldest_ft_age_s, opt.max_ft_age_s);
    // Instants between the silent leg's last sample and its being silent are summed late, not
    // lost: one sum per pace-leg sample over the whole run (leg 0's 11, then leg 1's 90 from
    // its sample 1 us after leg 0's last, when leg 0 is the one that stops).
    EXPECT_EQ(sums.size(), silent == 0 ? 11u + 90u : 100u);
  }
}

TEST(Corrector, RefusesANonFiniteCalibrationAndKeepsTheOldOne) {
  Corrector c({});
  const RobotCalibration good = MakeCalibration(1);
  c.SetCalibration(good, 1);
  RobotCalibration bad = good;
  bad.leg[3].com.z.a = std::nan("");
  EXPECT_THROW(
      {
        try {
          c.SetCalibration(bad, 2);
        } catch (const std::invalid_argument& e) {
          EXPECT_NE(std::string(e.what()).find("HR"), std::string::npos) << e.what();
          throw;
        }
      },
      std::invalid_argument);
  EXPECT_EQ(c.calibration_version(), 1);
}

}  // namespace
}  // namespace ftcal

namespace ftcal {
namespace {

// The calibration's servo delay (docs/method.md "Latencies"): servo states stamped 16 ms late
// correct the readings exactly once the calibration says so, and not without it.
TEST(Corrector, AppliesTheCalibrationsServoDelay) {
  RobotCalibration cal = testdata::MakeTruth(7, testdata::Mounting::kFull);
  cal.g0 = 9.80665;
  std::mt19937_64 rng(5);
  auto worst_error = [&](double delay_s) {
    cal.servo_delay_s = delay_s;
    Corrector c({});
    c.SetCalibration(cal, 1);
    double worst = 0.0;
    for (int frame = 0; frame < 100; ++frame) {
      const int64_t t = 2'000'000 + 10'000 * static_cast<int64_t>(frame);
      const double angle = 3.0 * 1e-6 * static_cast<double>(t - 2'000'000);  // 3 rad/s
      std::array<double, kNumLegs> a;
      a.fill(angle);
      c.AddServo({t + 16'000, a});  // reported 16 ms after its instant
      c.AddMocap({t, true, Mat3::Identity(), true});
      if (frame < 5) continue;
      // A transducer sample 5 ms after instant `t`: its angle is between two states.
      const int64_t ts = t - 45'000;
      const double at = 3.0 * 1e-6 * static_cast<double>(ts - 2'000'000);
      const Vec6 w_C = RandomGroundWrenchC(rng);
      const Vec6 reading = TransducerReading(cal, 0, w_C, at, Mat3::Identity());
      const auto out = c.AddFt({ts, 0, reading, 0}, false);
      if (!out) continue;
      worst = std::max(worst, (out->wrench_W[0] - w_C).cwiseAbs().maxCoeff());
    }
    return worst;
  };
  EXPECT_LT(worst_error(0.016), 1e-9);
  EXPECT_GT(worst_error(0.0), 1e-4);  // the same stream read without the delay is wrong
}

}  // namespace
}  // namespace ftcal
