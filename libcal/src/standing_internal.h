// What the files of step 2 share and the public header does not show: the precomputed terms of
// each pose, the parameter storage of one problem, the problem builder with its options, and the
// solves on a subset of poses that the model selection's cross-validation reuses.
// standing_cost.cc holds every Ceres template (cost functors, CayleyRotation, LegContribution),
// standing_solve.cc the joint and alternating solves, standing_covariance.cc the uncertainties,
// standing.cc the model selection, standing_output.cc the calibration-file output. Internal to
// libcal: tests use only standing.h.
#pragma once

#include <array>
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include <ceres/cost_function.h>
#include <ceres/loss_function.h>
#include <ceres/problem.h>
#include <ceres/solver.h>

#include "ftcal/standing.h"

namespace ftcal {
namespace standing_detail {

constexpr double kRadToDeg = 180.0 / M_PI;

// The nominally transformed quantities of one leg in one pose (primes of docs/method.md): step 1 is
// fixed during step 2, so these are computed once and the cost functor only rotates/shifts them.
struct LegTerms {
  Vec3 f = Vec3::Zero();    // f' = R_B_ft (w_m - w_o).f
  Vec3 tau = Vec3::Zero();  // tau' about the body origin
  Vec3 r = Vec3::Zero();    // r'_k(phi): leg CoM in B (nominal)
  Vec3 dr = Vec3::Zero();   // (m_k / M) (r'_k(phi) - r'_k(0)): leg-aware CoM shift term
  Vec3 F_g = Vec3::Zero();  // m_k g^C
};

struct PoseTerms {
  std::array<LegTerms, kNumLegs> leg;
  Mat3 R_WC = Mat3::Identity();
};

struct Prepared {
  std::vector<PoseTerms> poses;
  double G = 0.0;
  Vec6 sqrt_k = Vec6::Ones();
  bool leg_aware = false;
  // Hanging gravity directions (options.gravity_prior) and the pose residual sigma that puts
  // them in the units of the pose residuals; 0 leaves them out of the problem.
  std::vector<HangingGravityObservation> gravity_prior;
  double prior_scale = 0.0;
};

// Step 1's calibration and the poses checked and turned into the terms above (standing_cost.cc).
Prepared Prepare(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                 const StandingOptions& options);
// A pose's attitude checked (finite, near-orthonormal) and projected onto SO(3). p: the pose's
// index, for the message.
Mat3 ValidatedAttitude(const Mat3& R_WC, size_t p);

inline bool HasRotations(StandingModel m) {
  return m == StandingModel::kFull || m == StandingModel::kRotationsOneTranslation;
}
inline bool SharedTranslation(StandingModel m) {
  return m == StandingModel::kRotationsOneTranslation || m == StandingModel::kOneTranslation;
}
inline int TransSize(StandingModel m) { return SharedTranslation(m) ? 3 : 18; }

// Ceres's EigenQuaternionManifold moves q by q_delta = [cos|d|, sin|d| d/|d|] (x) q, so its
// tangent d is half the (left) rotation vector.
constexpr double kQuaternionTangentToRotationVector = 2.0;

// Parameter storage for one problem.
struct Params {
  std::array<double, 24> quat{};  // (x, y, z, w) per leg
  std::array<double, 18> cayley{};
  std::array<double, 18> trans{};  // first 3 used when shared
  Params() {
    for (int k = 0; k < kNumLegs; ++k) quat[4 * k + 3] = 1.0;
  }
};

// A fit's parameters into problem storage (quaternions and Cayley vectors both filled), and back.
Params ParamsFromFit(const StandingFit& fit);
StandingFit FitFromParams(StandingModel model, const Params& p, RotationParams rotations);
// Names of a model's parameters in tangent order (the Jacobian's columns).
std::vector<std::string> ParameterNames(StandingModel model);

// How one problem is parametrised and what it leaves free. The defaults are the joint solve's.
struct BuildOptions {
  RotationParams rotations = RotationParams::kQuaternion;
  // Free blocks are solved for; the others are held constant (the alternating scheme's halves).
  bool rotations_free = true;
  bool translations_free = true;
  // The configured robust loss (StandingOptions.robust_loss) on the pose residuals.
  bool use_loss = true;
};

// A Ceres problem over a subset of poses.
struct Built {
  std::unique_ptr<ceres::LossFunction> loss;
  std::unique_ptr<ceres::Problem> problem;
  double* rot = nullptr;
  double* trans = nullptr;
  std::vector<double*> free_blocks;
};

// The problem over the poses pose_ids, on the storage *params (standing_cost.cc). The hanging
// gravity prior is added for quaternion rotations when prep.prior_scale > 0.
Built Build(const Prepared& prep, const std::vector<int>& pose_ids, StandingModel model,
            const BuildOptions& build, Params* params, const StandingOptions& options);

// One pose's cost on its own, for a caller that evaluates it directly (the alternating scheme's
// linear translation step); its translation block is the model's (3 for a shared p^C_B, or 18).
ceres::CostFunction* MakeCost(StandingModel model, RotationParams rotations, const PoseTerms* terms,
                              const Prepared& prep);

// The residual the solver minimises at fit, per pose of ids, without the sqrt(K) weighting.
std::vector<Vec6> ResidualsOfPoses(const Prepared& prep, const StandingFit& fit,
                                   const std::vector<int>& ids);

// The Jacobian of every residual block (rows in the problem's order) with respect to `blocks`
// (columns in that order, each block's tangent space), as Problem::Evaluate gives it with the
// loss applied; the residuals too when `residuals` is not null.
Eigen::MatrixXd DenseJacobian(ceres::Problem* problem, const std::vector<double*>& blocks,
                              std::vector<double>* residuals);

// Sigmas and correlation of a fit from the sandwich covariance (standing_covariance.cc).
void AddCovariance(const Prepared& prep, const std::vector<int>& ids, StandingFit* fit,
                   const StandingOptions& options);

// Relative cost change at which a joint solve stops: to convergence for the calibration (noise-
// free data are recovered to 1e-9 and better); looser for the cross-validation folds, whose
// test MSE does not move in the digits reported at 1e-8.
constexpr double kFullDataTolerance = 1e-12;
constexpr double kCrossValidationTolerance = 1e-8;

void ValidateOptions(const StandingOptions& o);
void CheckPoseCount(size_t n, StandingModel model, const StandingOptions& options);
std::vector<int> AllIds(size_t n);

// Whether a solve first checks that its poses determine the model's parameters (naming the
// ones they do not). The fit on all poses does; the cross-validation folds and a second solve
// on the same poses need not repeat it.
enum class RankCheck { kCheck, kSkip };

// The joint solve on the poses ids, from *start when given (standing_solve.cc).
StandingFit JointOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                       const StandingOptions& options, const StandingFit* start, RankCheck rank,
                       double function_tolerance);
// The report's alternating scheme on the poses ids, from R~ = I and zero translations.
StandingFit AlternatingOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                             const StandingOptions& options, RankCheck rank);

}  // namespace standing_detail
}  // namespace ftcal
