// A plan's sigma from the information matrix (plan_prediction.h states the model). Step 1's
// per-sample model is the one Ceres template of this unit (HangBinResidual); step 2 reuses the
// calibrator's own problem (standing_detail::Build, PoseCost) and Jacobian (DenseJacobian).
#include "ftcal/plan_prediction.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <memory>
#include <stdexcept>
#include <string>

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <Eigen/Cholesky>

#include "hanging_internal.h"
#include "standing_internal.h"

namespace ftcal {
namespace {

constexpr double kRadToDeg = 180.0 / M_PI;
// The variance of a median of n Gaussian samples, over the sample variance / n.
constexpr double kMedianVarianceFactor = M_PI / 2.0;

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("plan prediction: " + what);
}

// ------------------------------------------------------------------ step 1

// Leg parameters of step 1 in one block: f_o (3), tau_o (3), m g, CoM (x a, c, d; y; z a, c, d).
constexpr int kLegBlock = 14;

// One phase bin of one hanging series of one leg: the reading the model predicts, weighted by
// sqrt(samples in the bin) / sigma so that J^T J is the information of every raw sample in it.
// s: the series' misalignment (rotation vector), exact rotation as step 1 uses by default.
struct HangBinResidual {
  Vec3 d;  // stated gravity in ft_k, unit
  double phase;
  double w_force, w_torque;
  template <typename T>
  bool operator()(const T* leg, const T* s, T* r) const {
    const T dd[3] = {T(d.x()), T(d.y()), T(d.z())};
    T rd[3];
    ceres::AngleAxisRotatePoint(s, dd, rd);
    const T mg = leg[6];
    const T g[3] = {mg * rd[0], mg * rd[1], mg * rd[2]};
    const double a = 2.0 * M_PI * phase;
    const T com[3] = {leg[7] * sin(T(a) + leg[8]) + leg[9], leg[10],
                      leg[11] * sin(T(a) + leg[12]) + leg[13]};
    T tau[3];
    ceres::CrossProduct(com, g, tau);
    for (int i = 0; i < 3; ++i) {
      r[i] = T(w_force) * (g[i] + leg[i]);
      r[3 + i] = T(w_torque) * (tau[i] + leg[3 + i]);
    }
    return true;
  }
};

Eigen::MatrixXd DenseOf(const ceres::CRSMatrix& crs) {
  Eigen::MatrixXd J = Eigen::MatrixXd::Zero(crs.num_rows, crs.num_cols);
  for (int r = 0; r < crs.num_rows; ++r) {
    for (int i = crs.rows[r]; i < crs.rows[r + 1]; ++i) J(r, crs.cols[i]) = crs.values[i];
  }
  return J;
}

Eigen::MatrixXd Inverse(const Eigen::MatrixXd& A, const std::string& what) {
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(A);
  const Eigen::VectorXd d = ldlt.vectorD();
  Require(ldlt.info() == Eigen::Success && d.minCoeff() > 1e-14 * std::max(1.0, d.maxCoeff()),
          what + ": the information matrix is singular (the plan does not determine it)");
  return ldlt.solve(Eigen::MatrixXd::Identity(A.rows(), A.cols()));
}

// Step 1 of one leg: the covariance of its 14 leg parameters.
Eigen::MatrixXd HangingLegCovariance(const RobotCalibration& nominal, int k,
                                     const std::vector<PlannedHangSeries>& series, int bins,
                                     const DeviceNoise& noise) {
  const LegCalibration& l = nominal.leg[k];
  const LegComModel& c = l.com;
  std::array<double, kLegBlock> leg = {
      l.offset[0], l.offset[1], l.offset[2], l.offset[3], l.offset[4], l.offset[5], l.weight_n,
      c.x.a,       c.x.c,       c.x.d,       c.y,         c.z.a,       c.z.c,       c.z.d};
  std::vector<std::array<double, 3>> s(series.size(), std::array<double, 3>{0.0, 0.0, 0.0});
  ceres::Problem problem;
  problem.AddParameterBlock(leg.data(), kLegBlock);
  std::vector<double*> blocks = {leg.data()};
  for (size_t i = 0; i < series.size(); ++i) {
    const PlannedHangSeries& ps = series[i];
    const Vec3 d = (nominal.X_B_ft[k].R.transpose() * ps.gravity_b).normalized();
    const int axis = std::abs(d.x()) >= std::abs(d.z()) ? 0 : 2;
    const double per_bin = ps.cycles * ps.samples_per_cycle / bins;
    for (int b = 0; b < bins; ++b) {
      auto* f = new HangBinResidual{d, (b + 0.5) / bins, std::sqrt(per_bin) / noise.force_n,
                                    std::sqrt(per_bin) / noise.torque_nm};
      problem.AddResidualBlock(new ceres::AutoDiffCostFunction<HangBinResidual, 6, kLegBlock, 3>(f),
                               nullptr, leg.data(), s[i].data());
    }
    // Step 1 holds the component about the gravity axis at 0: it is not observable.
    problem.SetManifold(s[i].data(), new ceres::SubsetManifold(3, {axis}));
    blocks.push_back(s[i].data());
  }
  ceres::Problem::EvaluateOptions eo;
  eo.parameter_blocks = blocks;
  ceres::CRSMatrix crs;
  problem.Evaluate(eo, nullptr, nullptr, nullptr, &crs);
  const Eigen::MatrixXd J = DenseOf(crs);
  const Eigen::MatrixXd C =
      Inverse(J.transpose() * J, "hanging series of leg " + std::string(kLegNames[k]));
  return C.topLeftCorner(kLegBlock, kLegBlock);
}

void AddHanging(const RobotCalibration& nominal, const PlanDesign& design, int bins,
                const DeviceNoise& noise, PlanPrediction* out,
                std::array<double, kNumLegs>* force_offset_sigma,
                std::array<Eigen::MatrixXd, kNumLegs>* leg_covariance) {
  const char* axes[3] = {"x", "y", "z"};
  const char* com_names[7] = {"CoM x a", "CoM x c", "CoM x d", "CoM y",
                              "CoM z a", "CoM z c", "CoM z d"};
  // Step 1 reports the spread of its per-cycle estimates, widened for their few cycles
  // (StudentWidening): what it would report is the bound so widened.
  int cycles = 0;
  for (const PlannedHangSeries& s : design.hanging)
    cycles = cycles == 0 ? s.cycles : std::min(cycles, s.cycles);
  const double widen = cycles >= 2 ? hanging_detail::StudentWidening(cycles) : 1.0;
  for (int k = 0; k < kNumLegs; ++k) {
    const Eigen::MatrixXd C = HangingLegCovariance(nominal, k, design.hanging, bins, noise);
    (*leg_covariance)[k] = C;
    const std::string leg = std::string(kLegNames[k]) + " ";
    double fo = 0.0;
    for (int i = 0; i < kLegBlock; ++i) {
      PredictedSigma p;
      p.sigma = p.bound = p.with_step1 = std::sqrt(std::max(0.0, C(i, i)));
      p.reported = widen * p.sigma;
      if (i < 3) {
        p.name = leg + "f_o " + axes[i];
        p.klass = "force offset";
        fo += C(i, i);  // the gravity prior weighs by the spread, unwidened (hanging.cc)
      } else if (i < 6) {
        p.name = leg + "tau_o " + axes[i - 3];
        p.klass = "torque offset";
      } else if (i == 6) {
        p.name = leg + "m g";
        p.klass = "leg weight";
      } else {
        p.name = leg + com_names[i - 7];
        p.klass = (i == 8 || i == 12) ? "leg CoM phase" : "leg CoM";
      }
      out->parameters.push_back(p);
    }
    (*force_offset_sigma)[k] = std::sqrt(fo / 3.0);
  }
}

// ------------------------------------------------------------------ step 2

// The K-weighted residual of pose p alone, at the nominal fit.
Vec6 PoseResidual(const RobotCalibration& nominal, const StandingPose& pose,
                  const StandingOptions& options, const StandingFit& fit) {
  StandingOptions o = options;
  o.gravity_prior.clear();
  const standing_detail::Prepared prep = standing_detail::Prepare(nominal, {pose}, o);
  return standing_detail::ResidualsOfPoses(prep, fit, {0})[0].cwiseProduct(prep.sqrt_k);
}

// The 6 x 6 covariance of pose p's weighted residual from its measurements' noise: the
// residual's derivative by each measured quantity (by differences: it is linear in the
// readings, smooth in the attitude and angles) times that quantity's variance as a median.
Mat6 PoseResidualCovariance(const RobotCalibration& nominal, const PlannedPose& pp,
                            const DeviceNoise& noise, const StandingOptions& options,
                            const StandingFit& fit) {
  const double n = pp.samples;
  const Vec6 r0 = PoseResidual(nominal, pp.pose, options, fit);
  Mat6 S = Mat6::Zero();
  auto add = [&](const Vec6& column, double sigma) {
    S += column * column.transpose() * (kMedianVarianceFactor * sigma * sigma / n);
  };
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      const double h = 1e-3;
      StandingPose q = pp.pose;
      q.wrench[k][i] += h;
      add((PoseResidual(nominal, q, options, fit) - r0) / h,
          i < 3 ? noise.force_n : noise.torque_nm);
    }
    if (noise.shaft_angle_rad > 0.0) {
      const double h = 1e-6;
      StandingPose a = pp.pose, b = pp.pose;
      a.angle_rad[k] += h;
      b.angle_rad[k] -= h;
      add((PoseResidual(nominal, a, options, fit) - PoseResidual(nominal, b, options, fit)) /
              (2 * h),
          noise.shaft_angle_rad);
    }
  }
  // Motion capture's noise turns R_WC about C's own axes (R_WC Exp(e)).
  for (int i = 0; i < 3; ++i) {
    const double h = 1e-6;
    StandingPose a = pp.pose, b = pp.pose;
    a.R_WC = pp.pose.R_WC * ExpSO3(h * Vec3::Unit(i));
    b.R_WC = pp.pose.R_WC * ExpSO3(-h * Vec3::Unit(i));
    add((PoseResidual(nominal, a, options, fit) - PoseResidual(nominal, b, options, fit)) / (2 * h),
        noise.attitude_rad);
  }
  return S;
}

// Step 1's leg parameter i (HangingLegCovariance's order) of leg k, for perturbing it.
double& LegParameter(RobotCalibration* cal, int k, int i) {
  LegCalibration& l = cal->leg[k];
  if (i < 6) return l.offset[i];
  double* com[7] = {&l.com.x.a, &l.com.x.c, &l.com.x.d, &l.com.y,
                    &l.com.z.a, &l.com.z.c, &l.com.z.d};
  return i == 6 ? l.weight_n : *com[i - 7];
}

// The K-weighted residuals of every pose, stacked, at `fit` with step 1 as in `step1`.
Eigen::VectorXd StackedResiduals(const RobotCalibration& step1,
                                 const std::vector<StandingPose>& poses, StandingOptions options,
                                 const StandingFit& fit) {
  options.gravity_prior.clear();
  const standing_detail::Prepared prep = standing_detail::Prepare(step1, poses, options);
  const std::vector<Vec6> r =
      standing_detail::ResidualsOfPoses(prep, fit, standing_detail::AllIds(poses.size()));
  Eigen::VectorXd out(6 * r.size());
  for (size_t p = 0; p < r.size(); ++p) out.segment<6>(6 * p) = r[p].cwiseProduct(prep.sqrt_k);
  return out;
}

// The gravity directions the hanging series would give each leg, with the sigma they would
// carry (hanging.cc GravityObservation: the mean force direction and the mean attitude over the
// series, and the force offset's sigma over |f|).
std::vector<HangingGravityObservation> PredictedGravityPrior(
    const RobotCalibration& nominal, const PlanDesign& design, const DeviceNoise& noise,
    const std::array<double, kNumLegs>& force_offset_sigma) {
  std::vector<HangingGravityObservation> out;
  for (const PlannedHangSeries& s : design.hanging) {
    const double n = s.cycles * s.samples_per_cycle;
    for (int k = 0; k < kNumLegs; ++k) {
      HangingGravityObservation o;
      o.leg = k;
      o.series = s.series;
      o.u_B = s.gravity_b.normalized();
      o.v_C = o.u_B;
      const double mg = nominal.leg[k].weight_n;
      const double su = noise.force_n / mg / std::sqrt(n);
      const double sv = noise.attitude_rad / std::sqrt(n);
      const double so = force_offset_sigma[k] / mg;
      o.sigma_rad = std::sqrt(su * su + sv * sv + so * so);
      out.push_back(o);
    }
  }
  return out;
}

void AddStanding(const RobotCalibration& nominal, const PlanDesign& design,
                 const DeviceNoise& noise, const StandingOptions& options_in,
                 const std::array<double, kNumLegs>& force_offset_sigma,
                 const std::array<Eigen::MatrixXd, kNumLegs>* leg_covariance, PlanPrediction* out) {
  using namespace standing_detail;  // NOLINT
  StandingOptions options = options_in;
  options.leg_aware_com = design.leg_aware_com;
  options.robust_loss = StandingLoss::kNone;
  options.gravity_prior.clear();
  if (design.gravity_prior && !design.hanging.empty())
    options.gravity_prior = PredictedGravityPrior(nominal, design, noise, force_offset_sigma);
  std::vector<StandingPose> poses;
  for (size_t p = 0; p < design.poses.size(); ++p) {
    Require(design.poses[p].samples >= 1.0,
            "standing pose " + std::to_string(p) + " has no steady samples (dwell too short)");
    poses.push_back(design.poses[p].pose);
  }
  Require(static_cast<int>(6 * poses.size()) > StandingModelDof(StandingModel::kFull),
          std::to_string(poses.size()) + " standing poses cannot determine the 36 parameters");
  StandingFit fit;
  fit.model = StandingModel::kFull;
  fit.dof = StandingModelDof(fit.model);
  for (int k = 0; k < kNumLegs; ++k) {
    fit.R_tilde[k] = nominal.leg[k].R_tilde;
    fit.p_tilde_prime[k] = nominal.leg[k].p_tilde_prime;
  }
  std::vector<Mat6> S(poses.size());
  double mean_trace = 0.0;
  for (size_t p = 0; p < poses.size(); ++p) {
    S[p] = PoseResidualCovariance(nominal, design.poses[p], noise, options, fit);
    mean_trace += S[p].trace() / 6.0;
  }
  mean_trace /= static_cast<double>(poses.size());
  Prepared prep = Prepare(nominal, poses, options);
  prep.prior_scale = options.gravity_prior.empty() ? 0.0 : std::sqrt(mean_trace);
  Params params = ParamsFromFit(fit);
  BuildOptions bo;
  bo.use_loss = false;
  Built b = Build(prep, AllIds(poses.size()), fit.model, bo, &params, options);
  const Eigen::MatrixXd J = DenseJacobian(b.problem.get(), b.free_blocks, nullptr);
  const int pose_rows = 6 * static_cast<int>(poses.size());
  const int n = static_cast<int>(J.cols());
  Eigen::MatrixXd M = Eigen::MatrixXd::Zero(n, n), Info = M;
  Vec6 s2c = Vec6::Zero();
  for (const Mat6& s : S) s2c += s.diagonal();
  s2c /= static_cast<double>(poses.size());
  out->residual_rms = s2c.cwiseSqrt().cwiseQuotient(prep.sqrt_k);
  Eigen::MatrixXd Mrep = M;
  for (size_t p = 0; p < poses.size(); ++p) {
    const auto Jp = J.middleRows(6 * static_cast<int>(p), 6);
    M += Jp.transpose() * S[p] * Jp;
    Mrep += Jp.transpose() * s2c.asDiagonal() * Jp;
    Info += Jp.transpose() * Inverse(S[p], "standing pose " + std::to_string(p)) * Jp;
  }
  const double prior_var = prep.prior_scale * prep.prior_scale;
  for (int r = pose_rows; r < J.rows(); ++r) {
    const auto Jr = J.row(r);
    M += prior_var * Jr.transpose() * Jr;
    Mrep += prior_var * Jr.transpose() * Jr;
    // The component along the direction carries no noise of its own; the two across do.
    Info += (2.0 / 3.0) / prior_var * Jr.transpose() * Jr;
  }
  const Eigen::MatrixXd Hinv = Inverse(J.transpose() * J, "standing poses");
  const Eigen::MatrixXd C = Hinv * M * Hinv;
  const Eigen::MatrixXd Crep = Hinv * Mrep * Hinv;
  const Eigen::MatrixXd Cb = Inverse(Info, "standing poses (information bound)");
  // Step 1's errors through step 2: d(theta2) = -H^-1 J^T (dr/d(theta1)) d(theta1); the
  // residuals are linear in the offsets and leg weights, smooth in the CoM curves.
  Eigen::MatrixXd C1 = C;
  if (leg_covariance != nullptr) {
    Eigen::MatrixXd D = Eigen::MatrixXd::Zero(pose_rows, kNumLegs * kLegBlock);
    for (int k = 0; k < kNumLegs; ++k) {
      for (int i = 0; i < kLegBlock; ++i) {
        const double h = 1e-6;
        RobotCalibration a = nominal, b = nominal;
        LegParameter(&a, k, i) += h;
        LegParameter(&b, k, i) -= h;
        D.col(kLegBlock * k + i) =
            (StackedResiduals(a, poses, options, fit) - StackedResiduals(b, poses, options, fit)) /
            (2 * h);
      }
    }
    const Eigen::MatrixXd A = Hinv * J.topRows(pose_rows).transpose() * D;
    Eigen::MatrixXd C1s = Eigen::MatrixXd::Zero(D.cols(), D.cols());
    for (int k = 0; k < kNumLegs; ++k)
      C1s.block(kLegBlock * k, kLegBlock * k, kLegBlock, kLegBlock) = (*leg_covariance)[k];
    C1 = C + A * C1s * A.transpose();
  }
  const char* axes[3] = {"x", "y", "z"};
  auto sd = [](const Eigen::MatrixXd& m, int j) { return std::sqrt(std::max(0.0, m(j, j))); };
  for (int j = 0; j < n; ++j) {
    PredictedSigma p;
    const int k = (j % 18) / 3, i = j % 3;
    const double scale = j < 18 ? kQuaternionTangentToRotationVector * kRadToDeg : 1.0;
    p.sigma = scale * sd(C, j);
    p.reported = scale * sd(Crep, j);
    p.bound = scale * sd(Cb, j);
    p.with_step1 = scale * sd(C1, j);
    if (j < 18) {
      p.name = std::string(kLegNames[k]) + " R~ " + axes[i];
      p.klass = i == 2 ? "rotation z" : "rotation x,y";
    } else {
      p.name = std::string(kLegNames[k]) + " p~' " + axes[i];
      p.klass = "p~'";
    }
    out->parameters.push_back(p);
  }
  Eigen::VectorXd a = Eigen::VectorXd::Zero(n);
  for (int k = 0; k < kNumLegs; ++k) a[18 + 3 * k + 2] = 1.0 / kNumLegs;
  out->common_p_z.name = "p~'_z common (mean of the six)";
  out->common_p_z.klass = "p~'_z common";
  out->common_p_z.sigma = std::sqrt(a.dot(C * a));
  out->common_p_z.reported = std::sqrt(a.dot(Crep * a));
  out->common_p_z.bound = std::sqrt(a.dot(Cb * a));
  out->common_p_z.with_step1 = std::sqrt(a.dot(C1 * a));
  out->standing_poses = static_cast<int>(poses.size());
}

}  // namespace

std::vector<ClassSummary> SummariseClasses(const std::vector<PredictedSigma>& parameters) {
  struct Unit {
    const char* klass;
    const char* unit;
    double scale;
  };
  const Unit units[] = {{"force offset", "N", 1.0},     {"torque offset", "mN m", 1e3},
                        {"leg weight", "N", 1.0},       {"leg CoM", "mm", 1e3},
                        {"leg CoM phase", "mrad", 1e3}, {"rotation x,y", "deg", 1.0},
                        {"rotation z", "deg", 1.0},     {"p~'", "mm", 1e3},
                        {"p~'_z common", "mm", 1e3}};
  std::vector<ClassSummary> out;
  for (const Unit& u : units) {
    std::vector<double> s, rep;
    ClassSummary c;
    c.klass = u.klass;
    c.unit = u.unit;
    c.scale = u.scale;
    for (const PredictedSigma& p : parameters) {
      if (p.klass != u.klass) continue;
      s.push_back(p.sigma);
      rep.push_back(p.reported);
      if (p.sigma >= c.worst_sigma) {
        c.worst_sigma = p.sigma;
        c.worst_reported = p.reported;
        c.worst_name = p.name;
      }
    }
    if (s.empty()) continue;
    auto median = [](std::vector<double> v) {
      std::sort(v.begin(), v.end());
      const size_t m = v.size() / 2;
      return v.size() % 2 ? v[m] : 0.5 * (v[m - 1] + v[m]);
    };
    c.median_sigma = median(s);
    c.median_reported = median(rep);
    out.push_back(c);
  }
  return out;
}

PlanPrediction PredictPlan(const RobotCalibration& nominal, const PlanDesign& design,
                           const DeviceNoise& noise, const HangingOptions& hanging_options,
                           const StandingOptions& standing_options) {
  for (double v : {noise.force_n, noise.torque_nm, noise.attitude_rad, noise.shaft_angle_rad})
    Require(std::isfinite(v) && v >= 0.0, "device noise must be finite and >= 0");
  Require(noise.force_n > 0.0 && noise.torque_nm > 0.0,
          "transducer noise must be > 0 (noise-free readings determine everything exactly)");
  Require(!design.hanging.empty() || !design.poses.empty(),
          "the plan has neither hanging series nor standing poses");
  for (const PlannedHangSeries& s : design.hanging) {
    Require(s.cycles >= 1 && s.samples_per_cycle >= 1.0,
            "hanging series " + HangSeriesName(s.series) + " has no full cycle of samples");
    Require(s.gravity_b.allFinite() && s.gravity_b.norm() > 0.5,
            "hanging series " + HangSeriesName(s.series) + " has no stated gravity direction");
  }
  PlanPrediction out;
  std::array<double, kNumLegs> force_offset_sigma{};
  std::array<Eigen::MatrixXd, kNumLegs> leg_covariance;
  if (!design.hanging.empty()) {
    Require(design.hanging.size() == kNumHangSeries,
            "step 1 needs all four hanging series, the plan has " +
                std::to_string(design.hanging.size()));
    AddHanging(nominal, design, std::max(8, hanging_options.phase_bins), noise, &out,
               &force_offset_sigma, &leg_covariance);
    for (const PlannedHangSeries& s : design.hanging)
      out.hanging_samples += s.cycles * s.samples_per_cycle;
  }
  if (!design.poses.empty())
    AddStanding(nominal, design, noise, standing_options, force_offset_sigma,
                design.hanging.empty() ? nullptr : &leg_covariance, &out);
  std::vector<PredictedSigma> all = out.parameters;
  if (!design.poses.empty()) all.push_back(out.common_p_z);
  out.classes = SummariseClasses(all);
  return out;
}

}  // namespace ftcal
