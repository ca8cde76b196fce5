// What ftcal-calibrator writes besides the calibration: the summary tables, the journal-terms
// RMSE, the residuals and walking CSVs (outputs.h).
#include "calibrator/outputs.h"

#include "calibrator/calibrator.h"  // OffsetReestimationRun

#include <algorithm>
#include <charconv>
#include <cmath>
#include <iterator>
#include <optional>

#include <fmt/compile.h>
#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/sensing_model.h"
#include "ftcal/standing.h"

namespace ftcal {

namespace {

constexpr const char* kComponents[6] = {"fx N", "fy N", "fz N", "tx Nm", "ty Nm", "tz Nm"};

// ",%.<precision>g" of `v` appended. std::to_chars gives printf's %g digits (fmt's {:.7g},
// byte for byte) in 40 % of fmt's time: 90 ms against 227 ms for 1.5 M numbers (g++ -O2,
// both compiled formats). The demo's walking file alone is 220,000 numbers.
void AppendGeneral(fmt::memory_buffer& out, double v, int precision) {
  char buf[40];
  buf[0] = ',';
  const std::to_chars_result r =
      std::to_chars(buf + 1, buf + sizeof buf, v, std::chars_format::general, precision);
  out.append(buf, r.ptr);
}

}  // namespace

void WriteCalibrationOutputs(const CalibrationRun& run, const std::string& out_path) {
  WriteCalibrationFile(run.proto, out_path);
  WriteFileAtomic(ResidualsPathFor(out_path), ResidualsCsv(run.standing));
}

std::string OffsetSummaryTable(const OffsetReestimationRun& run) {
  const calibration::OffsetReestimation& r = run.proto.offset_reestimation();
  std::string o = fmt::format(
      "Offsets of {} re-estimated (docs/method.md \"Offset drift\"): {} standing poses, {} "
      "unloaded-leg samples; rank {} of 36; K-weighted rms residual {:.4f}\n",
      run.proto.robot_name(), r.standing_poses(), r.unloaded_leg_samples(), r.rank(),
      r.residual_rms());
  o += fmt::format("{:<10}", "leg");
  for (const char* c : kComponents) o += fmt::format(" {:>9}", c);
  o += "\n";
  for (int k = 0; k < kNumLegs; ++k) {
    const char* rows[3] = {"new", "drift", "+-"};
    for (int row = 0; row < 3; ++row) {
      o += fmt::format("{:<4}{:<6}", row == 0 ? kLegNames[k] : "", rows[row]);
      for (int i = 0; i < 6; ++i) {
        if (!run.estimate.determined[k][i]) {
          o += fmt::format(" {:>9}", row == 0 ? "kept" : "-");
          continue;
        }
        const double v = row == 0   ? run.after.leg[k].offset[i]
                         : row == 1 ? run.after.leg[k].offset[i] - run.before.leg[k].offset[i]
                                    : run.estimate.sigma[k][i];
        o += fmt::format(" {:>9.4f}", v);
      }
      o += "\n";
    }
  }
  if (r.undetermined_size() > 0) {
    std::string list;
    for (const std::string& u : r.undetermined()) list += (list.empty() ? "" : ", ") + u;
    o += "not determined by this session, base values kept: " + list + "\n";
  }
  return o;
}

std::string SummaryTable(const CalibrationRun& run) {
  const calibration::Calibration& c = run.proto;
  std::string o;
  o += fmt::format("Calibration of {} ({} standing poses, model {})\n", c.robot_name(),
                   c.standing_poses(), calibration::StandingModel_Name(c.model()));
  const calibration::SolverInfo& m = c.solver();
  o += fmt::format(
      "Method: profile {}; step-2 solver {}; hanging rotations {}; hanging gravity "
      "prior {}; robot CoM {} ({})\n",
      m.profile(), m.solver(), m.exact_hanging_rotations() ? "exact" : "first-order (report)",
      m.hanging_gravity_prior() ? "on" : "off", m.leg_aware_com() ? "leg-aware" : "fixed (report)",
      m.com_model_source());
  if (c.has_latencies()) {
    const calibration::Latencies& l = c.latencies();
    o += l.has_servo_delay_s()
             ? fmt::format(
                   "Servo delay vs transducers: {:.2f} +- {:.2f} ms, dBIC {:.1f}: {}; applied "
                   "{:.2f} ms\n",
                   1e3 * l.servo_delay_s().value(), 1e3 * l.servo_delay_s().sigma(),
                   l.servo_delay_delta_bic(), l.servo_delay_source(),
                   1e3 * l.applied_servo_delay_s())
             : fmt::format("Servo delay vs transducers: {}\n", l.servo_delay_source());
  }
  if (c.has_mass_check()) {
    const calibration::MassCheck& mc = c.mass_check();
    o += fmt::format(
        "Total mass: configured {:.4f} kg, implied by the data {:.4f} +- {:.4f} kg "
        "(allowed difference {:.4f} kg): {}\n",
        mc.configured_kg(), mc.implied_kg(), mc.sigma_kg(), mc.allowed_kg(),
        mc.consistent() ? "consistent" : "MISMATCH (accepted)");
  }
  if (c.has_noise_floor() && c.noise_floor().has_residual_to_floor()) {
    o += fmt::format(
        "Standing residual: {:.2f} times the noise floor of the poses (warn above "
        "{:g})\n",
        c.noise_floor().residual_to_floor(), c.noise_floor().warn_factor());
  }
  for (const std::string& w : c.warning()) o += "WARNING: " + w + "\n";
  o += fmt::format(
      "{:<4} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9}\n",
      "leg", "fo_x N", "fo_y N", "fo_z N", "to_x Nm", "to_y Nm", "to_z Nm", "mg N", "+-", "rx deg",
      "ry deg", "rz deg", "p~'x mm", "p~'y mm");
  for (const auto& leg : c.leg()) {
    const auto& f = leg.force_offset_n();
    const auto& t = leg.torque_offset_nm();
    const auto& r = leg.mounting().rotation_vector_deg();
    const auto& p = leg.mounting().p_tilde_prime_m();
    o += fmt::format(
        "{:<4} {:>8.3f} {:>8.3f} {:>8.3f} {:>8.4f} {:>8.4f} {:>8.4f} {:>9.3f} {:>8.4f} {:>8.3f} "
        "{:>8.3f} {:>9.3f} {:>9.2f} {:>9.2f}  p~'z {:.2f} mm\n",
        leg.name(), f.x(), f.y(), f.z(), t.x(), t.y(), t.z(), leg.leg_weight_n().value(),
        leg.leg_weight_n().sigma(), r.x(), r.y(), r.z(), 1e3 * p.x(), 1e3 * p.y(), 1e3 * p.z());
  }
  if (c.has_p_c_b_m()) {
    o += fmt::format("p^C_B = ({:.2f}, {:.2f}, {:.2f}) mm\n", 1e3 * c.p_c_b_m().x(),
                     1e3 * c.p_c_b_m().y(), 1e3 * c.p_c_b_m().z());
  }
  o += fmt::format("\nModel selection (lowest BIC selected; solver {}):\n", m.solver());
  o += fmt::format("  {:<26} {:<10} {:>4} {:>12} {:>12} {:>12} {:>10}\n", "model", "robot CoM",
                   "DOF", "CV MSE", "RSS", "BIC", "dBIC");
  for (const auto& row : c.model_selection()) {
    o += fmt::format("{} {:<26} {:<10} {:>4} {:>12.5g} {:>12.5g} {:>12.5g} {:>10.1f}\n",
                     row.selected() ? "*" : " ", calibration::StandingModel_Name(row.model()),
                     row.leg_aware_com() ? "leg-aware" : "fixed", row.dof(), row.cv_mse(),
                     row.rss(), row.bic(), row.delta_bic());
  }
  if (m.has_bic_margin()) {
    o += fmt::format("  selected by a BIC margin of {:.1f} over {}", m.bic_margin(), m.runner_up());
    if (m.has_com_bic_margin()) {
      o += fmt::format("; {:.1f} over the best {} robot-CoM candidate", m.com_bic_margin(),
                       m.leg_aware_com() ? "fixed" : "leg-aware");
    }
    o += "\n";
  }
  if (c.result_rmse_size() > 0) {
    o += "\nGround-contact RMSE, naive tare -> calibrated (the journal's terms):\n";
    o += fmt::format("  {:<15} {:<6} {:<15} {:>7} {:>20} {:>22}\n", "samples", "wrench", "against",
                     "count", "force N", "torque N*m");
    for (const auto& r : c.result_rmse()) {
      auto pct = [](double a, double b) { return a > 0 ? 100.0 * (b - a) / a : 0.0; };
      o += fmt::format(
          "  {:<15} {:<6} {:<15} {:>7} {:>7.3f} -> {:<6.3f}{:>+5.0f}% {:>7.4f} -> "
          "{:<6.4f}{:>+5.0f}%\n",
          r.samples(), r.wrench(), r.reference(), r.count(), r.force_naive_n(),
          r.force_calibrated_n(), pct(r.force_naive_n(), r.force_calibrated_n()),
          r.torque_naive_nm(), r.torque_calibrated_nm(),
          pct(r.torque_naive_nm(), r.torque_calibrated_nm()));
    }
  }
  o += "\nResidual of the total wrench at the CoM in W (rms per component):\n";
  o += fmt::format("  {:<18} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}\n", "variant", "fx N", "fy N",
                   "fz N", "tx Nm", "ty Nm", "tz Nm");
  for (const auto& r : c.standing_residual()) {
    o += fmt::format("  {:<18}", r.label());
    for (int i = 0; i < r.rms_size(); ++i) o += fmt::format(" {:>8.4f}", r.rms(i));
    o += "\n";
  }
  return o;
}

namespace {

RobotCalibration NaiveTareCalibration(const CalibrationRun& run) {
  RobotCalibration naive = run.step1;
  for (int k = 0; k < kNumLegs; ++k) {
    naive.leg[k].offset = run.hanging.leg[k].naive_offset;
    naive.leg[k].weight_n = 0.0;
  }
  naive.p_C_B = Vec3::Zero();
  return naive;
}

struct RmsAccumulator {
  double f2 = 0.0, t2 = 0.0;
  uint32_t n = 0;
  void Add(const Vec6& d) {
    f2 += d.head<3>().squaredNorm();
    t2 += d.tail<3>().squaredNorm();
    ++n;
  }
  double F() const { return n ? std::sqrt(f2 / n) : 0.0; }
  double T() const { return n ? std::sqrt(t2 / n) : 0.0; }
};

void AddRow(const std::string& samples, const std::string& wrench, const std::string& reference,
            const RmsAccumulator& naive, const RmsAccumulator& cal, calibration::Calibration* out) {
  calibration::ResultRmse* r = out->add_result_rmse();
  r->set_samples(samples);
  r->set_wrench(wrench);
  r->set_reference(reference);
  r->set_count(cal.n);
  r->set_force_naive_n(naive.F());
  r->set_force_calibrated_n(cal.F());
  r->set_torque_naive_nm(naive.T());
  r->set_torque_calibrated_nm(cal.T());
}

}  // namespace

void AddResultRmse(const std::vector<SyncSample>& walk, const RobotCalibration* truth,
                   CalibrationRun* run) {
  calibration::Calibration& out = run->proto;
  out.clear_result_rmse();
  {
    RmsAccumulator naive, cal;
    for (const Vec6& r : run->standing.residual_naive) naive.Add(r);
    for (const Vec6& r : run->standing.residual_full) cal.Add(r);
    AddRow("standing poses", "total", "balance target", naive, cal, &out);
  }
  if (walk.empty()) return;
  const RobotCalibration naive_cal = NaiveTareCalibration(*run);
  const bool leg_aware = run->standing.selected_leg_aware_com;
  const double G = run->calibration.TotalWeightN();
  const GroundWrenchModel naive_model(naive_cal), cal_model(run->calibration);
  const std::optional<GroundWrenchModel> truth_model =
      truth != nullptr ? std::optional<GroundWrenchModel>(*truth) : std::nullopt;
  RmsAccumulator total_naive, total_cal;
  std::array<RmsAccumulator, kNumLegs> leg_naive, leg_cal;
  for (const SyncSample& s : walk) {
    if (!s.attitude_ok) continue;
    Vec6 target;
    target << 0, 0, G, 0, 0, 0;
    if (leg_aware) {
      target.tail<3>() = (s.R_WC * ComShiftC(run->calibration, s.angle_rad)).cross(Vec3(0, 0, G));
    }
    Vec6 sum_naive = Vec6::Zero(), sum_cal = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 wn = naive_model.W(k, s.wrench[k], s.angle_rad[k], s.R_WC);
      const Vec6 wc = cal_model.W(k, s.wrench[k], s.angle_rad[k], s.R_WC);
      sum_naive += wn;
      sum_cal += wc;
      if (truth_model) {
        const Vec6 wt = truth_model->W(k, s.wrench[k], s.angle_rad[k], s.R_WC);
        leg_naive[k].Add(wn - wt);
        leg_cal[k].Add(wc - wt);
      }
    }
    total_naive.Add(sum_naive - target);
    total_cal.Add(sum_cal - target);
  }
  AddRow("walk", "total", "balance target", total_naive, total_cal, &out);
  if (truth != nullptr) {
    for (int k = 0; k < kNumLegs; ++k) {
      AddRow("walk", std::string(kLegNames[k]), "true parameters", leg_naive[k], leg_cal[k], &out);
    }
  }
}

// fmt's "{:.Ng}" is printf's %.Ng, which is what an ostream with precision(N) writes: the same
// bytes as before, without the stream's locale and virtual calls (the walking file is ~2 M
// numbers).
std::string ResidualsCsv(const StandingResult& standing) {
  fmt::memory_buffer out;
  auto put = fmt::appender(out);
  fmt::format_to(put, "pose,variant,fx_n,fy_n,fz_n,tx_nm,ty_nm,tz_nm\n");
  const std::pair<const char*, const std::vector<Vec6>*> variants[] = {
      {"naive tare", &standing.residual_naive},
      {"without T~", &standing.residual_without},
      {"full calibration", &standing.residual_full}};
  for (const auto& [label, rows] : variants) {
    for (size_t p = 0; p < rows->size(); ++p) {
      const Vec6& r = (*rows)[p];
      fmt::format_to(put, FMT_COMPILE("{},{}"), p, label);
      for (int i = 0; i < 6; ++i) AppendGeneral(out, r[i], 10);
      out.push_back('\n');
    }
  }
  return fmt::to_string(out);
}

namespace {
std::string PathBeside(const std::string& calibration_path, const std::string& suffix) {
  std::string base = calibration_path;
  const auto slash = base.rfind('/');
  const auto dot = base.rfind('.');
  if (dot != std::string::npos && (slash == std::string::npos || dot > slash)) base.resize(dot);
  return base + suffix;
}
}  // namespace

std::string ResidualsPathFor(const std::string& calibration_path) {
  return PathBeside(calibration_path, ".residuals.csv");
}

std::string WalkingPathFor(const std::string& calibration_path) {
  return PathBeside(calibration_path, ".walking.csv");
}

std::string WalkingCsv(const std::vector<SyncSample>& samples, const CalibrationRun& run,
                       const RobotCalibration* truth, double period_s) {
  if (samples.empty()) throw std::invalid_argument("WalkingCsv: no walking samples");
  // The naive-tare baseline as the corrector would apply it (standing.h's NaiveTareResiduals).
  const RobotCalibration naive = NaiveTareCalibration(run);
  std::vector<std::pair<const char*, GroundWrenchModel>> variants = {
      {"full calibration", GroundWrenchModel(run.calibration)},
      {"naive tare", GroundWrenchModel(naive)}};
  if (truth != nullptr) variants.emplace_back("truth", GroundWrenchModel(*truth));

  fmt::memory_buffer out;
  auto put = fmt::appender(out);
  fmt::format_to(put, "t_s,variant");
  const char* comp[] = {"fx_n", "fy_n", "fz_n", "tx_nm", "ty_nm", "tz_nm"};
  for (int k = 0; k <= kNumLegs; ++k) {
    for (const char* c : comp) {
      fmt::format_to(put, ",{}_{}", k < kNumLegs ? kLegNames[k] : "total", c);
    }
  }
  fmt::format_to(put, "\n");
  const int64_t step_us = static_cast<int64_t>(std::llround(period_s * 1e6));
  const int64_t t0 = samples.front().utime;
  int64_t next = t0;
  for (const SyncSample& s : samples) {
    if (!s.attitude_ok || s.utime < next) continue;
    next = s.utime + step_us;
    for (const auto& [label, model] : variants) {
      fmt::format_to(put, FMT_COMPILE("{:.7g},{}"), 1e-6 * static_cast<double>(s.utime - t0),
                     label);
      Vec6 total = Vec6::Zero();
      for (int k = 0; k < kNumLegs; ++k) {
        const Vec6 w = model.W(k, s.wrench[k], s.angle_rad[k], s.R_WC);
        total += w;
        for (int i = 0; i < 6; ++i) AppendGeneral(out, w[i], 7);
      }
      for (int i = 0; i < 6; ++i) AppendGeneral(out, total[i], 7);
      out.push_back('\n');
    }
  }
  return fmt::to_string(out);
}

}  // namespace ftcal
