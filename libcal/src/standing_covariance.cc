// Step 2's uncertainties: the sandwich covariance of a fit at its solution (AddCovariance: the
// sigmas of R~, p~' or p^C_B and the parameter correlation the calibration file carries) and
// the correlation of a covariance matrix.
#include "ftcal/standing.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include <Eigen/Cholesky>

#include "standing_internal.h"

namespace ftcal {
namespace standing_detail {

// sigma from the sandwich covariance C = H^-1 M H^-1 at the solution, H = J^T J and
// M = sum_rows s2_row J_row^T J_row (J the K-weighted Jacobian in the tangent space). s2 of a pose
// row is the residual variance of its component [fx fy fz tx ty tz] over the poses (sum of the
// squared weighted residuals / (P - DOF / 6)); of a hanging-prior row the pooled
// RSS / (6 P - DOF) its weight was set with. Why not s2 H^-1 with one pooled s2 (the plain scaled
// covariance): the components' noise differs by an order of magnitude (motion-capture attitude
// noise lands in fx, fy only), so one pooled variance made the force-determined parameters (the
// common yaw of R~) overconfident and the torque-determined ones (p~') far too cautious (twin
// coverage of +-2 sigma 99.7 %). With equal variances the two agree. Both grow with the misfit.
void AddCovariance(const Prepared& prep, const std::vector<int>& ids, StandingFit* fit,
                   const StandingOptions& options) {
  Params params = ParamsFromFit(*fit);
  Built b = Build(prep, ids, fit->model, BuildOptions(), &params, options);
  std::vector<double> res;
  const Eigen::MatrixXd J = DenseJacobian(b.problem.get(), b.free_blocks, &res);
  // Pose residual blocks come first (Build adds them before the prior's), six rows each.
  const int pose_rows = 6 * static_cast<int>(ids.size());
  const double P = static_cast<double>(ids.size());
  const double dof_per_row = static_cast<double>(fit->dof) / 6.0;
  Vec6 s2c = Vec6::Zero();
  for (int r = 0; r < pose_rows; ++r) s2c[r % 6] += res[r] * res[r];
  s2c /= std::max(1.0, P - dof_per_row);
  const Eigen::MatrixXd H = J.transpose() * J;
  Eigen::VectorXd s2(J.rows());
  for (int r = 0; r < J.rows(); ++r) s2[r] = r < pose_rows ? s2c[r % 6] : fit->residual_variance;
  const Eigen::MatrixXd M = J.transpose() * s2.asDiagonal() * J;
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(H);
  const Eigen::VectorXd d = ldlt.vectorD();
  if (ldlt.info() != Eigen::Success || !(d.minCoeff() > 1e-14 * std::max(1.0, d.maxCoeff()))) {
    throw std::invalid_argument(std::string("standing step: covariance of model ") +
                                StandingModelName(fit->model) +
                                " is singular at the solution: the poses do not determine it");
  }
  const Eigen::MatrixXd Hinv = ldlt.solve(Eigen::MatrixXd::Identity(H.rows(), H.cols()));
  const Eigen::MatrixXd C = Hinv * M * Hinv;
  fit->correlation = CorrelationOfCovariance(C);
  fit->correlation_names.clear();
  const char* axes[3] = {"x", "y", "z"};
  if (HasRotations(fit->model)) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (const char* a : axes)
        fit->correlation_names.push_back(std::string(kLegNames[k]) + " R~ " + a);
    }
  }
  if (SharedTranslation(fit->model)) {
    for (const char* a : axes) fit->correlation_names.push_back(std::string("p^C_B ") + a);
  } else {
    for (int k = 0; k < kNumLegs; ++k) {
      for (const char* a : axes)
        fit->correlation_names.push_back(std::string(kLegNames[k]) + " p~' " + a);
    }
  }
  if (static_cast<Eigen::Index>(fit->correlation_names.size()) != C.rows()) {
    throw std::logic_error(std::string("standing step: covariance of model ") +
                           StandingModelName(fit->model) + " has " + std::to_string(C.rows()) +
                           " parameters, expected " +
                           std::to_string(fit->correlation_names.size()));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    fit->sigma_rotation_deg[k].setZero();
    fit->sigma_p_tilde_prime_m[k].setZero();
  }
  fit->sigma_p_C_B_m.setZero();
  int col = 0;
  if (HasRotations(fit->model)) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 3; ++i) {
        const int j = 3 * k + i;
        fit->sigma_rotation_deg[k][i] =
            kQuaternionTangentToRotationVector * std::sqrt(std::max(0.0, C(j, j))) * kRadToDeg;
      }
    }
    col = 18;
  }
  if (SharedTranslation(fit->model)) {
    for (int i = 0; i < 3; ++i) {
      fit->sigma_p_C_B_m[i] = std::sqrt(std::max(0.0, C(col + i, col + i)));
    }
    // p~'_k = R~_k^T p^C_B: R~ is within degrees of I, so its sigma is p^C_B's to first order.
    for (int k = 0; k < kNumLegs; ++k) fit->sigma_p_tilde_prime_m[k] = fit->sigma_p_C_B_m;
  } else {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 3; ++i) {
        const int j = col + 3 * k + i;
        fit->sigma_p_tilde_prime_m[k][i] = std::sqrt(std::max(0.0, C(j, j)));
      }
    }
  }
  fit->has_covariance = true;
}

}  // namespace standing_detail

Eigen::MatrixXd CorrelationOfCovariance(const Eigen::MatrixXd& covariance) {
  const Eigen::Index n = covariance.rows();
  if (covariance.cols() != n) {
    throw std::invalid_argument("CorrelationOfCovariance: a " + std::to_string(n) + " x " +
                                std::to_string(covariance.cols()) + " matrix is not square");
  }
  Eigen::VectorXd s(n);
  for (Eigen::Index i = 0; i < n; ++i) {
    const double v = covariance(i, i);
    if (!std::isfinite(v) || v < 0.0) {
      throw std::invalid_argument("CorrelationOfCovariance: variance " + std::to_string(i) +
                                  " is " + std::to_string(v));
    }
    s[i] = std::sqrt(v);
  }
  Eigen::MatrixXd r = Eigen::MatrixXd::Identity(n, n);
  for (Eigen::Index i = 0; i < n; ++i) {
    for (Eigen::Index j = 0; j < n; ++j) {
      // Averaged with its transpose: H^-1 M H^-1 is symmetric only to rounding.
      if (i != j && s[i] > 0.0 && s[j] > 0.0) {
        r(i, j) = 0.5 * (covariance(i, j) + covariance(j, i)) / (s[i] * s[j]);
      }
    }
  }
  return r;
}

}  // namespace ftcal
