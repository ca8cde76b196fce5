// Step 2 (docs/method.md "Step 2", report section III-B): the four mounting models fitted,
// cross-validated and selected by BIC (CalibrateStanding), and the residuals the report compares.
// The cost and every Ceres template are in standing_cost.cc, the solves in standing_solve.cc, the
// covariance in standing_covariance.cc, the calibration-file output in standing_output.cc; their
// shared declarations in standing_internal.h.
//
// Model: eq. 9 with p~'_k = R~_k^T (p~_k + p^C_B) (bilinear form, see standing.h):
//   w^C_gc,k = [ R~ f' - F_g ;  R~ tau' + s_k x R~ f' - (R~ r' + s_k) x F_g ],
//   s_k = R~_k p~'_k (models 1, 3) or p^C_B (models 2, 4).
// Residual (eq. 8): r_p = sqrt(K) ([R_WC sum_k w^C_gc,k] - [0, 0, G; delta_W x (0, 0, G)]),
//   delta = 0 (report) or the pose's CoM shift sum_k (m_k / M) R~_k (r'_k(phi) - r'_k(0)).
// Unknowns: R~_k (unit quaternions on ceres::EigenQuaternionManifold in the joint solve, Cayley
//   vectors in the report's alternating scheme), p~'_k or p^C_B.
// Hanging gravity prior (ftcal's extension, off by default): 24 more residuals
//   w (R~_k u_B - v_C) per leg and hanging series (hanging.h), w = pose residual sigma / sigma,
//   in the joint solve of the models with rotations. It pins the common yaw of the six R~,
//   which the poses see only through the chassis tilt (sigma 0.08 deg from them alone).
// Null spaces: none when the poses vary force directions and attitude; checked on the
//   Jacobian (SVD of the column-normalised Jacobian) and refused by name when present.
// Report: eq. 8 and 9, Table I (model selection), the 1e-3 alternating stop rule.
#include "ftcal/standing.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <limits>
#include <utility>

#include "ftcal/config.h"

#include "parallel.h"
#include "standing_internal.h"

namespace ftcal {

using standing_detail::AlternatingOnIds;
using standing_detail::JointOnIds;
using standing_detail::kCrossValidationTolerance;
using standing_detail::Prepare;
using standing_detail::Prepared;
using standing_detail::RankCheck;
using standing_detail::ResidualsOfPoses;
using standing_detail::ValidatedAttitude;
using standing_detail::ValidateOptions;

StandingFit::StandingFit() {
  for (int k = 0; k < kNumLegs; ++k) {
    R_tilde[k] = Mat3::Identity();
    p_tilde_prime[k].setZero();
    sigma_rotation_deg[k].setZero();
    sigma_p_tilde_prime_m[k].setZero();
  }
}

int StandingModelDof(StandingModel model) {
  switch (model) {
    case StandingModel::kFull:
      return 36;
    case StandingModel::kRotationsOneTranslation:
      return 21;
    case StandingModel::kTranslationsOnly:
      return 18;
    case StandingModel::kOneTranslation:
      return 3;
  }
  throw std::invalid_argument("unknown standing model");
}

const char* StandingModelName(StandingModel model) {
  switch (model) {
    case StandingModel::kFull:
      return "FULL";
    case StandingModel::kRotationsOneTranslation:
      return "ROTATIONS_ONE_TRANSLATION";
    case StandingModel::kTranslationsOnly:
      return "TRANSLATIONS_ONLY";
    case StandingModel::kOneTranslation:
      return "ONE_TRANSLATION";
  }
  return "?";
}

const StandingFit& StandingResult::FitOf(StandingModel model, bool leg_aware_com) const {
  for (const StandingFit& f : fits) {
    if (f.model == model && f.leg_aware_com == leg_aware_com) return f;
  }
  throw std::out_of_range(std::string("StandingResult: model ") + StandingModelName(model) +
                          (leg_aware_com ? " (leg-aware CoM)" : " (fixed CoM)") +
                          " was not a candidate");
}

std::string CandidateName(StandingModel model, bool leg_aware_com) {
  return std::string(StandingModelName(model)) +
         (leg_aware_com ? ", leg-aware CoM" : ", fixed CoM");
}

StandingOptions StandingOptionsFromConfig(const config::Calibrator& c) {
  StandingOptions o;
  o.k_weights = KWeights(c);
  o.solver =
      c.solver() == config::ALTERNATING ? StandingSolver::kAlternating : StandingSolver::kJoint;
  o.alternating_tolerance = c.alternating_tolerance();
  switch (c.robust_loss()) {
    case config::HUBER:
      o.robust_loss = StandingLoss::kHuber;
      break;
    case config::CAUCHY:
      o.robust_loss = StandingLoss::kCauchy;
      break;
    default:
      o.robust_loss = StandingLoss::kNone;
      break;
  }
  o.robust_loss_scale = c.robust_loss_scale();
  o.cv_folds = static_cast<int>(c.cv_folds());
  // The REPORT profile is the report's fixed C; otherwise com_model says, COM_BY_DATA (the
  // default) letting model selection choose.
  const bool report = c.profile() == config::REPORT;
  o.leg_aware_com = !report && c.com_model() == config::COM_LEG_AWARE;
  o.select_com = !report && c.com_model() == config::COM_BY_DATA;
  o.min_poses = static_cast<int>(c.min_poses());
  return o;
}

std::vector<Vec6> TotalWrenchResiduals(const RobotCalibration& cal,
                                       const std::vector<StandingPose>& poses, bool leg_aware_com) {
  const double G = cal.TotalWeightN();
  const GroundWrenchModel model(cal);
  std::vector<Vec6> out;
  out.reserve(poses.size());
  for (size_t p = 0; p < poses.size(); ++p) {
    const StandingPose& pose = poses[p];
    const Mat3 R_WC = ValidatedAttitude(pose.R_WC, p);
    Vec6 total = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      total += model.W(k, pose.wrench[k], pose.angle_rad[k], R_WC);
    }
    Vec6 target;
    target << 0, 0, G, 0, 0, 0;
    if (leg_aware_com) {
      const Vec3 delta_W = R_WC * ComShiftC(cal, pose.angle_rad);
      target.tail<3>() = delta_W.cross(Vec3(0, 0, G));
    }
    out.push_back(total - target);
  }
  return out;
}

RobotCalibration ApplyStandingFit(const RobotCalibration& step1, const StandingFit& fit) {
  RobotCalibration cal = step1;
  for (int k = 0; k < kNumLegs; ++k) {
    cal.leg[k].R_tilde = fit.R_tilde[k];
    cal.leg[k].p_tilde_prime = fit.p_tilde_prime[k];
  }
  cal.p_C_B = fit.has_p_C_B ? fit.p_C_B : Vec3::Zero();
  return cal;
}

std::vector<Vec6> NaiveTareResiduals(const RobotCalibration& step1,
                                     const std::array<Vec6, kNumLegs>& naive_offset,
                                     const std::vector<StandingPose>& poses) {
  for (int k = 0; k < kNumLegs; ++k) {
    if (!naive_offset[k].allFinite()) {
      throw std::invalid_argument("standing step: naive tare offset of leg " +
                                  std::string(kLegNames[k]) + " is not finite");
    }
  }
  const double G = step1.TotalWeightN();
  std::vector<Vec6> out;
  out.reserve(poses.size());
  for (size_t p = 0; p < poses.size(); ++p) {
    const Mat3 R_WC = ValidatedAttitude(poses[p].R_WC, p);
    Vec6 total = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      total += TransformWrench(Pose3(R_WC, Vec3::Zero()) * step1.X_B_ft[k],
                               poses[p].wrench[k] - naive_offset[k]);
    }
    total[2] -= G;
    out.push_back(total);
  }
  return out;
}

std::vector<Vec6> PoseNoiseFloor(const RobotCalibration& step1,
                                 const std::vector<StandingPose>& poses) {
  const double G = step1.TotalWeightN();
  std::vector<Vec6> out;
  out.reserve(poses.size());
  for (const StandingPose& pose : poses) {
    if (pose.samples <= 0) {
      out.push_back(Vec6::Constant(std::numeric_limits<double>::quiet_NaN()));
      continue;
    }
    const Mat3 R_WC = ProjectToSO3(pose.R_WC);
    Mat3 cov_f = Mat3::Zero(), cov_t = Mat3::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Mat3 R = R_WC * step1.X_B_ft[k].R;
      const Mat3 P = Skew(R_WC * step1.X_B_ft[k].p);
      const Mat3 cf = R * pose.wrench_sem[k].head<3>().cwiseAbs2().asDiagonal() * R.transpose();
      cov_f += cf;
      cov_t += R * pose.wrench_sem[k].tail<3>().cwiseAbs2().asDiagonal() * R.transpose() +
               P * cf * P.transpose();
    }
    // An attitude error d (rotation vector in W) turns the total force (0, 0, G) by d x.
    const Mat3 A = -Skew(Vec3(0, 0, G));
    cov_f += A * pose.attitude_sem_rad.cwiseAbs2().asDiagonal() * A.transpose();
    Vec6 sigma;
    sigma << cov_f.diagonal().cwiseSqrt(), cov_t.diagonal().cwiseSqrt();
    out.push_back(sigma);
  }
  return out;
}

double WeightedRss(const std::vector<Vec6>& residuals, const Vec6& k_weights) {
  double rss = 0.0;
  for (const Vec6& r : residuals) rss += r.cwiseProduct(r).dot(k_weights);
  return rss;
}

double CrossValidationMse(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                          const StandingFit& full_data_fit, const StandingOptions& options) {
  ValidateOptions(options);
  Prepared prep = Prepare(step1, poses, options);
  prep.prior_scale = std::sqrt(full_data_fit.residual_variance);
  const Vec6 k = options.k_weights;
  double sum = 0.0;
  for (int f = 0; f < options.cv_folds; ++f) {
    std::vector<int> train, test;
    for (size_t i = 0; i < poses.size(); ++i) {
      (static_cast<int>(i) % options.cv_folds == f ? test : train).push_back(static_cast<int>(i));
    }
    if (test.empty() || static_cast<int>(6 * train.size()) <= full_data_fit.dof) {
      throw std::invalid_argument("standing step: " + std::to_string(poses.size()) +
                                  " poses are too few for " + std::to_string(options.cv_folds) +
                                  "-fold cross-validation");
    }
    const StandingFit fit =
        options.solver == StandingSolver::kAlternating
            ? AlternatingOnIds(prep, train, full_data_fit.model, options, RankCheck::kSkip)
            : JointOnIds(prep, train, full_data_fit.model, options, &full_data_fit,
                         RankCheck::kSkip, kCrossValidationTolerance);
    sum += WeightedRss(ResidualsOfPoses(prep, fit, test), k) / static_cast<double>(test.size());
  }
  return sum / options.cv_folds;
}

StandingResult CalibrateStanding(const RobotCalibration& step1,
                                 const std::vector<StandingPose>& poses,
                                 const std::array<Vec6, kNumLegs>& naive_offset,
                                 const StandingOptions& options) {
  StandingResult result;
  result.options = options;
  result.poses = static_cast<int>(poses.size());
  const double P = static_cast<double>(poses.size());
  // The candidates (each a fit plus its 5-fold cross-validation) are independent Ceres problems
  // on const inputs, so they run side by side (parallel.h); results are kept in candidate order.
  struct ModelRun {
    StandingFit fit;
    double cv_mse = 0.0;
  };
  std::vector<bool> targets;
  if (options.select_com) {
    targets = {false, true};
  } else {
    targets = {options.leg_aware_com};
  }
  result.com_selected_by_data = options.select_com;
  // Each candidate is fitted and cross-validated by the configured solver, so the table
  // describes the parameters that are written.
  const bool alternating = options.solver == StandingSolver::kAlternating;
  std::vector<std::pair<bool, StandingModel>> candidates;
  for (const bool aware : targets) {
    for (StandingModel model : kStandingModels) candidates.emplace_back(aware, model);
  }
  std::vector<ModelRun> done(candidates.size());
  ParallelFor(candidates.size(), [&](size_t i) {
    StandingOptions o = options;
    o.leg_aware_com = candidates[i].first;
    const StandingModel model = candidates[i].second;
    done[i].fit = alternating ? FitStandingAlternating(step1, poses, model, o)
                              : FitStandingJoint(step1, poses, model, o);
    done[i].cv_mse = CrossValidationMse(step1, poses, done[i].fit, o);
  });
  double best_bic = 0.0;
  size_t best = 0;
  for (size_t m = 0; m < done.size(); ++m) {
    StandingFit& fit = done[m].fit;
    ModelSelectionRow row;
    row.model = fit.model;
    row.leg_aware_com = fit.leg_aware_com;
    row.dof = fit.dof;
    row.rss = fit.rss;
    row.bic = P * std::log(fit.rss / P) + fit.dof * std::log(P);
    row.cv_mse = done[m].cv_mse;
    if (result.model_selection.empty() || row.bic < best_bic) {
      best_bic = row.bic;
      best = m;
    }
    result.model_selection.push_back(row);
    result.fits.push_back(std::move(fit));
  }
  for (size_t m = 0; m < result.model_selection.size(); ++m) {
    result.model_selection[m].selected = m == best;
  }
  result.selected = result.fits[best].model;
  result.selected_leg_aware_com = result.fits[best].leg_aware_com;
  result.options.leg_aware_com = result.selected_leg_aware_com;
  result.fit = result.fits[best];
  result.calibration = ApplyStandingFit(step1, result.fit);
  RobotCalibration without = step1;
  for (int k = 0; k < kNumLegs; ++k) {
    without.leg[k].R_tilde = Mat3::Identity();
    without.leg[k].p_tilde_prime = Vec3::Zero();
  }
  without.p_C_B = Vec3::Zero();
  {
    const std::vector<Vec6> floor = PoseNoiseFloor(step1, poses);
    Vec6 sum2 = Vec6::Zero();
    for (const Vec6& f : floor) {
      if (!f.allFinite()) continue;
      ++result.poses_with_scatter;
      sum2 += f.cwiseAbs2();
    }
    if (result.poses_with_scatter == result.poses && result.poses > 0) {
      result.floor_rms = (sum2 / result.poses).cwiseSqrt();
      result.floor_variance = (sum2 / result.poses).dot(options.k_weights) / 6.0;
      if (result.floor_variance > 0.0) {
        result.residual_to_floor = std::sqrt(result.fit.residual_variance / result.floor_variance);
      }
    }
  }
  result.residual_naive = NaiveTareResiduals(step1, naive_offset, poses);
  result.residual_without = TotalWrenchResiduals(without, poses, result.selected_leg_aware_com);
  result.residual_full =
      TotalWrenchResiduals(result.calibration, poses, result.selected_leg_aware_com);
  return result;
}

}  // namespace ftcal
