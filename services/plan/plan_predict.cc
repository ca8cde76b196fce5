#include "plan/plan_predict.h"

#include <cmath>
#include <cstdio>
#include <random>
#include <stdexcept>
#include <string>

#include "ftcal/calibrate.h"
#include "sequencer/plan.h"

namespace ftcal::plan {
namespace {

constexpr double kDeg = M_PI / 180.0;

void RequireField(double v, bool positive, const std::string& field) {
  if (!std::isfinite(v) || v < 0.0 || (positive && v == 0.0)) {
    throw std::invalid_argument("configuration: planner." + field + " must be finite and " +
                                (positive ? "> 0" : ">= 0") + ", got " + std::to_string(v));
  }
}

HangSeries SeriesOf(config::HangOrientation o) {
  switch (o) {
    case config::HANG_X_POS:
      return HangSeries::kXPos;
    case config::HANG_X_NEG:
      return HangSeries::kXNeg;
    case config::HANG_Z_POS:
      return HangSeries::kZPos;
    case config::HANG_Z_NEG:
      return HangSeries::kZNeg;
    default:
      break;
  }
  throw std::invalid_argument("hanging phase without an orientation");
}

}  // namespace

DeviceNoise PlannerNoise(const config::Planner& p) {
  RequireField(p.force_noise_n(), true, "force_noise_n");
  RequireField(p.torque_noise_nm(), true, "torque_noise_nm");
  RequireField(p.attitude_noise_deg(), false, "attitude_noise_deg");
  RequireField(p.shaft_angle_noise_rad(), false, "shaft_angle_noise_rad");
  DeviceNoise noise;
  noise.force_n = p.force_noise_n();
  noise.torque_nm = p.torque_noise_nm();
  noise.attitude_rad = p.attitude_noise_deg() * kDeg;
  noise.shaft_angle_rad = p.shaft_angle_noise_rad();
  return noise;
}

TwinOptions NominalTwin(const config::Planner& p) {
  RequireField(p.internal_force_n(), false, "internal_force_n");
  TwinOptions o;
  o.mounting_errors = false;
  o.offset_force_spread_n = o.offset_torque_spread_nm = o.weight_spread_n = 0.0;
  o.p_C_B_min_m = o.p_C_B_max_m = 0.0;
  o.hang_tilt_min_deg = o.hang_tilt_max_deg = 0.0;
  o.internal_force_n = p.internal_force_n();
  return o;
}

void SetCalibratorChoices(const config::Config& config, PlanDesign* d) {
  // COM_BY_DATA predicts the report's fixed C, whose residual step 1 enters only through the
  // readings' offsets and the legs' gravity.
  d->leg_aware_com = config.calibrator().com_model() == config::COM_LEG_AWARE;
  d->gravity_prior = config.calibrator().hanging_gravity_prior() &&
                     config.calibrator().profile() != config::REPORT;
}

PlanDesign DesignOfPlan(const config::Config& config, const std::string& plan_name,
                        DeviceNoise* noise, RobotCalibration* nominal) {
  const config::Planner& p = config.planner();
  *noise = PlannerNoise(p);
  RequireField(p.settle_s(), false, "settle_s");

  const sequencer::Schedule schedule = sequencer::Expand(config, plan_name);
  const config::ExperimentPlan* plan = nullptr;
  for (const config::ExperimentPlan& candidate : config.plan()) {
    if (candidate.name() == schedule.plan_name) plan = &candidate;
  }
  if (plan == nullptr) throw std::logic_error("expanded plan not in the config");
  const BigAntTwin twin(config, NominalTwin(p));
  *nominal = twin.Truth();
  const double rate = config.segmenter().sample_rate_hz();
  std::mt19937 rng(1);  // the feet's self-balancing forces: one fixed draw per pose
  std::normal_distribution<double> normal(0.0, p.internal_force_n());
  std::array<bool, kNumLegs> all;
  all.fill(true);
  PlanDesign d;
  for (const sequencer::Step& s : schedule.steps) {
    const config::PlanPhase& phase = plan->phase(s.phase);
    if (phase.kind() == config::PHASE_HANG && s.kind == sequencer::StepKind::kTurn) {
      PlannedHangSeries h;
      h.series = SeriesOf(phase.orientation());
      const auto& g = schedule.phase_gravity_b[s.phase];
      h.gravity_b = Vec3(g[0], g[1], g[2]);
      h.cycles = static_cast<int>(std::lround(s.duration_s / s.cycle_s));
      h.samples_per_cycle = s.cycle_s * rate;
      d.hanging.push_back(h);
    } else if (phase.kind() == config::PHASE_STANDING_GRID &&
               s.kind == sequencer::StepKind::kHold) {
      std::array<Vec3, kNumLegs> internal;
      for (Vec3& v : internal) v = Vec3(normal(rng), normal(rng), 0.0);
      const StanceState st = twin.Equilibrium(s.to, all, internal);
      PlannedPose pp;
      for (int k = 0; k < kNumLegs; ++k) {
        pp.pose.wrench[k] = TransducerReading(*nominal, k, st.ground_w_C[k], s.to[k], st.R_WC);
        pp.pose.angle_rad[k] = s.to[k];
      }
      pp.pose.R_WC = st.R_WC;
      pp.samples = (s.duration_s - p.settle_s()) * rate;
      if (pp.samples < 1.0) {
        throw std::invalid_argument(
            "plan '" + schedule.plan_name + "', phase " + std::to_string(s.phase + 1) +
            ": dwell_s " + std::to_string(s.duration_s) +
            " leaves no steady sample after planner.settle_s " + std::to_string(p.settle_s()));
      }
      d.poses.push_back(pp);
    }
  }
  SetCalibratorChoices(config, &d);
  return d;
}

PlanPredictionReport PredictConfigPlan(const config::Config& config, const std::string& plan_name) {
  PlanPredictionReport r;
  DeviceNoise noise;
  RobotCalibration nominal;
  const PlanDesign design = DesignOfPlan(config, plan_name, &noise, &nominal);
  r.plan_name = sequencer::Expand(config, plan_name).plan_name;
  r.robot_time_s = sequencer::Expand(config, plan_name).duration_s;
  r.prediction = PredictPlan(nominal, design, noise,
                             HangingOptionsFromConfig(config.calibrator(), config.mocap()),
                             StandingOptionsFromConfig(config.calibrator()));
  return r;
}

std::string FormatReport(const PlanPredictionReport& report) {
  const PlanPrediction& p = report.prediction;
  std::string out;
  char line[256];
  std::snprintf(line, sizeof line,
                "plan '%s': %d standing poses, %.0f hanging samples per leg\n"
                "%-15s %-5s %10s %10s  %s\n",
                report.plan_name.c_str(), p.standing_poses, p.hanging_samples, "class", "unit",
                "sigma", "reported", "worst parameter");
  out += line;
  for (const ClassSummary& c : p.classes) {
    std::snprintf(line, sizeof line, "%-15s %-5s %10.4g %10.4g  %s %.4g\n", c.klass.c_str(),
                  c.unit.c_str(), c.median_sigma * c.scale, c.median_reported * c.scale,
                  c.worst_name.c_str(), c.worst_sigma * c.scale);
    out += line;
  }
  std::snprintf(line, sizeof line, "robot time: %.1f min\n", report.robot_time_s / 60.0);
  out += line;
  return out;
}

}  // namespace ftcal::plan
