// The information-matrix prediction of a plan's sigma (ftcal/plan_prediction.h) against the
// calibrator on the twin's data of the same plan: the twin runs the plan (hanging cycles,
// poses, dwell) with its default noise, Calibrate() reports its sigma; the prediction sees only
// the plan, the twin's noise-free readings of the same poses and the noise the twin is
// configured with. The truth is the calibrator's own reported sigma (it comes from the data's
// scatter: the spread over leg cycles in step 1, the residuals in step 2), so a prediction that
// mis-counts samples, mis-propagates a noise or drops a parameter fails here.
//
// Environment knobs for the investigation of issue 41 (numbers in docs/method.md): the number
// of seeds (FTCAL_PLAN_SEEDS), the report's whole experiment (FTCAL_PLAN_FULL), the CoM moving
// with the legs (FTCAL_PLAN_MOVING_COM), the prediction linearised at the true mounting
// (FTCAL_PLAN_AT_TRUTH), the twin's noise scaled (FTCAL_PLAN_NOISE_SCALE, or only the
// attitude's FTCAL_PLAN_ATTITUDE_SCALE, only the readings' FTCAL_PLAN_READING_SCALE). With any
// of them set, step 2 is also run from the true step 1. Without them it is the fast-tier check.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <string>
#include <vector>

#include "ftcal/plan_prediction.h"
#include "twin_calibration.h"

namespace ftcal {
namespace {

using namespace testing_twin;  // NOLINT

struct SmallPlan {
  int hang_cycles = 4;
  double hang_cycle_s = 10.0;
  int poses = 120;
  double dwell_s = 5.0;
};

TwinOptions TwinOf(const SmallPlan& plan, uint64_t seed) {
  TwinOptions o;
  o.seed = seed;
  o.hang_cycles = plan.hang_cycles;
  o.hang_cycle_s = plan.hang_cycle_s;
  o.pose_dwell_s = plan.dwell_s;
  // FTCAL_PLAN_MOVING_COM: the CoM moves with the legs (the leg-aware target).
  o.physical_com = std::getenv("FTCAL_PLAN_MOVING_COM") != nullptr;
  // FTCAL_PLAN_NOISE_SCALE: every noise scaled (small: what is left of an error is a bias).
  if (const char* scale = std::getenv("FTCAL_PLAN_NOISE_SCALE")) {
    const double f = std::atof(scale);
    o.force_noise_n *= f;
    o.torque_noise_nm *= f;
    o.attitude_noise_deg *= f;
    o.marker_noise_m *= f;
  }
  // ... or only the attitude's (FTCAL_PLAN_ATTITUDE_SCALE), only the readings' (_READING_).
  if (const char* scale = std::getenv("FTCAL_PLAN_ATTITUDE_SCALE"))
    o.attitude_noise_deg *= std::atof(scale);
  if (const char* scale = std::getenv("FTCAL_PLAN_READING_SCALE")) {
    o.force_noise_n *= std::atof(scale);
    o.torque_noise_nm *= std::atof(scale);
  }
  return o;
}

// The plan as the predictor sees it: the twin's poses without noise (same seed, so the same
// angles, loads and dropped poses), the samples the twin's steady part holds, and its noise.
PlanDesign DesignOf(const config::Config& config, const SmallPlan& plan, const TwinOptions& noisy,
                    const BigAntTwin& twin, DeviceNoise* noise) {
  TwinOptions quiet = noisy;
  quiet.force_noise_n = quiet.torque_noise_nm = quiet.attitude_noise_deg = 0.0;
  quiet.marker_noise_m = 0.0;
  const BigAntTwin clean(config, quiet);
  PlanDesign d;
  for (int s = 0; s < kNumHangSeries; ++s) {
    PlannedHangSeries h;
    h.series = static_cast<HangSeries>(s);
    h.gravity_b = twin.StatedGravityB(h.series);
    h.cycles = plan.hang_cycles;
    h.samples_per_cycle = plan.hang_cycle_s * noisy.sample_rate_hz;
    d.hanging.push_back(h);
  }
  const double steady = (plan.dwell_s - noisy.settle_cutoff_s) * noisy.sample_rate_hz;
  for (const StandingPose& p : clean.MakeSteadyPoses(plan.poses)) d.poses.push_back({p, steady});
  d.leg_aware_com = noisy.physical_com;
  noise->force_n = noisy.force_noise_n;
  noise->torque_nm = noisy.torque_noise_nm;
  noise->attitude_rad = noisy.attitude_noise_deg * kDegree;
  return d;
}

// The step-1 values the calibrator would start step 2 from, at the twin's truth; no mounting
// error (the nominal the prediction linearises at).
RobotCalibration NominalOf(const BigAntTwin& twin) {
  RobotCalibration cal = twin.Truth();
  // FTCAL_PLAN_AT_TRUTH: linearise at the true mounting instead (the investigation of issue 41).
  if (std::getenv("FTCAL_PLAN_AT_TRUTH") != nullptr) return cal;
  for (LegCalibration& l : cal.leg) {
    l.R_tilde = Mat3::Identity();
    l.p_tilde_prime = Vec3::Zero();
  }
  cal.p_C_B = Vec3::Zero();
  return cal;
}

// The calibrator's reported sigma per parameter, named as the prediction names them.
std::map<std::string, double> ReportedSigma(const CalibrationRun& run) {
  std::map<std::string, double> out;
  const char* axes[3] = {"x", "y", "z"};
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string leg = std::string(kLegNames[k]) + " ";
    const HangingVariant& h = run.hanging.leg[k].with_s;
    for (int i = 0; i < 3; ++i) {
      out[leg + "f_o " + axes[i]] = h.force_offset_n.sigma[i];
      out[leg + "tau_o " + axes[i]] = h.torque_offset_nm.sigma[i];
    }
    out[leg + "m g"] = h.weight_n.sigma;
    const ComFitResult& c = run.hanging.leg[k].com;
    out[leg + "CoM x a"] = c.sigma_x[0];
    out[leg + "CoM x c"] = c.sigma_x[1];
    out[leg + "CoM x d"] = c.sigma_x[2];
    out[leg + "CoM y"] = c.sigma_y_m;
    out[leg + "CoM z a"] = c.sigma_z[0];
    out[leg + "CoM z c"] = c.sigma_z[1];
    out[leg + "CoM z d"] = c.sigma_z[2];
    const StandingFit& f = run.standing.fit;
    for (int i = 0; i < 3; ++i) {
      out[leg + "R~ " + axes[i]] = f.sigma_rotation_deg[k][i];
      out[leg + "p~' " + axes[i]] = f.sigma_p_tilde_prime_m[k][i];
    }
  }
  return out;
}

// The reported sigma of the mean of the six p~'_z, from the fit's sigmas and correlation.
double ReportedCommonPz(const StandingFit& f) {
  const int n = static_cast<int>(f.correlation_names.size());
  std::vector<int> idx;
  std::vector<double> s;
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string name = std::string(kLegNames[k]) + " p~' z";
    for (int j = 0; j < n; ++j) {
      if (f.correlation_names[j] == name) idx.push_back(j);
    }
    s.push_back(f.sigma_p_tilde_prime_m[k][2]);
  }
  EXPECT_EQ(idx.size(), static_cast<size_t>(kNumLegs));
  double v = 0.0;
  for (int a = 0; a < kNumLegs; ++a) {
    for (int b = 0; b < kNumLegs; ++b) v += f.correlation(idx[a], idx[b]) * s[a] * s[b];
  }
  return std::sqrt(v) / kNumLegs;
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const size_t m = v.size() / 2;
  return v.size() % 2 ? v[m] : 0.5 * (v[m - 1] + v[m]);
}

struct SeedResult {
  std::map<std::string, std::vector<double>> ratio;  // class -> predicted / reported per param
  std::map<std::string, std::vector<double>> by_parameter;  // "CoM x a", ... over the legs
  double common_error = 0.0, common_reported = 0.0, common_predicted = 0.0;
  double common_honest = 0.0, common_bound = 0.0, common_with_step1 = 0.0;
  // Step 2 again from the true step 1 (the twin's offsets, leg weights and CoM curves).
  double common_error_true_step1 = 0.0, common_reported_true_step1 = 0.0;
};

double CommonPzError(const StandingFit& fit, const RobotCalibration& truth) {
  double err = 0.0;
  for (int k = 0; k < kNumLegs; ++k)
    err += fit.p_tilde_prime[k].z() - truth.leg[k].p_tilde_prime.z();
  return err / kNumLegs;
}

// The calibration's step 2 on the same poses from the true step 1.
StandingFit StandingFromTrueStepOne(const config::Config& config, const CalibrationRun& run,
                                    const std::vector<StandingPose>& poses,
                                    const RobotCalibration& truth) {
  HangingResult h = run.hanging;
  for (int k = 0; k < kNumLegs; ++k) {
    HangingVariant& v = h.leg[k].with_s;
    v.force_offset_n.value = truth.leg[k].offset.head<3>();
    v.torque_offset_nm.value = truth.leg[k].offset.tail<3>();
    v.weight_n.value = truth.leg[k].weight_n;
    h.leg[k].com.model = truth.leg[k].com;
  }
  return CalibrateFromHanging(h, poses, config, StandingOptionsFromConfig(config.calibrator()))
      .standing.fit;
}

SeedResult RunSeed(const config::Config& config, const SmallPlan& plan, uint64_t seed) {
  const TwinOptions o = TwinOf(plan, seed);
  const BigAntTwin twin(config, o);
  const std::vector<StandingPose> poses = twin.MakeSteadyPoses(plan.poses);
  const CalibrationRun run = Calibrate(HangingOf(twin), poses, config);
  DeviceNoise noise;
  const PlanDesign design = DesignOf(config, plan, o, twin, &noise);
  EXPECT_EQ(design.poses.size(), static_cast<size_t>(run.standing.poses));
  const PlanPrediction pred = PredictPlan(
      NominalOf(twin), design, noise, HangingOptionsFromConfig(config.calibrator(), config.mocap()),
      StandingOptionsFromConfig(config.calibrator()));
  const std::map<std::string, double> reported = ReportedSigma(run);
  SeedResult r;
  for (const PredictedSigma& p : pred.parameters) {
    const auto it = reported.find(p.name);
    EXPECT_NE(it, reported.end()) << p.name;
    if (it == reported.end() || !(it->second > 0.0)) continue;
    r.ratio[p.klass].push_back(p.reported / it->second);
    r.by_parameter[p.name.substr(3)].push_back(p.reported / it->second);
  }
  r.common_error = CommonPzError(run.standing.fit, twin.Truth());
  std::printf("plan prediction: seed %llu: selected %s\n", static_cast<unsigned long long>(seed),
              CandidateName(run.standing.fit.model, run.standing.selected_leg_aware_com).c_str());
  Vec6 ms = Vec6::Zero();
  for (const Vec6& v : run.standing.residual_full) ms += v.cwiseAbs2();
  const Vec6 rms = (ms / run.standing.residual_full.size()).cwiseSqrt();
  std::printf("plan prediction: seed %llu: residual rms / predicted [fx fy fz tx ty tz]:",
              static_cast<unsigned long long>(seed));
  for (int i = 0; i < 6; ++i) std::printf(" %.3f", rms[i] / pred.residual_rms[i]);
  std::printf("\n");
  r.common_with_step1 = pred.common_p_z.with_step1;
  if (std::getenv("FTCAL_PLAN_SEEDS") != nullptr) {
    const StandingFit t = StandingFromTrueStepOne(config, run, poses, twin.Truth());
    r.common_error_true_step1 = CommonPzError(t, twin.Truth());
    r.common_reported_true_step1 = ReportedCommonPz(t);
  }
  r.common_reported = ReportedCommonPz(run.standing.fit);
  r.common_predicted = pred.common_p_z.reported;
  r.common_honest = pred.common_p_z.sigma;
  r.common_bound = pred.common_p_z.bound;
  return r;
}

// Seeds: 3 here (the main tier); FTCAL_PLAN_SEEDS raises it for the investigation of issue 41.
int Seeds() {
  const char* s = std::getenv("FTCAL_PLAN_SEEDS");
  return s ? std::max(1, std::atoi(s)) : 3;
}

TEST(PlanPrediction, PredictedSigmaMatchesWhatTheCalibratorReportsOnTheTwin) {
  const config::Config config = SimConfig();
  SmallPlan plan;
  // FTCAL_PLAN_FULL: the report's experiment (10 cycles of 20 s, all 729 poses) instead.
  if (std::getenv("FTCAL_PLAN_FULL") != nullptr) plan = {10, 20.0, 729, 5.0};
  std::map<std::string, std::vector<double>> ratio, by_parameter;
  std::vector<double> z_reported, z_honest, z_step1, z_true_step1, ratio_common;
  const int seeds = Seeds();
  for (int i = 0; i < seeds; ++i) {
    const SeedResult r = RunSeed(config, plan, 4100 + i);
    for (const auto& [k, v] : r.ratio) ratio[k].insert(ratio[k].end(), v.begin(), v.end());
    for (const auto& [k, v] : r.by_parameter)
      by_parameter[k].insert(by_parameter[k].end(), v.begin(), v.end());
    ratio_common.push_back(r.common_predicted / r.common_reported);
    z_reported.push_back(std::abs(r.common_error) / r.common_reported);
    z_honest.push_back(std::abs(r.common_error) / r.common_honest);
    z_step1.push_back(std::abs(r.common_error) / r.common_with_step1);
    if (r.common_reported_true_step1 > 0.0)
      z_true_step1.push_back(std::abs(r.common_error_true_step1) / r.common_reported_true_step1);
    std::printf(
        "plan prediction: seed %d: common p~'_z error %+.1f um, reported sigma %.1f um, "
        "predicted: as reported %.1f um, true %.1f um, bound %.1f um, with step 1's errors "
        "%.1f um; from the true step 1: error %+.1f um, reported %.1f um\n",
        4100 + i, r.common_error * 1e6, r.common_reported * 1e6, r.common_predicted * 1e6,
        r.common_honest * 1e6, r.common_bound * 1e6, r.common_with_step1 * 1e6,
        r.common_error_true_step1 * 1e6, r.common_reported_true_step1 * 1e6);
  }
  for (const auto& [k, v] : by_parameter)
    std::printf("plan prediction:   %-10s predicted / reported: median %.3f\n", k.c_str(),
                Median(v));
  for (const auto& [k, v] : ratio) {
    const double m = Median(v);
    std::printf("plan prediction: %-14s predicted / reported sigma: median %.3f (%zu values)\n",
                k.c_str(), m, v.size());
    // Within 20 % (issue 41), except the leg CoM curve: step 1's estimator (per-sample CoM
    // resolved between the pairs, then a sinusoid fit) does not reach the information bound
    // for the sinusoids' amplitudes and phases (reported 1.4-1.6 times the bound over 12
    // seeds; offsets and y within 15 %), and the prediction is the bound.
    const bool com = k == "leg CoM" || k == "leg CoM phase";
    EXPECT_GT(m, com ? 0.6 : 0.8) << k;
    EXPECT_LT(m, 1.2) << k;
  }
  std::printf(
      "plan prediction: p~'_z common: predicted / reported median %.3f; median |error| / "
      "reported sigma %.2f, / predicted true sigma %.2f (0.67 for an honest sigma; %d seeds)\n",
      Median(ratio_common), Median(z_reported), Median(z_honest), seeds);
  std::printf(
      "plan prediction: p~'_z common: median |error| / predicted sigma with step 1's errors "
      "%.2f; from the true step 1, median |error| / its reported sigma %.2f\n",
      Median(z_step1), z_true_step1.empty() ? 0.0 : Median(z_true_step1));
  EXPECT_GT(Median(ratio_common), 0.8);
  EXPECT_LT(Median(ratio_common), 1.2);
}

}  // namespace
}  // namespace ftcal
