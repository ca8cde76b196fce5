// Step 2's solves (docs/method.md "Step 2"): the joint solve of all parameters on SO(3) and the
// report's alternating scheme (linear translations, nonlinear Cayley rotations, the 1e-3 stop
// rule), each on any subset of the poses so that the cross-validation folds reuse them; the
// rank check that refuses a model the poses do not determine; the conversions between a fit
// and the problem's parameter storage.
#include "ftcal/standing.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>

#include <Eigen/Cholesky>
#include <Eigen/QR>
#include <Eigen/SVD>
#include <ceres/manifold.h>

#include "standing_internal.h"

namespace ftcal {
namespace standing_detail {

Params ParamsFromFit(const StandingFit& fit) {
  Params p;
  for (int k = 0; k < kNumLegs; ++k) {
    const Quat q(fit.R_tilde[k]);
    p.quat[4 * k + 0] = q.x();
    p.quat[4 * k + 1] = q.y();
    p.quat[4 * k + 2] = q.z();
    p.quat[4 * k + 3] = q.w();
    const Vec3 c = RotationToCayley(fit.R_tilde[k]);
    for (int i = 0; i < 3; ++i) p.cayley[3 * k + i] = c[i];
  }
  if (SharedTranslation(fit.model)) {
    for (int i = 0; i < 3; ++i) p.trans[i] = fit.p_C_B[i];
  } else {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 3; ++i) p.trans[3 * k + i] = fit.p_tilde_prime[k][i];
    }
  }
  return p;
}

std::vector<std::string> ParameterNames(StandingModel model) {
  std::vector<std::string> names;
  const char* axes[3] = {"x", "y", "z"};
  if (HasRotations(model)) {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 3; ++i) {
        names.push_back(std::string(kLegNames[k]) + " R~ about " + axes[i]);
      }
    }
  }
  if (SharedTranslation(model)) {
    for (int i = 0; i < 3; ++i) names.push_back(std::string("p^C_B.") + axes[i]);
  } else {
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < 3; ++i) names.push_back(std::string(kLegNames[k]) + " p~'." + axes[i]);
    }
  }
  return names;
}

// Ceres's Problem::Evaluate builds a program, an evaluator and a sparse Jacobian on every call:
// in step 2 that set-up (and the page faults of its fresh buffers) was four fifths of each rank
// check in perf. Here each residual block's cost is evaluated straight into
// the dense matrix and taken to the tangent space as Ceres does (J_ambient * PlusJacobian).
// With a loss function on any block, Ceres's own evaluation (its residual and Jacobian
// correction).
Eigen::MatrixXd DenseJacobian(ceres::Problem* problem, const std::vector<double*>& blocks,
                              std::vector<double>* residuals) {
  std::vector<ceres::ResidualBlockId> ids;
  problem->GetResidualBlocks(&ids);
  bool any_loss = false;
  int rows = 0;
  for (ceres::ResidualBlockId id : ids) {
    any_loss = any_loss || problem->GetLossFunctionForResidualBlock(id) != nullptr;
    rows += problem->GetCostFunctionForResidualBlock(id)->num_residuals();
  }
  if (any_loss) {
    ceres::Problem::EvaluateOptions eo;
    eo.parameter_blocks = blocks;
    eo.apply_loss_function = true;
    ceres::CRSMatrix crs;
    problem->Evaluate(eo, nullptr, residuals, nullptr, &crs);
    Eigen::MatrixXd J = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
    for (int r = 0; r < crs.num_rows; ++r) {
      for (int i = crs.rows[r]; i < crs.rows[r + 1]; ++i) J(r, crs.cols[i]) = crs.values[i];
    }
    return J;
  }
  // Per block: its first column, its tangent size, and its manifold's Jacobian at the block's
  // value (the same for every residual block that uses it; empty: no manifold).
  using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  std::vector<int> column(blocks.size()), tangent(blocks.size());
  std::vector<RowMajor> plus(blocks.size());
  int cols = 0;
  for (size_t b = 0; b < blocks.size(); ++b) {
    column[b] = cols;
    tangent[b] = problem->ParameterBlockTangentSize(blocks[b]);
    cols += tangent[b];
    if (const ceres::Manifold* m = problem->GetManifold(blocks[b])) {
      plus[b].resize(m->AmbientSize(), tangent[b]);
      m->PlusJacobian(blocks[b], plus[b].data());
    }
  }
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(rows, cols);
  if (residuals != nullptr) residuals->resize(static_cast<size_t>(rows));
  std::vector<double*> params;
  std::vector<RowMajor> ambient;
  std::vector<double*> jacobians;
  std::vector<int> which;  // per parameter of the block: index into blocks, or -1
  Eigen::VectorXd r;
  int row = 0;
  for (ceres::ResidualBlockId id : ids) {
    const ceres::CostFunction* cost = problem->GetCostFunctionForResidualBlock(id);
    const int n = cost->num_residuals();
    problem->GetParameterBlocksForResidualBlock(id, &params);
    const std::vector<int32_t>& sizes = cost->parameter_block_sizes();
    ambient.resize(params.size());
    jacobians.assign(params.size(), nullptr);
    which.assign(params.size(), -1);
    for (size_t p = 0; p < params.size(); ++p) {
      const auto at = std::find(blocks.begin(), blocks.end(), params[p]);
      if (at == blocks.end()) continue;
      which[p] = static_cast<int>(at - blocks.begin());
      ambient[p].resize(n, sizes[p]);
      jacobians[p] = ambient[p].data();
    }
    r.resize(n);
    if (!cost->Evaluate(params.data(), r.data(), jacobians.data()) || !r.allFinite()) {
      throw std::runtime_error("standing step: a residual could not be evaluated for the Jacobian");
    }
    if (residuals != nullptr) std::copy(r.data(), r.data() + n, residuals->begin() + row);
    for (size_t p = 0; p < params.size(); ++p) {
      if (which[p] < 0) continue;
      const auto b = static_cast<size_t>(which[p]);
      auto out = J.block(row, column[b], n, tangent[b]);
      if (plus[b].size() > 0) {
        out.noalias() = ambient[p] * plus[b];
      } else {
        out = ambient[p];
      }
    }
    row += n;
  }
  return J;
}

namespace {

// Refuses a model whose parameters the poses do not determine: SVD of the column-normalised
// Jacobian; a singular value below 1e-8 of the largest marks a null direction, and the
// parameters carrying it are named.
void CheckIdentifiable(ceres::Problem* problem, const std::vector<double*>& blocks,
                       StandingModel model, size_t n_poses) {
  Eigen::MatrixXd J = DenseJacobian(problem, blocks, nullptr);
  const std::vector<std::string> names = ParameterNames(model);
  if (J.cols() != static_cast<int>(names.size())) {
    throw std::logic_error("standing step: Jacobian has " + std::to_string(J.cols()) +
                           " columns, expected the tangent size " + std::to_string(names.size()));
  }
  std::vector<std::string> bad;
  Eigen::VectorXd norms = J.colwise().norm();
  const double max_norm = norms.maxCoeff();
  for (int j = 0; j < J.cols(); ++j) {
    if (!(norms[j] > 1e-12 * max_norm)) {
      norms[j] = 1.0;
      bad.push_back(names[j]);
    }
  }
  J = J * norms.cwiseInverse().asDiagonal();
  // J = Q R, so J's singular values and right singular vectors are R's: a blocked Householder
  // QR in place (backward stable: R's singular values are J's to within eps |J|, far below the
  // threshold), then the SVD of the small square R. JacobiSVD, not BDCSVD: Eigen 3.4.0's BDCSVD
  // proved inaccurate (see offset_reestimation.cc). On a 3516 x 42 matrix this took half the time
  // of JacobiSVD of J itself (1.9 ms against 3.8 ms, memory warm), whose pivoted QR is unblocked
  // and works on a copy.
  const Eigen::HouseholderQR<Eigen::Ref<Eigen::MatrixXd>> qr(J);
  const Eigen::MatrixXd R = J.topRows(std::min(J.rows(), J.cols())).triangularView<Eigen::Upper>();
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(R, Eigen::ComputeThinV);
  const Eigen::VectorXd& sv = svd.singularValues();
  for (int i = 0; i < sv.size(); ++i) {
    if (sv[i] >= 1e-8 * sv[0]) continue;
    const Eigen::VectorXd v = svd.matrixV().col(i);
    for (int j = 0; j < v.size(); ++j) {
      if (std::abs(v[j]) > 0.2 && std::find(bad.begin(), bad.end(), names[j]) == bad.end()) {
        bad.push_back(names[j]);
      }
    }
  }
  if (bad.empty()) return;
  std::ostringstream msg;
  msg << "standing step: the " << n_poses << " poses do not determine these parameters of model "
      << StandingModelName(model) << " (rank-deficient Jacobian): ";
  for (size_t i = 0; i < bad.size(); ++i) msg << (i ? ", " : "") << bad[i];
  msg << "; vary shaft angles, foot loads and chassis attitude across poses";
  throw std::invalid_argument(msg.str());
}

}  // namespace

StandingFit FitFromParams(StandingModel model, const Params& p, RotationParams rotations) {
  StandingFit fit;
  fit.model = model;
  fit.dof = StandingModelDof(model);
  for (int k = 0; k < kNumLegs; ++k) {
    if (!HasRotations(model)) {
      fit.R_tilde[k] = Mat3::Identity();
    } else if (rotations == RotationParams::kCayley) {
      fit.R_tilde[k] =
          CayleyToRotation(Vec3(p.cayley[3 * k], p.cayley[3 * k + 1], p.cayley[3 * k + 2]));
    } else {
      fit.R_tilde[k] = Quat(p.quat[4 * k + 3], p.quat[4 * k], p.quat[4 * k + 1], p.quat[4 * k + 2])
                           .normalized()
                           .toRotationMatrix();
    }
  }
  if (SharedTranslation(model)) {
    fit.has_p_C_B = true;
    fit.p_C_B = Vec3(p.trans[0], p.trans[1], p.trans[2]);
    for (int k = 0; k < kNumLegs; ++k)
      fit.p_tilde_prime[k] = fit.R_tilde[k].transpose() * fit.p_C_B;
  } else {
    for (int k = 0; k < kNumLegs; ++k) {
      fit.p_tilde_prime[k] = Vec3(p.trans[3 * k], p.trans[3 * k + 1], p.trans[3 * k + 2]);
    }
  }
  return fit;
}

void CheckPoseCount(size_t n, StandingModel model, const StandingOptions& options) {
  if (static_cast<int>(n) < options.min_poses) {
    throw std::invalid_argument(
        "standing step: " + std::to_string(n) +
        " steady poses, fewer than min_poses = " + std::to_string(options.min_poses));
  }
  if (static_cast<int>(6 * n) <= StandingModelDof(model)) {
    throw std::invalid_argument(
        "standing step: " + std::to_string(n) + " poses give fewer equations than model " +
        StandingModelName(model) + "'s " + std::to_string(StandingModelDof(model)) + " parameters");
  }
}

std::vector<int> AllIds(size_t n) {
  std::vector<int> ids(n);
  for (size_t i = 0; i < n; ++i) ids[i] = static_cast<int>(i);
  return ids;
}

void FinishFit(const Prepared& prep, const std::vector<int>& ids, StandingFit* fit) {
  const std::vector<Vec6> res = ResidualsOfPoses(prep, *fit, ids);
  Vec6 k = prep.sqrt_k.cwiseProduct(prep.sqrt_k);
  fit->rss = WeightedRss(res, k);
  fit->poses = static_cast<int>(ids.size());
  const int redundancy = 6 * fit->poses - fit->dof;
  fit->residual_variance = redundancy > 0 ? fit->rss / redundancy : 0.0;
}

namespace {

ceres::Solver::Options SolverOptions(int max_iterations, double function_tolerance) {
  ceres::Solver::Options so;
  so.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  // The Jacobian is dense (every pose sees every parameter) and small (6 P x <= 42), and
  // CheckIdentifiable has refused ill-conditioned problems: normal equations are safe and
  // half the cost of QR here.
  so.linear_solver_type = ceres::DENSE_NORMAL_CHOLESKY;
  so.max_num_iterations = max_iterations;
  so.function_tolerance = function_tolerance;
  so.gradient_tolerance = 1e-14;
  so.parameter_tolerance = 1e-12;
  so.num_threads = 1;
  so.logging_type = ceres::SILENT;
  so.minimizer_progress_to_stdout = false;
  return so;
}

}  // namespace

StandingFit JointOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                       const StandingOptions& options, const StandingFit* start, RankCheck rank,
                       double function_tolerance) {
  Params params;
  if (start != nullptr) {
    StandingFit s = *start;
    s.model = model;
    params = ParamsFromFit(s);
  }
  Built b = Build(prep, ids, model, BuildOptions(), &params, options);
  if (rank == RankCheck::kCheck)
    CheckIdentifiable(b.problem.get(), b.free_blocks, model, ids.size());
  ceres::Solver::Summary summary;
  ceres::Solve(SolverOptions(options.max_iterations, function_tolerance), b.problem.get(),
               &summary);
  if (!summary.IsSolutionUsable()) {
    throw std::runtime_error("standing step: Ceres failed for model " +
                             std::string(StandingModelName(model)) + ": " + summary.message);
  }
  StandingFit fit = FitFromParams(model, params, RotationParams::kQuaternion);
  fit.leg_aware_com = prep.leg_aware;
  fit.solver = "joint";
  fit.iterations = static_cast<int>(summary.iterations.size()) - 1;
  fit.initial_cost = summary.initial_cost;
  fit.final_cost = summary.final_cost;
  fit.converged = summary.termination_type == ceres::CONVERGENCE;
  FinishFit(prep, ids, &fit);
  return fit;
}

void ValidateOptions(const StandingOptions& o) {
  if (o.cv_folds < 2) throw std::invalid_argument("standing step: cv_folds must be >= 2");
  if (!(o.alternating_tolerance > 0.0)) {
    throw std::invalid_argument("standing step: alternating_tolerance must be > 0");
  }
  if (o.robust_loss != StandingLoss::kNone && !(o.robust_loss_scale > 0.0)) {
    throw std::invalid_argument("standing step: robust_loss_scale must be > 0");
  }
}

// The report's alternating scheme on a subset of poses (FitStandingAlternating's description).
StandingFit AlternatingOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                             const StandingOptions& options, RankCheck rank) {
  const int n_trans = TransSize(model);
  Params params;  // Cayley q = 0 (R~ = I), translations 0
  if (rank == RankCheck::kCheck) {
    BuildOptions rank_check;
    rank_check.rotations = RotationParams::kCayley;
    rank_check.use_loss = false;
    Built b = Build(prep, ids, model, rank_check, &params, options);
    CheckIdentifiable(b.problem.get(), b.free_blocks, model, ids.size());
  }
  // The residual is affine in the translations with the rotations fixed, so one Jacobian
  // evaluation at t = 0 gives the linear least-squares problem exactly (closed form, normal
  // equations: at most 18 unknowns, well conditioned once CheckIdentifiable passed).
  auto solve_translations = [&]() {
    Eigen::MatrixXd JtJ = Eigen::MatrixXd::Zero(n_trans, n_trans);
    Eigen::VectorXd Jtr = Eigen::VectorXd::Zero(n_trans);
    std::array<double, 18> zero{};
    Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor> Jt(6, n_trans);
    for (int id : ids) {
      std::unique_ptr<ceres::CostFunction> cost(
          MakeCost(model, RotationParams::kCayley, &prep.poses[id], prep));
      const double* blocks[2] = {params.cayley.data(), zero.data()};
      double r[6];
      double* jac[2] = {nullptr, Jt.data()};
      cost->Evaluate(blocks, r, jac);
      JtJ += Jt.transpose() * Jt;
      Jtr += Jt.transpose() * Eigen::Map<const Vec6>(r);
    }
    const Eigen::VectorXd t = -JtJ.ldlt().solve(Jtr);
    for (int i = 0; i < n_trans; ++i) params.trans[i] = t[i];
  };
  // Report: scipy least_squares (trust region reflective) with cost tolerance 1e-3.
  ceres::Solver::Options rot_opts = SolverOptions(options.max_iterations, 1e-3);
  rot_opts.parameter_tolerance = 1e-8;
  rot_opts.gradient_tolerance = 1e-10;

  BuildOptions rotation_step;  // the translations held at the linear solve's values
  rotation_step.rotations = RotationParams::kCayley;
  rotation_step.translations_free = false;

  int sweeps = 0;
  bool converged = false;
  double initial_cost = -1.0, last_cost = 0.0;
  while (sweeps < options.alternating_max_sweeps) {
    const Params before = params;
    solve_translations();
    if (HasRotations(model)) {
      Built b = Build(prep, ids, model, rotation_step, &params, options);
      ceres::Solver::Summary summary;
      ceres::Solve(rot_opts, b.problem.get(), &summary);
      if (initial_cost < 0) initial_cost = summary.initial_cost;
      last_cost = summary.final_cost;
    }
    ++sweeps;
    double change = 0.0;
    for (int i = 0; i < 18; ++i) {
      change = std::max(change, std::abs(params.cayley[i] - before.cayley[i]));
      change = std::max(change, std::abs(params.trans[i] - before.trans[i]));
    }
    if (change < options.alternating_tolerance) {
      converged = true;
      break;
    }
    if (!HasRotations(model)) {  // nothing to alternate with: the linear solve is exact
      converged = true;
      break;
    }
  }
  StandingFit fit = FitFromParams(model, params, RotationParams::kCayley);
  fit.leg_aware_com = prep.leg_aware;
  fit.solver = "alternating";
  fit.iterations = sweeps;
  fit.converged = converged;
  FinishFit(prep, ids, &fit);
  fit.initial_cost = initial_cost < 0 ? 0.5 * fit.rss : initial_cost;
  fit.final_cost = HasRotations(model) ? last_cost : 0.5 * fit.rss;
  return fit;
}

}  // namespace standing_detail

using standing_detail::AddCovariance;
using standing_detail::AllIds;
using standing_detail::AlternatingOnIds;
using standing_detail::CheckPoseCount;
using standing_detail::HasRotations;
using standing_detail::JointOnIds;
using standing_detail::kFullDataTolerance;
using standing_detail::Prepare;
using standing_detail::Prepared;
using standing_detail::RankCheck;
using standing_detail::ValidateOptions;

StandingFit FitStandingJoint(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                             StandingModel model, const StandingOptions& options,
                             const StandingFit* start, bool compute_covariance) {
  ValidateOptions(options);
  CheckPoseCount(poses.size(), model, options);
  Prepared prep = Prepare(step1, poses, options);
  const std::vector<int> ids = AllIds(poses.size());
  StandingFit fit =
      JointOnIds(prep, ids, model, options, start, RankCheck::kCheck, kFullDataTolerance);
  if (HasRotations(model) && !prep.gravity_prior.empty()) {
    // The poses alone first, for the residual sigma that weights the hanging directions; then
    // both, from there. The pose-only rank check above stands: the prior only adds rank.
    prep.prior_scale = std::sqrt(fit.residual_variance);
    if (prep.prior_scale > 0.0) {
      const StandingFit poses_only = fit;
      fit =
          JointOnIds(prep, ids, model, options, &poses_only, RankCheck::kSkip, kFullDataTolerance);
    }
  }
  if (compute_covariance) AddCovariance(prep, ids, &fit, options);
  return fit;
}

StandingFit FitStandingAlternating(const RobotCalibration& step1,
                                   const std::vector<StandingPose>& poses, StandingModel model,
                                   const StandingOptions& options, bool compute_covariance) {
  ValidateOptions(options);
  CheckPoseCount(poses.size(), model, options);
  const Prepared prep = Prepare(step1, poses, options);
  const std::vector<int> ids = AllIds(poses.size());
  StandingFit fit = AlternatingOnIds(prep, ids, model, options, RankCheck::kCheck);
  if (compute_covariance) AddCovariance(prep, ids, &fit, options);
  return fit;
}

}  // namespace ftcal
