// The whole method (Calibrate) on the BigAnt twin, every estimate against the twin's truth:
// default seed, default noise, all 729 standing poses. Figures are printed for the record.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <memory>

#include "twin_calibration.h"

namespace ftcal {
namespace {

using namespace testing_twin;  // NOLINT

constexpr int kAllPoses = 729;

struct Scenario {
  std::unique_ptr<BigAntTwin> twin;
  std::vector<HangingRecording> hanging;
  std::vector<StandingPose> poses;
  CalibrationRun run;
};

// The report's procedure (calibrator.profile REPORT): first-order hanging rotations, fixed C,
// no gravity prior.
config::Config ReportConfig() {
  config::Config config = SimConfig();
  config.mutable_calibrator()->set_profile(config::REPORT);
  return config;
}

std::unique_ptr<Scenario> MakeScenario(const TwinOptions& options, const config::Config& config,
                                       bool compare_alternating) {
  auto s = std::make_unique<Scenario>();
  s->twin = std::make_unique<BigAntTwin>(config, options);
  s->hanging = HangingOf(*s->twin);
  s->poses = s->twin->MakeSteadyPoses(kAllPoses);
  CalibrateOptions co;
  co.compare_alternating = compare_alternating;
  s->run = Calibrate(s->hanging, s->poses, config, co);
  return s;
}

// The default twin (its CoM fixed at C) through the report's procedure.
const Scenario& Default() {
  static const std::unique_ptr<Scenario> s = MakeScenario(TwinOptions(), ReportConfig(), true);
  return *s;
}

const Scenario& NoMounting() {
  static const std::unique_ptr<Scenario> s = [] {
    TwinOptions o;
    o.mounting_errors = false;
    return MakeScenario(o, ReportConfig(), false);
  }();
  return *s;
}

// The default twin through the report's procedure with exact hanging rotations exp([s]) (the
// poses alone in step 2: no gravity prior).
const CalibrationRun& DefaultExact() {
  static const CalibrationRun run = [] {
    config::Config config = SimConfig();
    config.mutable_calibrator()->set_hanging_gravity_prior(false);
    config.mutable_calibrator()->set_com_model(config::COM_FIXED);
    return Calibrate(Default().hanging, Default().poses, config);
  }();
  return run;
}

// ftcal's method as shipped (config/sim.pbtxt): exact hanging rotations, the gravity prior, the
// robot-CoM model chosen by the data.
config::Config FtcalConfig() { return SimConfig(); }

const CalibrationRun& DefaultFtcal() {
  static const CalibrationRun run = Calibrate(Default().hanging, Default().poses, FtcalConfig());
  return run;
}

double Rms(const std::vector<Vec6>& residuals, const Vec6& k) {
  return std::sqrt(WeightedRss(residuals, k) / static_cast<double>(residuals.size()));
}

// The common yaw of the six R~ is seen by the standing poses only through the chassis tilt
// (< 3 deg): a yaw of every transducer about z leaves a vertical total force unchanged. From
// the poses alone (exact hanging rotations, no gravity prior) it comes out ~0.17 deg off on the
// default seed: probes with the twin's noise sources switched off one at a time traced it to the
// motion capture attitude noise, which lands in the horizontal forces only. With one residual
// variance pooled over the six components it was 2.2 reported sigma; the per-component sandwich
// covariance (standing_covariance.cc, AddCovariance) reports it as 1.6 sigma. The hanging
// gravity prior (ftcal's method) sees that yaw directly and removes the problem; this check
// shows, for the poses alone, every leg's tilt (x, y) and rotation relative to the common yaw
// within 0.15 deg and the common yaw within 3 reported sigma.
void ExpectRotationsWithinBoundButCommonYaw(const StandingFit& fit, const RobotCalibration& truth,
                                            const std::string& name) {
  Vec3 common = Vec3::Zero();
  double sigma_z = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    common += RotationErrorDeg(fit.R_tilde[k], truth.leg[k].R_tilde) / kNumLegs;
    sigma_z += fit.sigma_rotation_deg[k].z() / kNumLegs;
  }
  double tilt = 0, differential = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const Vec3 e = RotationErrorDeg(fit.R_tilde[k], truth.leg[k].R_tilde);
    tilt = std::max(tilt, e.head<2>().norm());
    differential = std::max(differential, (e - Vec3(0, 0, common.z())).norm());
  }
  std::printf(
      "recovery: %s: rotation error about x,y max %.3f deg; relative to the common yaw "
      "max %.3f deg (bound 0.15); common yaw %.3f deg = %.1f reported sigma (%.3f deg)\n",
      name.c_str(), tilt, differential, common.z(), common.z() / sigma_z, sigma_z);
  EXPECT_LT(tilt, 0.15) << name;
  EXPECT_LT(differential, 0.15) << name;
  EXPECT_LT(std::abs(common.z()), 3.0 * sigma_z) << name;
}

// Step 1 as the report writes it (first-order rotations I + [s], config/sim.pbtxt) and with
// the exact rotations exp([s]) (docs/method.md, beyond the report). The first-order form
// underestimates m g by |s|^2 / 2 (the tilt of gravity off the transducer axis, here hanging
// tilt plus mounting tilt, 2-5 deg): 0.05-0.4 %, i.e. up to ~0.02 N on a 6 N leg, more than
// the 0.015 N bound and far more than the cycle-spread sigma. So the weight bound is asserted
// on the exact form, and the first-order form is asserted to carry that bias (low, in range).
void CheckStep1ParametersAgainstTheTruth() {
  const RobotCalibration& truth = Default().twin->Truth();
  for (const bool exact : {false, true}) {
    const RobotCalibration& est = exact ? DefaultExact().calibration : Default().run.calibration;
    const char* name = exact ? "exact rotations" : "first-order (report)";
    double weight = 0, force = 0, torque = 0, com = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      const LegCalibration& e = est.leg[k];
      const LegCalibration& t = truth.leg[k];
      weight = std::max(weight, std::abs(e.weight_n - t.weight_n));
      force = std::max(force, (e.offset.head<3>() - t.offset.head<3>()).cwiseAbs().maxCoeff());
      torque = std::max(torque, (e.offset.tail<3>() - t.offset.tail<3>()).cwiseAbs().maxCoeff());
      com = std::max(com, MaxCurveDistance(e.com, t.com));
      if (!exact) {
        const double relative = (e.weight_n - t.weight_n) / t.weight_n;
        EXPECT_LT(relative, -0.0002) << "leg " << k;
        EXPECT_GT(relative, -0.005) << "leg " << k;
      }
    }
    std::printf("recovery: %s: leg weight max error %.4f N (bound 0.015, exact form)\n", name,
                weight);
    std::printf("recovery: %s: force offset max error %.4f N (bound 0.02)\n", name, force);
    std::printf("recovery: %s: torque offset max error %.5f N*m (bound 0.001)\n", name, torque);
    std::printf("recovery: %s: leg CoM curve max error %.3f mm (bound 0.2)\n", name, com * 1e3);
    if (exact) {
      EXPECT_LT(weight, 0.015);
    }
    EXPECT_LT(force, 0.02) << name;
    EXPECT_LT(torque, 0.001) << name;
    EXPECT_LT(com, 0.2e-3) << name;
  }
}

void CheckMountingParametersAgainstTheTruth() {
  const RobotCalibration& truth = Default().twin->Truth();
  for (const int variant : {0, 1, 2}) {
    const StandingFit& fit = variant == 2   ? DefaultFtcal().standing.fit
                             : variant == 1 ? DefaultExact().standing.fit
                                            : Default().run.standing.fit;
    const char* name = variant == 2   ? "ftcal as shipped (exact rotations, gravity prior)"
                       : variant == 1 ? "exact rotations, poses alone"
                                      : "first-order (report)";
    ASSERT_EQ(fit.model, StandingModel::kFull) << name;
    double rot = 0, pp = 0;
    Vec3 common = Vec3::Zero(), common_sigma = Vec3::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec3 e = RotationErrorDeg(fit.R_tilde[k], truth.leg[k].R_tilde);
      const Vec3 ep = fit.p_tilde_prime[k] - truth.leg[k].p_tilde_prime;
      common += e / kNumLegs;
      common_sigma += fit.sigma_rotation_deg[k] / kNumLegs;
      rot = std::max(rot, e.norm());
      pp = std::max(pp, ep.norm());
      std::printf(
          "recovery: %s: leg %d rotation error (%.3f %.3f %.3f) deg, sigma (%.3f %.3f %.3f); "
          "p~' error (%.3f %.3f %.3f) mm, sigma (%.3f %.3f %.3f)\n",
          name, k, e.x(), e.y(), e.z(), fit.sigma_rotation_deg[k].x(),
          fit.sigma_rotation_deg[k].y(), fit.sigma_rotation_deg[k].z(), ep.x() * 1e3, ep.y() * 1e3,
          ep.z() * 1e3, fit.sigma_p_tilde_prime_m[k].x() * 1e3,
          fit.sigma_p_tilde_prime_m[k].y() * 1e3, fit.sigma_p_tilde_prime_m[k].z() * 1e3);
    }
    std::printf(
        "recovery: %s: common rotation error of the six R~ (%.3f %.3f %.3f) deg, mean "
        "per-leg sigma (%.3f %.3f %.3f) deg\n",
        name, common.x(), common.y(), common.z(), common_sigma.x(), common_sigma.y(),
        common_sigma.z());
    std::printf("recovery: %s: mounting rotation max error %.3f deg (bound 0.15)\n", name, rot);
    std::printf("recovery: %s: p~' max error %.3f mm (bound 0.5)\n", name, pp * 1e3);
    EXPECT_LT(pp, 0.5e-3) << name;
    if (variant == 1) {
      ExpectRotationsWithinBoundButCommonYaw(fit, truth, name);
    } else {
      EXPECT_LT(rot, 0.15) << name;
    }
    if (variant == 2) {
      // The reported sigmas are honest: every rotation component within 3 sigma.
      for (int k = 0; k < kNumLegs; ++k) {
        const Vec3 e = RotationErrorDeg(fit.R_tilde[k], truth.leg[k].R_tilde);
        for (int i = 0; i < 3; ++i) {
          EXPECT_LT(std::abs(e[i]), 3.0 * fit.sigma_rotation_deg[k][i]) << name << " leg " << k;
        }
      }
    }
  }
}

void CheckResidualAtTheNoiseFloorAndBaselinesWorse() {
  const Scenario& s = Default();
  const Vec6 k = s.run.standing.options.k_weights;
  const double truth_rms = Rms(TotalWrenchResiduals(s.twin->Truth(), s.poses, false), k);
  const double first = Rms(s.run.standing.residual_full, k);
  const double exact = Rms(DefaultFtcal().standing.residual_full, k);
  const double without = Rms(DefaultFtcal().standing.residual_without, k);
  const double naive = Rms(s.run.standing.residual_naive, k);
  std::printf(
      "recovery: %zu poses; K-weighted rms total-wrench residual: true parameters %.4f; "
      "full calibration: ftcal %.4f (ratio %.3f, bound 1.2), first-order "
      "%.4f (ratio %.3f); step 1 only %.4f (ratio %.1f); naive tare %.4f (ratio %.1f)\n",
      s.poses.size(), truth_rms, exact, exact / truth_rms, first, first / truth_rms, without,
      without / truth_rms, naive, naive / truth_rms);
  // Per component (K-weighted): the mocap attitude noise lands in fx, fy only (why the
  // covariance takes each component's residual variance; see the common yaw).
  const calibration::ResidualStats stats =
      ResidualStatsOf("full", DefaultFtcal().standing.residual_full);
  std::printf(
      "recovery: ftcal: sqrt(K) * rms residual per component [fx fy fz tx ty "
      "tz]: %.4f %.4f %.4f %.4f %.4f %.4f\n",
      std::sqrt(k[0]) * stats.rms(0), std::sqrt(k[1]) * stats.rms(1),
      std::sqrt(k[2]) * stats.rms(2), std::sqrt(k[3]) * stats.rms(3),
      std::sqrt(k[4]) * stats.rms(4), std::sqrt(k[5]) * stats.rms(5));
  EXPECT_LE(exact, 1.2 * truth_rms);
  // The first-order weights miss sum_k m_k g by ~0.1 N in total: above the floor, but far
  // below the baselines.
  EXPECT_LT(first, 5.0 * truth_rms);
  EXPECT_GT(without, 10.0 * truth_rms);
  EXPECT_GT(naive, 10.0 * truth_rms);
  EXPECT_GT(naive, without);
}

void CheckModelSelectionPicksFullWithMountingErrors() {
  const Scenario& s = Default();
  for (const ModelSelectionRow& row : s.run.standing.model_selection)
    std::printf("recovery: mounting errors: model %s dof %d cv_mse %.5f rss %.3f bic %.1f%s\n",
                StandingModelName(row.model), row.dof, row.cv_mse, row.rss, row.bic,
                row.selected ? " (selected)" : "");
  EXPECT_EQ(s.run.standing.selected, StandingModel::kFull);
  EXPECT_EQ(s.run.proto.model(), calibration::FULL);
}

void CheckModelSelectionPicksASmallerModelWithoutMountingErrors() {
  const Scenario& s = NoMounting();
  for (const ModelSelectionRow& row : s.run.standing.model_selection)
    std::printf("recovery: no mounting errors: model %s dof %d cv_mse %.5f rss %.3f bic %.1f%s\n",
                StandingModelName(row.model), row.dof, row.cv_mse, row.rss, row.bic,
                row.selected ? " (selected)" : "");
  EXPECT_NE(s.run.standing.selected, StandingModel::kFull);
}

// Model 2 (six R~, one p^C_B) is the model whose p^C_B means something: it holds exactly when
// p~ = 0. The twin tilts transducers about their own origins (p~ = (I - R~) p_B_ft != 0), so
// the twin whose truth has p~ = 0 is the one without mounting errors (R~ = I as well).
void CheckCoMOffsetFromModelTwo() {
  const Scenario& s = NoMounting();
  const StandingFit& fit = s.run.standing.fits[1];
  ASSERT_EQ(fit.model, StandingModel::kRotationsOneTranslation);
  const Vec3 e = fit.p_C_B - s.twin->Truth().p_C_B;
  std::printf(
      "recovery: p^C_B (model 2) error (%.3f %.3f %.3f) mm, |e| %.3f mm (bound 1.5), "
      "sigma (%.3f %.3f %.3f) mm\n",
      e.x() * 1e3, e.y() * 1e3, e.z() * 1e3, e.norm() * 1e3, fit.sigma_p_C_B_m.x() * 1e3,
      fit.sigma_p_C_B_m.y() * 1e3, fit.sigma_p_C_B_m.z() * 1e3);
  EXPECT_LT(e.norm(), 1.5e-3);
}

void CheckAlternatingSchemeAgainstTheJointOptimum() {
  const Scenario& s = Default();
  ASSERT_TRUE(s.run.has_alternating);
  const StandingFit& joint = s.run.standing.fits[0];
  const StandingFit& alt = s.run.alternating;
  double rot = 0, pp = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    rot = std::max(rot, RotationErrorDeg(alt.R_tilde[k], joint.R_tilde[k]).norm());
    pp = std::max(pp, (alt.p_tilde_prime[k] - joint.p_tilde_prime[k]).norm());
  }
  std::printf(
      "recovery: alternating scheme: %d sweeps, rss %.4f vs joint %.4f; distance from "
      "the joint optimum: rotations %.3f deg, p~' %.3f mm (max over legs)\n",
      alt.iterations, alt.rss, joint.rss, rot, pp * 1e3);
  // The joint solve is the optimum of the same cost.
  EXPECT_GE(alt.rss, joint.rss * (1.0 - 1e-9));
}

void CheckExactHangingRotationsRemoveTheWeightBias() {
  const RobotCalibration& truth = Default().twin->Truth();
  const CalibrationRun& first = Default().run;
  const CalibrationRun& exact = DefaultExact();
  double mean_first = 0, mean_exact = 0, max_exact = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const double t = truth.leg[k].weight_n;
    const double e1 = first.calibration.leg[k].weight_n - t;
    const double e2 = exact.calibration.leg[k].weight_n - t;
    std::printf(
        "recovery: leg %d m g %.4f N: first-order error %+.4f N (%+.3f%%), exact %+.4f N "
        "(%+.3f%%), sigma %.4f N\n",
        k, t, e1, 100 * e1 / t, e2, 100 * e2 / t, exact.hanging.leg[k].with_s.weight_n.sigma);
    mean_first += e1 / t / kNumLegs;
    mean_exact += e2 / t / kNumLegs;
    max_exact = std::max(max_exact, std::abs(e2));
  }
  std::printf(
      "recovery: mean relative m g error: first-order %+.3f%%, exact %+.3f%%; exact max "
      "|error| %.4f N (bound 0.015)\n",
      100 * mean_first, 100 * mean_exact, max_exact);
  EXPECT_LT(mean_first, -0.0005);
  EXPECT_GT(mean_first, -0.003);
  EXPECT_LT(std::abs(mean_exact), 0.1 * std::abs(mean_first));
  EXPECT_LT(max_exact, 0.015);
}

// With the physical CoM (the legs carry nearly half the mass, so the robot's CoM moves with the
// shaft angles) the report's fixed-CoM target is wrong by delta x (0, 0, G), a moment of up to
// ~0.1 N*m that the plain model absorbs into p~'. The leg-aware target (docs/method.md) removes it.
// Step 1 with exact rotations and the hanging gravity prior (ftcal's method), to isolate this
// effect.
void CheckLegAwareComRemovesTheBiasOfAMovingCoM() {
  TwinOptions o;
  o.physical_com = true;
  const BigAntTwin twin(SimConfig(), o);
  const std::vector<StandingPose> poses = twin.MakeSteadyPoses(kAllPoses);
  config::Config config = SimConfig();
  config.mutable_calibrator()->set_exact_hanging_rotations(true);
  RobotCalibration step1 = NominalRobot(config);
  const HangingResult hanging = RunHanging(
      HangingOf(twin), step1.X_B_ft, HangingOptionsFromConfig(config.calibrator(), config.mocap()));
  ApplyHangingResult(hanging, &step1);
  StandingOptions options = StandingOptionsFromConfig(SimConfig().calibrator());
  options.gravity_prior = hanging.gravity_observations;
  double rot[2] = {0, 0}, pp[2] = {0, 0};
  StandingFit aware_fit;
  for (const bool aware : {false, true}) {
    options.leg_aware_com = aware;
    const StandingFit fit = FitStandingJoint(step1, poses, StandingModel::kFull, options);
    if (aware) aware_fit = fit;
    for (int k = 0; k < kNumLegs; ++k) {
      rot[aware] = std::max(rot[aware],
                            RotationErrorDeg(fit.R_tilde[k], twin.Truth().leg[k].R_tilde).norm());
      pp[aware] =
          std::max(pp[aware], (fit.p_tilde_prime[k] - twin.Truth().leg[k].p_tilde_prime).norm());
    }
    std::printf(
        "recovery: physical CoM, %s target: rotation max error %.3f deg, p~' max error "
        "%.3f mm (bounds 0.15 deg, 0.5 mm)\n",
        aware ? "leg-aware" : "fixed-CoM (report)", rot[aware], pp[aware] * 1e3);
  }
  EXPECT_GT(pp[0], 0.5e-3);
  EXPECT_LT(pp[1], 0.5e-3);
  EXPECT_LT(rot[1], 0.15);
}

void CheckCalibrationFileIsComplete() {
  const calibration::Calibration& p = Default().run.proto;
  ASSERT_EQ(p.leg_size(), kNumLegs);
  for (int k = 0; k < kNumLegs; ++k) {
    const calibration::LegCalibration& leg = p.leg(k);
    EXPECT_EQ(leg.name(), std::string(kLegNames[k]));
    EXPECT_GT(leg.force_offset_n().sigma_x(), 0.0);
    EXPECT_GT(leg.torque_offset_nm().sigma_z(), 0.0);
    EXPECT_GT(leg.leg_weight_n().sigma(), 0.0);
    EXPECT_GT(leg.com().x().sigma_a_m(), 0.0);
    EXPECT_GT(leg.mounting().rotation_vector_deg().sigma_z(), 0.0);
    EXPECT_GT(leg.mounting().p_tilde_prime_m().sigma_x(), 0.0);
    EXPECT_EQ(leg.hanging_size(), 2);
    EXPECT_EQ(leg.naive_offset_size(), 6);
    // The file's numbers are the calibration's.
    EXPECT_DOUBLE_EQ(leg.leg_weight_n().value(), Default().run.calibration.leg[k].weight_n);
  }
  EXPECT_EQ(p.model_selection_size(), 4);
  EXPECT_EQ(p.solver().profile(), "REPORT");
  EXPECT_FALSE(p.solver().exact_hanging_rotations());
  EXPECT_FALSE(p.solver().leg_aware_com());
  EXPECT_EQ(p.solver().com_model_source(), "fixed by the config");
  // The default: both robot-CoM targets times four mounting models, margins stated.
  const calibration::Calibration& f = DefaultFtcal().proto;
  EXPECT_EQ(f.model_selection_size(), 8);
  EXPECT_EQ(f.solver().profile(), "FTCAL");
  EXPECT_EQ(f.solver().com_model_source(), "selected by the data");
  EXPECT_GT(f.solver().bic_margin(), 0.0);
  EXPECT_GT(f.solver().com_bic_margin(), 0.0);
  EXPECT_FALSE(f.solver().runner_up().empty());
  int leg_aware_rows = 0;
  for (const auto& row : f.model_selection()) {
    leg_aware_rows += row.leg_aware_com();
    if (row.selected()) {
      EXPECT_EQ(row.delta_bic(), 0.0);
    } else {
      EXPECT_GT(row.delta_bic(), 0.0);
    }
  }
  EXPECT_EQ(leg_aware_rows, 4);
  EXPECT_EQ(f.warning_size(), 0);
  EXPECT_EQ(p.standing_residual_size(), 3);
  EXPECT_EQ(p.hanging_residual_size(), 3 * kNumLegs);
  EXPECT_EQ(p.hanging_uncertainty(), calibration::CYCLE_SPREAD);
  EXPECT_EQ(p.standing_uncertainty(), calibration::SOLVER_COVARIANCE);
  EXPECT_EQ(p.solver().solver(), "joint");
  EXPECT_FALSE(p.solver().hanging_gravity_prior());
  EXPECT_TRUE(DefaultFtcal().proto.solver().hanging_gravity_prior());
  EXPECT_TRUE(DefaultFtcal().proto.solver().exact_hanging_rotations());
  EXPECT_EQ(p.standing_poses(), Default().poses.size());
  EXPECT_EQ(p.robot_name(), SimConfig().robot().name());
}

void CheckDegenerateInputNamesTheStage() {
  const Scenario& s = Default();
  const config::Config config = SimConfig();
  std::vector<HangingRecording> three(s.hanging.begin(), s.hanging.begin() + 3);
  try {
    Calibrate(three, s.poses, config);
    ADD_FAILURE() << "three hanging series accepted";
  } catch (const CalibrationStageError& e) {
    std::cout << "recovery: " << e.what() << "\n";
    EXPECT_EQ(std::string(e.what()).rfind("step 1 (hanging): ", 0), 0u) << e.what();
  }
  std::vector<StandingPose> few(s.poses.begin(), s.poses.begin() + 5);
  try {
    Calibrate(s.hanging, few, config);
    ADD_FAILURE() << "five standing poses accepted";
  } catch (const CalibrationStageError& e) {
    std::cout << "recovery: " << e.what() << "\n";
    EXPECT_EQ(std::string(e.what()).rfind("step 2 (standing): ", 0), 0u) << e.what();
  }
}

// The default twin with its CoM moving with the legs, through ftcal's method as shipped.
const Scenario& LegAwareTwin() {
  static const std::unique_ptr<Scenario> s = [] {
    TwinOptions o;
    o.physical_com = true;
    return MakeScenario(o, FtcalConfig(), false);
  }();
  return *s;
}

// Every estimate against the truth within the bounds the report's procedure meets on the twin
// it was built for (CheckStep1ParametersAgainstTheTruth, CheckMountingParametersAgainstTheTruth).
// Without the hanging gravity prior the common yaw of the six R~ comes from the chassis tilt
// alone and is checked against its sigma instead (ExpectRotationsWithinBoundButCommonYaw).
void ExpectRecovered(const CalibrationRun& run, const RobotCalibration& truth,
                     const std::string& name) {
  double weight = 0, force = 0, torque = 0, com = 0, rot = 0, pp = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& e = run.calibration.leg[k];
    const LegCalibration& t = truth.leg[k];
    weight = std::max(weight, std::abs(e.weight_n - t.weight_n));
    force = std::max(force, (e.offset.head<3>() - t.offset.head<3>()).cwiseAbs().maxCoeff());
    torque = std::max(torque, (e.offset.tail<3>() - t.offset.tail<3>()).cwiseAbs().maxCoeff());
    com = std::max(com, MaxCurveDistance(e.com, t.com));
    rot = std::max(rot, RotationErrorDeg(e.R_tilde, t.R_tilde).norm());
    pp = std::max(pp, (e.p_tilde_prime - t.p_tilde_prime).norm());
  }
  std::printf(
      "recovery: %s: max errors: m g %.4f N (bound 0.015), force offset %.4f N (0.02), "
      "torque offset %.5f N*m (0.001), CoM curve %.3f mm (0.2), R~ %.3f deg (0.15), "
      "p~' %.3f mm (0.5)\n",
      name.c_str(), weight, force, torque, com * 1e3, rot, pp * 1e3);
  EXPECT_LT(weight, 0.015) << name;
  EXPECT_LT(force, 0.02) << name;
  EXPECT_LT(torque, 0.001) << name;
  EXPECT_LT(com, 0.2e-3) << name;
  EXPECT_LT(pp, 0.5e-3) << name;
  if (run.proto.solver().hanging_gravity_prior()) {
    EXPECT_LT(rot, 0.15) << name;
  } else {
    ExpectRotationsWithinBoundButCommonYaw(run.standing.fit, truth, name);
  }
}

void PrintModelSelection(const CalibrationRun& run, const std::string& name) {
  for (const ModelSelectionRow& row : run.standing.model_selection) {
    std::printf("recovery: %s: %-40s dof %2d cv_mse %.5f rss %9.3f bic %9.1f%s\n", name.c_str(),
                CandidateName(row.model, row.leg_aware_com).c_str(), row.dof, row.cv_mse, row.rss,
                row.bic, row.selected ? " (selected)" : "");
  }
  std::printf(
      "recovery: %s: selected by a BIC margin of %.1f over %s; %.1f over the other "
      "robot-CoM model\n",
      name.c_str(), run.proto.solver().bic_margin(), run.proto.solver().runner_up().c_str(),
      run.proto.solver().com_bic_margin());
}

// The default as shipped picks the robot-CoM model each twin was made with, and recovers the
// truth on both.
void CheckDefaultOnTheFixedCoMTwin() {
  const CalibrationRun& run = DefaultFtcal();
  PrintModelSelection(run, "fixed-CoM twin, default");
  EXPECT_EQ(run.standing.selected, StandingModel::kFull);
  EXPECT_FALSE(run.standing.selected_leg_aware_com);
  EXPECT_FALSE(run.proto.solver().leg_aware_com());
  EXPECT_TRUE(run.proto.solver().hanging_gravity_prior());
  ExpectRecovered(run, Default().twin->Truth(), "fixed-CoM twin, default");
}

void CheckDefaultOnTheLegAwareTwin() {
  const Scenario& s = LegAwareTwin();
  PrintModelSelection(s.run, "leg-aware twin, default");
  EXPECT_EQ(s.run.standing.selected, StandingModel::kFull);
  EXPECT_TRUE(s.run.standing.selected_leg_aware_com);
  EXPECT_TRUE(s.run.proto.solver().leg_aware_com());
  ExpectRecovered(s.run, s.twin->Truth(), "leg-aware twin, default");
  // The noise floor: the right model's residual is at it; the report's fixed C is well above.
  const StandingResult& st = s.run.standing;
  ASSERT_EQ(st.poses_with_scatter, st.poses);
  const double wrong =
      std::sqrt(st.FitOf(StandingModel::kFull, false).residual_variance / st.floor_variance);
  std::printf(
      "recovery: leg-aware twin: residual / noise floor %.2f (leg-aware CoM, selected), "
      "%.2f (fixed CoM); floor rms [fx fy fz tx ty tz] %.4f %.4f %.4f %.5f %.5f %.5f\n",
      st.residual_to_floor, wrong, st.floor_rms[0], st.floor_rms[1], st.floor_rms[2],
      st.floor_rms[3], st.floor_rms[4], st.floor_rms[5]);
  EXPECT_LT(st.residual_to_floor, s.run.proto.noise_floor().warn_factor());
  EXPECT_FALSE(s.run.proto.noise_floor().above_floor());
  EXPECT_GT(wrong, 2.0 * st.residual_to_floor);
}

// The report's own experiment has no motion capture of the hanging robot: the default skips
// the gravity prior, says so, and still calibrates.
void CheckDefaultWithoutHangingMotionCapture() {
  std::vector<HangingRecording> blind = Default().hanging;
  for (HangingRecording& h : blind) h.attitude.clear();
  const CalibrationRun run = Calibrate(blind, Default().poses, FtcalConfig());
  ASSERT_EQ(run.proto.warning_size(), 1);
  std::printf("recovery: no hanging motion capture: warning: %s\n", run.proto.warning(0).c_str());
  EXPECT_NE(run.proto.warning(0).find("gravity prior skipped"), std::string::npos);
  EXPECT_FALSE(run.proto.solver().hanging_gravity_prior());
  EXPECT_EQ(run.standing.selected, StandingModel::kFull);
  EXPECT_FALSE(run.standing.selected_leg_aware_com);
  ExpectRecovered(run, Default().twin->Truth(), "fixed-CoM twin, no hanging mocap, default");
}

// The data checks the config: a robot configured 70 g heavier than the one that made the data.
// Step 1's leg weights and the standing poses' vertical force imply the true mass; the
// configured one is refused, naming both, unless the mismatch is accepted.
// A smaller twin experiment (six hanging cycles, 243 poses) for the checks of the input.
struct Small {
  std::unique_ptr<BigAntTwin> twin;
  std::vector<HangingRecording> hanging;
  std::vector<StandingPose> poses;
};
const Small& SmallScenario() {
  static const Small s = [] {
    TwinOptions o;
    o.seed = 7;
    o.hang_cycles = 6;
    Small out;
    out.twin = std::make_unique<BigAntTwin>(FtcalConfig(), o);
    out.hanging = HangingOf(*out.twin);
    out.poses = out.twin->MakeSteadyPoses(243);
    return out;
  }();
  return s;
}

void CheckMassMismatchIsCaught() {
  const config::Config truth_config = FtcalConfig();
  const std::vector<HangingRecording>& hanging = SmallScenario().hanging;
  const std::vector<StandingPose>& poses = SmallScenario().poses;
  const double true_kg = truth_config.robot().total_mass_kg();

  const CalibrationRun right = Calibrate(hanging, poses, truth_config);
  const calibration::MassCheck& ok = right.proto.mass_check();
  std::printf(
      "recovery: mass check, right config: configured %.4f kg, implied %.4f +- %.4f kg, "
      "allowed %.4f kg\n",
      ok.configured_kg(), ok.implied_kg(), ok.sigma_kg(), ok.allowed_kg());
  EXPECT_TRUE(ok.consistent());
  EXPECT_NEAR(ok.implied_kg(), true_kg, ok.allowed_kg());

  config::Config heavy = truth_config;
  heavy.mutable_robot()->set_total_mass_kg(true_kg + 0.070);
  try {
    Calibrate(hanging, poses, heavy);
    ADD_FAILURE() << "a 70 g mass error accepted";
  } catch (const MassMismatchError& e) {
    const std::string what = e.what();
    std::printf("recovery: %s\n", what.c_str());
    char configured[32];
    std::snprintf(configured, sizeof configured, "total_mass_kg %g kg", true_kg + 0.070);
    EXPECT_NE(what.find(configured), std::string::npos) << what;
    EXPECT_NE(what.find("the data implies 8.1"), std::string::npos) << what;
  }
  CalibrateOptions accept;
  accept.accept_mass_mismatch = true;
  const CalibrationRun anyway = Calibrate(hanging, poses, heavy, accept);
  const calibration::MassCheck& bad = anyway.proto.mass_check();
  EXPECT_FALSE(bad.consistent());
  EXPECT_TRUE(bad.accepted_mismatch());
  // The data's mass is the robot's, not the config's.
  EXPECT_NEAR(bad.implied_kg(), true_kg, 0.02);
  ASSERT_GE(anyway.proto.warning_size(), 1);
  EXPECT_NE(anyway.proto.warning(anyway.proto.warning_size() - 1).find("mass check"),
            std::string::npos);
}

// One second of 300 N (beyond the 130 N rated range of fx) in one leg's hanging series: left
// out of step 1 and counted, so the leg's CoM stays within its bound.
void CheckSaturatedSamplesAreExcluded() {
  const Small& s = SmallScenario();
  const RobotCalibration& truth = s.twin->Truth();
  std::vector<HangingRecording> hanging = s.hanging;
  constexpr int kLeg = 2;  // FL
  LegSamples& samples = hanging[static_cast<int>(HangSeries::kXPos)].legs[kLeg];
  const size_t start = samples.wrench.size() / 3;
  for (size_t i = start; i < start + 100; ++i) samples.wrench[i][0] = 300.0;
  const CalibrationRun run = Calibrate(hanging, s.poses, FtcalConfig());
  const double com = MaxCurveDistance(run.calibration.leg[kLeg].com, truth.leg[kLeg].com);
  const double weight = std::abs(run.calibration.leg[kLeg].weight_n - truth.leg[kLeg].weight_n);
  std::printf(
      "recovery: 1 s of 300 N in HANG_X_POS leg FL: %u samples left out; CoM curve max "
      "error %.3f mm (bound 0.2), m g error %.4f N (bound 0.015)\n",
      run.proto.leg(kLeg).saturated_samples(), com * 1e3, weight);
  EXPECT_EQ(run.proto.leg(kLeg).saturated_samples(), 100u);
  EXPECT_EQ(run.proto.leg(0).saturated_samples(), 0u);
  EXPECT_LT(com, 0.2e-3);
  EXPECT_LT(weight, 0.015);
  bool warned = false;
  for (const std::string& w : run.proto.warning()) warned |= w.find("FL 100") != std::string::npos;
  EXPECT_TRUE(warned);
  // The same data with no rated range configured for FL: the second of 300 N goes into the fit.
  config::Config unguarded = FtcalConfig();
  unguarded.mutable_robot()->mutable_leg(kLeg)->mutable_ati()->clear_rated_range();
  const CalibrationRun bad = Calibrate(hanging, s.poses, unguarded);
  const double com_bad = MaxCurveDistance(bad.calibration.leg[kLeg].com, truth.leg[kLeg].com);
  std::printf("recovery: the same without a rated range: CoM curve max error %.3f mm\n",
              com_bad * 1e3);
  EXPECT_EQ(bad.proto.leg(kLeg).saturated_samples(), 0u);
  EXPECT_GT(com_bad, 0.2e-3);
}

// The data checks the config's leg map: two legs' servo ids swapped in the Dynamixel bridge's
// config give each of them the other's shaft angles (the bridge names each servo's leg by its
// id); two transducer addresses swapped in the ATI bridge's give each the other's readings. Both
// are refused naming the legs, unless accepted; with the config right every transducer follows its
// own shaft.
void CheckLegMapMismatchIsCaught() {
  const Small& s = SmallScenario();
  const CalibrationRun right = Calibrate(s.hanging, s.poses, FtcalConfig());
  const calibration::LegMapCheck& ok = right.proto.leg_map_check();
  ASSERT_EQ(ok.rms_nm_size(), kNumLegs * kNumLegs);
  EXPECT_TRUE(ok.consistent());
  EXPECT_EQ(ok.poses(), s.poses.size());
  for (int k = 0; k < kNumLegs; ++k) {
    double other = 1e300;
    for (int j = 0; j < kNumLegs; ++j) {
      if (j != k) other = std::min(other, ok.rms_nm(kNumLegs * k + j));
    }
    const double own = ok.rms_nm(kNumLegs * k + k);
    std::printf(
        "recovery: leg map, right config: %s own shaft rms %.4f N m, best other %.4f N m "
        "(%.0f times worse)\n",
        std::string(kLegNames[k]).c_str(), own, other, other / own);
    EXPECT_LT(own * LegMapResult::kRatioLimit, other) << kLegNames[k];
  }

  auto expect_refused = [&](const std::vector<StandingPose>& poses, const char* what) {
    try {
      Calibrate(s.hanging, poses, FtcalConfig());
      ADD_FAILURE() << what << ": accepted";
    } catch (const LegMapMismatchError& e) {
      const std::string msg = e.what();
      std::printf("recovery: %s: %s\n", what, msg.c_str());
      EXPECT_NE(msg.find("legs HL, ML contradicts"), std::string::npos) << msg;
      EXPECT_NE(msg.find("HL's transducer follows ML's shaft"), std::string::npos) << msg;
      EXPECT_NE(msg.find("ML's transducer follows HL's shaft"), std::string::npos) << msg;
    }
  };
  std::vector<StandingPose> servos = s.poses;
  for (StandingPose& p : servos) std::swap(p.angle_rad[0], p.angle_rad[1]);
  expect_refused(servos, "HL and ML servo ids swapped");
  std::vector<StandingPose> transducers = s.poses;
  for (StandingPose& p : transducers) {
    std::swap(p.wrench[0], p.wrench[1]);
    std::swap(p.wrench_sem[0], p.wrench_sem[1]);
  }
  expect_refused(transducers, "HL and ML transducer addresses swapped");

  CalibrateOptions accept;
  accept.accept_leg_map_mismatch = true;
  const CalibrationRun anyway = Calibrate(s.hanging, servos, FtcalConfig(), accept);
  EXPECT_FALSE(anyway.proto.leg_map_check().consistent());
  EXPECT_TRUE(anyway.proto.leg_map_check().accepted_mismatch());
  bool warned = false;
  for (const std::string& w : anyway.proto.warning()) warned |= w.find("leg map check") == 0;
  EXPECT_TRUE(warned);
}

// One test per twin scenario: ctest runs every test in its own process, and the scenarios (twin
// data and calibration) are the cost.
TEST(Recovery, DefaultTwin) {
  for (void (*check)() :
       {CheckStep1ParametersAgainstTheTruth, CheckMountingParametersAgainstTheTruth,
        CheckResidualAtTheNoiseFloorAndBaselinesWorse,
        CheckModelSelectionPicksFullWithMountingErrors,
        CheckAlternatingSchemeAgainstTheJointOptimum, CheckExactHangingRotationsRemoveTheWeightBias,
        CheckCalibrationFileIsComplete, CheckDegenerateInputNamesTheStage}) {
    check();
  }
}

TEST(Recovery, TwinWithoutMountingErrors) {
  CheckModelSelectionPicksASmallerModelWithoutMountingErrors();
  CheckCoMOffsetFromModelTwo();
}

TEST(Recovery, TwinWithPhysicalCoM) { CheckLegAwareComRemovesTheBiasOfAMovingCoM(); }

TEST(Recovery, DefaultChoosesTheCoMModelOfEachTwin) {
  CheckDefaultOnTheFixedCoMTwin();
  CheckDefaultOnTheLegAwareTwin();
}

TEST(Recovery, DefaultWithoutHangingMotionCapture) { CheckDefaultWithoutHangingMotionCapture(); }

TEST(Recovery, MassMismatchIsCaught) { CheckMassMismatchIsCaught(); }

TEST(Recovery, LegMapMismatchIsCaught) { CheckLegMapMismatchIsCaught(); }

TEST(Recovery, SaturatedSamplesAreExcluded) { CheckSaturatedSamplesAreExcluded(); }

}  // namespace
}  // namespace ftcal
