// The BigAnt twin against independent truths: the sensing model run backwards, static
// equilibrium, a hand-computed hanging reading, file round trips, seeds and stated ranges.
#include "sim/twin.h"

#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <string>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"

namespace ftcal {
namespace {

constexpr double kDeg = M_PI / 180.0;

config::Config SimConfig() { return LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt"); }

TwinOptions NoiseFree(uint64_t seed = 7) {
  TwinOptions o;
  o.seed = seed;
  o.force_noise_n = 0.0;
  o.torque_noise_nm = 0.0;
  o.attitude_noise_deg = 0.0;
  o.marker_noise_m = 0.0;
  o.marker_dropout_rate_hz = 0.0;
  o.hang_cycles = 1;
  return o;
}

Vec6 SumInW(const TwinFrame& f) {
  Vec6 sum = Vec6::Zero();
  for (int k = 0; k < kNumLegs; ++k)
    sum += TransformWrench(Pose3(f.R_WC, Vec3::Zero()), f.ground_w_C[k]);
  return sum;
}

// The target computed here from the truth, not taken from the twin.
Vec6 Target(const RobotCalibration& truth, bool physical, const std::array<double, kNumLegs>& angle,
            const Mat3& R_WC) {
  const Vec3 up(0, 0, truth.total_mass_kg * truth.g0);
  const Vec3 shift = physical ? Vec3(R_WC * ComShiftC(truth, angle)) : Vec3::Zero();
  Vec6 t;
  t << up, shift.cross(up);
  return t;
}

TEST(Twin, NoiseFreeReadingsGiveBackTheTrueGroundWrenches) {
  for (bool physical : {false, true}) {
    TwinOptions o = NoiseFree();
    o.physical_com = physical;
    const BigAntTwin twin(SimConfig(), o);
    long frames = 0;
    double worst = 0.0;
    auto check = [&](const TwinFrame& f) {
      const RobotCalibration& cal = f.drifted ? twin.DriftedTruth() : twin.Truth();
      for (int k = 0; k < kNumLegs; ++k) {
        const Vec6 w = GroundWrenchC(cal, k, f.reading[k], f.angle_rad[k], f.R_WC);
        worst = std::max(worst, (w - f.ground_w_C[k]).cwiseAbs().maxCoeff());
      }
      ++frames;
    };
    double t = twin.Hanging(HangSeries::kZNeg, RunOptions{}, check);
    t = twin.Standing(12, RunOptions{t, t + 30.0}, check);
    t = twin.TripodStances(3, RunOptions{t}, check);
    twin.TripodWalk(30.0, RunOptions{t}, check);
    EXPECT_GT(frames, 10000);
    EXPECT_LT(worst, 1e-9) << "physical_com=" << physical;
  }
}

TEST(Twin, EveryStandingPoseIsInEquilibriumWithTheTarget) {
  for (bool physical : {false, true}) {
    TwinOptions o = NoiseFree();
    o.physical_com = physical;
    const BigAntTwin twin(SimConfig(), o);
    std::array<bool, kNumLegs> all;
    all.fill(true);
    std::array<Vec3, kNumLegs> internal;
    for (int k = 0; k < kNumLegs; ++k)
      internal[k] = Vec3(3.0 * std::sin(k + 1.0), 3.0 * std::cos(2.0 * k), 0.0);
    double largest_shift = 0.0, largest_horizontal = 0.0;
    for (int p = 0; p < 729; ++p) {
      const std::array<double, kNumLegs> angle = twin.StandingPoseAngles(p);
      const StanceState st = twin.Equilibrium(angle, all, internal);
      Vec6 sum = Vec6::Zero();
      for (int k = 0; k < kNumLegs; ++k) {
        sum += TransformWrench(Pose3(st.R_WC, Vec3::Zero()), st.ground_w_C[k]);
        // Feet push: a physically consistent load distribution has every normal force up.
        ASSERT_GT(st.force_W[k].z(), 1.0) << "pose " << p << " leg " << kLegNames[k];
        largest_horizontal = std::max(largest_horizontal, st.force_W[k].head<2>().norm());
      }
      ASSERT_LT((sum - Target(twin.Truth(), physical, angle, st.R_WC)).cwiseAbs().maxCoeff(), 1e-9)
          << "pose " << p << " physical_com=" << physical;
      largest_shift = std::max(largest_shift, ComShiftC(twin.Truth(), angle).norm());
      // The chassis tilts a little, as on the lab robot; never by much.
      ASSERT_LT(LogSO3(st.R_WC).norm(), 3.0 * kDeg);
    }
    EXPECT_GT(largest_shift, 5e-4);      // the legs move the CoM by about a millimetre
    EXPECT_GT(largest_horizontal, 1.0);  // self-balancing forces of a few newtons
    EXPECT_LT(largest_horizontal, 20.0);
  }
}

TEST(Twin, SteadyStandingFramesSumToTheTargetInBothComModes) {
  for (bool physical : {false, true}) {
    TwinOptions o = NoiseFree(11);
    o.physical_com = physical;
    const BigAntTwin twin(SimConfig(), o);
    int steady = 0, settling = 0;
    twin.Standing(15, RunOptions{}, [&](const TwinFrame& f) {
      const Vec6 miss = SumInW(f) - Target(twin.Truth(), physical, f.angle_rad, f.R_WC);
      if (f.steady) {
        ++steady;
        ASSERT_LT(miss.cwiseAbs().maxCoeff(), 1e-9) << "t " << f.t_s;
      } else if (miss.head<3>().norm() > 0.5) {
        ++settling;  // the oscillation after a change is dynamic: not in equilibrium
      }
    });
    EXPECT_GE(steady, 15 * 250);
    EXPECT_GT(settling, 15 * 20);
  }
}

TEST(Twin, WalkingFramesAreQuasiStaticAndSwingFeetCarryNothing) {
  const BigAntTwin twin(SimConfig(), NoiseFree());
  int swing = 0, three = 0, six = 0;
  twin.TripodWalk(1.0 / 0.08, RunOptions{}, [&](const TwinFrame& f) {
    int n = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      if (f.in_contact[k]) {
        ++n;
      } else {
        ++swing;
        ASSERT_TRUE(f.ground_w_C[k].isZero(0.0));
        // A swing leg is outside the stance sweep of +-36 deg.
        EXPECT_GT(std::abs(std::remainder(f.angle_rad[k], 2 * M_PI)), 35.9 * kDeg);
      }
    }
    three += n == 3;
    six += n == 6;
    ASSERT_TRUE(n == 3 || n == 6) << n;
    ASSERT_LT((SumInW(f) - Target(twin.Truth(), false, f.angle_rad, f.R_WC)).cwiseAbs().maxCoeff(),
              1e-9);
  });
  EXPECT_GT(swing, 0);
  EXPECT_GT(three, 0);
  EXPECT_GT(six, 0);
}

TEST(Twin, FeetInTheAirHaveZeroGroundWrench) {
  const BigAntTwin twin(SimConfig(), NoiseFree());
  twin.Hanging(HangSeries::kXPos, RunOptions{}, [](const TwinFrame& f) {
    for (int k = 0; k < kNumLegs; ++k) {
      ASSERT_FALSE(f.in_contact[k]);
      ASSERT_TRUE(f.ground_w_C[k].isZero(0.0));
    }
  });
  int lifted_frames = 0;
  twin.TripodStances(4, RunOptions{}, [&](const TwinFrame& f) {
    if (!f.steady) return;
    int n = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      if (f.in_contact[k]) {
        ++n;
        EXPECT_GT(f.ground_w_C[k][2], 1.0);  // C is level within a few degrees: z is up
      } else {
        ASSERT_TRUE(f.ground_w_C[k].isZero(0.0));
        // Lifted legs point up (pi +- 0.3 rad).
        EXPECT_LT(std::abs(std::remainder(f.angle_rad[k] - M_PI, 2 * M_PI)), 0.31);
      }
    }
    ASSERT_EQ(n, 3);
    ++lifted_frames;
  });
  EXPECT_GE(lifted_frames, 4 * 250);
  const std::vector<LoadSample> samples = twin.MakeTripodLoadSamples(4, false);
  ASSERT_EQ(samples.size(), 4u);
  for (int i = 0; i < 4; ++i) {
    // Stances alternate tripods: {HL, FL, MR} first, then {ML, HR, FR}.
    for (int k = 0; k < kNumLegs; ++k) {
      const bool first_tripod =
          kLegNames[k] == "HL" || kLegNames[k] == "FL" || kLegNames[k] == "MR";
      EXPECT_EQ(samples[i].unloaded[k], first_tripod == (i % 2 == 0)) << kLegNames[k];
    }
  }
}

// Leg at phase 0, no mounting error, the robot hung exactly with body +x down: the reading of a
// left leg (ft axes = body axes) is offset + [w; r x w] with w = (W, 0, 0), worked out by hand:
// r x w = (0, r_z W, -r_y W). A right leg (turned 180 deg about z) has gravity along its -x.
TEST(Twin, HangingReadingMatchesTheHandComputedOne) {
  TwinOptions o = NoiseFree(3);
  o.mounting_errors = false;
  o.hang_tilt_min_deg = 0.0;
  o.hang_tilt_max_deg = 0.0;
  const BigAntTwin twin(SimConfig(), o);
  EXPECT_EQ(twin.StatedGravityB(HangSeries::kXPos), Vec3(1, 0, 0));
  EXPECT_EQ(twin.StatedGravityB(HangSeries::kXNeg), Vec3(-1, 0, 0));
  EXPECT_EQ(twin.StatedGravityB(HangSeries::kZPos), Vec3(0, 0, 1));
  EXPECT_EQ(twin.StatedGravityB(HangSeries::kZNeg), Vec3(0, 0, -1));
  bool seen = false;
  twin.Hanging(HangSeries::kXPos, RunOptions{}, [&](const TwinFrame& f) {
    if (seen) return;
    seen = true;
    ASSERT_EQ(f.angle_rad[0], 0.0);
    for (int k : {*LegIndex("HL"), *LegIndex("HR")}) {
      const LegCalibration& leg = twin.Truth().leg[k];
      const double W = leg.weight_n;
      const double r_y = leg.com.y;
      const double r_z = leg.com.z.a * std::sin(leg.com.z.c) + leg.com.z.d;
      const double s = kLegNames[k] == "HL" ? 1.0 : -1.0;
      Vec6 expected;
      expected << s * W, 0.0, 0.0, 0.0, s * r_z * W, -s * r_y * W;
      expected += leg.offset;
      EXPECT_LT((f.reading[k] - expected).cwiseAbs().maxCoeff(), 1e-12) << kLegNames[k];
    }
  });
  EXPECT_TRUE(seen);
}

TEST(Twin, HangingSeriesIsTiltedByOneToThreeDegreesFromTheStatedAxis) {
  const BigAntTwin twin(SimConfig(), TwinOptions{});
  for (int s = 0; s < kNumHangSeries; ++s) {
    const HangSeries series = static_cast<HangSeries>(s);
    const Vec3 g_C = twin.HangingAttitude(series).transpose() * Vec3(0, 0, -1);
    const double angle = std::acos(std::clamp(g_C.dot(twin.StatedGravityB(series)), -1.0, 1.0));
    EXPECT_GE(angle, 1.0 * kDeg - 1e-9);
    EXPECT_LE(angle, 3.0 * kDeg + 1e-9);
  }
}

TEST(Twin, HangingRecordingHasTenCyclesAtOneHundredHertz) {
  TwinOptions o;
  o.seed = 5;
  const BigAntTwin twin(SimConfig(), o);
  const HangingRecording rec = twin.MakeHangingRecording(HangSeries::kZPos);
  EXPECT_EQ(rec.series, HangSeries::kZPos);
  EXPECT_EQ(rec.gravity_b, Vec3(0, 0, 1));
  for (const LegSamples& leg : rec.legs) {
    ASSERT_EQ(leg.t_s.size(), 20000u);
    ASSERT_EQ(leg.wrench.size(), 20000u);
    EXPECT_NEAR(leg.angle_rad.back() - leg.angle_rad.front(), 10 * 2 * M_PI, 2 * M_PI / 1000);
    EXPECT_NEAR(leg.t_s[1] - leg.t_s[0], 0.01, 1e-12);
  }
  EXPECT_EQ(rec.attitude.size(), 20000u);
}

TEST(Twin, TruthFileRoundTrip) {
  const config::Config config = SimConfig();
  const BigAntTwin twin(config, TwinOptions{});
  const std::string path =
      ::testing::TempDir() + "twin_truth_" + std::to_string(::getpid()) + ".pbtxt";
  twin.WriteTruthFile(path);
  const calibration::Calibration proto = ReadCalibrationFile(path);
  std::remove(path.c_str());
  EXPECT_EQ(proto.hanging_uncertainty(), calibration::TRUTH);
  const RobotCalibration back = CalibrationFromProto(proto, config.robot());
  const RobotCalibration& truth = twin.Truth();
  EXPECT_NEAR(back.total_mass_kg, truth.total_mass_kg, 1e-12);
  EXPECT_NEAR(back.g0, truth.g0, 1e-12);
  EXPECT_LT((back.p_C_B - truth.p_C_B).norm(), 1e-12);
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& a = back.leg[k];
    const LegCalibration& b = truth.leg[k];
    EXPECT_LT((a.offset - b.offset).cwiseAbs().maxCoeff(), 1e-12) << kLegNames[k];
    EXPECT_NEAR(a.weight_n, b.weight_n, 1e-12);
    EXPECT_NEAR(a.com.x.a, b.com.x.a, 1e-12);
    EXPECT_NEAR(a.com.x.c, b.com.x.c, 1e-12);
    EXPECT_NEAR(a.com.x.d, b.com.x.d, 1e-12);
    EXPECT_NEAR(a.com.y, b.com.y, 1e-12);
    EXPECT_NEAR(a.com.z.a, b.com.z.a, 1e-12);
    EXPECT_NEAR(a.com.z.c, b.com.z.c, 1e-12);
    EXPECT_NEAR(a.com.z.d, b.com.z.d, 1e-12);
    EXPECT_LT((a.R_tilde - b.R_tilde).cwiseAbs().maxCoeff(), 1e-9) << kLegNames[k];
    EXPECT_LT((a.p_tilde_prime - b.p_tilde_prime).norm(), 1e-12) << kLegNames[k];
    EXPECT_LT((back.X_C_ft(k).p - truth.X_C_ft(k).p).norm(), 1e-9);
    EXPECT_LT((back.X_B_ft[k].p - truth.X_B_ft[k].p).norm(), 1e-15);
  }
}

TEST(Twin, SameSeedSameOutputDifferentSeedDifferentParameters) {
  const config::Config config = SimConfig();
  TwinOptions o;
  o.seed = 42;
  o.marker_dropout_rate_hz = 0.05;
  const BigAntTwin a(config, o), b(config, o);
  std::vector<TwinFrame> fa, fb;
  a.Standing(3, RunOptions{}, [&](const TwinFrame& f) { fa.push_back(f); });
  b.Standing(3, RunOptions{}, [&](const TwinFrame& f) { fb.push_back(f); });
  ASSERT_EQ(fa.size(), fb.size());
  for (size_t i = 0; i < fa.size(); ++i) {
    for (int k = 0; k < kNumLegs; ++k) {
      ASSERT_EQ(fa[i].reading[k], fb[i].reading[k]);
      ASSERT_EQ(fa[i].angle_rad[k], fb[i].angle_rad[k]);
    }
    ASSERT_EQ(fa[i].R_GC, fb[i].R_GC);
    ASSERT_EQ(fa[i].marker_tracked, fb[i].marker_tracked);
  }
  // Scenario streams are independent: generating another scenario first changes nothing.
  const BigAntTwin c(config, o);
  c.TripodWalk(5.0, RunOptions{}, [](const TwinFrame&) {});
  size_t i = 0;
  c.Standing(3, RunOptions{},
             [&](const TwinFrame& f) { ASSERT_EQ(f.reading[2], fa[i++].reading[2]); });

  TwinOptions o2 = o;
  o2.seed = 43;
  const BigAntTwin d(config, o2);
  EXPECT_NE(a.Truth().leg[0].offset, d.Truth().leg[0].offset);
  EXPECT_NE(a.Truth().p_C_B, d.Truth().p_C_B);
  EXPECT_GT((a.Truth().leg[1].R_tilde - d.Truth().leg[1].R_tilde).norm(), 1e-3);
}

TEST(Twin, TrueParametersStayWithinTheStatedRanges) {
  const config::Config config = SimConfig();
  for (uint64_t seed = 1; seed <= 25; ++seed) {
    TwinOptions o;
    o.seed = seed;
    const BigAntTwin twin(config, o);
    const RobotCalibration& t = twin.Truth();
    EXPECT_GE(t.p_C_B.norm(), 0.008 - 1e-12);
    EXPECT_LE(t.p_C_B.norm(), 0.012 + 1e-12);
    for (int k = 0; k < kNumLegs; ++k) {
      const LegCalibration& leg = t.leg[k];
      const double tilt = LogSO3(leg.R_tilde).norm();
      EXPECT_GE(tilt, 1.0 * kDeg - 1e-12);
      EXPECT_LE(tilt, 3.0 * kDeg + 1e-12);
      // The shift about the transducer's own origin, recovered from p~ = d + (I - R~) p^B_ft.
      const Vec3 d = t.PTilde(k) - (Mat3::Identity() - leg.R_tilde) * t.X_B_ft[k].p;
      EXPECT_GE(d.norm(), 0.002 - 1e-12);
      EXPECT_LE(d.norm(), 0.008 + 1e-12);
      EXPECT_GE(leg.weight_n, 5.99);
      EXPECT_LE(leg.weight_n, 6.51);
      EXPECT_LE(leg.offset.head<3>().cwiseAbs().maxCoeff(), 9.5);
      EXPECT_LE(leg.offset.tail<3>().cwiseAbs().maxCoeff(), 0.3911 + 1e-12);
      EXPECT_GE(leg.com.x.a, 0.01);
      EXPECT_LE(leg.com.x.a, 0.02);
      EXPECT_GE(leg.com.z.a, 0.01);
      EXPECT_LE(leg.com.z.a, 0.02);
      const Vec6 drift = twin.DriftedTruth().leg[k].offset - leg.offset;
      EXPECT_LE(drift.head<3>().cwiseAbs().maxCoeff(), 3.0);
      EXPECT_LE(drift.tail<3>().cwiseAbs().maxCoeff(), 0.1);
    }
    EXPECT_NEAR(t.total_mass_kg, 8.18, 1e-12);
  }
  TwinOptions none;
  none.mounting_errors = false;
  const BigAntTwin twin(config, none);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_EQ(twin.Truth().leg[k].R_tilde, Mat3::Identity());
    EXPECT_LT(twin.Truth().PTilde(k).norm(), 1e-15);
  }
}

TEST(Twin, MarkerDropoutsHappenAtTheConfiguredRate) {
  TwinOptions o;
  o.marker_dropout_rate_hz = 0.05;
  o.marker_dropout_mean_s = 0.5;
  o.hang_cycles = 10;
  const BigAntTwin twin(SimConfig(), o);
  long marker_frames = 0, untracked = 0;
  twin.Hanging(HangSeries::kXPos, RunOptions{}, [&](const TwinFrame& f) {
    for (int m = 0; m < kNumChassisMarkers; ++m) {
      ++marker_frames;
      if (!f.marker_tracked[m]) {
        ++untracked;
        ASSERT_TRUE(f.marker_G_m[m].array().isNaN().all());
      } else {
        // A tracked marker is where the body pose puts it (to its 0.5 mm noise).
        const Vec3 predicted = f.p_GB_m + f.R_GC * (twin.MarkersB()[m]);
        ASSERT_LT((f.marker_G_m[m] - predicted).norm(), 0.01);
      }
    }
  });
  // Alternating renewal process: untracked fraction = rate * mean / (1 + rate * mean).
  const double expected = 0.05 * 0.5 / (1 + 0.05 * 0.5);
  EXPECT_NEAR(static_cast<double>(untracked) / marker_frames, expected, 0.35 * expected);

  o.marker_dropout_rate_hz = 0.0;
  const BigAntTwin clean(SimConfig(), o);
  clean.Hanging(HangSeries::kXPos, RunOptions{}, [](const TwinFrame& f) {
    for (bool tracked : f.marker_tracked) ASSERT_TRUE(tracked);
  });
}

// The medians the segmenter would report, pushed through eq. 3 with the true calibration,
// balance the robot's weight to within what the noise leaves; poses with dropouts are gone.
TEST(Twin, SteadyPosesBalanceTheWeightAndSkipDropouts) {
  TwinOptions o;
  o.seed = 9;
  o.marker_dropout_rate_hz = 0.0;
  const BigAntTwin twin(SimConfig(), o);
  const std::vector<StandingPose> poses = twin.MakeSteadyPoses(20);
  ASSERT_EQ(poses.size(), 20u);
  const double G = twin.Truth().TotalWeightN();
  for (const StandingPose& p : poses) {
    Vec6 sum = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k)
      sum += GroundWrenchW(twin.Truth(), k, p.wrench[k], p.angle_rad[k], p.R_WC);
    EXPECT_LT((sum.head<3>() - Vec3(0, 0, G)).norm(), 0.1);
    EXPECT_LT(sum.tail<3>().norm(), 0.02);
  }
  // 12 markers at 0.01 Hz: about a third of the 3 s steady windows see a dropout.
  o.marker_dropout_rate_hz = 0.01;
  const BigAntTwin lossy(SimConfig(), o);
  const size_t kept = lossy.MakeSteadyPoses(20).size();
  EXPECT_LT(kept, 20u);
  EXPECT_GT(kept, 5u);
}

TEST(Twin, QuantizedReadingsAreWholeCounts) {
  TwinOptions o;
  o.quantize = true;
  o.counts_per_force = 1e6;
  o.counts_per_torque = 1e6;
  o.hang_cycles = 1;
  const BigAntTwin twin(SimConfig(), o);
  int n = 0;
  twin.Hanging(HangSeries::kXNeg, RunOptions{}, [&](const TwinFrame& f) {
    if (++n > 100) return;
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 6; ++i) ASSERT_EQ(f.reading[k][i], f.counts[k][i] / 1e6);
    }
  });
}

// The drift moves the offsets and nothing else: the same seed draws the same noise, so a
// drifted frame differs from the undrifted one by exactly the drift.
TEST(Twin, OffsetDriftAppliesFromItsTimeOnAndChangesOnlyTheOffsets) {
  TwinOptions o;
  o.seed = 21;
  const BigAntTwin twin(SimConfig(), o);
  std::vector<TwinFrame> plain, drifted;
  twin.TripodStances(2, RunOptions{}, [&](const TwinFrame& f) { plain.push_back(f); });
  twin.TripodStances(2, RunOptions{0.0, 10.0}, [&](const TwinFrame& f) { drifted.push_back(f); });
  ASSERT_EQ(plain.size(), drifted.size());
  int after = 0;
  for (size_t i = 0; i < plain.size(); ++i) {
    ASSERT_EQ(drifted[i].drifted, drifted[i].t_s >= 10.0);
    after += drifted[i].drifted;
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 expected =
          drifted[i].drifted ? Vec6(twin.DriftedTruth().leg[k].offset - twin.Truth().leg[k].offset)
                             : Vec6::Zero();
      ASSERT_LT((drifted[i].reading[k] - plain[i].reading[k] - expected).cwiseAbs().maxCoeff(),
                1e-12);
    }
  }
  EXPECT_GT(after, 100);
  EXPECT_GT((twin.DriftedTruth().leg[0].offset - twin.Truth().leg[0].offset).norm(), 0.1);
}

// Buehler clock at 0.08 Hz turning right by 9.08 deg per cycle; the body moves forward.
TEST(Twin, TripodWalkTurnsRightAtTheConfiguredRate) {
  const BigAntTwin twin(SimConfig(), NoiseFree());
  std::vector<TwinFrame> frames;
  twin.TripodWalk(2.0 / 0.08, RunOptions{}, [&](const TwinFrame& f) { frames.push_back(f); });
  ASSERT_EQ(frames.size(), 2500u);
  const TwinFrame& a = frames.front();
  const TwinFrame& b = frames[1250];  // one gait cycle later
  EXPECT_NEAR(std::remainder(HeadingYaw(b.R_GC) - HeadingYaw(a.R_GC), 2 * M_PI), -9.08 * kDeg,
              0.1 * kDeg);
  const Vec3 heading(std::cos(HeadingYaw(a.R_GC)), std::sin(HeadingYaw(a.R_GC)), 0.0);
  EXPECT_GT((b.p_GB_m - a.p_GB_m).dot(heading), 0.02);
  // Every leg turns one full turn per cycle, the right ones the other way.
  for (int k = 0; k < kNumLegs; ++k) {
    const double turn = frames[1250].angle_rad[k] - frames[0].angle_rad[k];
    EXPECT_NEAR(std::abs(turn), 2 * M_PI, 1e-9) << kLegNames[k];
    EXPECT_EQ(turn > 0, kLegNames[k].back() == 'L') << kLegNames[k];
  }
}

// BigAntTwin::Driven: frames at shaft angles from outside, standing on all six feet.
TEST(Twin, DrivenFramesStandInEquilibriumAndReadAsTheSensingModel) {
  const config::Config config = SimConfig();
  TwinOptions noisy;  // the default noise
  noisy.seed = 7;
  TwinOptions quiet = noisy;
  quiet.force_noise_n = 0.0;
  quiet.torque_noise_nm = 0.0;
  const BigAntTwin a(config, noisy), b(config, quiet);
  BigAntTwin::Driven da(a), db(b);
  // The internal forces are the same with and without noise: a noise-free twin gives the
  // expected readings of a noisy one.
  for (int k = 0; k < kNumLegs; ++k) EXPECT_EQ(da.InternalForces()[k], db.InternalForces()[k]);
  double largest_horizontal = 0.0;
  std::array<bool, kNumLegs> all;
  all.fill(true);
  long samples = 0;
  std::array<double, 6> sum_sq{};
  for (int p = 0; p < 40; ++p) {
    const std::array<double, kNumLegs> angle = a.StandingPoseAngles(p);
    const double t = 0.01 * p;
    const TwinFrame fa = da.Frame(t, angle);
    const TwinFrame& fb = db.Frame(t, angle);
    for (const TwinFrame* f : {&fa, &fb}) {
      SCOPED_TRACE("pose " + std::to_string(p));
      EXPECT_EQ(f->t_s, t);
      EXPECT_EQ(f->angle_rad, angle);
      EXPECT_EQ(f->phase, ExperimentPhase::kStanding);
      for (int k = 0; k < kNumLegs; ++k) EXPECT_TRUE(f->in_contact[k]);
      // Equilibrium: the ground wrenches sum to the weight (fixed CoM).
      ASSERT_LT((SumInW(*f) - Target(a.Truth(), false, angle, f->R_WC)).cwiseAbs().maxCoeff(),
                1e-9);
      // The same state as Equilibrium on all six feet with the Driven's internal forces.
      const StanceState st = a.Equilibrium(angle, all, da.InternalForces());
      for (int k = 0; k < kNumLegs; ++k) {
        ASSERT_LT((f->ground_w_C[k] - st.ground_w_C[k]).cwiseAbs().maxCoeff(), 1e-12);
        ASSERT_GT(st.force_W[k].z(), 1.0);
        largest_horizontal = std::max(largest_horizontal, st.force_W[k].head<2>().norm());
      }
      ASSERT_LT((f->R_WC - st.R_WC).cwiseAbs().maxCoeff(), 1e-15);
    }
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 model = TransducerReading(a.Truth(), k, fb.ground_w_C[k], angle[k], fb.R_WC);
      // Noise off: exactly the sensing model; counts are the readings at 1e6 counts per unit.
      ASSERT_LT((fb.reading[k] - model).cwiseAbs().maxCoeff(), 1e-12) << kLegNames[k];
      for (int i = 0; i < 6; ++i) EXPECT_EQ(fb.counts[k][i], std::lround(model[i] * 1e6));
      // Noise on: the sensing model within 5 sigma, each component.
      const Vec6 miss = fa.reading[k] - model;
      for (int i = 0; i < 6; ++i) {
        const double sigma = i < 3 ? noisy.force_noise_n : noisy.torque_noise_nm;
        EXPECT_LT(std::abs(miss[i]), 5.0 * sigma) << kLegNames[k] << " axis " << i;
        sum_sq[i] += miss[i] * miss[i] / (sigma * sigma);
      }
      ++samples;
    }
  }
  // The noise is there, at its stated size (240 draws per axis: rms within 20%).
  for (int i = 0; i < 6; ++i) EXPECT_NEAR(std::sqrt(sum_sq[i] / samples), 1.0, 0.2) << "axis " << i;
  EXPECT_GT(largest_horizontal, 1.0);  // the self-balancing forces are there
}

TEST(Twin, DrivenChassisStaysPutAndFramesAreDeterministic) {
  const config::Config config = SimConfig();
  const BigAntTwin twin(config, NoiseFree(5));
  BigAntTwin::Driven d(twin);
  std::array<double, kNumLegs> zero{};
  std::array<double, kNumLegs> bent = {0.3, -0.2, 0.5, -0.4, 0.1, -0.6};
  const TwinFrame f0 = d.Frame(0.0, zero);
  const TwinFrame f1 = d.Frame(0.01, zero);
  const TwinFrame f2 = d.Frame(0.02, bent);
  const TwinFrame f3 = d.Frame(0.03, bent);
  EXPECT_TRUE(f0.steady);
  EXPECT_TRUE(f1.steady);
  EXPECT_FALSE(f2.steady);  // the legs moved since the last frame
  EXPECT_TRUE(f3.steady);
  // Same heading (no attitude noise: R_GC = Rz(yaw0) R_WC) and position over the origin.
  EXPECT_NEAR(HeadingYaw(f0.R_GC * f0.R_WC.transpose()), HeadingYaw(f2.R_GC * f2.R_WC.transpose()),
              1e-12);
  const Vec3 c0 = f0.p_GB_m - f0.R_GC * twin.Truth().p_C_B;
  const Vec3 c2 = f2.p_GB_m - f2.R_GC * twin.Truth().p_C_B;
  EXPECT_LT((c0 - c2).head<2>().norm(), 1e-12);
  EXPECT_GT(c0.z(), 0.05);  // standing on its feet
  // Moving the legs moves load between the feet by far more than the noise.
  double largest = 0.0;
  for (int k = 0; k < kNumLegs; ++k)
    largest = std::max(largest, (f2.reading[k] - f0.reading[k]).head<3>().norm());
  EXPECT_GT(largest, 1.0);

  // The same seed and calls give the same frames, noise and dropouts included.
  TwinOptions o;
  o.seed = 9;
  o.marker_dropout_rate_hz = 5.0;
  const BigAntTwin p(config, o), q(config, o);
  BigAntTwin::Driven dp(p), dq(q);
  int untracked = 0;
  for (int i = 0; i < 300; ++i) {
    std::array<double, kNumLegs> angle;
    for (int k = 0; k < kNumLegs; ++k) angle[k] = 0.5 * std::sin(0.01 * i + k);
    const TwinFrame fp = dp.Frame(0.01 * i, angle);
    const TwinFrame& fq = dq.Frame(0.01 * i, angle);
    for (int k = 0; k < kNumLegs; ++k) ASSERT_EQ(fp.reading[k], fq.reading[k]);
    ASSERT_EQ(fp.R_GC, fq.R_GC);
    ASSERT_EQ(fp.marker_tracked, fq.marker_tracked);
    for (bool tracked : fp.marker_tracked) untracked += !tracked;
  }
  EXPECT_GT(untracked, 0);  // dropouts as in every scenario
  std::array<double, kNumLegs> bad = zero;
  bad[2] = NAN;
  EXPECT_THROW(d.Frame(1.0, bad), std::invalid_argument);
}

TEST(Twin, BadOptionsAreRefusedByName) {
  TwinOptions o;
  o.force_noise_n = -1.0;
  try {
    BigAntTwin twin(SimConfig(), o);
    FAIL() << "accepted a negative noise level";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("force_noise_n"), std::string::npos) << e.what();
  }
  const BigAntTwin twin(SimConfig(), TwinOptions{});
  EXPECT_THROW(twin.Standing(730, RunOptions{}, [](const TwinFrame&) {}), std::invalid_argument);
  std::array<bool, kNumLegs> two{};
  two[0] = two[1] = true;
  EXPECT_THROW(twin.Equilibrium(twin.StandingPoseAngles(0), two, {}), std::invalid_argument);
}

}  // namespace
}  // namespace ftcal

namespace ftcal {
namespace {

// The operator's hands on the driven twin (ftcal-sim live --control): hung in a series' attitude
// or lifted for the tare, a Driven frame is the frame the recorded scenario makes at the same
// shaft angles (the same physics, Hanging() and Tare()); set down again, it stands.
TEST(Twin, DrivenHangsAndLiftsAsTheRecordedHangingAndTare) {
  for (const bool physical_com : {false, true}) {
    TwinOptions o = NoiseFree(9);
    o.physical_com = physical_com;
    o.marker_dropout_rate_hz = 0.0;
    o.hang_cycles = 1;
    const BigAntTwin twin(SimConfig(), o);
    BigAntTwin::Driven driven(twin);
    for (int s = 0; s < kNumHangSeries; ++s) {
      const HangSeries series = static_cast<HangSeries>(s);
      std::vector<TwinFrame> recorded;
      twin.Hanging(series, RunOptions{}, [&](const TwinFrame& f) { recorded.push_back(f); });
      driven.SetSupport(BigAntTwin::Driven::Support::kHanging, series);
      for (std::size_t i = 0; i < recorded.size(); i += 137) {
        const TwinFrame& want = recorded[i];
        const TwinFrame& got =
            driven.Frame(static_cast<double>(s) * 100 + i * 0.01, want.angle_rad);
        EXPECT_EQ(static_cast<int>(got.phase), static_cast<int>(want.phase));
        EXPECT_LT((got.R_WC - twin.HangingAttitude(series)).norm(), 1e-15);
        EXPECT_LT((got.R_GC - want.R_GC).norm(), 1e-12);
        EXPECT_LT((got.p_GB_m - want.p_GB_m).norm(), 1e-12);
        for (int k = 0; k < kNumLegs; ++k) {
          EXPECT_FALSE(got.in_contact[k]);
          EXPECT_LT((got.reading[k] - want.reading[k]).norm(), 1e-9)
              << "series " << s << " leg " << k << " frame " << i;
        }
      }
    }
    std::vector<TwinFrame> tare;
    twin.Tare(RunOptions{}, [&](const TwinFrame& f) { tare.push_back(f); });
    driven.SetSupport(BigAntTwin::Driven::Support::kLifted);
    const TwinFrame& lifted = driven.Frame(1000.0, tare.front().angle_rad);
    EXPECT_EQ(lifted.phase, ExperimentPhase::kTare);
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_LT((lifted.reading[k] - tare.front().reading[k]).norm(), 1e-9) << "leg " << k;
    }
    // Set down: on its six feet again, carrying the robot's weight.
    driven.SetSupport(BigAntTwin::Driven::Support::kStanding);
    const TwinFrame& standing = driven.Frame(1001.0, std::array<double, kNumLegs>{});
    EXPECT_EQ(standing.phase, ExperimentPhase::kStanding);
    double fz = 0.0;
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_TRUE(standing.in_contact[k]);
      fz += standing.ground_w_C[k][2];
    }
    EXPECT_NEAR(fz, SimConfig().robot().total_mass_kg() * SimConfig().robot().g0_m_s2(), 0.5);
  }
}

}  // namespace
}  // namespace ftcal
