// Step 1 (hanging): each equation on a hand-computed case, then the whole step on data made
// by a forward model from known parameters: eq. 4-7 written out (first order or with finite
// rotations) and, independently, the sensing model of sensing_model.h with mounting errors and
// a tilted hang.
#include "ftcal/hanging.h"

#include "hanging_test_data.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>
#include <string>

namespace ftcal {
namespace {

using namespace hanging_testdata;  // NOLINT

HangingOptions ExactOptions() {
  HangingOptions o;
  // The smoother trusts the observations (noise-free data): its random-walk prior then leaves
  // no smoothing error on the CoM.
  o.smoother_observation_var_nm2 = 1e-14;
  return o;
}

double CurveError(const LegComModel& a, const LegComModel& b) {
  double worst = 0.0;
  for (int i = 0; i < 400; ++i) worst = std::max(worst, (a.At(i / 400.0) - b.At(i / 400.0)).norm());
  return worst;
}

void ExpectSinusoid(const SinusoidFit& got, const SinusoidFit& want, double tol) {
  EXPECT_NEAR(got.a, want.a, tol);
  EXPECT_NEAR(std::remainder(got.c - want.c, kTwoPi), 0.0, tol / want.a);
  EXPECT_NEAR(got.d, want.d, tol);
}

// ------------------------------------------------------------ the equations, by hand

TEST(HangingEquations, SPlusFromOneKnownRotation) {
  const double mg = 6.0;
  const Vec3 s(0.0, 0.02, -0.03);
  // (I + [s]) mg e_x = mg (1, s_z, -s_y) = (6, -0.18, -0.12)
  const Vec3 f_first(6.0, -0.18, -0.12);
  EXPECT_LT((SPlusClosedForm(f_first, Vec3::UnitX(), false) - s).norm(), 1e-15);
  // exp([s]) e_x by Rodrigues: rotation by |s| about s/|s|.
  const Vec3 f_exact = mg * (RotVec(s) * Vec3::UnitX());
  EXPECT_LT((SPlusClosedForm(f_exact, Vec3::UnitX(), true) - s).norm(), 1e-14);
  // z axis: (I + [s]) e_z with s = (0.01, -0.04, 0) is (s_y, -s_x, 1) = (-0.04, -0.01, 1).
  EXPECT_LT(
      (SPlusClosedForm(Vec3(-0.24, -0.06, 6.0), Vec3::UnitZ(), false) - Vec3(0.01, -0.04, 0.0))
          .norm(),
      1e-15);
  // The report's objective is zero at s and positive elsewhere.
  const std::vector<Vec3> f(5, f_first);
  EXPECT_LT(SPlusObjective(s, f, Vec3::UnitX(), false), 1e-15);
  EXPECT_GT(SPlusObjective(Vec3(0, 0.021, -0.03), f, Vec3::UnitX(), false), 1e-3);
}

TEST(HangingEquations, SmootherRecoversCoMAcrossTheWeight) {
  // tau- = -[f-] r: with r = (0.01, 0.02, -0.03) and f- = (6, 0, 0),
  // r x f = (0, r_z f_x, -r_y f_x) = (0, -0.18, -0.12).
  const Vec3 r(0.01, 0.02, -0.03);
  const Vec3 f(6.0, 0.0, 0.0);
  const Vec3 tau(0.0, -0.18, -0.12);
  ASSERT_LT((-Skew(f) * r - tau).norm(), 1e-15);
  const std::vector<Vec3> est =
      SmoothLegCom(std::vector<Vec3>(50, f), std::vector<Vec3>(50, tau), 0.01, 0.01);
  for (const Vec3& e : est) {
    // Known up to p f-: the components across f- are exact.
    EXPECT_NEAR(e.y(), 0.02, 1e-12);
    EXPECT_NEAR(e.z(), -0.03, 1e-12);
  }
  // Observations trusted (tiny R): exact.
  const std::vector<Vec3> sharp =
      SmoothLegCom(std::vector<Vec3>(50, f), std::vector<Vec3>(50, tau), 0.01, 1e-14);
  for (const Vec3& e : sharp) {
    EXPECT_NEAR(e.y(), 0.02, 1e-12);
    EXPECT_NEAR(e.z(), -0.03, 1e-12);
  }
}

TEST(HangingEquations, NullSpaceResolvedByTheOtherPair) {
  // r = (0.01, 0.02, -0.03); the x pair gives r - 0.004 f, the z pair r + 0.002 f'.
  const Vec3 f(6.0, 0.0, 0.0), f_prime(0.0, 0.0, 6.0);
  const Vec3 r_est(-0.014, 0.02, -0.03), r_est_prime(0.01, 0.02, -0.018);
  EXPECT_LT((ResolveComNullSpace(r_est, f, r_est_prime, f_prime) - Vec3(0.01, 0.02, -0.03)).norm(),
            1e-15);
  // Disagreeing components across both weights are averaged: y 0.02 vs 0.024 -> 0.022.
  EXPECT_NEAR(ResolveComNullSpace(r_est, f, Vec3(0.01, 0.024, -0.018), f_prime).y(), 0.022, 1e-15);
  EXPECT_THROW(ResolveComNullSpace(r_est, f, r_est_prime, 2.0 * f), std::invalid_argument);
}

TEST(HangingEquations, SinusoidFit) {
  // 0.04 sin(2 pi phi + 0.3) + 0.01 at phi = 0, 1/4, 1/2, 3/4:
  // 0.01 + 0.04 sin(0.3), 0.01 + 0.04 cos(0.3), 0.01 - 0.04 sin(0.3), 0.01 - 0.04 cos(0.3).
  const std::vector<double> phase = {0.0, 0.25, 0.5, 0.75};
  const std::vector<double> v = {0.01 + 0.04 * std::sin(0.3), 0.01 + 0.04 * std::cos(0.3),
                                 0.01 - 0.04 * std::sin(0.3), 0.01 - 0.04 * std::cos(0.3)};
  const SinusoidFit fit = FitSinusoid(phase, v);
  EXPECT_NEAR(fit.a, 0.04, 1e-15);
  EXPECT_NEAR(fit.c, 0.3, 1e-14);
  EXPECT_NEAR(fit.d, 0.01, 1e-15);
}

TEST(HangingOptions, FromConfigDefaults) {
  const HangingOptions o = HangingOptionsFromConfig(config::Calibrator(), config::Mocap());
  EXPECT_EQ(o.phase_bins, 200);
  EXPECT_EQ(o.smoother_transition_var_m2, 0.01);
  EXPECT_EQ(o.smoother_observation_var_nm2, 0.01);
  EXPECT_TRUE(o.exact_rotations);  // the default: exact rotations, never worse
  EXPECT_NEAR(o.axis_tolerance_rad, 10.0 * M_PI / 180.0, 1e-15);
  // The report's profile is the report's first-order I + [s], whatever the switch says.
  config::Calibrator report;
  report.set_profile(config::REPORT);
  report.set_exact_hanging_rotations(true);
  EXPECT_FALSE(HangingOptionsFromConfig(report, config::Mocap()).exact_rotations);
}

// ------------------------------------------------------------ the whole step, noise-free

TEST(Hanging, FirstOrderDataExactRecovery) {
  const auto X = NominalPoses();
  const auto truth = MakeTruth(0.03);
  Motion m;
  const auto recs = MakeRecordings(X, truth, m, nullptr);
  const HangingResult res = RunHanging(recs, X, ExactOptions());
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(std::string(kLegNames[k]));
    const LegHangingResult& r = res.leg[k];
    const LegTruth& t = truth[k];
    EXPECT_NEAR(r.with_s.weight_n.value, t.weight_n, 1e-9);
    EXPECT_LT((r.with_s.Offset() - t.offset).norm(), 1e-9);
    for (int p = 0; p < 2; ++p) {
      const HangingPairResult& pr = r.with_s.pair[p];
      EXPECT_EQ(pr.axis, p == 0 ? 'x' : 'z');
      EXPECT_EQ(pr.matched_samples, 2000);
      EXPECT_EQ(pr.cycles, 10);
      EXPECT_NEAR(pr.weight_n.value, t.weight_n, 1e-9);
      const Vec3& s_down = t.s[2 * p];
      const Vec3& s_up = t.s[2 * p + 1];
      EXPECT_LT((pr.s_plus_rad.value - 0.5 * (s_down + s_up)).norm(), 1e-9);
      EXPECT_LT((pr.s_minus_rad.value - 0.5 * (s_down - s_up)).norm(), 1e-9);
      EXPECT_LT((pr.force_offset_n.value - t.offset.head<3>()).norm(), 1e-9);
      EXPECT_LT((pr.torque_offset_nm.value - t.offset.tail<3>()).norm(), 1e-9);
    }
    ExpectSinusoid(r.com.model.x, t.com.x, 1e-9);
    ExpectSinusoid(r.com.model.z, t.com.z, 1e-9);
    EXPECT_NEAR(r.com.model.y, t.com.y, 1e-9);
    // Per-bin medians lie on the curve.
    ASSERT_EQ(r.com_bins.phase.size(), 200u);
    for (size_t b = 0; b < r.com_bins.phase.size(); ++b) {
      EXPECT_LT((r.com_bins.median_m[b] - t.com.At(r.com_bins.phase[b])).norm(), 1e-9);
    }
    // The model explains every sample; without s it does not.
    EXPECT_LT(r.with_s.residual.rms.maxCoeff(), 1e-9);
    EXPECT_GT(r.without_s.residual.rms.head<3>().maxCoeff(), 0.05);
    EXPECT_EQ(r.with_s.residual.count, 4 * 2000);
  }
  // Mirrored legs: HR's x-down series is HANG_X_NEG, MR's z-down is HANG_Z_NEG.
  EXPECT_EQ(res.leg[0].with_s.pair[0].down_series, HangSeries::kXPos);
  EXPECT_EQ(res.leg[3].with_s.pair[0].down_series, HangSeries::kXNeg);
  EXPECT_EQ(res.leg[4].with_s.pair[1].down_series, HangSeries::kZNeg);
  EXPECT_EQ(res.leg[5].with_s.pair[0].down_series, HangSeries::kXNeg);
  EXPECT_EQ(res.leg[5].with_s.pair[1].down_series, HangSeries::kZNeg);
}

TEST(Hanging, FiniteRotationsExactOptionRecoversFirstOrderIsBiasedLow) {
  const auto X = NominalPoses();
  const auto truth = MakeTruth(0.045);  // 3-4 deg misalignments
  Motion m;
  m.exact = true;
  m.bins = 100;
  const auto recs = MakeRecordings(X, truth, m, nullptr);
  HangingOptions o = ExactOptions();
  o.phase_bins = 100;
  o.exact_rotations = true;
  const HangingResult exact = RunHanging(recs, X, o);
  o.exact_rotations = false;
  const HangingResult first = RunHanging(recs, X, o);
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(std::string(kLegNames[k]));
    const LegTruth& t = truth[k];
    const LegHangingResult& r = exact.leg[k];
    EXPECT_NEAR(r.with_s.weight_n.value, t.weight_n, 1e-9);
    EXPECT_LT((r.with_s.Offset() - t.offset).norm(), 1e-9);
    for (int p = 0; p < 2; ++p) {
      const Vec3 s_plus = 0.5 * (t.s[2 * p] + t.s[2 * p + 1]);
      const Vec3 s_minus = 0.5 * (t.s[2 * p] - t.s[2 * p + 1]);
      EXPECT_LT((r.with_s.pair[p].s_plus_rad.value - s_plus).norm(), 1e-9);
      EXPECT_LT((r.with_s.pair[p].s_minus_rad.value - s_minus).norm(), 1e-9);
    }
    EXPECT_LT(CurveError(r.com.model, t.com), 1e-9);
    EXPECT_LT(r.with_s.residual.rms.maxCoeff(), 1e-9);
    // I + [s] shortens the misaligned weight: m g comes out low by about |s|^2 / 2.
    const double bias = (t.weight_n - first.leg[k].with_s.weight_n.value) / t.weight_n;
    const double s2 = 0.5 * (t.s[0].squaredNorm() + t.s[1].squaredNorm());
    EXPECT_GT(bias, 0.3 * s2 / 2);
    EXPECT_LT(bias, 3.0 * s2 / 2);
    EXPECT_GT(bias, 5e-4);
  }
}

// Independent route: the sensing model of sensing_model.h, with mounting errors R~ and a hang
// tilted away from the stated axis; the truth s is the smallest rotation from the transducer
// axis to the gravity direction each leg actually sees.
TEST(Hanging, SensingModelTwinExactOption) {
  const auto X = NominalPoses();
  RobotCalibration cal;
  cal.X_B_ft = X;
  const auto truth = MakeTruth(0.0);
  for (int k = 0; k < kNumLegs; ++k) {
    cal.leg[k].offset = truth[k].offset;
    cal.leg[k].weight_n = truth[k].weight_n;
    cal.leg[k].com = truth[k].com;
    cal.leg[k].R_tilde = RotVec(Vec3(0.01 * k, -0.02 + 0.005 * k, 0.015));
    cal.leg[k].p_tilde_prime = Vec3(0.003, -0.002 * k, 0.001);
  }
  cal.p_C_B = Vec3(0.01, -0.005, 0.02);
  const int bins = 100;
  std::vector<HangingRecording> recs;
  std::array<Mat3, kNumHangSeries> R_WC;
  const Vec3 tilts[4] = {Vec3(0.02, 0.03, 0.0), Vec3(-0.03, 0.01, 0.2), Vec3(0.01, -0.02, 1.0),
                         Vec3(0.025, 0.02, -0.4)};
  for (int s = 0; s < kNumHangSeries; ++s) {
    const HangSeries series = static_cast<HangSeries>(s);
    HangingRecording rec;
    rec.series = series;
    rec.gravity_b = SeriesGravityB(series);
    // R_WC takes the stated gravity_b to world down, then a small tilt.
    const Mat3 R_nominal = Quat::FromTwoVectors(rec.gravity_b, Vec3(0, 0, -1)).toRotationMatrix();
    R_WC[s] =
        RotVec(Vec3(0, 0, tilts[s].z())) * R_nominal * RotVec(Vec3(tilts[s].x(), tilts[s].y(), 0));
    rec.attitude.assign(10, R_WC[s]);
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 5 * bins; ++i) {
        const double th =
            std::remainder((k < 3 ? 1 : -1) * kTwoPi * (i + 0.5 + 17 * s) / bins, kTwoPi);
        rec.legs[k].t_s.push_back(0.01 * i);
        rec.legs[k].angle_rad.push_back(th);
        rec.legs[k].wrench.push_back(TransducerReading(cal, k, Vec6::Zero(), th, R_WC[s]));
      }
    }
    recs.push_back(rec);
  }
  HangingOptions o = ExactOptions();
  o.phase_bins = bins;
  o.exact_rotations = true;
  const HangingResult res = RunHanging(recs, X, o);
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(std::string(kLegNames[k]));
    const LegHangingResult& r = res.leg[k];
    EXPECT_NEAR(r.with_s.weight_n.value, truth[k].weight_n, 1e-9);
    EXPECT_LT((r.with_s.Offset() - truth[k].offset).norm(), 1e-9);
    EXPECT_LT(CurveError(r.com.model, truth[k].com), 1e-9);
    for (int p = 0; p < 2; ++p) {
      const HangingPairResult& pr = r.with_s.pair[p];
      const Vec3 axis = p == 0 ? Vec3::UnitX() : Vec3::UnitZ();
      Vec3 s_of[2];
      const HangSeries series_of[2] = {pr.down_series, pr.up_series};
      for (int d = 0; d < 2; ++d) {
        const Mat3 R_C_ft = cal.X_C_ft(k).R;
        const Vec3 g_ft =
            R_C_ft.transpose() * R_WC[static_cast<int>(series_of[d])].transpose() * Vec3(0, 0, -1);
        const Eigen::AngleAxisd aa(Quat::FromTwoVectors(axis, (d == 0 ? 1.0 : -1.0) * g_ft));
        s_of[d] = aa.angle() * aa.axis();
      }
      EXPECT_LT((pr.s_plus_rad.value - 0.5 * (s_of[0] + s_of[1])).norm(), 1e-9);
      EXPECT_LT((pr.s_minus_rad.value - 0.5 * (s_of[0] - s_of[1])).norm(), 1e-9);
    }
  }
  // What each transducer saw of gravity, beside motion capture: R~_k u_B = v_C exactly (the
  // hanging gravity prior of step 2), one observation per leg and series, no spread.
  ASSERT_EQ(res.gravity_observations.size(), static_cast<size_t>(kNumLegs * kNumHangSeries));
  for (const HangingGravityObservation& obs : res.gravity_observations) {
    SCOPED_TRACE(std::string(kLegNames[obs.leg]) + " " + HangSeriesName(obs.series));
    const Vec3 v = R_WC[static_cast<int>(obs.series)].transpose() * Vec3(0, 0, -1);
    EXPECT_LT((obs.v_C - v).norm(), 1e-12);
    EXPECT_LT((cal.leg[obs.leg].R_tilde * obs.u_B - v).norm(), 1e-9);
    EXPECT_LT(obs.sigma_rad, 1e-9);
  }
  // Without attitude samples there is nothing to observe.
  {
    std::vector<HangingRecording> blind = recs;
    blind[2].attitude.clear();
    EXPECT_TRUE(RunHanging(blind, X, o).gravity_observations.empty());
  }

  // With the result in the sensing model, eq. 3 gives zero ground wrench while hanging.
  RobotCalibration estimated = cal;
  for (int k = 0; k < kNumLegs; ++k) estimated.leg[k] = LegCalibration{};
  for (int k = 0; k < kNumLegs; ++k) {
    estimated.leg[k].R_tilde = cal.leg[k].R_tilde;
    estimated.leg[k].p_tilde_prime = cal.leg[k].p_tilde_prime;
  }
  ApplyHangingResult(res, &estimated);
  for (int s = 0; s < kNumHangSeries; ++s) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 500; i += 37) {
        const LegSamples& ls = recs[s].legs[k];
        EXPECT_LT(GroundWrenchC(estimated, k, ls.wrench[i], ls.angle_rad[i], R_WC[s]).norm(), 1e-9);
      }
    }
  }
}

// ------------------------------------------------------------ the whole step with noise

TEST(Hanging, NoisyDataWithinToleranceAndSigmasHonest) {
  const auto X = NominalPoses();
  const auto truth = MakeTruth(0.03);
  Motion m;
  m.aligned = false;
  m.samples_per_cycle = 970.0;  // 9.7 s per cycle at 100 Hz, not a multiple of the bins
  m.cycles = 10.02;
  m.angle_quantum_rad = kTwoPi / 4096;
  m.f_noise_n = 0.05;
  m.tau_noise_nm = 0.002;
  std::mt19937 rng(20240611);
  const auto recs = MakeRecordings(X, truth, m, &rng);
  const HangingResult res = RunHanging(recs, X, HangingOptions());
  double z2 = 0.0;
  int nz = 0;
  auto z = [&](double err, double sigma) {
    EXPECT_GT(sigma, 0.0);
    EXPECT_LT(std::abs(err), 5.0 * sigma);
    z2 += (err / sigma) * (err / sigma);
    ++nz;
  };
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(std::string(kLegNames[k]));
    const LegHangingResult& r = res.leg[k];
    const LegTruth& t = truth[k];
    EXPECT_NEAR(r.with_s.weight_n.value, t.weight_n, 0.015);
    EXPECT_LT((r.with_s.force_offset_n.value - t.offset.head<3>()).cwiseAbs().maxCoeff(), 0.02);
    EXPECT_LT((r.with_s.torque_offset_nm.value - t.offset.tail<3>()).cwiseAbs().maxCoeff(), 0.001);
    EXPECT_LT(CurveError(r.com.model, t.com), 0.2e-3);
    z(r.with_s.weight_n.value - t.weight_n, r.with_s.weight_n.sigma);
    for (int c = 0; c < 3; ++c) {
      z(r.with_s.force_offset_n.value(c) - t.offset(c), r.with_s.force_offset_n.sigma(c));
      z(r.with_s.torque_offset_nm.value(c) - t.offset(3 + c), r.with_s.torque_offset_nm.sigma(c));
    }
    for (int p = 0; p < 2; ++p) {
      const HangingPairResult& pr = r.with_s.pair[p];
      const Vec3 s_plus = 0.5 * (t.s[2 * p] + t.s[2 * p + 1]);
      const Vec3 s_minus = 0.5 * (t.s[2 * p] - t.s[2 * p + 1]);
      const int across[2] = {p == 0 ? 1 : 0, p == 0 ? 2 : 1};
      for (int c : across) {
        z(pr.s_plus_rad.value(c) - s_plus(c), pr.s_plus_rad.sigma(c));
        z(pr.s_minus_rad.value(c) - s_minus(c), pr.s_minus_rad.sigma(c));
      }
    }
    z(r.com.model.x.d - t.com.x.d, r.com.sigma_x(2));
    z(r.com.model.z.a - t.com.z.a, r.com.sigma_z(0));
    // Residuals: with s at the noise level, the naive tare far above it.
    EXPECT_LT(r.with_s.residual.std.head<3>().maxCoeff(), 0.06);
    EXPECT_GT(r.naive_residual.rms.head<3>().maxCoeff(), 5.0);
    // Naive tare: upright reading near theta = 0, so it carries the leg's weight.
    const int slot_up = SlotOf(X[k], -Vec3::UnitZ());
    const Vec3 f_up = (slot_up == 2 ? 1.0 : -1.0) * t.weight_n *
                      ((Mat3::Identity() + Skew(t.s[slot_up])) * Vec3::UnitZ());
    EXPECT_LT((r.naive_offset.head<3>() - (t.offset.head<3>() + f_up)).norm(), 0.02);
  }
  // Residual statistics of the naive tare, recomputed by brute force (sort) for one leg.
  {
    const LegHangingResult& r = res.leg[4];
    std::vector<std::vector<double>> c(6);
    for (const HangingRecording& rec : recs) {
      for (const Vec6& w : rec.legs[4].wrench) {
        for (int k = 0; k < 6; ++k) c[k].push_back(w(k) - r.naive_offset(k));
      }
    }
    ASSERT_EQ(r.naive_residual.count, static_cast<int>(c[0].size()));
    const size_t n = c[0].size();
    for (int k = 0; k < 6; ++k) {
      std::sort(c[k].begin(), c[k].end());
      EXPECT_EQ(r.naive_residual.p05(k), c[k][static_cast<size_t>(std::floor(0.05 * (n - 1)))]);
      EXPECT_EQ(r.naive_residual.p95(k), c[k][static_cast<size_t>(std::ceil(0.95 * (n - 1)))]);
      double sum = 0.0;
      for (double v : c[k]) sum += v;
      EXPECT_NEAR(r.naive_residual.mean(k), sum / n, 1e-9);
    }
  }
  // The sigmas describe the actual errors: mean squared z-score near 1.
  const double mean_z2 = z2 / nz;
  EXPECT_GT(mean_z2, 0.3);
  EXPECT_LT(mean_z2, 2.5);
}

TEST(Hanging, NoisyFiniteRotationsExactOption) {
  const auto X = NominalPoses();
  const auto truth = MakeTruth(0.06);  // 4-6 deg: I + [s] would be off by ~0.25% of m g
  Motion m;
  m.exact = true;
  m.aligned = false;
  m.samples_per_cycle = 830.0;
  m.cycles = 10.01;
  m.angle_quantum_rad = kTwoPi / 4096;
  m.f_noise_n = 0.05;
  m.tau_noise_nm = 0.002;
  std::mt19937 rng(99);
  const auto recs = MakeRecordings(X, truth, m, &rng);
  HangingOptions o;
  o.exact_rotations = true;
  const HangingResult res = RunHanging(recs, X, o);
  for (int k = 0; k < kNumLegs; ++k) {
    SCOPED_TRACE(std::string(kLegNames[k]));
    const LegHangingResult& r = res.leg[k];
    const LegTruth& t = truth[k];
    EXPECT_NEAR(r.with_s.weight_n.value, t.weight_n, 0.015);
    EXPECT_LT(std::abs(r.with_s.weight_n.value - t.weight_n), 5.0 * r.with_s.weight_n.sigma);
    EXPECT_LT((r.with_s.force_offset_n.value - t.offset.head<3>()).cwiseAbs().maxCoeff(), 0.02);
    EXPECT_LT((r.with_s.torque_offset_nm.value - t.offset.tail<3>()).cwiseAbs().maxCoeff(), 0.001);
    EXPECT_LT(CurveError(r.com.model, t.com), 0.2e-3);
  }
}

// ------------------------------------------------------------ output

TEST(Hanging, WritesCalibrationProto) {
  const auto X = NominalPoses();
  const auto truth = MakeTruth(0.03);
  Motion m;
  m.bins = 50;
  m.cycles = 3;
  const auto recs = MakeRecordings(X, truth, m, nullptr);
  HangingOptions o = ExactOptions();
  o.phase_bins = 50;
  const HangingResult res = RunHanging(recs, X, o);
  calibration::Calibration cal;
  WriteHangingToCalibration(res, &cal);
  EXPECT_EQ(cal.hanging_uncertainty(), calibration::CYCLE_SPREAD);
  ASSERT_EQ(cal.leg_size(), kNumLegs);
  ASSERT_EQ(cal.hanging_residual_size(), 3 * kNumLegs);
  EXPECT_EQ(cal.hanging_residual(3).label(), "ML with s");
  for (int k = 0; k < kNumLegs; ++k) {
    const calibration::LegCalibration& l = cal.leg(k);
    EXPECT_EQ(l.name(), kLegNames[k]);
    EXPECT_NEAR(l.leg_weight_n().value(), truth[k].weight_n, 1e-9);
    EXPECT_NEAR(l.force_offset_n().z(), truth[k].offset(2), 1e-9);
    EXPECT_NEAR(l.torque_offset_nm().x(), truth[k].offset(3), 1e-9);
    EXPECT_NEAR(l.com().x().a_m(), truth[k].com.x.a, 1e-9);
    EXPECT_NEAR(l.com().y_m().value(), truth[k].com.y, 1e-9);
    EXPECT_EQ(l.com().bin_phase_size(), 50);
    ASSERT_EQ(l.hanging_size(), 2);
    EXPECT_EQ(l.hanging(1).axis(), "z");
    EXPECT_EQ(l.hanging(0).matched_samples(), 150u);
    EXPECT_EQ(l.naive_offset_size(), 6);
  }
  // Writing again updates the same legs rather than appending.
  WriteHangingToCalibration(res, &cal);
  EXPECT_EQ(cal.leg_size(), kNumLegs);
  EXPECT_EQ(cal.hanging_residual_size(), 3 * kNumLegs);
}

// ------------------------------------------------------------ degenerate input

class HangingRefuses : public ::testing::Test {
 protected:
  void SetUp() override {
    x_ = NominalPoses();
    truth_ = MakeTruth(0.03);
    motion_.bins = 40;
    motion_.cycles = 3;
    options_.phase_bins = 40;
    recs_ = MakeRecordings(x_, truth_, motion_, nullptr);
  }
  // Runs and returns the error message ("" when it did not throw).
  std::string Message() {
    try {
      RunHanging(recs_, x_, options_);
    } catch (const std::invalid_argument& e) {
      return e.what();
    }
    return "";
  }
  std::array<Pose3, kNumLegs> x_;
  std::array<LegTruth, kNumLegs> truth_;
  Motion motion_;
  HangingOptions options_;
  std::vector<HangingRecording> recs_;
};

TEST_F(HangingRefuses, NothingWrongWithTheBaseData) { EXPECT_EQ(Message(), ""); }

TEST_F(HangingRefuses, MissingSeries) {
  recs_.pop_back();
  EXPECT_EQ(Message(), "hanging: series HANG_Z_NEG is missing");
}

TEST_F(HangingRefuses, DuplicateSeries) {
  recs_[1].series = HangSeries::kXPos;
  EXPECT_EQ(Message(), "hanging: series HANG_X_POS given twice");
}

TEST_F(HangingRefuses, TooFewCycles) {
  LegSamples& ls = recs_[2].legs[4];
  const size_t keep = 60;  // 1.5 cycles of 40 bins
  ls.t_s.resize(keep);
  ls.angle_rad.resize(keep);
  ls.wrench.resize(keep);
  const std::string msg = Message();
  EXPECT_NE(msg.find("HANG_Z_POS, leg MR"), std::string::npos) << msg;
  EXPECT_NE(msg.find("cycles"), std::string::npos) << msg;
}

TEST_F(HangingRefuses, PhaseCoverage) {
  // A dropout over a third of every cycle in one series.
  LegSamples& ls = recs_[1].legs[2];
  LegSamples kept;
  for (size_t i = 0; i < ls.t_s.size(); ++i) {
    const double phase = LegPhase(ls.angle_rad[i]);
    if (phase > 0.2 && phase < 0.55) continue;
    kept.t_s.push_back(ls.t_s[i]);
    kept.angle_rad.push_back(ls.angle_rad[i]);
    kept.wrench.push_back(ls.wrench[i]);
  }
  ls = kept;
  const std::string msg = Message();
  EXPECT_NE(msg.find("HANG_X_NEG, leg FL"), std::string::npos) << msg;
  EXPECT_NE(msg.find("phase coverage"), std::string::npos) << msg;
}

TEST_F(HangingRefuses, NonFiniteSample) {
  recs_[0].legs[1].wrench[17](4) = std::numeric_limits<double>::quiet_NaN();
  const std::string msg = Message();
  EXPECT_NE(msg.find("HANG_X_POS, leg ML: non-finite value in sample 17"), std::string::npos)
      << msg;
  SetUp();
  recs_[3].legs[0].angle_rad[5] = std::numeric_limits<double>::infinity();
  EXPECT_NE(Message().find("HANG_Z_NEG, leg HL: non-finite value in sample 5"), std::string::npos);
}

TEST_F(HangingRefuses, MismatchedLengths) {
  recs_[2].legs[5].angle_rad.pop_back();
  const std::string msg = Message();
  EXPECT_NE(msg.find("HANG_Z_POS, leg FR: mismatched sample vectors"), std::string::npos) << msg;
}

TEST_F(HangingRefuses, EmptyLeg) {
  recs_[0].legs[3] = LegSamples{};
  EXPECT_NE(Message().find("HANG_X_POS, leg HR: no samples"), std::string::npos);
}

TEST_F(HangingRefuses, TimeGoingBackwards) {
  recs_[0].legs[0].t_s[9] = -1.0;
  EXPECT_NE(Message().find("HANG_X_POS, leg HL: sample 9 is earlier"), std::string::npos);
}

TEST_F(HangingRefuses, StatedAxisOffTheTransducerAxes) {
  recs_[2].gravity_b = Vec3(0.0, 1.0, 1.0).normalized();
  const std::string msg = Message();
  EXPECT_NE(msg.find("HANG_Z_POS, leg HL: stated gravity in the transducer frame"),
            std::string::npos)
      << msg;
  EXPECT_NE(msg.find("45 deg from the nearest transducer x or z axis"), std::string::npos) << msg;
}

TEST_F(HangingRefuses, TwoSeriesOnOneAxis) {
  recs_[1].gravity_b = Vec3::UnitX();  // HANG_X_NEG stated like HANG_X_POS
  const std::string msg = Message();
  EXPECT_NE(msg.find("leg HL: series HANG_X_POS and HANG_X_NEG both have gravity along +x"),
            std::string::npos)
      << msg;
}

TEST_F(HangingRefuses, MotionCaptureDisagreesWithStatedAxis) {
  // Motion capture shows the robot 20 deg off the stated nose-down hang.
  const Mat3 R_nominal = Quat::FromTwoVectors(Vec3::UnitX(), Vec3(0, 0, -1)).toRotationMatrix();
  recs_[0].attitude.assign(5, R_nominal * RotVec(Vec3(0, 20.0 * M_PI / 180, 0)));
  const std::string msg = Message();
  EXPECT_NE(msg.find("hanging series HANG_X_POS: motion capture"), std::string::npos) << msg;
  EXPECT_NE(msg.find("20 deg from the stated"), std::string::npos) << msg;
  // 5 deg off is within the default 10 deg.
  recs_[0].attitude.assign(5, R_nominal * RotVec(Vec3(0, 5.0 * M_PI / 180, 0)));
  EXPECT_EQ(Message(), "");
}

TEST_F(HangingRefuses, WeightTheWrongWayRound) {
  // The x-down and x-up series swapped in content: the leg's weight points the wrong way.
  std::swap(recs_[0].legs, recs_[1].legs);
  const std::string msg = Message();
  EXPECT_NE(msg.find("x pair"), std::string::npos) << msg;
  EXPECT_NE(msg.find("wrong way round"), std::string::npos) << msg;
}

}  // namespace
}  // namespace ftcal
