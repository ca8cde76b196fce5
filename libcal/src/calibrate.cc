// The whole method in one call. Model, residuals and unknowns of each stage are documented at
// the stages (hanging.h, standing.h); this file only sequences them, adds the stage to their
// errors and assembles the calibration file.
#include "ftcal/calibrate.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <utility>

#include <Eigen/QR>

#include "ftcal/config.h"
#include "ftcal/geometry.h"
#include "ftcal/latency.h"

namespace ftcal {

RobotCalibration NominalRobot(const config::Config& config) {
  RobotCalibration cal;
  cal.X_B_ft = NominalTransducerPoses(config.robot());
  cal.total_mass_kg = config.robot().total_mass_kg();
  cal.g0 = config.robot().g0_m_s2();
  return cal;
}

namespace {

// The mass the data implies: sum_k m_k g from step 1 plus, per standing pose, the total vertical
// ground force minus the target, i.e. G_data = G_config + mean_p r_p,z of the full calibration
// (the leg weights enter r_p,z through -F_g; no standing parameter absorbs a uniform fz bias,
// the rotations conserve each leg's force magnitude). Its sigma: the standard error of that mean
// over the poses, the leg weights' and the force offsets' sigmas (step 1), in quadrature.
calibration::MassCheck CheckTotalMass(const CalibrationRun& run, const config::Config& config) {
  const std::vector<Vec6>& r = run.standing.residual_full;
  const double g0 = run.step1.g0;
  const double P = static_cast<double>(r.size());
  double mean = 0.0;
  for (const Vec6& v : r) mean += v[2] / P;
  double var = 0.0;
  for (const Vec6& v : r) var += (v[2] - mean) * (v[2] - mean) / std::max(1.0, P - 1.0);
  double s2 = var / P;
  for (int k = 0; k < kNumLegs; ++k) {
    const HangingVariant& h = run.hanging.leg[k].with_s;
    s2 += h.weight_n.sigma * h.weight_n.sigma + h.force_offset_n.sigma.squaredNorm();
  }
  calibration::MassCheck m;
  m.set_configured_kg(config.robot().total_mass_kg());
  m.set_implied_kg(config.robot().total_mass_kg() + mean / g0);
  m.set_sigma_kg(std::sqrt(s2) / g0);
  m.set_tolerance_kg(config.calibrator().mass_tolerance_kg());
  m.set_allowed_kg(config.calibrator().mass_check_sigmas() * m.sigma_kg() + m.tolerance_kg());
  m.set_consistent(std::abs(m.implied_kg() - m.configured_kg()) <= m.allowed_kg());
  return m;
}

// rms of transducer k's standing torques against tau = p(theta_j) x f + c(theta_j), p and c of
// the form u + v cos(theta) + w sin(theta): 18 unknowns by linear least squares over 3 P rows.
// The leg gravity torque r(theta) x m g and the offsets' (p(theta) x (f_o + m g)) are of c's form
// when the chassis is near level; the rest of the residual is noise and tilt.
double LegMapRms(const std::vector<StandingPose>& poses, int k, int j) {
  using Mat18 = Eigen::Matrix<double, 18, 18>;
  using Vec18 = Eigen::Matrix<double, 18, 1>;
  auto rows = [&](const StandingPose& pose) {
    const Vec3 f = pose.wrench[k].head<3>();
    const double c = std::cos(pose.angle_rad[j]), s = std::sin(pose.angle_rad[j]);
    Eigen::Matrix<double, 3, 18> a;
    const Mat3 mf = -Skew(f);  // p x f = -[f] p
    a << mf, c * mf, s * mf, Mat3::Identity(), c * Mat3::Identity(), s * Mat3::Identity();
    return a;
  };
  Mat18 h = Mat18::Zero();
  Vec18 g = Vec18::Zero();
  for (const StandingPose& pose : poses) {
    const Eigen::Matrix<double, 3, 18> a = rows(pose);
    h.noalias() += a.transpose() * a;
    g.noalias() += a.transpose() * pose.wrench[k].tail<3>();
  }
  // Rank-revealing: a shaft that never moved leaves its cos and sin columns dependent.
  const Vec18 x = h.completeOrthogonalDecomposition().solve(g);
  double rss = 0.0;
  for (const StandingPose& pose : poses) {
    rss += (rows(pose) * x - pose.wrench[k].tail<3>()).squaredNorm();
  }
  return std::sqrt(rss / (3.0 * static_cast<double>(poses.size())));
}

}  // namespace

bool LegMapResult::consistent() const {
  for (bool c : contradicted) {
    if (c) return false;
  }
  return true;
}

std::string LegMapResult::Describe() const {
  std::string legs, detail;
  for (int k = 0; k < kNumLegs; ++k) {
    if (!contradicted[k]) continue;
    const int j = best_other[k];
    legs += (legs.empty() ? "" : ", ") + std::string(kLegNames[k]);
    char buf[200];
    std::snprintf(buf, sizeof buf,
                  "%s%s's transducer follows %s's shaft (rms torque misfit %.4f N m) better than "
                  "its own (%.4f N m, %.1f times worse)",
                  detail.empty() ? "" : "; ", std::string(kLegNames[k]).c_str(),
                  std::string(kLegNames[j]).c_str(), rms_nm[k][j], rms_nm[k][k],
                  rms_nm[k][k] / rms_nm[k][j]);
    detail += buf;
  }
  if (legs.empty()) return "";
  return "leg map check: over the " + std::to_string(poses) + " standing poses the data of legs " +
         legs + " contradicts their configured position: " + detail +
         " (allowed: " + std::to_string(static_cast<int>(kRatioLimit)) +
         " times): were those legs' servo ids (robot.leg servo.id: the Dynamixel bridge names each "
         "servo's leg by it) or transducer addresses (ati.address: the ATI bridge publishes each "
         "box as its leg's FT channel) swapped in the config the bridges ran with?";
}

LegMapResult CheckLegMap(const std::vector<StandingPose>& poses) {
  LegMapResult r;
  r.poses = static_cast<int>(poses.size());
  if (r.poses < LegMapResult::kMinLegMapPoses) return r;
  r.checked = true;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int j = 0; j < kNumLegs; ++j) r.rms_nm[k][j] = LegMapRms(poses, k, j);
    int best = k == 0 ? 1 : 0;
    for (int j = 0; j < kNumLegs; ++j) {
      if (j != k && r.rms_nm[k][j] < r.rms_nm[k][best]) best = j;
    }
    r.best_other[k] = best;
    r.contradicted[k] = r.rms_nm[k][k] > LegMapResult::kRatioLimit * r.rms_nm[k][best];
  }
  return r;
}

CalibrationRun CalibrateFromHanging(const HangingResult& hanging,
                                    const std::vector<StandingPose>& poses,
                                    const config::Config& config,
                                    const StandingOptions& standing_options,
                                    const CalibrateOptions& options) {
  CalibrationRun run;
  run.hanging = hanging;
  if (options.has_naive_tare) {
    for (int k = 0; k < kNumLegs; ++k) run.hanging.leg[k].naive_offset = options.naive_tare[k];
  }
  run.step1 = NominalRobot(config);
  ApplyHangingResult(hanging, &run.step1);

  StandingOptions standing = standing_options;
  const config::Calibrator& cc = config.calibrator();
  if (cc.profile() != config::REPORT && cc.hanging_gravity_prior()) {
    if (hanging.gravity_observations.empty()) {
      run.warnings.push_back(
          "hanging gravity prior skipped: at least one hanging series has no motion capture "
          "attitude, so the common yaw of the six R~ comes from the chassis tilt of the "
          "standing poses alone");
    } else {
      standing.gravity_prior = hanging.gravity_observations;
    }
  }

  std::array<Vec6, kNumLegs> naive{};
  for (int k = 0; k < kNumLegs; ++k) naive[k] = run.hanging.leg[k].naive_offset;
  try {
    run.standing = CalibrateStanding(run.step1, poses, naive, standing);
    if (options.compare_alternating) {
      StandingOptions selected = standing;
      selected.leg_aware_com = run.standing.selected_leg_aware_com;
      run.alternating = FitStandingAlternating(run.step1, poses, run.standing.selected, selected);
      run.has_alternating = true;
    }
  } catch (const std::invalid_argument& e) {
    throw CalibrationStageError(std::string("step 2 (standing): ") + e.what());
  }
  run.calibration = run.standing.calibration;

  calibration::NoiseFloor floor;
  floor.set_poses_with_scatter(static_cast<uint32_t>(run.standing.poses_with_scatter));
  floor.set_warn_factor(config.calibrator().residual_floor_warn_factor());
  if (run.standing.residual_to_floor > 0.0) {
    for (int i = 0; i < 6; ++i) floor.add_floor_rms(run.standing.floor_rms[i]);
    floor.set_residual_to_floor(run.standing.residual_to_floor);
    floor.set_above_floor(run.standing.residual_to_floor > floor.warn_factor());
    if (floor.above_floor()) {
      char buf[400];
      std::snprintf(
          buf, sizeof buf,
          "the standing residual is %.1f times the noise floor of the poses (more than "
          "calibrator.residual_floor_warn_factor = %g): the selected model (%s) misses "
          "something the data sees; its sigmas are scaled by the residual but a bias "
          "may remain",
          floor.residual_to_floor(), floor.warn_factor(),
          CandidateName(run.standing.selected, run.standing.selected_leg_aware_com).c_str());
      run.warnings.push_back(buf);
    }
  }
  calibration::MassCheck mass = CheckTotalMass(run, config);
  if (!mass.consistent()) {
    char buf[640];
    std::snprintf(buf, sizeof buf,
                  "mass check: the standing poses' total vertical force differs from the config's "
                  "weight: total_mass_kg %g kg, but the data implies %.4f +- %.4f kg (sum of the "
                  "leg weights from the hanging series plus the transducers' vertical force over "
                  "the standing poses; allowed difference %.4f kg = %g sigma + "
                  "calibrator.mass_tolerance_kg): is the config (total_mass_kg) this robot's?",
                  config.robot().total_mass_kg(), mass.implied_kg(), mass.sigma_kg(),
                  mass.allowed_kg(), config.calibrator().mass_check_sigmas());
    const std::string what = buf;
    if (!options.accept_mass_mismatch)
      throw MassMismatchError(what + " (--accept-mass-mismatch to calibrate anyway)");
    mass.set_accepted_mismatch(true);
    run.warnings.push_back(what + "; calibrated anyway (--accept-mass-mismatch)");
  }

  calibration::Calibration& out = run.proto;
  *out.mutable_mass_check() = mass;
  *out.mutable_noise_floor() = floor;
  out.set_robot_name(config.robot().name());
  out.set_g0_m_s2(run.step1.g0);
  out.set_total_mass_kg(run.step1.total_mass_kg);
  out.set_version(1);
  // Legs in config order before the stages fill them by name.
  for (int k = 0; k < kNumLegs; ++k) out.add_leg()->set_name(std::string(kLegNames[k]));
  WriteHangingToCalibration(run.hanging, &out);
  out.set_naive_tare_source(options.has_naive_tare
                                ? "TARE phase"
                                : "upright hanging series near theta = 0 (no TARE phase)");
  FillStandingProto(run.standing, &out);
  // FillStandingProto rewrites the solver block; keep step 1's flag in it.
  out.mutable_solver()->set_exact_hanging_rotations(hanging.exact_rotations);
  out.mutable_solver()->set_hanging_gravity_prior(!standing.gravity_prior.empty());
  out.mutable_solver()->set_profile(config::CalibrationProfile_Name(cc.profile()));
  {
    std::string legs;
    for (int k = 0; k < kNumLegs; ++k) {
      const int n = hanging.leg[k].saturated_samples;
      out.mutable_leg(k)->set_saturated_samples(static_cast<uint32_t>(n));
      if (n > 0)
        legs += (legs.empty() ? "" : ", ") + std::string(kLegNames[k]) + " " + std::to_string(n);
    }
    if (!legs.empty()) {
      run.warnings.push_back(
          "hanging samples beyond the transducer's rated range (saturated) "
          "left out of step 1: " +
          legs);
    }
  }
  for (const std::string& w : run.warnings) out.add_warning(w);
  return run;
}

CalibrationRun Calibrate(const std::vector<HangingRecording>& hanging,
                         const std::vector<StandingPose>& poses, const config::Config& config,
                         const CalibrateOptions& options) {
  HangingResult step1;
  HangingOptions hanging_options = HangingOptionsFromConfig(config.calibrator(), config.mocap());
  SetRatedRanges(config.robot(), &hanging_options);
  // The servo stream's delay first (docs/method.md "Latencies"): when the data selects it, step 1
  // pairs each transducer sample with the shaft angle of its own instant.
  ServoDelayEstimate delay;
  const bool estimate_delay = config.calibrator().profile() != config::REPORT;
  try {
    if (estimate_delay) delay = EstimateServoDelay(hanging);
    const double applied = delay.selected ? delay.delay_s : 0.0;
    step1 = RunHanging(applied != 0.0 ? ShiftServoAngles(hanging, applied) : hanging,
                       NominalTransducerPoses(config.robot()), hanging_options);
  } catch (const std::invalid_argument& e) {
    throw CalibrationStageError(std::string("step 1 (hanging): ") + e.what());
  }
  // A pose whose median reading is beyond a transducer's rated range is saturated: dropped,
  // counted against that transducer.
  std::vector<StandingPose> kept;
  kept.reserve(poses.size());
  std::array<int, kNumLegs> saturated_poses{};
  for (const StandingPose& pose : poses) {
    bool ok = true;
    for (int k = 0; k < kNumLegs; ++k) {
      if ((pose.wrench[k].cwiseAbs().array() > hanging_options.rated_range[k].array()).any()) {
        ++saturated_poses[k];
        ok = false;
      }
    }
    if (ok) kept.push_back(pose);
  }
  // Before step 2: with two legs' shafts or transducers swapped every figure of it is wrong.
  const LegMapResult leg_map = CheckLegMap(kept);
  std::string leg_map_warning;
  if (leg_map.checked && !leg_map.consistent()) {
    if (!options.accept_leg_map_mismatch) {
      throw LegMapMismatchError(leg_map.Describe() +
                                " (--accept-leg-map-mismatch to calibrate "
                                "anyway)");
    }
    leg_map_warning = leg_map.Describe() + "; calibrated anyway (--accept-leg-map-mismatch)";
  }
  CalibrationRun run = CalibrateFromHanging(
      step1, kept, config, StandingOptionsFromConfig(config.calibrator()), options);
  run.servo_delay = delay;
  run.calibration.servo_delay_s = delay.selected ? delay.delay_s : 0.0;
  {
    calibration::Latencies* l = run.proto.mutable_latencies();
    l->set_applied_servo_delay_s(run.calibration.servo_delay_s);
    l->set_servo_delay_selected(delay.selected);
    if (!estimate_delay) {
      l->set_servo_delay_source("not estimated (REPORT profile)");
    } else if (!delay.estimated) {
      l->set_servo_delay_source("not estimated: too few hanging samples");
    } else {
      l->mutable_servo_delay_s()->set_value(delay.delay_s);
      l->mutable_servo_delay_s()->set_sigma(delay.sigma_s);
      l->set_servo_delay_delta_bic(delay.delta_bic);
      l->set_servo_delay_sigma_covariance_s(delay.sigma_covariance_s);
      l->set_servo_delay_sigma_spread_s(delay.sigma_spread_s);
      l->set_servo_delay_residuals(static_cast<uint64_t>(delay.residuals));
      l->set_servo_delay_source(delay.selected ? "selected by the data (BIC)"
                                               : "rejected by the data (BIC)");
    }
  }
  {
    calibration::LegMapCheck* m = run.proto.mutable_leg_map_check();
    m->set_poses(static_cast<uint32_t>(leg_map.poses));
    m->set_ratio_limit(LegMapResult::kRatioLimit);
    if (leg_map.checked) {
      for (int k = 0; k < kNumLegs; ++k) {
        for (int j = 0; j < kNumLegs; ++j) m->add_rms_nm(leg_map.rms_nm[k][j]);
      }
    }
    m->set_consistent(leg_map.consistent());
    m->set_accepted_mismatch(!leg_map_warning.empty());
    if (!leg_map_warning.empty()) {
      run.warnings.push_back(leg_map_warning);
      run.proto.add_warning(leg_map_warning);
    }
  }
  std::string legs;
  for (int k = 0; k < kNumLegs; ++k) {
    run.proto.mutable_leg(k)->set_saturated_poses(static_cast<uint32_t>(saturated_poses[k]));
    if (saturated_poses[k] > 0) {
      legs += (legs.empty() ? "" : ", ") + std::string(kLegNames[k]) + " " +
              std::to_string(saturated_poses[k]);
    }
  }
  if (!legs.empty()) {
    const std::string w = std::to_string(poses.size() - kept.size()) +
                          " standing poses dropped: a median reading beyond the transducer's "
                          "rated range (saturated) on " +
                          legs;
    run.warnings.push_back(w);
    run.proto.add_warning(w);
  }
  return run;
}

}  // namespace ftcal
