// Step 2 of the method (docs/method.md "Step 2", report section III-B): standing poses give the
// mounting errors T~_k = (R~_k, p~_k) and the body-to-CoM offset p^C_B.
//
// Model (eq. 9, with p~'_k = R~_k^T (p~_k + p^C_B), see sensing_model.h): per pose p and leg k,
// with the step-1 parameters fixed and primes the nominally transformed quantities in B,
//   f'  = R_B_ft (w_m - w_o).f,  tau' = R_B_ft (w_m - w_o).tau + p_B_ft x f',
//   r'  = X_B_ft r_k(phi),        F_g = m_k g^C,
//   w^C_gc,k = [ R~ f' - F_g ;  R~ tau' + s_k x R~ f' - (R~ r' + s_k) x F_g ],
// where s_k = R~_k p~'_k (models 1, 3) or s_k = p^C_B (models 2, 4: p~'_k = R~_k^T p^C_B).
// Residual of pose p (eq. 8): r_p = R_WC sum_k w^C_gc,k - [0, 0, G; delta_p x (0, 0, G)], with
// delta_p = 0 (the report) or, leg-aware, the whole-robot CoM shift of the pose in W.
// Cost: sum_p ||r_p||^2_K (K diagonal, default 1,1,1,10,10,10).
// Unknowns: six R~_k on SO(3) and six p~'_k (FULL, 36); six R~_k and p^C_B (21); six p~'_k
// with R~ = I (18); p^C_B alone (3).
// Null spaces: none in general, but only if the poses excite them: p~' along a leg's force is
// seen only through force directions that vary (horizontal foot forces, chassis tilt); p^C_B_z
// only through tilt. A rank-deficient Jacobian is refused (std::invalid_argument naming the
// parameters), never returned as a calibration.
#pragma once

#include <array>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/hanging.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ceres {
class CostFunction;
}

namespace ftcal {

// Table I of the report; values equal calibration.proto's StandingModel.
enum class StandingModel {
  kFull = 1,                     // six R~ + six p~'        (36)
  kRotationsOneTranslation = 2,  // six R~ + one p^C_B      (21)
  kTranslationsOnly = 3,         // R~ = I, six p~'         (18)
  kOneTranslation = 4,           // p^C_B only              (3)
};
inline constexpr std::array<StandingModel, 4> kStandingModels = {
    StandingModel::kFull, StandingModel::kRotationsOneTranslation, StandingModel::kTranslationsOnly,
    StandingModel::kOneTranslation};
int StandingModelDof(StandingModel model);
// How a solve holds the six mounting rotations: unit quaternions on their manifold (the joint
// solve), or Cayley vectors (the report's alternating scheme, unconstrained).
enum class RotationParams { kQuaternion, kCayley };
const char* StandingModelName(StandingModel model);
// "FULL, fixed CoM", "ONE_TRANSLATION, leg-aware CoM", ...
std::string CandidateName(StandingModel model, bool leg_aware_com);

enum class StandingSolver { kJoint, kAlternating };
enum class StandingLoss { kNone, kHuber, kCauchy };

struct StandingOptions {
  Vec6 k_weights = (Vec6() << 1, 1, 1, 10, 10, 10).finished();
  StandingSolver solver = StandingSolver::kJoint;
  double alternating_tolerance = 1e-3;  // max-norm change of (Cayley q, p~' in m) per sweep
  int alternating_max_sweeps = 1000;
  StandingLoss robust_loss = StandingLoss::kNone;
  double robust_loss_scale = 1.0;
  int cv_folds = 5;
  // The robot-CoM target of a fit: false the report's fixed C, true the leg-aware CoM.
  bool leg_aware_com = false;
  // CalibrateStanding: fit the four mounting models with both robot-CoM targets and let model
  // selection choose (leg_aware_com is then ignored there).
  bool select_com = false;
  int min_poses = 30;
  int max_iterations = 200;  // Levenberg-Marquardt iterations per joint solve
  // ftcal's extension (config calibrator.hanging_gravity_prior): the hanging series' gravity
  // directions as observations R~_k u_B = v_C in the joint solve of the models with rotations,
  // each weighted by (pose residual sigma) / sigma_rad so both kinds of residual are in the
  // same units. Empty: the report's step 2. The alternating scheme ignores them.
  std::vector<HangingGravityObservation> gravity_prior;
};

// From the config's calibrator section (k_weights via KWeights(), enums mapped).
StandingOptions StandingOptionsFromConfig(const config::Calibrator& calibrator);

// One model fitted to a set of poses.
struct StandingFit {
  StandingModel model = StandingModel::kFull;
  int dof = 0;
  std::array<Mat3, kNumLegs> R_tilde;        // I where the model has no rotations
  std::array<Vec3, kNumLegs> p_tilde_prime;  // m; R~^T p^C_B in models 2 and 4
  bool has_p_C_B = false;                    // models 2 and 4
  Vec3 p_C_B = Vec3::Zero();                 // m
  // 1-sigma from the sandwich covariance with per-component residual variances
  // (standing_covariance.cc, AddCovariance); zero for what the model fixes.
  // Rotations: sigma of the left rotation-vector perturbation R~ = Exp(dv) R~_hat, in degrees.
  bool has_covariance = false;
  std::array<Vec3, kNumLegs> sigma_rotation_deg;
  std::array<Vec3, kNumLegs> sigma_p_tilde_prime_m;
  Vec3 sigma_p_C_B_m = Vec3::Zero();
  // The correlation matrix of the same covariance, over the model's free parameters in the
  // solver's order (rotations "HL R~ x".."FR R~ z" when the model has them, then "p^C_B x".."z"
  // or "HL p~' x".."FR p~' z"), named in correlation_names. Empty without the covariance.
  std::vector<std::string> correlation_names;
  Eigen::MatrixXd correlation;
  double rss = 0.0;                // sum_p ||r_p||^2_K at the solution (robust loss or not)
  double residual_variance = 0.0;  // rss / (6 P - dof)
  int poses = 0;
  bool leg_aware_com = false;                   // the robot-CoM target it was fitted with
  std::string solver;                           // "joint" or "alternating"
  int iterations = 0;                           // LM iterations (joint) or sweeps (alternating)
  double initial_cost = 0.0, final_cost = 0.0;  // Ceres cost (1/2 sum of squares, robustified)
  bool converged = false;

  StandingFit();
};

// Joint solve of all the model's parameters at once, rotations on SO(3)
// (ceres::EigenQuaternionManifold), to convergence. `start`, when given, warm-starts it.
// Throws std::invalid_argument on too few poses, non-finite input, or parameters the poses
// do not determine (named).
StandingFit FitStandingJoint(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                             StandingModel model, const StandingOptions& options,
                             const StandingFit* start = nullptr, bool compute_covariance = true);

// The report's alternating scheme: translations by linear least squares with the rotations
// fixed, rotations (Cayley parameters) by a nonlinear solve with the translations fixed
// (cost tolerance 1e-3, as the report's scipy call), until successive solutions differ by less
// than options.alternating_tolerance (max norm). Stops where that rule says, which can be far
// from the optimum (docs/method.md). iterations = sweeps.
StandingFit FitStandingAlternating(const RobotCalibration& step1,
                                   const std::vector<StandingPose>& poses, StandingModel model,
                                   const StandingOptions& options, bool compute_covariance = true);

// Residual r_p of every pose (total ground wrench at the CoM in W minus the target) for the
// parameters in `cal` (offsets, weights, CoM curves, R~, p~' as stored).
std::vector<Vec6> TotalWrenchResiduals(const RobotCalibration& cal,
                                       const std::vector<StandingPose>& poses, bool leg_aware_com);
// The same with a fit's mounting parameters applied to the step-1 parameters.
RobotCalibration ApplyStandingFit(const RobotCalibration& step1, const StandingFit& fit);
// Naive-tare baseline: offsets = the naive tare, no leg gravity model, nominal mounting,
// CoM at the body origin.
std::vector<Vec6> NaiveTareResiduals(const RobotCalibration& step1,
                                     const std::array<Vec6, kNumLegs>& naive_offset,
                                     const std::vector<StandingPose>& poses);
// The noise floor of each pose's residual r_p: 1-sigma per component [fx fy fz tx ty tz] from
// the pose's within-pose scatter (StandingPose::wrench_sem, attitude_sem_rad) propagated through
// the nominal transform (each leg's force and torque into C, the attitude error tilting the
// weight G); a pose without scatter (samples == 0) gives NaN.
std::vector<Vec6> PoseNoiseFloor(const RobotCalibration& step1,
                                 const std::vector<StandingPose>& poses);

// sum_p ||r_p||^2_K.
double WeightedRss(const std::vector<Vec6>& residuals, const Vec6& k_weights);

struct ModelSelectionRow {
  StandingModel model = StandingModel::kFull;
  bool leg_aware_com = false;
  int dof = 0;
  double cv_mse = 0.0;  // mean over folds of the test poses' mean ||r_p||^2_K
  double rss = 0.0;     // over all poses
  double bic = 0.0;     // P ln(RSS / P) + DOF ln P
  bool selected = false;
};

// k-fold cross-validation on poses (pose i in fold i % folds) with the solver that made
// `full_data_fit` (options.solver): the joint solve warm-started from it, the alternating scheme
// from R~ = I as the report runs it; returns the mean test MSE.
double CrossValidationMse(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                          const StandingFit& full_data_fit, const StandingOptions& options);

struct StandingResult {
  // Every candidate fitted by the configured solver, Table I order, the fixed-CoM rows first
  // (only the configured robot-CoM target's rows without select_com).
  std::vector<StandingFit> fits;
  std::vector<ModelSelectionRow> model_selection;  // Table I, same order as fits
  StandingModel selected = StandingModel::kFull;   // lowest BIC
  bool selected_leg_aware_com = false;             // ... and its robot-CoM target
  bool com_selected_by_data = false;               // both robot-CoM targets were candidates
  StandingFit fit;  // the selected candidate (a copy of its entry in fits)
  // The candidate of `model` with the given robot-CoM target; throws when it was not fitted.
  const StandingFit& FitOf(StandingModel model, bool leg_aware_com) const;
  RobotCalibration calibration;                                       // step 1 + the selected fit
  std::vector<Vec6> residual_naive, residual_without, residual_full;  // per pose
  int poses = 0;
  StandingOptions options;  // as given, with leg_aware_com set to the selected target
  // The noise floor (PoseNoiseFloor) and the selected fit's residual against it:
  // residual_to_floor = sqrt((RSS / (6 P - DOF)) / floor_variance), floor_variance the mean over
  // poses and components of K_i floor_i^2; 0 when some pose has no within-pose scatter.
  int poses_with_scatter = 0;
  Vec6 floor_rms = Vec6::Zero();  // rms over poses of the floor per component
  double floor_variance = 0.0;
  double residual_to_floor = 0.0;
};

// The whole of step 2: every candidate (four mounting models, times the two robot-CoM targets
// with select_com) fitted by the configured solver and cross-validated by the same solver,
// model selection by BIC (with CV MSE), residuals of the three variants for the selected one.
StandingResult CalibrateStanding(const RobotCalibration& step1,
                                 const std::vector<StandingPose>& poses,
                                 const std::array<Vec6, kNumLegs>& naive_offset,
                                 const StandingOptions& options);

// C_ij / sqrt(C_ii C_jj) of a covariance matrix (C_ij averaged with C_ji); a parameter with zero
// variance (fixed) gets 0 off the diagonal and 1 on it. Throws std::invalid_argument for a
// non-square matrix or a negative or non-finite variance.
Eigen::MatrixXd CorrelationOfCovariance(const Eigen::MatrixXd& covariance);

// Mean, std (sample), rms, 5th and 95th percentiles (linear interpolation) per component.
calibration::ResidualStats ResidualStatsOf(const std::string& label,
                                           const std::vector<Vec6>& residuals);

// Fills the step-2 parts of the calibration file: per leg mounting (quaternion, rotation vector
// and p~' with sigma, p~ where p^C_B is known), p_c_b_m, model, model_selection, solver,
// standing_residual ("naive tare", "without T~", "full calibration"), standing_poses,
// standing_uncertainty. Legs missing in `out` are added with their names.
void FillStandingProto(const StandingResult& result, calibration::Calibration* out);

// The cost function of one pose as the solvers use it (6 residuals; parameter blocks: rotations
// as 24 quaternion entries (x, y, z, w per leg) or 18 Cayley entries, then 18 p~' or 3 p^C_B
// entries). For gradient checks; owns a copy of what it needs.
std::unique_ptr<ceres::CostFunction> StandingPoseCostForCheck(const RobotCalibration& step1,
                                                              const StandingPose& pose,
                                                              StandingModel model,
                                                              RotationParams rotations,
                                                              const StandingOptions& options);

}  // namespace ftcal
