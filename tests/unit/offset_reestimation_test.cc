// Offset drift re-estimation against data from known (drifted) offsets.
#include "ftcal/offset_reestimation.h"

#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include <gtest/gtest.h>

#include "standing_test_data.h"

namespace ftcal {
namespace {

using namespace testdata;  // NOLINT: the generator of this test family

// Tripods of the alternating gait: HL, FL, MR and ML, HR, FR.
constexpr std::array<bool, kNumLegs> kTripodA = {true, false, true, false, true, false};
constexpr std::array<bool, kNumLegs> kTripodB = {false, true, false, true, false, true};

// The truth after six months: every offset component moved (up to 10 N, 0.3 N*m).
RobotCalibration Drifted(const RobotCalibration& cal, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  RobotCalibration out = cal;
  for (LegCalibration& l : out.leg) {
    l.offset +=
        (Vec6() << 10 * u(rng), 10 * u(rng), 10 * u(rng), 0.3 * u(rng), 0.3 * u(rng), 0.3 * u(rng))
            .finished();
  }
  return out;
}

// Single raw samples (no medians) with the `lifted` legs in the air: their readings are their
// own gravity plus offset; the others carry an arbitrary ground load the method must not use.
std::vector<LoadSample> TripodSamples(const RobotCalibration& truth,
                                      const std::array<bool, kNumLegs>& lifted, int count,
                                      double force_noise_n, double torque_noise_nm, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> n01(0.0, 1.0);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::vector<LoadSample> out;
  for (int s = 0; s < count; ++s) {
    LoadSample sample;
    sample.R_WC = RotationFromRollPitchYaw(3 * kDeg * u(rng), 3 * kDeg * u(rng), 0.0);
    for (int k = 0; k < kNumLegs; ++k) {
      sample.angle_rad[k] = M_PI * u(rng);
      sample.unloaded[k] = lifted[k];
      Vec6 w_gc = Vec6::Zero();
      if (!lifted[k]) w_gc << 3 * u(rng), 3 * u(rng), 25 + 5 * u(rng), u(rng), u(rng), u(rng);
      sample.wrench[k] = TransducerReading(truth, k, w_gc, sample.angle_rad[k], sample.R_WC);
      for (int i = 0; i < 6; ++i) {
        sample.wrench[k][i] += (i < 3 ? force_noise_n : torque_noise_nm) * n01(rng);
      }
    }
    out.push_back(sample);
  }
  return out;
}

std::vector<LoadSample> Concat(std::vector<LoadSample> a, const std::vector<LoadSample>& b) {
  a.insert(a.end(), b.begin(), b.end());
  return a;
}

TEST(OffsetReestimation, NoiseFreeStandingAndBothTripodsRecoverEveryOffsetExactly) {
  const RobotCalibration before = MakeTruth(71, Mounting::kFull);
  const RobotCalibration now = Drifted(before, 72);
  const auto standing = MakePoses(now, GridSubset(40, 73), Noise{0, 0, 0, 0}, false, 74);
  const auto samples =
      Concat(TripodSamples(now, kTripodA, 5, 0, 0, 75), TripodSamples(now, kTripodB, 5, 0, 0, 76));
  const OffsetReestimate r = ReestimateOffsets(before, standing, samples, {});
  EXPECT_EQ(r.rank, 36);
  EXPECT_TRUE(r.undetermined.empty());
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_LT((r.offset[k] - now.leg[k].offset).cwiseAbs().maxCoeff(), 1e-9) << kLegNames[k];
    for (int i = 0; i < 6; ++i) EXPECT_TRUE(r.determined[k][i]);
  }
  const RobotCalibration applied = ApplyOffsetReestimate(before, r);
  EXPECT_LT((applied.leg[3].offset - now.leg[3].offset).norm(), 1e-9);
}

TEST(OffsetReestimation, NoisyDataRecoverOffsetsWithConsistentSigma) {
  const RobotCalibration before = MakeTruth(81, Mounting::kFull);
  const RobotCalibration now = Drifted(before, 82);
  const auto standing = MakePoses(now, GridSubset(60, 83), kReportNoise, false, 84);
  const auto samples = Concat(TripodSamples(now, kTripodA, 100, 0.05, 0.002, 85),
                              TripodSamples(now, kTripodB, 100, 0.05, 0.002, 86));
  const OffsetReestimate r = ReestimateOffsets(before, standing, samples, {});
  double worst_f = 0.0, worst_t = 0.0, worst_z = 0.0, drift = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      const double err = std::abs(r.offset[k][i] - now.leg[k].offset[i]);
      ASSERT_GT(r.sigma[k][i], 0.0);
      (i < 3 ? worst_f : worst_t) = std::max(i < 3 ? worst_f : worst_t, err);
      worst_z = std::max(worst_z, err / r.sigma[k][i]);
      drift = std::max(drift, std::abs(now.leg[k].offset[i] - before.leg[k].offset[i]));
    }
  }
  std::printf(
      "drift up to %.2f; error after re-estimation: force %.4f N, torque %.5f N*m, "
      "worst |error|/sigma %.2f\n",
      drift, worst_f, worst_t, worst_z);
  EXPECT_LT(worst_f, 0.03);
  EXPECT_LT(worst_t, 0.002);
  EXPECT_LT(worst_z, 5.0);
}

TEST(OffsetReestimation, RefusesComponentsTheDataDoesNotDetermine) {
  const RobotCalibration before = MakeTruth(91, Mounting::kFull);
  const RobotCalibration now = Drifted(before, 92);
  const auto standing = MakePoses(now, GridSubset(40, 93), Noise{0, 0, 0, 0}, false, 94);
  const auto samples = TripodSamples(now, kTripodA, 10, 0, 0, 95);  // only HL, FL, MR lifted
  try {
    ReestimateOffsets(before, standing, samples, {});
    FAIL() << "returned offsets of legs never unloaded";
  } catch (const std::invalid_argument& e) {
    const std::string what = e.what();
    for (const char* name : {"ML fx", "HR tz", "FR fy"}) {
      EXPECT_NE(what.find(name), std::string::npos) << what;
    }
    for (const char* name : {"HL fx", "FL tz", "MR fy"}) {
      EXPECT_EQ(what.find(name), std::string::npos) << what;
    }
    EXPECT_NE(what.find("18 offset components"), std::string::npos) << what;
  }
}

TEST(OffsetReestimation, ReturnsOnlyTheDeterminedComponentsWhenAsked) {
  const RobotCalibration before = MakeTruth(101, Mounting::kFull);
  const RobotCalibration now = Drifted(before, 102);
  const auto standing = MakePoses(now, GridSubset(40, 103), Noise{0, 0, 0, 0}, false, 104);
  const auto samples = TripodSamples(now, kTripodA, 10, 0, 0, 105);
  OffsetReestimationOptions options;
  options.require_all = false;
  const OffsetReestimate r = ReestimateOffsets(before, standing, samples, options);
  EXPECT_EQ(r.undetermined.size(), 18u);
  // Tripod A's 18 + the 6 combinations the standing poses see of tripod B's offsets.
  EXPECT_EQ(r.rank, 24);
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      EXPECT_EQ(r.determined[k][i], kTripodA[k]) << kLegNames[k] << i;
      if (kTripodA[k]) {
        EXPECT_NEAR(r.offset[k][i], now.leg[k].offset[i], 1e-9);
      } else {
        EXPECT_EQ(r.offset[k][i], before.leg[k].offset[i]);  // left as it was
        EXPECT_EQ(r.sigma[k][i], 0.0);
      }
    }
  }
}

TEST(OffsetReestimation, StandingAloneDeterminesNoSingleOffset) {
  const RobotCalibration before = MakeTruth(111, Mounting::kFull);
  const auto standing =
      MakePoses(Drifted(before, 112), GridSubset(40, 113), Noise{0, 0, 0, 0}, false, 114);
  OffsetReestimationOptions options;
  options.require_all = false;
  const OffsetReestimate r = ReestimateOffsets(before, standing, {}, options);
  EXPECT_EQ(r.rank, 6);  // the sum over legs, 6 numbers (docs/method.md)
  EXPECT_EQ(r.undetermined.size(), 36u);
}

// Fewer equations than the 36 unknowns: the null space is still all that the rows leave open
// (a thin SVD's V has only as many columns as rows, and lost most of it).
TEST(OffsetReestimation, FewerEquationsThanUnknownsLeaveTheRestUndetermined) {
  const RobotCalibration before = MakeTruth(131, Mounting::kFull);
  const RobotCalibration now = Drifted(before, 132);
  constexpr std::array<bool, kNumLegs> kOnlyHL = {true, false, false, false, false, false};
  const auto samples = TripodSamples(now, kOnlyHL, 3, 0, 0, 133);  // 18 equations
  OffsetReestimationOptions options;
  options.require_all = false;
  const OffsetReestimate r = ReestimateOffsets(before, {}, samples, options);
  EXPECT_EQ(r.rank, 6);
  EXPECT_EQ(r.undetermined.size(), 30u);
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      EXPECT_EQ(r.determined[k][i], k == 0) << kLegNames[k] << i;
      if (k == 0) {
        EXPECT_NEAR(r.offset[k][i], now.leg[k].offset[i], 1e-9);
      } else {
        EXPECT_EQ(r.offset[k][i], before.leg[k].offset[i]);
      }
    }
  }
}

// As many independent equations as determined unknowns: an exact fit, whose residual says
// nothing of the noise, so no uncertainty can be given. Refused rather than sigma = 0.
TEST(OffsetReestimation, RefusesDataWithoutRedundancy) {
  const RobotCalibration before = MakeTruth(141, Mounting::kFull);
  const auto samples = TripodSamples(Drifted(before, 142), kTripodA, 1, 0.05, 0.002, 143);
  OffsetReestimationOptions options;
  options.require_all = false;
  try {
    ReestimateOffsets(before, {}, samples, options);
    FAIL() << "accepted an exact fit";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("no redundancy"), std::string::npos) << e.what();
  }
}

TEST(OffsetReestimation, RefusesNonFiniteSamplesAndNoData) {
  const RobotCalibration cal = MakeTruth(121, Mounting::kFull);
  auto samples = TripodSamples(cal, kTripodA, 3, 0, 0, 122);
  samples[2].wrench[5][4] = std::nan("");
  try {
    ReestimateOffsets(cal, {}, samples, {});
    FAIL() << "accepted a NaN";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("load sample 2 leg FR"), std::string::npos) << e.what();
  }
  EXPECT_THROW(ReestimateOffsets(cal, {}, {}, {}), std::invalid_argument);
}

}  // namespace
}  // namespace ftcal
