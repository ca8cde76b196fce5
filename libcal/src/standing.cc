// Step 2 (docs/method.md "Step 2", report section III-B). All Ceres templates of step 2 live in
// this one translation unit: they compile slowly.
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
#include <exception>
#include <future>
#include <limits>
#include <utility>

#include <Eigen/Cholesky>
#include <Eigen/SVD>
#include <ceres/ceres.h>
#include <ceres/manifold.h>
#include <ceres/product_manifold.h>

#include "ftcal/config.h"

namespace ftcal {

namespace {

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

void RequireFinite(double v, const std::string& what) {
  if (!std::isfinite(v)) {
    throw std::invalid_argument("standing step: " + what + " is not finite (" + std::to_string(v) +
                                ")");
  }
}

std::string PoseLeg(size_t p, int k) {
  return "pose " + std::to_string(p) + " leg " + std::string(kLegNames[k]);
}

void ValidateStep1(const RobotCalibration& cal) {
  RequireFinite(cal.total_mass_kg, "step-1 total_mass_kg");
  RequireFinite(cal.g0, "step-1 g0");
  if (!(cal.TotalWeightN() > 0.0)) {
    throw std::invalid_argument("standing step: total weight G = total_mass_kg * g0 must be > 0");
  }
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string leg = "step-1 leg " + std::string(kLegNames[k]);
    for (int i = 0; i < 6; ++i) RequireFinite(cal.leg[k].offset[i], leg + " offset");
    RequireFinite(cal.leg[k].weight_n, leg + " weight_n");
    const LegComModel& c = cal.leg[k].com;
    for (double v : {c.x.a, c.x.c, c.x.d, c.y, c.z.a, c.z.c, c.z.d}) RequireFinite(v, leg + " CoM");
    if (OrthonormalityError(cal.X_B_ft[k].R) > 1e-6 || !cal.X_B_ft[k].p.allFinite()) {
      throw std::invalid_argument("standing step: nominal X_B_ft of leg " +
                                  std::string(kLegNames[k]) + " is not a rigid transform");
    }
  }
}

Mat3 ValidatedAttitude(const Mat3& R_WC, size_t p) {
  if (!R_WC.allFinite()) {
    throw std::invalid_argument("standing step: pose " + std::to_string(p) +
                                " attitude R_WC is not finite");
  }
  // A pose's attitude is a median of samples, so it is orthonormal only approximately.
  const double err = OrthonormalityError(R_WC);
  if (err > 1e-3) {
    throw std::invalid_argument("standing step: pose " + std::to_string(p) +
                                " attitude R_WC is not a rotation (orthonormality error " +
                                std::to_string(err) + ")");
  }
  return ProjectToSO3(R_WC);
}

Prepared Prepare(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                 const StandingOptions& options) {
  ValidateStep1(step1);
  for (int i = 0; i < 6; ++i) {
    if (!(options.k_weights[i] > 0.0) || !std::isfinite(options.k_weights[i])) {
      throw std::invalid_argument("standing step: k_weights[" + std::to_string(i) +
                                  "] must be finite and > 0");
    }
  }
  Prepared out;
  out.G = step1.TotalWeightN();
  out.sqrt_k = options.k_weights.cwiseSqrt();
  out.leg_aware = options.leg_aware_com;
  for (const HangingGravityObservation& o : options.gravity_prior) {
    const std::string what =
        "gravity prior of leg " + std::to_string(o.leg) + " series " + HangSeriesName(o.series);
    if (o.leg < 0 || o.leg >= kNumLegs)
      throw std::invalid_argument("standing step: " + what + ": no such leg");
    if (!o.u_B.allFinite() || !o.v_C.allFinite() || std::abs(o.u_B.norm() - 1.0) > 1e-6 ||
        std::abs(o.v_C.norm() - 1.0) > 1e-6) {
      throw std::invalid_argument("standing step: " + what + ": directions are not unit vectors");
    }
    RequireFinite(o.sigma_rad, what + " sigma_rad");
  }
  out.gravity_prior = options.gravity_prior;
  out.poses.resize(poses.size());
  for (size_t p = 0; p < poses.size(); ++p) {
    const StandingPose& pose = poses[p];
    PoseTerms& t = out.poses[p];
    t.R_WC = ValidatedAttitude(pose.R_WC, p);
    const Vec3 down_C = t.R_WC.transpose() * Vec3(0, 0, -1);
    for (int k = 0; k < kNumLegs; ++k) {
      if (!pose.wrench[k].allFinite()) {
        throw std::invalid_argument("standing step: " + PoseLeg(p, k) + " wrench is not finite");
      }
      RequireFinite(pose.angle_rad[k], PoseLeg(p, k) + " shaft angle");
      const Pose3& X = step1.X_B_ft[k];
      const LegCalibration& l = step1.leg[k];
      const Vec6 w = pose.wrench[k] - l.offset;
      LegTerms& lt = t.leg[k];
      lt.f = X.R * w.head<3>();
      lt.tau = X.R * w.tail<3>() + X.p.cross(lt.f);
      lt.r = X * l.com.At(LegPhase(pose.angle_rad[k]));
      lt.dr = (l.weight_n / out.G) * (lt.r - X * l.com.At(0.0));
      lt.F_g = l.weight_n * down_C;
    }
  }
  return out;
}

// Cayley map in closed form, R = ((1 - q.q) I + 2 q q^T - 2 [q]) / (1 + q.q), equal to
// (I - [q])(I + [q])^-1 (geometry.h) and differentiable by Jets without a matrix inverse.
template <typename T>
Eigen::Matrix<T, 3, 3> CayleyRotation(const T* q) {
  const T n = q[0] * q[0] + q[1] * q[1] + q[2] * q[2];
  const T s = T(1) / (T(1) + n);
  Eigen::Matrix<T, 3, 3> R;
  R(0, 0) = (T(1) - n + T(2) * q[0] * q[0]) * s;
  R(1, 1) = (T(1) - n + T(2) * q[1] * q[1]) * s;
  R(2, 2) = (T(1) - n + T(2) * q[2] * q[2]) * s;
  R(0, 1) = (T(2) * q[0] * q[1] + T(2) * q[2]) * s;
  R(1, 0) = (T(2) * q[0] * q[1] - T(2) * q[2]) * s;
  R(0, 2) = (T(2) * q[0] * q[2] - T(2) * q[1]) * s;
  R(2, 0) = (T(2) * q[0] * q[2] + T(2) * q[1]) * s;
  R(1, 2) = (T(2) * q[1] * q[2] + T(2) * q[0]) * s;
  R(2, 1) = (T(2) * q[1] * q[2] - T(2) * q[0]) * s;
  return R;
}

// Leg k's contribution to one pose's total ground wrench in C (eq. 9 with the primes):
//   c_k = [ R~ f' - F_g ; R~ tau' + s x R~ f' - (R~ r' + s) x F_g - (R~ dr) x G^C ],
// s = R~ t (t = p~'_k) or s = t (t = p^C_B, shared); the last term is the leg-aware CoM shift
// (dr = 0 otherwise). kRotParams: 4 = unit quaternion in Eigen's (x, y, z, w) storage,
// 3 = Cayley vector.
template <int kRotParams, typename T>
void LegContribution(const LegTerms& l, const T* rot, const T* t, bool shared, bool leg_aware,
                     const Vec3& G_C, T* c) {
  using V3 = Eigen::Matrix<T, 3, 1>;
  Eigen::Matrix<T, 3, 3> R;
  if constexpr (kRotParams == 3) {
    R = CayleyRotation(rot);
  } else {
    R = Eigen::Map<const Eigen::Quaternion<T>>(rot).toRotationMatrix();
  }
  const V3 Rf = R * l.f.cast<T>();
  const V3 F_g = l.F_g.cast<T>();
  const V3 tv(t[0], t[1], t[2]);
  const V3 s = shared ? tv : V3(R * tv);
  const V3 force = Rf - F_g;
  V3 torque = R * l.tau.cast<T>() + s.cross(Rf) - (R * l.r.cast<T>() + s).cross(F_g);
  if (leg_aware) torque -= (R * l.dr.cast<T>()).cross(G_C.cast<T>());
  for (int i = 0; i < 3; ++i) {
    c[i] = force[i];
    c[3 + i] = torque[i];
  }
}

// One pose's residual r_p = sqrt(K) (blockdiag(R_WC, R_WC) sum_k c_k - (0, 0, G, 0, 0, 0)).
// Parameter blocks: rotations (24 quaternion or 18 Cayley entries) and translations (18, or 3
// when shared). The residual is a sum over legs and leg k touches only its own rotation (and
// translation), so each leg is differentiated with a Jet of its own 6 or 7 parameters (Ceres's
// autodiff, per leg) and scattered into the block Jacobians: a single 42-wide Jet over the
// whole pose would cost about six times as much for the same numbers.
class PoseCost final : public ceres::CostFunction {
 public:
  PoseCost(const PoseTerms* terms, const Prepared& prep, bool shared, bool cayley)
      : terms_(terms), shared_(shared), cayley_(cayley), leg_aware_(prep.leg_aware), G_(prep.G) {
    set_num_residuals(6);
    mutable_parameter_block_sizes()->push_back(cayley ? 18 : 24);
    mutable_parameter_block_sizes()->push_back(shared ? 3 : 18);
    M_.setZero();
    M_.topLeftCorner<3, 3>() = terms->R_WC;
    M_.bottomRightCorner<3, 3>() = terms->R_WC;
    M_ = prep.sqrt_k.asDiagonal() * M_;
    sqrt_k_ = prep.sqrt_k;
    G_C_ = terms->R_WC.transpose().col(2) * prep.G;
  }

  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    return cayley_ ? EvaluateT<3>(parameters, residuals, jacobians)
                   : EvaluateT<4>(parameters, residuals, jacobians);
  }

 private:
  template <int kR>
  bool EvaluateT(double const* const* parameters, double* residuals, double** jacobians) const {
    constexpr int kN = kR + 3;
    using J = ceres::Jet<double, kN>;
    const bool need_rot = jacobians != nullptr && jacobians[0] != nullptr;
    const bool need_t = jacobians != nullptr && jacobians[1] != nullptr;
    const int n_rot = kR * kNumLegs;
    const int n_t = shared_ ? 3 : 18;
    using RowJ = Eigen::Matrix<double, 6, Eigen::Dynamic, Eigen::RowMajor>;
    if (need_rot) Eigen::Map<RowJ>(jacobians[0], 6, n_rot).setZero();
    if (need_t) Eigen::Map<RowJ>(jacobians[1], 6, n_t).setZero();
    Vec6 sum = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const double* rk = parameters[0] + kR * k;
      const double* tk = shared_ ? parameters[1] : parameters[1] + 3 * k;
      const LegTerms& l = terms_->leg[k];
      if (!need_rot && !need_t) {
        double c[6];
        LegContribution<kR>(l, rk, tk, shared_, leg_aware_, G_C_, c);
        for (int i = 0; i < 6; ++i) sum[i] += c[i];
        continue;
      }
      J r[kR], t[3], c[6];
      for (int i = 0; i < kR; ++i) r[i] = J(rk[i], i);
      for (int i = 0; i < 3; ++i) t[i] = J(tk[i], kR + i);
      LegContribution<kR>(l, r, t, shared_, leg_aware_, G_C_, c);
      Eigen::Matrix<double, 6, kN> d;
      for (int i = 0; i < 6; ++i) {
        sum[i] += c[i].a;
        d.row(i) = c[i].v.transpose();
      }
      const Eigen::Matrix<double, 6, kN> Md = M_ * d;
      if (need_rot) {
        Eigen::Map<RowJ>(jacobians[0], 6, n_rot).block<6, kR>(0, kR * k) =
            Md.template leftCols<kR>();
      }
      if (need_t) {
        Eigen::Map<RowJ> Jt(jacobians[1], 6, n_t);
        if (shared_) {
          Jt.block<6, 3>(0, 0) += Md.template rightCols<3>();
        } else {
          Jt.block<6, 3>(0, 3 * k) = Md.template rightCols<3>();
        }
      }
    }
    Eigen::Map<Vec6> res(residuals);
    res = M_ * sum;
    res[2] -= sqrt_k_[2] * G_;
    return true;
  }

  const PoseTerms* terms_;
  bool shared_, cayley_, leg_aware_;
  double G_;
  Mat6 M_;
  Vec6 sqrt_k_;
  Vec3 G_C_;
};

// One hanging gravity direction (ftcal's extension): r = w (R~_k u_B - v_C), w = pose residual
// sigma / sigma_rad. The component along v_C is second order; the two across it carry the
// observation.
struct GravityPriorResidual {
  GravityPriorResidual(const HangingGravityObservation& o, double weight)
      : leg(o.leg), u(o.u_B), v(o.v_C), w(weight) {}
  template <typename T>
  bool operator()(const T* quats, T* r) const {
    const Eigen::Map<const Eigen::Quaternion<T>> q(quats + 4 * leg);
    const Eigen::Matrix<T, 3, 1> d = q * u.cast<T>() - v.cast<T>();
    for (int i = 0; i < 3; ++i) r[i] = T(w) * d[i];
    return true;
  }
  int leg;
  Vec3 u, v;
  double w;
};

// Observations without a measurable spread (noise-free data) get this floor, not infinity.
constexpr double kMinPriorSigmaRad = 1e-9;

ceres::CostFunction* MakeCost(int trans_size, bool cayley, const PoseTerms* terms,
                              const Prepared& prep) {
  return new PoseCost(terms, prep, trans_size == 3, cayley);
}

bool HasRotations(StandingModel m) {
  return m == StandingModel::kFull || m == StandingModel::kRotationsOneTranslation;
}
bool SharedTranslation(StandingModel m) {
  return m == StandingModel::kRotationsOneTranslation || m == StandingModel::kOneTranslation;
}
int TransSize(StandingModel m) { return SharedTranslation(m) ? 3 : 18; }

// Ceres's EigenQuaternionManifold moves q by q_delta = [cos|d|, sin|d| d/|d|] (x) q, so its
// tangent d is half the (left) rotation vector.
constexpr double kQuaternionTangentToRotationVector = 2.0;

using SixQuaternions =
    ceres::ProductManifold<ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold,
                           ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold,
                           ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold>;

// Parameter storage for one problem.
struct Params {
  std::array<double, 24> quat{};  // (x, y, z, w) per leg
  std::array<double, 18> cayley{};
  std::array<double, 18> trans{};  // first 3 used when shared
  Params() {
    for (int k = 0; k < kNumLegs; ++k) quat[4 * k + 3] = 1.0;
  }
};

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

std::unique_ptr<ceres::LossFunction> MakeLoss(const StandingOptions& o) {
  switch (o.robust_loss) {
    case StandingLoss::kHuber:
      return std::make_unique<ceres::HuberLoss>(o.robust_loss_scale);
    case StandingLoss::kCauchy:
      return std::make_unique<ceres::CauchyLoss>(o.robust_loss_scale);
    case StandingLoss::kNone:
      break;
  }
  return nullptr;
}

// A Ceres problem over a subset of poses.
struct Built {
  std::unique_ptr<ceres::LossFunction> loss;
  std::unique_ptr<ceres::Problem> problem;
  double* rot = nullptr;
  double* trans = nullptr;
  std::vector<double*> free_blocks;
};

Built Build(const Prepared& prep, const std::vector<int>& pose_ids, StandingModel model,
            bool cayley, bool rotations_free, bool translations_free, Params* params,
            const StandingOptions& options, bool use_loss) {
  Built b;
  if (use_loss) b.loss = MakeLoss(options);
  ceres::Problem::Options po;
  po.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  b.problem = std::make_unique<ceres::Problem>(po);
  b.rot = cayley ? params->cayley.data() : params->quat.data();
  b.trans = params->trans.data();
  const int n_trans = TransSize(model);
  for (int id : pose_ids) {
    b.problem->AddResidualBlock(MakeCost(n_trans, cayley, &prep.poses[id], prep), b.loss.get(),
                                b.rot, b.trans);
  }
  if (!cayley && HasRotations(model) && prep.prior_scale > 0.0) {
    for (const HangingGravityObservation& o : prep.gravity_prior) {
      const double w = prep.prior_scale / std::max(o.sigma_rad, kMinPriorSigmaRad);
      b.problem->AddResidualBlock(new ceres::AutoDiffCostFunction<GravityPriorResidual, 3, 24>(
                                      new GravityPriorResidual(o, w)),
                                  nullptr, b.rot);
    }
  }
  if (!cayley) b.problem->SetManifold(b.rot, new SixQuaternions());
  if (rotations_free && HasRotations(model)) {
    b.free_blocks.push_back(b.rot);
  } else {
    b.problem->SetParameterBlockConstant(b.rot);
  }
  if (translations_free) {
    b.free_blocks.push_back(b.trans);
  } else {
    b.problem->SetParameterBlockConstant(b.trans);
  }
  return b;
}

Eigen::MatrixXd DenseJacobian(ceres::Problem* problem, const std::vector<double*>& blocks) {
  ceres::Problem::EvaluateOptions eo;
  eo.parameter_blocks = blocks;
  eo.apply_loss_function = true;
  ceres::CRSMatrix crs;
  problem->Evaluate(eo, nullptr, nullptr, nullptr, &crs);
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int i = crs.rows[r]; i < crs.rows[r + 1]; ++i) J(r, crs.cols[i]) = crs.values[i];
  }
  return J;
}

// Refuses a model whose parameters the poses do not determine: SVD of the column-normalised
// Jacobian; a singular value below 1e-8 of the largest marks a null direction, and the
// parameters carrying it are named.
void CheckIdentifiable(ceres::Problem* problem, const std::vector<double*>& blocks,
                       StandingModel model, size_t n_poses) {
  Eigen::MatrixXd J = DenseJacobian(problem, blocks);
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
  // JacobiSVD (QR-preconditioned), not BDCSVD: Eigen 3.4.0's BDCSVD proved inaccurate on tall
  // matrices (see offset_reestimation.cc).
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(J, Eigen::ComputeThinV);
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

StandingFit FitFromParams(StandingModel model, const Params& p, bool cayley) {
  StandingFit fit;
  fit.model = model;
  fit.dof = StandingModelDof(model);
  for (int k = 0; k < kNumLegs; ++k) {
    if (!HasRotations(model)) {
      fit.R_tilde[k] = Mat3::Identity();
    } else if (cayley) {
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
  Built b = Build(prep, ids, fit->model, false, true, true, &params, options, true);
  ceres::Problem::EvaluateOptions eo;
  eo.parameter_blocks = b.free_blocks;
  eo.apply_loss_function = true;
  std::vector<double> res;
  ceres::CRSMatrix crs;
  b.problem->Evaluate(eo, nullptr, &res, nullptr, &crs);
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int i = crs.rows[r]; i < crs.rows[r + 1]; ++i) J(r, crs.cols[i]) = crs.values[i];
  }
  // Pose residual blocks come first (Build adds them before the prior's), six rows each.
  const int pose_rows = 6 * static_cast<int>(ids.size());
  const double P = static_cast<double>(ids.size());
  const double dof_per_row = static_cast<double>(fit->dof) / 6.0;
  Vec6 s2c = Vec6::Zero();
  for (int r = 0; r < pose_rows; ++r) s2c[r % 6] += res[r] * res[r];
  s2c /= std::max(1.0, P - dof_per_row);
  const Eigen::MatrixXd H = J.transpose() * J;
  Eigen::MatrixXd M = Eigen::MatrixXd::Zero(H.rows(), H.cols());
  for (int r = 0; r < J.rows(); ++r) {
    const double s2 = r < pose_rows ? s2c[r % 6] : fit->residual_variance;
    M.noalias() += s2 * J.row(r).transpose() * J.row(r);
  }
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

std::vector<Vec6> ResidualsOfPoses(const Prepared& prep, const StandingFit& fit,
                                   const std::vector<int>& ids) {
  // The same residual the solver minimises (un-weighted by sqrt(K) below).
  Params p = ParamsFromFit(fit);
  std::vector<Vec6> out;
  out.reserve(ids.size());
  const bool shared = SharedTranslation(fit.model);
  for (int id : ids) {
    double r[6];
    const PoseCost cost(&prep.poses[id], prep, shared, false);
    const double* blocks[2] = {p.quat.data(), p.trans.data()};
    cost.Evaluate(blocks, r, nullptr);
    Vec6 v;
    for (int i = 0; i < 6; ++i) v[i] = r[i] / prep.sqrt_k[i];
    out.push_back(v);
  }
  return out;
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

// Relative cost change at which a joint solve stops: to convergence for the calibration (noise-
// free data are recovered to 1e-9 and better); looser for the cross-validation folds, whose
// test MSE does not move in the digits reported at 1e-8.
constexpr double kFullDataTolerance = 1e-12;
constexpr double kCrossValidationTolerance = 1e-8;

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

StandingFit JointOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                       const StandingOptions& options, const StandingFit* start, bool check_rank,
                       double function_tolerance) {
  Params params;
  if (start != nullptr) {
    StandingFit s = *start;
    s.model = model;
    params = ParamsFromFit(s);
  }
  Built b = Build(prep, ids, model, false, true, true, &params, options, true);
  if (check_rank) CheckIdentifiable(b.problem.get(), b.free_blocks, model, ids.size());
  ceres::Solver::Summary summary;
  ceres::Solve(SolverOptions(options.max_iterations, function_tolerance), b.problem.get(),
               &summary);
  if (!summary.IsSolutionUsable()) {
    throw std::runtime_error("standing step: Ceres failed for model " +
                             std::string(StandingModelName(model)) + ": " + summary.message);
  }
  StandingFit fit = FitFromParams(model, params, false);
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

}  // namespace

namespace {
// PoseCost with its own copy of the precomputed pose terms.
class OwningPoseCost final : public ceres::CostFunction {
 public:
  OwningPoseCost(Prepared prep, bool shared, bool cayley)
      : prep_(std::move(prep)), cost_(&prep_.poses[0], prep_, shared, cayley) {
    set_num_residuals(cost_.num_residuals());
    *mutable_parameter_block_sizes() = cost_.parameter_block_sizes();
  }
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    return cost_.Evaluate(parameters, residuals, jacobians);
  }

 private:
  Prepared prep_;
  PoseCost cost_;
};
}  // namespace

std::unique_ptr<ceres::CostFunction> StandingPoseCostForCheck(const RobotCalibration& step1,
                                                              const StandingPose& pose,
                                                              StandingModel model, bool cayley,
                                                              const StandingOptions& options) {
  return std::make_unique<OwningPoseCost>(Prepare(step1, {pose}, options), SharedTranslation(model),
                                          cayley);
}

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

StandingFit FitStandingJoint(const RobotCalibration& step1, const std::vector<StandingPose>& poses,
                             StandingModel model, const StandingOptions& options,
                             const StandingFit* start, bool compute_covariance) {
  ValidateOptions(options);
  CheckPoseCount(poses.size(), model, options);
  Prepared prep = Prepare(step1, poses, options);
  const std::vector<int> ids = AllIds(poses.size());
  StandingFit fit = JointOnIds(prep, ids, model, options, start, true, kFullDataTolerance);
  if (HasRotations(model) && !prep.gravity_prior.empty()) {
    // The poses alone first, for the residual sigma that weights the hanging directions; then
    // both, from there. The pose-only rank check above stands: the prior only adds rank.
    prep.prior_scale = std::sqrt(fit.residual_variance);
    if (prep.prior_scale > 0.0) {
      const StandingFit poses_only = fit;
      fit = JointOnIds(prep, ids, model, options, &poses_only, false, kFullDataTolerance);
    }
  }
  if (compute_covariance) AddCovariance(prep, ids, &fit, options);
  return fit;
}

namespace {
// The report's alternating scheme on a subset of poses (FitStandingAlternating's description).
StandingFit AlternatingOnIds(const Prepared& prep, const std::vector<int>& ids, StandingModel model,
                             const StandingOptions& options, bool check_rank) {
  const int n_trans = TransSize(model);
  Params params;  // Cayley q = 0 (R~ = I), translations 0
  if (check_rank) {
    Built b = Build(prep, ids, model, true, true, true, &params, options, false);
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
      std::unique_ptr<ceres::CostFunction> cost(MakeCost(n_trans, true, &prep.poses[id], prep));
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

  int sweeps = 0;
  bool converged = false;
  double initial_cost = -1.0, last_cost = 0.0;
  while (sweeps < options.alternating_max_sweeps) {
    const Params before = params;
    solve_translations();
    if (HasRotations(model)) {
      Built b = Build(prep, ids, model, true, true, false, &params, options, true);
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
  StandingFit fit = FitFromParams(model, params, true);
  fit.leg_aware_com = prep.leg_aware;
  fit.solver = "alternating";
  fit.iterations = sweeps;
  fit.converged = converged;
  FinishFit(prep, ids, &fit);
  fit.initial_cost = initial_cost < 0 ? 0.5 * fit.rss : initial_cost;
  fit.final_cost = HasRotations(model) ? last_cost : 0.5 * fit.rss;
  return fit;
}
}  // namespace

StandingFit FitStandingAlternating(const RobotCalibration& step1,
                                   const std::vector<StandingPose>& poses, StandingModel model,
                                   const StandingOptions& options, bool compute_covariance) {
  ValidateOptions(options);
  CheckPoseCount(poses.size(), model, options);
  const Prepared prep = Prepare(step1, poses, options);
  const std::vector<int> ids = AllIds(poses.size());
  StandingFit fit = AlternatingOnIds(prep, ids, model, options, true);
  if (compute_covariance) AddCovariance(prep, ids, &fit, options);
  return fit;
}

std::vector<Vec6> TotalWrenchResiduals(const RobotCalibration& cal,
                                       const std::vector<StandingPose>& poses, bool leg_aware_com) {
  const double G = cal.TotalWeightN();
  std::vector<Vec6> out;
  out.reserve(poses.size());
  for (size_t p = 0; p < poses.size(); ++p) {
    const StandingPose& pose = poses[p];
    const Mat3 R_WC = ValidatedAttitude(pose.R_WC, p);
    Vec6 total = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      total += GroundWrenchW(cal, k, pose.wrench[k], pose.angle_rad[k], R_WC);
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
    const StandingFit fit = options.solver == StandingSolver::kAlternating
                                ? AlternatingOnIds(prep, train, full_data_fit.model, options, false)
                                : JointOnIds(prep, train, full_data_fit.model, options,
                                             &full_data_fit, false, kCrossValidationTolerance);
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
  // The four models (each a joint fit plus its 5-fold cross-validation) are independent Ceres
  // problems on const inputs, so they run on their own threads: on a two-core machine this
  // nearly halves step 2's wall time. Results are gathered in model order, so the outcome does
  // not depend on scheduling; an exception in any model is rethrown here by future::get().
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
  std::vector<std::future<ModelRun>> runs;
  for (const bool aware : targets) {
    for (StandingModel model : kStandingModels) {
      StandingOptions o = options;
      o.leg_aware_com = aware;
      runs.push_back(std::async(std::launch::async, [&step1, &poses, o, model, alternating] {
        ModelRun run;
        run.fit = alternating ? FitStandingAlternating(step1, poses, model, o)
                              : FitStandingJoint(step1, poses, model, o);
        run.cv_mse = CrossValidationMse(step1, poses, run.fit, o);
        return run;
      }));
    }
  }
  std::vector<ModelRun> done;
  std::exception_ptr first_error;
  for (auto& r : runs) {  // every future is waited for before anything is rethrown
    try {
      done.push_back(r.get());
    } catch (...) {
      if (!first_error) first_error = std::current_exception();
    }
  }
  if (first_error) std::rethrow_exception(first_error);
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
