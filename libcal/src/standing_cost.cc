// Step 2's cost, in the one translation unit that instantiates Ceres templates (they compile
// slowly, so no other file of step 2 includes the autodiff headers): the terms of each pose
// precomputed from step 1 (Prepare), eq. 9 per leg (LegContribution, on quaternions or Cayley
// vectors), eq. 8 per pose (PoseCost, with its Jacobian), the hanging gravity prior, and the
// problem builder every solve uses (Build).
#include "ftcal/standing.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>

#include <ceres/ceres.h>
#include <ceres/manifold.h>
#include <ceres/product_manifold.h>

#include "standing_internal.h"

#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
#define FTCAL_FLATTEN
#else
#define FTCAL_FLATTEN [[gnu::flatten]]
#endif

namespace ftcal {
namespace standing_detail {
namespace {

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

}  // namespace

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

namespace {

// Cayley map in closed form, R = ((1 - q.q) I + 2 q q^T - 2 [q]) / (1 + q.q), equal to
// (I - [q])(I + [q])^-1 (geometry.h) and differentiable by Jets without a matrix inverse.
// CayleyToRotation (geometry.cc) is not this template at T = double: it inverts (I + [q]), and
// the two differ in the last bit for most q (up to 6e-16 measured), so one version for both
// would change either the alternating fit's R~ or the solver's derivatives (issue 15, item 5).
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
  PoseCost(const PoseTerms* terms, const Prepared& prep, StandingModel model,
           RotationParams rotations)
      : terms_(terms),
        shared_(SharedTranslation(model)),
        cayley_(rotations == RotationParams::kCayley),
        leg_aware_(prep.leg_aware),
        G_(prep.G) {
    set_num_residuals(6);
    mutable_parameter_block_sizes()->push_back(cayley_ ? 18 : 24);
    mutable_parameter_block_sizes()->push_back(shared_ ? 3 : 18);
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
  // Flattened: GCC 12 at -O3 left the Jet's Eigen arithmetic as out-of-line calls (half of
  // step 2's time in perf); inlined here it is the same arithmetic, in half the time. Not under
  // the sanitizers: their instrumentation of the flattened function kept GCC compiling this
  // file for over 25 minutes.
  template <int kR>
  FTCAL_FLATTEN bool EvaluateT(double const* const* parameters, double* residuals,
                               double** jacobians) const {
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

using SixQuaternions =
    ceres::ProductManifold<ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold,
                           ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold,
                           ceres::EigenQuaternionManifold, ceres::EigenQuaternionManifold>;

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

// PoseCost with its own copy of the precomputed pose terms.
class OwningPoseCost final : public ceres::CostFunction {
 public:
  OwningPoseCost(Prepared prep, StandingModel model, RotationParams rotations)
      : prep_(std::move(prep)), cost_(&prep_.poses[0], prep_, model, rotations) {
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

ceres::CostFunction* MakeCost(StandingModel model, RotationParams rotations, const PoseTerms* terms,
                              const Prepared& prep) {
  return new PoseCost(terms, prep, model, rotations);
}

Built Build(const Prepared& prep, const std::vector<int>& pose_ids, StandingModel model,
            const BuildOptions& build, Params* params, const StandingOptions& options) {
  const bool cayley = build.rotations == RotationParams::kCayley;
  Built b;
  if (build.use_loss) b.loss = MakeLoss(options);
  ceres::Problem::Options po;
  po.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  b.problem = std::make_unique<ceres::Problem>(po);
  b.rot = cayley ? params->cayley.data() : params->quat.data();
  b.trans = params->trans.data();
  for (int id : pose_ids) {
    b.problem->AddResidualBlock(MakeCost(model, build.rotations, &prep.poses[id], prep),
                                b.loss.get(), b.rot, b.trans);
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
  if (build.rotations_free && HasRotations(model)) {
    b.free_blocks.push_back(b.rot);
  } else {
    b.problem->SetParameterBlockConstant(b.rot);
  }
  if (build.translations_free) {
    b.free_blocks.push_back(b.trans);
  } else {
    b.problem->SetParameterBlockConstant(b.trans);
  }
  return b;
}

std::vector<Vec6> ResidualsOfPoses(const Prepared& prep, const StandingFit& fit,
                                   const std::vector<int>& ids) {
  // The same residual the solver minimises (un-weighted by sqrt(K) below).
  Params p = ParamsFromFit(fit);
  std::vector<Vec6> out;
  out.reserve(ids.size());
  for (int id : ids) {
    double r[6];
    const PoseCost cost(&prep.poses[id], prep, fit.model, RotationParams::kQuaternion);
    const double* blocks[2] = {p.quat.data(), p.trans.data()};
    cost.Evaluate(blocks, r, nullptr);
    Vec6 v;
    for (int i = 0; i < 6; ++i) v[i] = r[i] / prep.sqrt_k[i];
    out.push_back(v);
  }
  return out;
}

}  // namespace standing_detail

using standing_detail::OwningPoseCost;
using standing_detail::Prepare;

std::unique_ptr<ceres::CostFunction> StandingPoseCostForCheck(const RobotCalibration& step1,
                                                              const StandingPose& pose,
                                                              StandingModel model,
                                                              RotationParams rotations,
                                                              const StandingOptions& options) {
  return std::make_unique<OwningPoseCost>(Prepare(step1, {pose}, options), model, rotations);
}

}  // namespace ftcal
