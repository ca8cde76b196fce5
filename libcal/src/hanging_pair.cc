// The pair equations of step 1 (eq. 4-7, docs/method.md "Step 1"): for the pair of series whose
// transducer axis a is along gravity, the half-differences and half-sums of the matched samples,
// s+ (closed form, then the report's objective refined with Ceres), m g, s- and the offsets
// f_o, tau_o, on all matched samples and on each full cycle for the sigmas, and the
// inverse-variance combination of the two pairs. hanging.cc's opening comment states the model.
#include <ceres/autodiff_first_order_function.h>
#include <ceres/gradient_problem.h>
#include <ceres/gradient_problem_solver.h>
#include <ceres/rotation.h>

#include <boost/math/distributions/normal.hpp>
#include <boost/math/distributions/students_t.hpp>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include <Eigen/Cholesky>

#include "hanging_internal.h"

namespace ftcal {
namespace hanging_detail {

Vec3 RotApply(const Vec3& s, const Vec3& v, bool exact) {
  return exact ? Vec3(ExpSO3(s) * v) : Vec3(v + s.cross(v));
}

namespace {

// R(s)^-1 v for the first-order (I + [s]) or exact (exp([s])) model.
Vec3 RotInverseApply(const Vec3& s, const Vec3& v, bool exact) {
  if (exact) return ExpSO3(s).transpose() * v;
  // (I + [s])^-1 = (I - [s] + s s^T) / (1 + |s|^2).
  return (v - s.cross(v) + s * s.dot(v)) / (1.0 + s.squaredNorm());
}

// Rotation vector of the smallest rotation taking unit a to unit u (axis orthogonal to a).
Vec3 MinimalRotation(const Vec3& a, const Vec3& u) {
  const Vec3 axis = a.cross(u);
  const double sin_angle = axis.norm();
  const double angle = std::atan2(sin_angle, a.dot(u));
  if (sin_angle < 1e-12) return axis;  // angle ~ sin_angle: first-order series
  return axis * (angle / sin_angle);
}

// The two ft axes across a (the report's e_j, j != axis).
void AcrossAxes(int axis_index, Vec3* b1, Vec3* b2) {
  if (axis_index == 0) {
    *b1 = Vec3::UnitY();
    *b2 = Vec3::UnitZ();
  } else {
    *b1 = Vec3::UnitX();
    *b2 = Vec3::UnitY();
  }
}

// ---------------------------------------------------------------- s+ (report's objective)

// The report's objective in the two components t of s+ across the axis (s+ = t1 b1 + t2 b2),
// templated for Ceres' automatic differentiation.
struct SPlusCost {
  const Vec3* f = nullptr;
  int n = 0;
  Vec3 axis, b1, b2;
  bool exact = false;

  // RotInverseApply at T = double, but not its arithmetic (a reciprocal instead of a division,
  // AngleAxisRotatePoint instead of ExpSO3): the results differ in the last bit, so sharing one
  // template would move m g, s- and the offsets, which RotInverseApply feeds (issue 15, item 5).
  template <typename T>
  void Corrected(const T* s, const Vec3& v, T* g) const {
    const T vv[3] = {T(v.x()), T(v.y()), T(v.z())};
    if (exact) {
      const T minus_s[3] = {-s[0], -s[1], -s[2]};
      ceres::AngleAxisRotatePoint(minus_s, vv, g);
      return;
    }
    // (I + [s])^-1 v = (v - s x v + s (s.v)) / (1 + |s|^2)
    T sxv[3];
    ceres::CrossProduct(s, vv, sxv);
    const T sv = ceres::DotProduct(s, vv);
    const T inv = T(1.0) / (T(1.0) + ceres::DotProduct(s, s));
    for (int k = 0; k < 3; ++k) g[k] = (vv[k] - sxv[k] + s[k] * sv) * inv;
  }

  template <typename T>
  bool operator()(const T* t, T* cost) const {
    T s[3];
    for (int k = 0; k < 3; ++k) s[k] = t[0] * b1[k] + t[1] * b2[k];
    T sum1(0.0), sum2(0.0), sum_a(0.0);
    T g[3];
    for (int i = 0; i < n; ++i) {
      Corrected(s, f[i], g);
      const T g1 = g[0] * b1.x() + g[1] * b1.y() + g[2] * b1.z();
      const T g2 = g[0] * b2.x() + g[1] * b2.y() + g[2] * b2.z();
      sum1 += g1 * g1;
      sum2 += g2 * g2;
      sum_a += g[0] * axis.x() + g[1] * axis.y() + g[2] * axis.z();
    }
    const T mean_a = sum_a / T(n);
    T var_a(0.0);
    for (int i = 0; i < n; ++i) {
      Corrected(s, f[i], g);
      const T d = g[0] * axis.x() + g[1] * axis.y() + g[2] * axis.z() - mean_a;
      var_a += d * d;
    }
    using std::sqrt;
    *cost = sqrt(sum1 / T(n)) + sqrt(sum2 / T(n)) + sqrt(var_a / T(n));
    return true;
  }
};

// Refines the closed-form s+ on the report's objective. The objective is a sum of norms, not a
// sum of squares, so it is a general smooth minimisation (Ceres' GradientProblemSolver), except
// where an rms is zero (noise-free data): there the closed form is already the minimiser.
Vec3 RefineSPlus(const Vec3& s0, const std::vector<Vec3>& f_minus, int lo, int hi,
                 const PairData& pair, bool exact) {
  SPlusCost cost;
  cost.f = f_minus.data() + lo;
  cost.n = hi - lo;
  cost.axis = pair.axis;
  AcrossAxes(pair.axis_index, &cost.b1, &cost.b2);
  cost.exact = exact;
  double scale = 0.0;
  double sum1 = 0.0, sum2 = 0.0;
  for (int i = lo; i < hi; ++i) {
    const Vec3 g = RotInverseApply(s0, f_minus[i], exact);
    sum1 += std::pow(g.dot(cost.b1), 2);
    sum2 += std::pow(g.dot(cost.b2), 2);
    scale += g.norm();
  }
  scale /= (hi - lo);
  if (std::sqrt(std::min(sum1, sum2) / (hi - lo)) < 1e-12 * scale) return s0;
  double t[2] = {s0.dot(cost.b1), s0.dot(cost.b2)};
  double initial_cost = 0.0;
  cost(t, &initial_cost);
  ceres::GradientProblem problem(
      new ceres::AutoDiffFirstOrderFunction<SPlusCost, 2>(new SPlusCost(cost)));
  ceres::GradientProblemSolver::Options solver_options;
  solver_options.logging_type = ceres::SILENT;
  solver_options.max_num_iterations = 100;
  // The objective is ~ the noise rms (1e-2 N): relative 1e-10 is far below anything it resolves.
  solver_options.function_tolerance = 1e-10;
  solver_options.gradient_tolerance = 1e-12;
  solver_options.parameter_tolerance = 1e-12;
  ceres::GradientProblemSolver::Summary summary;
  ceres::Solve(solver_options, problem, t, &summary);
  if (!std::isfinite(t[0]) || !std::isfinite(t[1]) || !(summary.final_cost <= initial_cost)) {
    return s0;
  }
  return t[0] * cost.b1 + t[1] * cost.b2;
}

}  // namespace

PairData MakePair(const LegMatched& m, int slot_down, int slot_up, int axis_index) {
  PairData p;
  p.axis_index = axis_index;
  p.axis = axis_index == 0 ? Vec3::UnitX() : Vec3::UnitZ();
  const size_t n = m.phase.size();
  p.f_minus.resize(n);
  p.tau_minus.resize(n);
  p.f_plus.resize(n);
  p.tau_plus.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const Vec6& down = m.w[slot_down][i];
    const Vec6& up = m.w[slot_up][i];
    p.f_minus[i] = 0.5 * (down.head<3>() - up.head<3>());
    p.tau_minus[i] = 0.5 * (down.tail<3>() - up.tail<3>());
    p.f_plus[i] = 0.5 * (down.head<3>() + up.head<3>());
    p.tau_plus[i] = 0.5 * (down.tail<3>() + up.tail<3>());
  }
  return p;
}

}  // namespace hanging_detail

using hanging_detail::AcrossAxes;
using hanging_detail::MinimalRotation;
using hanging_detail::RotInverseApply;
using hanging_detail::SPlusCost;

Vec3 SPlusClosedForm(const Vec3& f_minus_mean, const Vec3& axis, bool exact_rotations) {
  const double along = axis.dot(f_minus_mean);
  if (!(along > 0.0)) {
    throw std::invalid_argument("SPlusClosedForm: mean half-difference force is not along +axis");
  }
  if (exact_rotations) return MinimalRotation(axis, f_minus_mean.normalized());
  // (I + [s]) a = a + s x a must be parallel to f-; with s orthogonal to a,
  // s = a x (s x a) = a x (f- / (a . f-)).
  return axis.cross(f_minus_mean / along);
}

double SPlusObjective(const Vec3& s_plus, const std::vector<Vec3>& f_minus, const Vec3& axis,
                      bool exact_rotations) {
  SPlusCost cost;
  cost.f = f_minus.data();
  cost.n = static_cast<int>(f_minus.size());
  cost.axis = axis;
  AcrossAxes(std::abs(axis.x()) > 0.5 ? 0 : 2, &cost.b1, &cost.b2);
  cost.exact = exact_rotations;
  // Evaluate with s itself (its component about the axis included) rather than through t.
  double sum1 = 0.0, sum2 = 0.0, sum_a = 0.0;
  std::vector<double> along(f_minus.size());
  for (size_t i = 0; i < f_minus.size(); ++i) {
    const Vec3 g = RotInverseApply(s_plus, f_minus[i], exact_rotations);
    sum1 += std::pow(g.dot(cost.b1), 2);
    sum2 += std::pow(g.dot(cost.b2), 2);
    along[i] = g.dot(axis);
    sum_a += along[i];
  }
  const double n = static_cast<double>(f_minus.size());
  double var = 0.0;
  for (double v : along) var += std::pow(v - sum_a / n, 2);
  return std::sqrt(sum1 / n) + std::sqrt(sum2 / n) + std::sqrt(var / n);
}

namespace hanging_detail {
namespace {

// One pair on the matched samples [lo, hi) (all of them, or one cycle). r_fit: the fitted CoM
// curve at each sample's phase.
PairEstimate SolvePair(const PairData& pair, const std::vector<Vec3>& r_fit, int lo, int hi,
                       const PairSolve& how, const std::string& where) {
  const bool exact = how.exact_rotations;
  const double n = hi - lo;
  Vec3 f_minus_mean = Vec3::Zero(), f_plus_mean = Vec3::Zero();
  Vec3 tau_plus_mean = Vec3::Zero(), r_mean = Vec3::Zero();
  for (int i = lo; i < hi; ++i) {
    f_minus_mean += pair.f_minus[i];
    f_plus_mean += pair.f_plus[i];
    tau_plus_mean += pair.tau_plus[i];
    r_mean += r_fit[i];
  }
  f_minus_mean /= n;
  f_plus_mean /= n;
  tau_plus_mean /= n;
  r_mean /= n;
  PairEstimate e;
  if (!(pair.axis.dot(f_minus_mean) > 0.0)) {
    Fail(where + "the half-difference force is not along +" + (pair.axis_index == 0 ? "x" : "z") +
         ": the down and up series carry the leg's weight the wrong way round");
  }
  if (!how.use_s) {
    e.weight_n = pair.axis.dot(f_minus_mean);
  } else {
    e.s_plus = SPlusClosedForm(f_minus_mean, pair.axis, exact);
    if (how.refine_s_plus) e.s_plus = RefineSPlus(e.s_plus, pair.f_minus, lo, hi, pair, exact);
    double m = 0.0;
    for (int i = lo; i < hi; ++i) {
      m += pair.axis.dot(RotInverseApply(e.s_plus, pair.f_minus[i], exact));
    }
    m /= n;
    // d = t1 c1 + t2 c2: first order d = m g s- x a with s- across a; exact d orthogonal to
    // the mean of R(s_down) a and R(s_up) a, i.e. to R(s+) a.
    Vec3 c1, c2, b1, b2;
    AcrossAxes(pair.axis_index, &b1, &b2);
    if (exact) {
      OrthonormalComplement(RotApply(e.s_plus, pair.axis, true).normalized(), &c1, &c2);
    } else {
      c1 = m * b1.cross(pair.axis);
      c2 = m * b2.cross(pair.axis);
    }
    // min over t of sum_i |dtau+_i - dr_i x d|^2 (means removed: the std criterion).
    Eigen::Matrix2d ata = Eigen::Matrix2d::Zero();
    Eigen::Vector2d atb = Eigen::Vector2d::Zero();
    for (int i = lo; i < hi; ++i) {
      const Vec3 dr = r_fit[i] - r_mean;
      Eigen::Matrix<double, 3, 2> a;
      a.col(0) = dr.cross(c1);
      a.col(1) = dr.cross(c2);
      ata += a.transpose() * a;
      atb += a.transpose() * (pair.tau_plus[i] - tau_plus_mean);
    }
    Eigen::LDLT<Eigen::Matrix2d> ldlt(ata);
    if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > 1e-9)) {
      Fail(where + "s- is unobservable: the leg CoM does not move across the gravity axis");
    }
    const Eigen::Vector2d t = ldlt.solve(atb);
    e.d = t(0) * c1 + t(1) * c2;
    if (exact) {
      e.weight_n = std::sqrt(m * m + e.d.squaredNorm());
      const Vec3 centre = m * RotApply(e.s_plus, pair.axis, true);
      e.s_down = MinimalRotation(pair.axis, (centre + e.d).normalized());
      e.s_up = MinimalRotation(pair.axis, (centre - e.d).normalized());
      e.s_plus = 0.5 * (e.s_down + e.s_up);
      e.s_minus = 0.5 * (e.s_down - e.s_up);
    } else {
      e.weight_n = m;
      e.s_minus = t(0) * b1 + t(1) * b2;
      e.s_down = e.s_plus + e.s_minus;
      e.s_up = e.s_plus - e.s_minus;
    }
  }
  e.force_offset = f_plus_mean - e.d;
  // mean_i(tau+_i - r_i x d)
  e.torque_offset = tau_plus_mean - r_mean.cross(e.d);
  return e;
}

}  // namespace

double StudentWidening(int n) {
  // A normal sigma would claim 95 % at +-1.96 where n values' spread gives only the t
  // distribution's coverage (90 % at +-2 for six cycles).
  if (n < 2) return std::numeric_limits<double>::quiet_NaN();
  const boost::math::students_t t(n - 1.0);
  return boost::math::quantile(t, 0.975) / boost::math::quantile(boost::math::normal(), 0.975);
}

double StdError(const std::vector<double>& v) {
  const double n = static_cast<double>(v.size());
  if (v.size() < 2) return std::numeric_limits<double>::quiet_NaN();
  double mean = 0.0;
  for (double x : v) mean += x;
  mean /= n;
  double ss = 0.0;
  for (double x : v) ss += (x - mean) * (x - mean);
  return StudentWidening(static_cast<int>(v.size())) * std::sqrt(ss / (n - 1.0) / n);
}

Vec3 StdError3(const std::vector<Vec3>& v) {
  std::vector<double> c(v.size());
  Vec3 out;
  for (int k = 0; k < 3; ++k) {
    for (size_t j = 0; j < v.size(); ++j) c[j] = v[j](k);
    out(k) = StdError(c);
  }
  return out;
}

HangingPairResult PairResult(const PairData& pair, const std::vector<Vec3>& r_fit,
                             const LegMatched& m, const PairSolve& how, const std::string& where,
                             PairEstimate* full) {
  const int n = static_cast<int>(m.phase.size());
  *full = SolvePair(pair, r_fit, 0, n, how, where);
  // Per-cycle estimates use the closed-form s+ (the refinement changes s+ by far less than
  // its per-cycle spread) to keep the spread cheap.
  std::vector<double> weight;
  std::vector<Vec3> s_plus, s_minus, f_o, tau_o;
  for (const auto& [lo, hi] : m.cycles) {
    PairSolve closed_form = how;
    closed_form.refine_s_plus = false;
    const PairEstimate c = SolvePair(pair, r_fit, lo, hi, closed_form, where);
    weight.push_back(c.weight_n);
    s_plus.push_back(c.s_plus);
    s_minus.push_back(c.s_minus);
    f_o.push_back(c.force_offset);
    tau_o.push_back(c.torque_offset);
  }
  HangingPairResult r;
  r.axis = pair.axis_index == 0 ? 'x' : 'z';
  r.s_plus_rad = {full->s_plus, StdError3(s_plus)};
  r.s_minus_rad = {full->s_minus, StdError3(s_minus)};
  r.weight_n = {full->weight_n, StdError(weight)};
  r.force_offset_n = {full->force_offset, StdError3(f_o)};
  r.torque_offset_nm = {full->torque_offset, StdError3(tau_o)};
  r.matched_samples = n;
  r.cycles = static_cast<int>(m.cycles.size());
  return r;
}

// Inverse-variance weighting; where a sigma is exactly 0 (noise-free data) the zero-sigma
// values are averaged plainly.
ScalarSigma Combine(const ScalarSigma& a, const ScalarSigma& b) {
  if (a.sigma == 0.0 || b.sigma == 0.0) {
    if (a.sigma == 0.0 && b.sigma == 0.0) return {0.5 * (a.value + b.value), 0.0};
    return a.sigma == 0.0 ? a : b;
  }
  const double wa = 1.0 / (a.sigma * a.sigma), wb = 1.0 / (b.sigma * b.sigma);
  return {(wa * a.value + wb * b.value) / (wa + wb), 1.0 / std::sqrt(wa + wb)};
}

Vec3Sigma Combine(const Vec3Sigma& a, const Vec3Sigma& b) {
  Vec3Sigma out;
  for (int k = 0; k < 3; ++k) {
    const ScalarSigma c = Combine({a.value(k), a.sigma(k)}, {b.value(k), b.sigma(k)});
    out.value(k) = c.value;
    out.sigma(k) = c.sigma;
  }
  return out;
}

}  // namespace hanging_detail
}  // namespace ftcal
