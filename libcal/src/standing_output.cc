// Step 2 into the calibration file: the selected model's mounting parameters with their sigmas,
// the model-selection table with its margins, the solver summary, the residual statistics of
// the report's Fig. 2 and the parameter correlation.
#include "ftcal/standing.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include "standing_internal.h"

namespace ftcal {

using standing_detail::kRadToDeg;

calibration::ResidualStats ResidualStatsOf(const std::string& label,
                                           const std::vector<Vec6>& residuals) {
  calibration::ResidualStats s;
  s.set_label(label);
  s.set_count(static_cast<uint32_t>(residuals.size()));
  if (residuals.empty()) return s;
  const double n = static_cast<double>(residuals.size());
  std::vector<double> col(residuals.size());
  for (int i = 0; i < 6; ++i) {
    double sum = 0.0, sum2 = 0.0;
    for (size_t j = 0; j < residuals.size(); ++j) {
      col[j] = residuals[j][i];
      sum += col[j];
      sum2 += col[j] * col[j];
    }
    const double mean = sum / n;
    double var = 0.0;
    for (double v : col) var += (v - mean) * (v - mean);
    std::sort(col.begin(), col.end());
    auto quantile = [&](double q) {
      const double pos = q * (n - 1.0);
      const size_t lo = static_cast<size_t>(std::floor(pos));
      const size_t hi = std::min(lo + 1, col.size() - 1);
      return col[lo] + (pos - lo) * (col[hi] - col[lo]);
    };
    s.add_mean(mean);
    s.add_std(residuals.size() > 1 ? std::sqrt(var / (n - 1.0)) : 0.0);
    s.add_rms(std::sqrt(sum2 / n));
    s.add_p05(quantile(0.05));
    s.add_p95(quantile(0.95));
  }
  return s;
}

namespace {
void SetVec3(const Vec3& v, const Vec3& sigma, calibration::Vec3Estimate* out) {
  out->set_x(v.x());
  out->set_y(v.y());
  out->set_z(v.z());
  out->set_sigma_x(sigma.x());
  out->set_sigma_y(sigma.y());
  out->set_sigma_z(sigma.z());
}
}  // namespace

void FillStandingProto(const StandingResult& result, calibration::Calibration* out) {
  const StandingFit& fit = result.fit;
  for (int k = out->leg_size(); k < kNumLegs; ++k) {
    out->add_leg()->set_name(std::string(kLegNames[k]));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    calibration::LegCalibration* leg = out->mutable_leg(k);
    if (leg->name() != kLegNames[k]) {
      throw std::invalid_argument("FillStandingProto: calibration leg " + std::to_string(k) +
                                  " is named '" + leg->name() + "', expected " +
                                  std::string(kLegNames[k]));
    }
    calibration::Mounting* m = leg->mutable_mounting();
    m->clear_quaternion_wxyz();
    const Eigen::Vector4d q = RotationToQuaternion(fit.R_tilde[k]);
    for (int i = 0; i < 4; ++i) m->add_quaternion_wxyz(q[i]);
    SetVec3(LogSO3(fit.R_tilde[k]) * kRadToDeg, fit.sigma_rotation_deg[k],
            m->mutable_rotation_vector_deg());
    SetVec3(fit.p_tilde_prime[k], fit.sigma_p_tilde_prime_m[k], m->mutable_p_tilde_prime_m());
    if (fit.has_p_C_B) {
      // Models 2 and 4 assume p~ = 0 (p~' = R~^T p^C_B exactly): fixed by the model, sigma 0.
      SetVec3(fit.R_tilde[k] * fit.p_tilde_prime[k] - fit.p_C_B, Vec3::Zero(),
              m->mutable_p_tilde_m());
    } else {
      m->clear_p_tilde_m();
    }
  }
  if (fit.has_p_C_B) {
    SetVec3(fit.p_C_B, fit.sigma_p_C_B_m, out->mutable_p_c_b_m());
  } else {
    out->clear_p_c_b_m();
  }
  out->set_model(static_cast<calibration::StandingModel>(static_cast<int>(fit.model)));
  out->clear_model_selection();
  for (const ModelSelectionRow& row : result.model_selection) {
    calibration::ModelRow* r = out->add_model_selection();
    r->set_model(static_cast<calibration::StandingModel>(static_cast<int>(row.model)));
    r->set_dof(static_cast<uint32_t>(row.dof));
    r->set_cv_mse(row.cv_mse);
    r->set_rss(row.rss);
    r->set_bic(row.bic);
    r->set_selected(row.selected);
    r->set_leg_aware_com(row.leg_aware_com);
  }
  // Margins: how much the selected candidate won by.
  double selected_bic = 0.0;
  for (const ModelSelectionRow& row : result.model_selection) {
    if (row.selected) selected_bic = row.bic;
  }
  double runner_up = std::numeric_limits<double>::infinity();
  double other_com = std::numeric_limits<double>::infinity();
  std::string runner_up_name;
  for (int i = 0; i < out->model_selection_size(); ++i) {
    const ModelSelectionRow& row = result.model_selection[static_cast<size_t>(i)];
    out->mutable_model_selection(i)->set_delta_bic(row.bic - selected_bic);
    if (row.selected) continue;
    if (row.bic < runner_up) {
      runner_up = row.bic;
      runner_up_name = CandidateName(row.model, row.leg_aware_com);
    }
    if (row.leg_aware_com != result.selected_leg_aware_com)
      other_com = std::min(other_com, row.bic);
  }
  calibration::SolverInfo* s = out->mutable_solver();
  s->set_solver(fit.solver);
  s->set_iterations(static_cast<uint32_t>(std::max(0, fit.iterations)));
  s->set_initial_cost(fit.initial_cost);
  s->set_final_cost(fit.final_cost);
  s->set_converged(fit.converged);
  const char* loss = result.options.robust_loss == StandingLoss::kHuber    ? "HUBER"
                     : result.options.robust_loss == StandingLoss::kCauchy ? "CAUCHY"
                                                                           : "NONE";
  s->set_robust_loss(loss);
  s->set_leg_aware_com(result.selected_leg_aware_com);
  s->set_com_model_source(result.com_selected_by_data ? "selected by the data"
                                                      : "fixed by the config");
  s->clear_bic_margin();
  s->clear_runner_up();
  s->clear_com_bic_margin();
  if (std::isfinite(runner_up)) {
    s->set_bic_margin(runner_up - selected_bic);
    s->set_runner_up(runner_up_name);
  }
  if (std::isfinite(other_com)) s->set_com_bic_margin(other_com - selected_bic);
  out->clear_standing_residual();
  *out->add_standing_residual() = ResidualStatsOf("naive tare", result.residual_naive);
  *out->add_standing_residual() = ResidualStatsOf("without T~", result.residual_without);
  *out->add_standing_residual() = ResidualStatsOf("full calibration", result.residual_full);
  out->set_standing_poses(static_cast<uint32_t>(result.poses));
  out->set_standing_uncertainty(calibration::SOLVER_COVARIANCE);
  out->clear_correlation();
  if (fit.has_covariance && fit.correlation.rows() > 0) {
    calibration::ParameterCorrelation* c = out->mutable_correlation();
    for (const std::string& name : fit.correlation_names) c->add_parameter(name);
    const Eigen::Index n = fit.correlation.rows();
    c->mutable_value()->Reserve(static_cast<int>(n * n));
    for (Eigen::Index i = 0; i < n; ++i) {
      for (Eigen::Index j = 0; j < n; ++j) c->add_value(fit.correlation(i, j));
    }
  }
}

}  // namespace ftcal
