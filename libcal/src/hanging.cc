// Step 1 — hanging: offsets, leg weight, leg CoM (docs/method.md "Step 1", report section III-A).
//
// Model (eq. 4-7), for the pair whose transducer axis a (e_x or e_z) is along gravity:
//   f_down = R(s_down) m g a + f_o,      tau_down = [r(phi)] R(s_down) m g a + tau_o,
//   f_up   = -R(s_up) m g a + f_o,       tau_up   = -[r(phi)] R(s_up) m g a + tau_o,
// with R(s) = I + [s] (the report) or exp([s]) (option exact_rotations).
// Matched samples i: both series of a pair (and both pairs) resampled onto a common phase
// grid, per-cycle order kept. Half-differences and half-sums per i:
//   f- = (f_down - f_up)/2, tau- = (tau_down - tau_up)/2 = [r] f- = -[f-] r,
//   f+ = (f_down + f_up)/2 = d + f_o, tau+ = (tau_down + tau_up)/2 = [r] d + tau_o,
//   with d = m g (R(s_down) - R(s_up)) a / 2   (first order: d = [s-] m g a).
// Unknowns and how each is solved:
//   s+  : the report's objective (rms across the axis of R(s+)^-1 f-, plus the std along it),
//         closed form from the mean f- then refined by L-BFGS (Ceres). Null space: the
//         component of s+ about a does not change R(s+) a; held at 0.
//   m g : mean_i a^T R(s+)^-1 f-_i (first order); with exact rotations m g = |(f- +- d)|,
//         i.e. sqrt(m-^2 + |d|^2), since R(s_down) a and R(s_up) a are unit vectors.
//   r   : RTS smoother over i on tau- = -[f-] r (random-walk r). Null space: r + p_i f-_i for
//         any p_i; fixed per sample by the other pair (least squares over the 3 equations of
//         r + p f- = r' + p' f'-), then r_x, r_z = A sin(2 pi phi + C) + D, r_y = const.
//   s-  : minimises std_i(tau+_i - [r(phi_i)] d): linear least squares in the two components
//         of d across the axis (first order: d = m g s- x a; exact: d orthogonal to f-). The
//         component of s- about a is unobservable and held at 0.
//   f_o = mean_i(f+_i - d), tau_o = mean_i(tau+_i - [r(phi_i)] d).
// Both pairs estimate m g and w_o; they are combined by inverse-variance weighting.
// Uncertainty: every estimate is repeated on each full leg cycle alone; sigma is the standard
// error of the per-cycle values (CYCLE_SPREAD).
#include "ftcal/hanging.h"

#include <ceres/autodiff_first_order_function.h>
#include <ceres/gradient_problem.h>
#include <ceres/gradient_problem_solver.h>
#include <ceres/rotation.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

namespace ftcal {
namespace {

constexpr double kTwoPi = 2.0 * M_PI;
constexpr double kRadToDeg = 180.0 / M_PI;
// Slots of the four series per leg: gravity along +x, -x, +z, -z of the transducer.
constexpr int kSlotXDown = 0, kSlotXUp = 1, kSlotZDown = 2, kSlotZUp = 3;
// A cycle counts towards the spread when at least this fraction of its bins was matched.
constexpr double kFullCycleFraction = 0.9;

std::string Where(HangSeries series, int leg) {
  std::ostringstream s;
  s << "hanging series " << HangSeriesName(series) << ", leg " << kLegNames[leg] << ": ";
  return s.str();
}

[[noreturn]] void Fail(const std::string& what) { throw std::invalid_argument(what); }

// To [-pi, pi] (std::remainder is exact but several times slower, and this runs per sample).
double WrapPi(double angle) { return angle - kTwoPi * std::nearbyint(angle / kTwoPi); }

// R(s) v and R(s)^-1 v for the first-order (I + [s]) or exact (exp([s])) model.
Vec3 RotApply(const Vec3& s, const Vec3& v, bool exact) {
  return exact ? Vec3(ExpSO3(s) * v) : Vec3(v + s.cross(v));
}
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

// Two unit vectors completing unit n to an orthonormal basis.
void OrthonormalComplement(const Vec3& n, Vec3* u, Vec3* v) {
  const Vec3 seed = std::abs(n.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  *u = n.cross(seed).normalized();
  *v = n.cross(*u);
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

// ---------------------------------------------------------------- phase matching

// One series of one leg, averaged into cells of the continuous phase grid (cell n covers
// unwrapped phase [n, n+1) / bins), with the cells listed per bin in cycle order.
struct BinnedSeries {
  double cycles = 0.0;
  std::vector<Vec6> cell_wrench;
  std::vector<double> cell_phase;  // mean leg phase of the cell's samples, in [0, 1)
  std::vector<int> occurrences;    // per bin: how many cycles have it
  std::vector<int> lookup;         // [bin * max_occurrences + j] -> cell
  int max_occurrences = 0;
};

void ValidateSamples(const LegSamples& samples, HangSeries series, int leg) {
  const size_t n = samples.t_s.size();
  if (n == 0) Fail(Where(series, leg) + "no samples");
  if (samples.angle_rad.size() != n || samples.wrench.size() != n) {
    std::ostringstream s;
    s << Where(series, leg) << "mismatched sample vectors: " << n << " times, "
      << samples.angle_rad.size() << " angles, " << samples.wrench.size() << " wrenches";
    Fail(s.str());
  }
  for (size_t i = 0; i < n; ++i) {
    if (!std::isfinite(samples.t_s[i]) || !std::isfinite(samples.angle_rad[i]) ||
        !samples.wrench[i].allFinite()) {
      std::ostringstream s;
      s << Where(series, leg) << "non-finite value in sample " << i << " (t_s " << samples.t_s[i]
        << ", angle_rad " << samples.angle_rad[i] << ", wrench " << samples.wrench[i].transpose()
        << ")";
      Fail(s.str());
    }
    if (i > 0 && samples.t_s[i] < samples.t_s[i - 1]) {
      std::ostringstream s;
      s << Where(series, leg) << "sample " << i << " is earlier than the one before (t_s "
        << samples.t_s[i] << " < " << samples.t_s[i - 1] << ")";
      Fail(s.str());
    }
  }
}

BinnedSeries BinSeries(const LegSamples& samples, HangSeries series, int leg,
                       const HangingOptions& options) {
  const int bins = options.phase_bins;
  const size_t n = samples.t_s.size();
  // Unwrapped angle: consecutive samples are far less than half a turn apart, so the wrap of
  // the shaft angle at +-pi is undone by wrapping each increment.
  double psi = samples.angle_rad[0] / kTwoPi;
  double psi_min = psi, psi_max = psi;
  const double psi_first = psi;
  std::vector<double> psi_all(n);
  psi_all[0] = psi;
  for (size_t i = 1; i < n; ++i) {
    psi += WrapPi(samples.angle_rad[i] - samples.angle_rad[i - 1]) / kTwoPi;
    psi_all[i] = psi;
    psi_min = std::min(psi_min, psi);
    psi_max = std::max(psi_max, psi);
  }
  BinnedSeries out;
  out.cycles = std::abs(psi - psi_first);
  if (out.cycles < options.min_cycles) {
    std::ostringstream s;
    s << Where(series, leg) << "the leg turned " << out.cycles << " cycles, need at least "
      << options.min_cycles;
    Fail(s.str());
  }
  const bool forward = psi > psi_first;
  const long n_min = static_cast<long>(std::floor(psi_min * bins));
  const long n_max = static_cast<long>(std::floor(psi_max * bins));
  const long num_cells = n_max - n_min + 1;
  if (num_cells > 100000000L / bins) {
    Fail(Where(series, leg) + "shaft angle spans an implausible number of turns");
  }
  // Per cell: the samples' wrench is regressed on their position x in the cell and evaluated
  // at the bin centre, so that every series gives its value at the same phase (a plain mean
  // would sit at each series' own mean phase, which differs between series by up to half a
  // bin: ~0.5 mm of CoM on a typical leg). Too few or too clustered samples: their mean.
  out.cell_wrench.assign(num_cells, Vec6::Zero());
  std::vector<double> cell_pos(num_cells, 0.0);  // position of the value inside the cell, [0, 1)
  std::vector<int> count(num_cells, 0);
  std::vector<double> sum_x(num_cells, 0.0), sum_xx(num_cells, 0.0);
  std::vector<Vec6> sum_xw(num_cells, Vec6::Zero());
  for (size_t i = 0; i < n; ++i) {
    const double x = psi_all[i] * bins;
    const long cell = std::min(static_cast<long>(std::floor(x)) - n_min, num_cells - 1);
    const double pos = x - static_cast<double>(cell + n_min);
    out.cell_wrench[cell] += samples.wrench[i];
    sum_x[cell] += pos;
    sum_xx[cell] += pos * pos;
    sum_xw[cell] += pos * samples.wrench[i];
    ++count[cell];
  }
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    const double k = count[c];
    const Vec6 mean_w = out.cell_wrench[c] / k;
    const double mean_x = sum_x[c] / k;
    const double var_x = sum_xx[c] / k - mean_x * mean_x;
    // 1/48: half the spread of samples uniform over the cell.
    if (count[c] >= 3 && var_x >= 1.0 / 48.0) {
      const Vec6 slope = (sum_xw[c] / k - mean_x * mean_w) / var_x;
      out.cell_wrench[c] = mean_w + slope * (0.5 - mean_x);
      cell_pos[c] = 0.5;
    } else {
      out.cell_wrench[c] = mean_w;
      cell_pos[c] = mean_x;
    }
  }
  // Short gaps (a few bins without a sample, e.g. a fast stretch or a dropped packet) are
  // filled by linear interpolation between the neighbouring cells at the bin centre.
  long last = -1;
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    if (last >= 0 && c - last > 1 && c - last - 1 <= options.max_gap_bins) {
      const double x0 = last + cell_pos[last], x1 = c + cell_pos[c];
      for (long g = last + 1; g < c; ++g) {
        const double w = (g + 0.5 - x0) / (x1 - x0);
        out.cell_wrench[g] = (1.0 - w) * out.cell_wrench[last] + w * out.cell_wrench[c];
        cell_pos[g] = 0.5;
        count[g] = -1;  // interpolated
      }
    }
    last = c;
  }
  // Cells per bin in the order the leg passed them.
  out.occurrences.assign(bins, 0);
  out.cell_phase.assign(num_cells, 0.0);
  auto bin_of = [&](long c) {
    const long global = c + n_min;
    return static_cast<int>(((global % bins) + bins) % bins);
  };
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    const int b = bin_of(c);
    out.cell_phase[c] = (b + cell_pos[c]) / bins;
    ++out.occurrences[b];
  }
  out.max_occurrences = *std::max_element(out.occurrences.begin(), out.occurrences.end());
  out.lookup.assign(static_cast<size_t>(bins) * out.max_occurrences, -1);
  std::vector<int> filled(bins, 0);
  for (long k = 0; k < num_cells; ++k) {
    const long c = forward ? k : num_cells - 1 - k;
    if (count[c] == 0) continue;
    const int b = bin_of(c);
    out.lookup[static_cast<size_t>(b) * out.max_occurrences + filled[b]++] = static_cast<int>(c);
  }
  return out;
}

// ---------------------------------------------------------------- per-leg data

// The matched samples of one leg: index i runs over cycles j (major) and bins (minor).
struct LegMatched {
  std::array<std::vector<Vec6>, 4> w;  // per slot
  std::vector<double> phase;
  std::vector<int> bin;
  std::vector<std::pair<int, int>> cycles;  // [begin, end) of each full cycle
  int num_cycles_total = 0;
};

// Half-differences and half-sums of one pair.
struct PairData {
  Vec3 axis = Vec3::UnitX();
  int axis_index = 0;
  std::vector<Vec3> f_minus, tau_minus, f_plus, tau_plus;
};

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

// ---------------------------------------------------------------- s+ (report's objective)

// The report's objective in the two components t of s+ across the axis (s+ = t1 b1 + t2 b2),
// templated for Ceres' automatic differentiation.
struct SPlusCost {
  const Vec3* f = nullptr;
  int n = 0;
  Vec3 axis, b1, b2;
  bool exact = false;

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

// ---------------------------------------------------------------- public equations

std::string HangSeriesName(HangSeries series) {
  switch (series) {
    case HangSeries::kXPos:
      return "HANG_X_POS";
    case HangSeries::kXNeg:
      return "HANG_X_NEG";
    case HangSeries::kZPos:
      return "HANG_Z_POS";
    case HangSeries::kZNeg:
      return "HANG_Z_NEG";
  }
  return "HANG_<invalid " + std::to_string(static_cast<int>(series)) + ">";
}

void SetRatedRanges(const config::Robot& robot, HangingOptions* options) {
  for (int k = 0; k < kNumLegs && k < robot.leg_size(); ++k) {
    const config::AtiTransducer& ati = robot.leg(k).ati();
    if (ati.rated_range_size() != 6) continue;
    for (int i = 0; i < 6; ++i) options->rated_range[k][i] = ati.rated_range(i);
  }
}

HangingOptions HangingOptionsFromConfig(const config::Calibrator& calibrator,
                                        const config::Mocap& mocap) {
  HangingOptions o;
  o.phase_bins = static_cast<int>(calibrator.phase_bins());
  o.smoother_transition_var_m2 = calibrator.smoother_transition_var();
  o.smoother_observation_var_nm2 = calibrator.smoother_observation_var();
  // The REPORT profile is the report's first-order I + [s].
  o.exact_rotations =
      calibrator.profile() != config::REPORT && calibrator.exact_hanging_rotations();
  o.axis_tolerance_rad = mocap.hang_axis_tolerance_deg() / kRadToDeg;
  return o;
}

Vec6 HangingVariant::Offset() const {
  Vec6 w;
  w << force_offset_n.value, torque_offset_nm.value;
  return w;
}

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

// Kalman filter + Rauch-Tung-Striebel smoother, written here because no packaged C++ library
// offers one (Eigen has none; a 3-state random walk is a few lines). The component of
// tau- along f- carries no information on r (f-^T [f-] = 0): the update uses only the two
// components across f-, which gives the same posterior as the report's 3-D observation with
// isotropic noise and stays well conditioned for any observation variance.
std::vector<Vec3> SmoothLegCom(const std::vector<Vec3>& f_minus, const std::vector<Vec3>& tau_minus,
                               double transition_var_m2, double observation_var_nm2) {
  if (f_minus.size() != tau_minus.size()) {
    throw std::invalid_argument("SmoothLegCom: f_minus and tau_minus differ in length");
  }
  if (!(transition_var_m2 > 0.0) || !(observation_var_nm2 > 0.0)) {
    throw std::invalid_argument("SmoothLegCom: smoother variances must be positive");
  }
  const size_t n = f_minus.size();
  std::vector<Vec3> x_f(n);
  std::vector<Mat3> p_f(n);
  const Mat3 q = transition_var_m2 * Mat3::Identity();
  // Prior: the first sample's own least-norm solution r = f- x tau- / |f-|^2, with 1 m^2 (far
  // wider than any leg's CoM) so that it weighs nothing against the observations; a prior at 0
  // would pull the first samples towards 0 by (R / |f-|^2) / P0, ~3e-4 relative.
  Vec3 x = Vec3::Zero();
  if (n > 0 && f_minus[0].squaredNorm() > 0.0) {
    x = f_minus[0].cross(tau_minus[0]) / f_minus[0].squaredNorm();
  }
  Mat3 p = Mat3::Identity();
  for (size_t i = 0; i < n; ++i) {
    if (i > 0) p += q;
    const double f_norm = f_minus[i].norm();
    if (f_norm > 0.0) {
      Vec3 u, v;
      OrthonormalComplement(f_minus[i] / f_norm, &u, &v);
      Eigen::Matrix<double, 2, 3> basis;
      basis.row(0) = u.transpose();
      basis.row(1) = v.transpose();
      const Eigen::Matrix<double, 2, 3> h = -basis * Skew(f_minus[i]);
      const Eigen::Vector2d z = basis * tau_minus[i];
      const Eigen::Matrix2d s =
          h * p * h.transpose() + observation_var_nm2 * Eigen::Matrix2d::Identity();
      const Eigen::Matrix<double, 3, 2> k = p * h.transpose() * s.inverse();
      x += k * (z - h * x);
      const Mat3 i_kh = Mat3::Identity() - k * h;
      // Joseph form: stays symmetric positive definite for tiny observation variances.
      p = i_kh * p * i_kh.transpose() + observation_var_nm2 * k * k.transpose();
    }
    x_f[i] = x;
    p_f[i] = p;
  }
  std::vector<Vec3> x_s(n);
  if (n == 0) return x_s;
  x_s[n - 1] = x_f[n - 1];
  for (size_t i = n - 1; i-- > 0;) {
    const Mat3 p_pred = p_f[i] + q;
    const Mat3 gain = p_f[i] * p_pred.inverse();
    x_s[i] = x_f[i] + gain * (x_s[i + 1] - x_f[i]);
  }
  return x_s;
}

Vec3 ResolveComNullSpace(const Vec3& r_est, const Vec3& f_minus, const Vec3& r_est_prime,
                         const Vec3& f_minus_prime) {
  Eigen::Matrix<double, 3, 2> a;
  a.col(0) = f_minus;
  a.col(1) = -f_minus_prime;
  const Eigen::Matrix2d ata = a.transpose() * a;
  if (!(std::abs(ata.determinant()) > 1e-12 * ata.squaredNorm())) {
    throw std::invalid_argument(
        "ResolveComNullSpace: the two pairs' gravity directions are parallel");
  }
  const Eigen::Vector2d p = ata.ldlt().solve(a.transpose() * (r_est_prime - r_est));
  return 0.5 * ((r_est + p(0) * f_minus) + (r_est_prime + p(1) * f_minus_prime));
}

namespace {

// Linear least squares of v = alpha sin(2 pi phi) + beta cos(2 pi phi) + d over [lo, hi).
// a sin(x + c) = a cos(c) sin(x) + a sin(c) cos(x), so the nonlinear fit of (a, c, d) has the
// same minimiser as this linear one (a bijection for a > 0): no iterative solver is needed.
template <class Value>
SinusoidFit FitSinusoidRange(const std::vector<double>& phase, int lo, int hi, Value value) {
  Mat3 ata = Mat3::Zero();
  Vec3 atb = Vec3::Zero();
  for (int i = lo; i < hi; ++i) {
    const double x = kTwoPi * phase[i];
    const Vec3 row(std::sin(x), std::cos(x), 1.0);
    ata += row * row.transpose();
    atb += row * value(i);
  }
  Eigen::LDLT<Mat3> ldlt(ata);
  if (ldlt.info() != Eigen::Success || !(ldlt.rcond() > 1e-10)) {
    throw std::invalid_argument("FitSinusoid: phases do not span the cycle");
  }
  const Vec3 coef = ldlt.solve(atb);
  SinusoidFit fit;
  fit.a = std::hypot(coef(0), coef(1));
  fit.c = std::atan2(coef(1), coef(0));
  fit.d = coef(2);
  return fit;
}

}  // namespace

SinusoidFit FitSinusoid(const std::vector<double>& phase, const std::vector<double>& value) {
  if (phase.size() != value.size() || phase.size() < 3) {
    throw std::invalid_argument("FitSinusoid: need equal-length phase and value, 3 or more");
  }
  return FitSinusoidRange(phase, 0, static_cast<int>(phase.size()),
                          [&](int i) { return value[i]; });
}

namespace {

// ---------------------------------------------------------------- pair solve

struct PairEstimate {
  Vec3 s_plus = Vec3::Zero(), s_minus = Vec3::Zero();
  Vec3 s_down = Vec3::Zero(), s_up = Vec3::Zero();
  double weight_n = 0.0;
  Vec3 d = Vec3::Zero();
  Vec3 force_offset = Vec3::Zero(), torque_offset = Vec3::Zero();
};

// One pair on the matched samples [lo, hi) (all of them, or one cycle). r_fit: the fitted CoM
// curve at each sample's phase.
PairEstimate SolvePair(const PairData& pair, const std::vector<Vec3>& r_fit, int lo, int hi,
                       bool use_s, bool exact, bool refine, const std::string& where) {
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
  if (!use_s) {
    e.weight_n = pair.axis.dot(f_minus_mean);
  } else {
    e.s_plus = SPlusClosedForm(f_minus_mean, pair.axis, exact);
    if (refine) e.s_plus = RefineSPlus(e.s_plus, pair.f_minus, lo, hi, pair, exact);
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

double StdError(const std::vector<double>& v) {
  const double n = static_cast<double>(v.size());
  if (v.size() < 2) return std::numeric_limits<double>::quiet_NaN();
  double mean = 0.0;
  for (double x : v) mean += x;
  mean /= n;
  double ss = 0.0;
  for (double x : v) ss += (x - mean) * (x - mean);
  return std::sqrt(ss / (n - 1.0) / n);
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
                             const LegMatched& m, bool use_s, bool exact, bool refine,
                             const std::string& where, PairEstimate* full) {
  const int n = static_cast<int>(m.phase.size());
  *full = SolvePair(pair, r_fit, 0, n, use_s, exact, refine, where);
  // Per-cycle estimates use the closed-form s+ (the refinement changes s+ by far less than
  // its per-cycle spread) to keep the spread cheap.
  std::vector<double> weight;
  std::vector<Vec3> s_plus, s_minus, f_o, tau_o;
  for (const auto& [lo, hi] : m.cycles) {
    const PairEstimate c = SolvePair(pair, r_fit, lo, hi, use_s, exact, false, where);
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

// Per component, the values of ranks k_lo <= k_hi (0-based), exactly: one pass counts every
// component into buckets between its min and max (monotone, so ranks are preserved), a second
// collects the values of the two buckets holding the ranks, and the selection runs inside them.
// Both passes read each sample once for all six components: std::nth_element per component
// over the whole vector dominated the step's run time.
void TwoRanks(const std::vector<Vec6>& v, const Vec6& lo, const Vec6& hi, size_t k_lo, size_t k_hi,
              Vec6* at_lo, Vec6* at_hi) {
  constexpr int kBuckets = 1024;
  Vec6 scale;
  for (int c = 0; c < 6; ++c) scale(c) = hi(c) > lo(c) ? kBuckets / (hi(c) - lo(c)) : 0.0;
  auto bucket = [&](const Vec6& r, int c) {
    return std::min(kBuckets - 1, static_cast<int>((r(c) - lo(c)) * scale(c)));
  };
  std::vector<std::array<size_t, kBuckets>> count(6);
  for (auto& c : count) c.fill(0);
  for (const Vec6& r : v) {
    for (int c = 0; c < 6; ++c) ++count[c][bucket(r, c)];
  }
  std::array<int, 6> b_lo, b_hi;
  std::array<size_t, 6> rank_lo, rank_hi;
  auto find = [&](int c, size_t k, size_t* rank_in_bucket) {
    size_t before = 0;
    int b = 0;
    while (before + count[c][b] <= k) before += count[c][b++];
    *rank_in_bucket = k - before;
    return b;
  };
  std::array<std::vector<double>, 6> in_lo, in_hi;
  for (int c = 0; c < 6; ++c) {
    b_lo[c] = find(c, k_lo, &rank_lo[c]);
    b_hi[c] = find(c, k_hi, &rank_hi[c]);
    in_lo[c].reserve(count[c][b_lo[c]]);
    in_hi[c].reserve(count[c][b_hi[c]]);
  }
  for (const Vec6& r : v) {
    for (int c = 0; c < 6; ++c) {
      const int b = bucket(r, c);
      if (b == b_lo[c]) in_lo[c].push_back(r(c));
      if (b == b_hi[c]) in_hi[c].push_back(r(c));
    }
  }
  for (int c = 0; c < 6; ++c) {
    std::nth_element(in_lo[c].begin(), in_lo[c].begin() + rank_lo[c], in_lo[c].end());
    std::nth_element(in_hi[c].begin(), in_hi[c].begin() + rank_hi[c], in_hi[c].end());
    (*at_lo)(c) = in_lo[c][rank_lo[c]];
    (*at_hi)(c) = in_hi[c][rank_hi[c]];
  }
}

WrenchResidualStats Stats(const std::string& label, const std::vector<Vec6>& residual) {
  WrenchResidualStats s;
  s.label = label;
  s.count = static_cast<int>(residual.size());
  if (residual.empty()) return s;
  const double n = static_cast<double>(residual.size());
  Vec6 lo = residual[0], hi = residual[0];
  for (const Vec6& r : residual) {
    s.mean += r;
    s.rms += r.cwiseProduct(r);
    lo = lo.cwiseMin(r);
    hi = hi.cwiseMax(r);
  }
  s.mean /= n;
  s.rms = (s.rms / n).cwiseSqrt();
  for (const Vec6& r : residual) s.std += (r - s.mean).cwiseProduct(r - s.mean);
  s.std = (s.std / std::max(1.0, n - 1.0)).cwiseSqrt();
  const size_t i05 = static_cast<size_t>(std::floor(0.05 * (n - 1)));
  const size_t i95 = static_cast<size_t>(std::ceil(0.95 * (n - 1)));
  TwoRanks(residual, lo, hi, i05, i95, &s.p05, &s.p95);
  return s;
}

void ValidateOptions(const HangingOptions& o) {
  auto bad = [](const std::string& what) { Fail("hanging options: " + what); };
  if (o.phase_bins < 8) bad("phase_bins must be at least 8, got " + std::to_string(o.phase_bins));
  if (!(o.smoother_transition_var_m2 > 0.0) || !(o.smoother_observation_var_nm2 > 0.0)) {
    bad("smoother variances must be positive");
  }
  if (!(o.axis_tolerance_rad > 0.0 && o.axis_tolerance_rad < M_PI / 4)) {
    bad("axis tolerance must be in (0, 45) deg");
  }
  if (o.min_cycles < 2) bad("min_cycles must be at least 2 (sigmas come from the cycle spread)");
  if (o.max_gap_bins < 0) bad("max_gap_bins must be non-negative");
  if (!(o.min_phase_coverage > 0.0 && o.min_phase_coverage <= 1.0)) {
    bad("min_phase_coverage must be in (0, 1]");
  }
  if (!(o.naive_tare_max_angle_rad > 0.0)) bad("naive_tare_max_angle_rad must be positive");
}

// Gravity direction of a series in body frame, checked against motion capture when present.
Vec3 SeriesGravity(const HangingRecording& rec, const HangingOptions& options) {
  const std::string where = "hanging series " + HangSeriesName(rec.series) + ": ";
  const double norm = rec.gravity_b.norm();
  if (!rec.gravity_b.allFinite() || std::abs(norm - 1.0) > 1e-3) {
    std::ostringstream s;
    s << where << "stated gravity_b (" << rec.gravity_b.transpose() << ") is not a unit vector";
    Fail(s.str());
  }
  const Vec3 g_b = rec.gravity_b / norm;
  if (!rec.attitude.empty()) {
    Vec3 measured = Vec3::Zero();
    for (size_t i = 0; i < rec.attitude.size(); ++i) {
      const Mat3& r = rec.attitude[i];
      if (!r.allFinite() || OrthonormalityError(r) > 1e-3) {
        Fail(where + "attitude sample " + std::to_string(i) + " is not a rotation");
      }
      measured += r.transpose() * Vec3(0, 0, -1);  // gravity in C (axes of B)
    }
    measured.normalize();
    const double angle = std::acos(std::clamp(measured.dot(g_b), -1.0, 1.0));
    if (angle > options.axis_tolerance_rad) {
      std::ostringstream s;
      s << where << "motion capture puts gravity at (" << measured.transpose() << ") in B, "
        << angle * kRadToDeg << " deg from the stated (" << g_b.transpose() << "); tolerance "
        << options.axis_tolerance_rad * kRadToDeg << " deg";
      Fail(s.str());
    }
  }
  return g_b;
}

// Unit mean of directions split into kGravityBlocks contiguous time blocks, and the standard
// error (per axis across the mean direction) of that mean from the spread of the blocks.
constexpr int kGravityBlocks = 10;

template <typename DirectionOf>
std::pair<Vec3, double> MeanDirection(size_t n, const DirectionOf& direction_of) {
  std::array<Vec3, kGravityBlocks> block;
  block.fill(Vec3::Zero());
  Vec3 mean = Vec3::Zero();
  for (size_t i = 0; i < n; ++i) {
    const Vec3 d = direction_of(i);
    block[std::min<size_t>(kGravityBlocks - 1, i * kGravityBlocks / n)] += d;
    mean += d;
  }
  mean.normalize();
  double ss = 0.0;
  int used = 0;
  for (const Vec3& b : block) {
    if (b.norm() == 0.0) continue;
    ss += (b.normalized() - mean).squaredNorm();
    ++used;
  }
  // Two axes across the direction share the squared deviation.
  const double sigma = used > 1 ? std::sqrt(ss / (2.0 * (used - 1)) / used) : 0.0;
  return {mean, sigma};
}

HangingGravityObservation GravityObservation(const HangingRecording& rec, int leg,
                                             const Pose3& X_B_ft, const Vec3Sigma& force_offset) {
  const LegSamples& ls = rec.legs[leg];
  HangingGravityObservation obs;
  obs.leg = leg;
  obs.series = rec.series;
  Vec3 f_mean = Vec3::Zero();
  for (const Vec6& w : ls.wrench) f_mean += w.head<3>() - force_offset.value;
  f_mean /= static_cast<double>(ls.wrench.size());
  const auto [u_ft, sigma_u] = MeanDirection(ls.wrench.size(), [&](size_t i) {
    return Vec3(ls.wrench[i].head<3>() - force_offset.value);
  });
  const auto [v, sigma_v] = MeanDirection(rec.attitude.size(), [&](size_t i) {
    return Vec3(rec.attitude[i].transpose() * Vec3(0, 0, -1));
  });
  obs.u_B = X_B_ft.R * u_ft;
  obs.v_C = v;
  const double sigma_offset = force_offset.sigma.norm() / std::sqrt(3.0) / f_mean.norm();
  obs.sigma_rad = std::sqrt(sigma_u * sigma_u + sigma_v * sigma_v + sigma_offset * sigma_offset);
  return obs;
}

// Which slot (x/z, down/up) a series is for leg k.
int SeriesSlot(const HangingRecording& rec, const Vec3& g_b, const Pose3& X_B_ft, int leg,
               const HangingOptions& options) {
  const Vec3 g_ft = X_B_ft.R.transpose() * g_b;
  const int axis = std::abs(g_ft.x()) >= std::abs(g_ft.z()) ? 0 : 2;
  const double angle = std::acos(std::clamp(std::abs(g_ft(axis)), 0.0, 1.0));
  if (angle > options.axis_tolerance_rad) {
    std::ostringstream s;
    s << Where(rec.series, leg) << "stated gravity in the transducer frame is (" << g_ft.transpose()
      << "), " << angle * kRadToDeg << " deg from the nearest transducer x or z axis; tolerance "
      << options.axis_tolerance_rad * kRadToDeg << " deg";
    Fail(s.str());
  }
  const bool down = g_ft(axis) > 0.0;
  return axis == 0 ? (down ? kSlotXDown : kSlotXUp) : (down ? kSlotZDown : kSlotZUp);
}

const char* SlotName(int slot) {
  static const char* kNames[] = {"+x", "-x", "+z", "-z"};
  return kNames[slot];
}

}  // namespace

// ---------------------------------------------------------------- the step

HangingResult RunHanging(const std::vector<HangingRecording>& recordings,
                         const std::array<Pose3, kNumLegs>& X_B_ft, const HangingOptions& options) {
  ValidateOptions(options);
  // Exactly one recording per series.
  std::array<const HangingRecording*, kNumHangSeries> by_series{};
  for (const HangingRecording& rec : recordings) {
    const int s = static_cast<int>(rec.series);
    if (s < 0 || s >= kNumHangSeries) Fail("hanging: recording with an invalid series value");
    if (by_series[s] != nullptr)
      Fail("hanging: series " + HangSeriesName(rec.series) + " given twice");
    by_series[s] = &rec;
  }
  for (int s = 0; s < kNumHangSeries; ++s) {
    if (by_series[s] == nullptr) {
      Fail("hanging: series " + HangSeriesName(static_cast<HangSeries>(s)) + " is missing");
    }
  }
  // Saturated samples (beyond the rated range) out, counted per leg: a copy only of the
  // recordings that have any.
  std::array<int, kNumLegs> saturated{};
  std::vector<HangingRecording> unsaturated;
  unsaturated.reserve(kNumHangSeries);
  for (int s = 0; s < kNumHangSeries; ++s) {
    const HangingRecording& rec = *by_series[s];
    bool any = false;
    for (int k = 0; k < kNumLegs && !any; ++k) {
      for (const Vec6& w : rec.legs[k].wrench) {
        if ((w.cwiseAbs().array() > options.rated_range[k].array()).any()) {
          any = true;
          break;
        }
      }
    }
    if (!any) continue;
    HangingRecording copy;
    copy.series = rec.series;
    copy.gravity_b = rec.gravity_b;
    copy.attitude = rec.attitude;
    for (int k = 0; k < kNumLegs; ++k) {
      const LegSamples& in = rec.legs[k];
      LegSamples& out = copy.legs[k];
      for (size_t i = 0; i < in.wrench.size(); ++i) {
        if ((in.wrench[i].cwiseAbs().array() > options.rated_range[k].array()).any()) {
          ++saturated[k];
          continue;
        }
        out.t_s.push_back(i < in.t_s.size() ? in.t_s[i] : 0.0);
        out.angle_rad.push_back(i < in.angle_rad.size() ? in.angle_rad[i] : 0.0);
        out.wrench.push_back(in.wrench[i]);
      }
    }
    unsaturated.push_back(std::move(copy));
    by_series[s] = &unsaturated.back();
  }
  std::array<Vec3, kNumHangSeries> g_b;
  for (int s = 0; s < kNumHangSeries; ++s) g_b[s] = SeriesGravity(*by_series[s], options);
  // The upright series (gravity closest to -z_B) for the naive tare.
  int upright = 0;
  for (int s = 1; s < kNumHangSeries; ++s) {
    if (g_b[s].z() < g_b[upright].z()) upright = s;
  }

  bool has_attitude = true;
  for (const HangingRecording* rec : by_series)
    has_attitude = has_attitude && !rec->attitude.empty();

  const int bins = options.phase_bins;
  HangingResult result;
  result.exact_rotations = options.exact_rotations;
  result.phase_bins = bins;
  for (int leg = 0; leg < kNumLegs; ++leg) result.leg[leg].saturated_samples = saturated[leg];
  for (int leg = 0; leg < kNumLegs; ++leg) {
    const std::string leg_where = std::string("hanging, leg ") + std::string(kLegNames[leg]) + ": ";
    // Slot of each series for this leg.
    std::array<int, 4> series_of_slot = {-1, -1, -1, -1};
    for (int s = 0; s < kNumHangSeries; ++s) {
      const int slot = SeriesSlot(*by_series[s], g_b[s], X_B_ft[leg], leg, options);
      if (series_of_slot[slot] >= 0) {
        Fail(leg_where + "series " + HangSeriesName(static_cast<HangSeries>(series_of_slot[slot])) +
             " and " + HangSeriesName(static_cast<HangSeries>(s)) + " both have gravity along " +
             SlotName(slot) + " of the transducer");
      }
      series_of_slot[slot] = s;
    }
    for (int slot = 0; slot < 4; ++slot) {
      if (series_of_slot[slot] < 0) {
        Fail(leg_where + "no series has gravity along " + SlotName(slot) + " of the transducer");
      }
    }
    // Bin the four series and match them.
    std::array<BinnedSeries, 4> binned;
    for (int slot = 0; slot < 4; ++slot) {
      const HangingRecording& rec = *by_series[series_of_slot[slot]];
      ValidateSamples(rec.legs[leg], rec.series, leg);
      binned[slot] = BinSeries(rec.legs[leg], rec.series, leg, options);
    }
    std::vector<int> matched_per_bin(bins);
    int covered = 0, cycles_max = 0;
    for (int b = 0; b < bins; ++b) {
      int n_b = binned[0].occurrences[b];
      for (int slot = 1; slot < 4; ++slot) n_b = std::min(n_b, binned[slot].occurrences[b]);
      matched_per_bin[b] = n_b;
      covered += n_b > 0;
      cycles_max = std::max(cycles_max, n_b);
    }
    if (covered < options.min_phase_coverage * bins) {
      int worst = 0, worst_covered = bins + 1;
      for (int slot = 0; slot < 4; ++slot) {
        const int c = static_cast<int>(std::count_if(binned[slot].occurrences.begin(),
                                                     binned[slot].occurrences.end(),
                                                     [](int o) { return o > 0; }));
        if (c < worst_covered) worst_covered = c, worst = slot;
      }
      std::ostringstream s;
      s << Where(by_series[series_of_slot[worst]]->series, leg) << "only " << covered << " of "
        << bins << " phase bins are matched in all four series (this series covers "
        << worst_covered << "): less than one full cycle of phase coverage";
      Fail(s.str());
    }
    LegMatched m;
    {
      size_t total = 0;
      for (int n_b : matched_per_bin) total += n_b;
      for (auto& w : m.w) w.reserve(total);
      m.phase.reserve(total);
      m.bin.reserve(total);
    }
    for (int j = 0; j < cycles_max; ++j) {
      const int begin = static_cast<int>(m.phase.size());
      for (int b = 0; b < bins; ++b) {
        if (j >= matched_per_bin[b]) continue;
        double phase = 0.0;
        for (int slot = 0; slot < 4; ++slot) {
          const BinnedSeries& bs = binned[slot];
          const int cell = bs.lookup[static_cast<size_t>(b) * bs.max_occurrences + j];
          m.w[slot].push_back(bs.cell_wrench[cell]);
          phase += bs.cell_phase[cell];
        }
        m.phase.push_back(phase / 4.0);
        m.bin.push_back(b);
      }
      const int end = static_cast<int>(m.phase.size());
      if (end - begin >= kFullCycleFraction * bins) m.cycles.emplace_back(begin, end);
    }
    if (static_cast<int>(m.cycles.size()) < options.min_cycles) {
      std::ostringstream s;
      s << leg_where << "only " << m.cycles.size()
        << " full cycles are matched across the four series, need at least " << options.min_cycles;
      Fail(s.str());
    }
    const int n = static_cast<int>(m.phase.size());

    const PairData px = MakePair(m, kSlotXDown, kSlotXUp, 0);
    const PairData pz = MakePair(m, kSlotZDown, kSlotZUp, 2);
    LegHangingResult& out = result.leg[leg];

    // Leg CoM: smoother per pair, null space resolved per sample, sinusoid fit.
    const std::vector<Vec3> r_x =
        SmoothLegCom(px.f_minus, px.tau_minus, options.smoother_transition_var_m2,
                     options.smoother_observation_var_nm2);
    const std::vector<Vec3> r_z =
        SmoothLegCom(pz.f_minus, pz.tau_minus, options.smoother_transition_var_m2,
                     options.smoother_observation_var_nm2);
    std::vector<Vec3> r(n);
    for (int i = 0; i < n; ++i) {
      r[i] = ResolveComNullSpace(r_x[i], px.f_minus[i], r_z[i], pz.f_minus[i]);
    }
    auto fit_range = [&](int lo, int hi, LegComModel* model) {
      model->x = FitSinusoidRange(m.phase, lo, hi, [&](int i) { return r[i].x(); });
      model->z = FitSinusoidRange(m.phase, lo, hi, [&](int i) { return r[i].z(); });
      double y = 0.0;
      for (int i = lo; i < hi; ++i) y += r[i].y();
      model->y = y / (hi - lo);
    };
    fit_range(0, n, &out.com.model);
    {
      std::vector<Vec3> cx, cz;
      std::vector<double> cy;
      for (const auto& [lo, hi] : m.cycles) {
        LegComModel c;
        fit_range(lo, hi, &c);
        // Phases relative to the full fit, so a wrap at +-pi does not inflate the spread.
        cx.emplace_back(c.x.a, out.com.model.x.c + WrapPi(c.x.c - out.com.model.x.c), c.x.d);
        cz.emplace_back(c.z.a, out.com.model.z.c + WrapPi(c.z.c - out.com.model.z.c), c.z.d);
        cy.push_back(c.y);
      }
      out.com.sigma_x = StdError3(cx);
      out.com.sigma_z = StdError3(cz);
      out.com.sigma_y_m = StdError(cy);
    }
    // Per-bin median and spread over cycles (Fig. 4/7).
    {
      std::vector<std::vector<int>> samples_of_bin(bins);
      for (int i = 0; i < n; ++i) samples_of_bin[m.bin[i]].push_back(i);
      std::vector<double> c;
      for (int b = 0; b < bins; ++b) {
        const std::vector<int>& idx = samples_of_bin[b];
        if (idx.empty()) continue;
        Vec3 median, sigma;
        for (int k = 0; k < 3; ++k) {
          c.clear();
          for (int i : idx) c.push_back(r[i](k));
          double mean = 0.0;
          for (double v : c) mean += v;
          mean /= c.size();
          double ss = 0.0;
          for (double v : c) ss += (v - mean) * (v - mean);
          // One cycle has no spread to show: NaN rather than a made-up 0.
          sigma(k) = c.size() > 1 ? std::sqrt(ss / (c.size() - 1))
                                  : std::numeric_limits<double>::quiet_NaN();
          std::sort(c.begin(), c.end());
          const size_t h = c.size() / 2;
          median(k) = c.size() % 2 ? c[h] : 0.5 * (c[h - 1] + c[h]);
        }
        out.com_bins.phase.push_back((b + 0.5) / bins);
        out.com_bins.median_m.push_back(median);
        out.com_bins.sigma_m.push_back(sigma);
      }
    }
    std::vector<Vec3> r_fit(n);
    for (int i = 0; i < n; ++i) r_fit[i] = out.com.model.At(m.phase[i]);

    // Both variants and their residuals over every raw sample of the four series.
    std::array<std::vector<Vec3>, 4> com_raw;  // r(phi) at each raw sample, shared by both
    size_t raw_count = 0;
    {
      // r(phi) = LegComModel::At, with one sin/cos of the shaft angle per sample:
      // a sin(theta + c) + d = a (sin theta cos c + cos theta sin c) + d (2 pi phi = theta mod 2
      // pi).
      const LegComModel& com = out.com.model;
      const double xs = com.x.a * std::cos(com.x.c), xc = com.x.a * std::sin(com.x.c);
      const double zs = com.z.a * std::cos(com.z.c), zc = com.z.a * std::sin(com.z.c);
      for (int slot = 0; slot < 4; ++slot) {
        const LegSamples& ls = by_series[series_of_slot[slot]]->legs[leg];
        com_raw[slot].resize(ls.angle_rad.size());
        for (size_t i = 0; i < ls.angle_rad.size(); ++i) {
          const double sn = std::sin(ls.angle_rad[i]), cs = std::cos(ls.angle_rad[i]);
          com_raw[slot][i] = Vec3(xs * sn + xc * cs + com.x.d, com.y, zs * sn + zc * cs + com.z.d);
        }
        raw_count += ls.angle_rad.size();
      }
    }
    std::vector<Vec6> residual;
    residual.reserve(raw_count);
    for (int variant = 0; variant < 2; ++variant) {
      const bool use_s = variant == 0;
      HangingVariant& v = use_s ? out.with_s : out.without_s;
      std::array<PairEstimate, 2> est;
      const std::array<const PairData*, 2> pairs = {&px, &pz};
      for (int p = 0; p < 2; ++p) {
        const int down = series_of_slot[p == 0 ? kSlotXDown : kSlotZDown];
        const int up = series_of_slot[p == 0 ? kSlotXUp : kSlotZUp];
        const std::string where = leg_where + (p == 0 ? "x" : "z") + " pair (" +
                                  HangSeriesName(static_cast<HangSeries>(down)) + ", " +
                                  HangSeriesName(static_cast<HangSeries>(up)) + "): ";
        v.pair[p] = PairResult(*pairs[p], r_fit, m, use_s, options.exact_rotations,
                               options.refine_s_plus, where, &est[p]);
        v.pair[p].down_series = static_cast<HangSeries>(down);
        v.pair[p].up_series = static_cast<HangSeries>(up);
      }
      v.weight_n = Combine(v.pair[0].weight_n, v.pair[1].weight_n);
      v.force_offset_n = Combine(v.pair[0].force_offset_n, v.pair[1].force_offset_n);
      v.torque_offset_nm = Combine(v.pair[0].torque_offset_nm, v.pair[1].torque_offset_nm);
      residual.clear();
      for (int slot = 0; slot < 4; ++slot) {
        const PairEstimate& e = est[slot / 2];
        const Vec3 axis = slot / 2 == 0 ? Vec3::UnitX() : Vec3::UnitZ();
        const bool down = slot % 2 == 0;
        const Vec3 f_leg = (down ? 1.0 : -1.0) * v.weight_n.value *
                           RotApply(down ? e.s_down : e.s_up, axis, options.exact_rotations);
        const LegSamples& ls = by_series[series_of_slot[slot]]->legs[leg];
        for (size_t i = 0; i < ls.t_s.size(); ++i) {
          Vec6 model;
          model << f_leg + v.force_offset_n.value,
              com_raw[slot][i].cross(f_leg) + v.torque_offset_nm.value;
          residual.push_back(ls.wrench[i] - model);
        }
      }
      v.residual =
          Stats(std::string(kLegNames[leg]) + (use_s ? " with s" : " without s"), residual);
    }

    // Naive tare: the upright reading near theta = 0, no leg gravity model.
    {
      const LegSamples& ls = by_series[upright]->legs[leg];
      Vec6 sum = Vec6::Zero();
      int count = 0;
      for (size_t i = 0; i < ls.t_s.size(); ++i) {
        if (std::abs(WrapPi(ls.angle_rad[i])) <= options.naive_tare_max_angle_rad) {
          sum += ls.wrench[i];
          ++count;
        }
      }
      if (count == 0) {
        std::ostringstream s;
        s << Where(by_series[upright]->series, leg) << "no sample within "
          << options.naive_tare_max_angle_rad * kRadToDeg << " deg of theta = 0 for the naive tare";
        Fail(s.str());
      }
      out.naive_offset = sum / count;
      residual.clear();
      for (int s = 0; s < kNumHangSeries; ++s) {
        for (const Vec6& w : by_series[s]->legs[leg].wrench)
          residual.push_back(w - out.naive_offset);
      }
      out.naive_residual = Stats(std::string(kLegNames[leg]) + " naive tare", residual);
    }

    if (has_attitude) {
      for (int s = 0; s < kNumHangSeries; ++s) {
        result.gravity_observations.push_back(
            GravityObservation(*by_series[s], leg, X_B_ft[leg], out.with_s.force_offset_n));
      }
    }
  }
  return result;
}

// ---------------------------------------------------------------- outputs

void ApplyHangingResult(const HangingResult& result, RobotCalibration* cal) {
  for (int k = 0; k < kNumLegs; ++k) {
    cal->leg[k].offset = result.leg[k].with_s.Offset();
    cal->leg[k].weight_n = result.leg[k].with_s.weight_n.value;
    cal->leg[k].com = result.leg[k].com.model;
  }
}

namespace {

void SetVec3(const Vec3Sigma& v, calibration::Vec3Estimate* out) {
  out->set_x(v.value.x());
  out->set_y(v.value.y());
  out->set_z(v.value.z());
  out->set_sigma_x(v.sigma.x());
  out->set_sigma_y(v.sigma.y());
  out->set_sigma_z(v.sigma.z());
}

void SetScalar(const ScalarSigma& v, calibration::ScalarEstimate* out) {
  out->set_value(v.value);
  out->set_sigma(v.sigma);
}

void SetSinusoid(const SinusoidFit& fit, const Vec3& sigma, calibration::SinusoidFit* out) {
  out->set_a_m(fit.a);
  out->set_c_rad(fit.c);
  out->set_d_m(fit.d);
  out->set_sigma_a_m(sigma(0));
  out->set_sigma_c_rad(sigma(1));
  out->set_sigma_d_m(sigma(2));
}

void SetStats(const WrenchResidualStats& s, calibration::ResidualStats* out) {
  out->set_label(s.label);
  out->set_count(static_cast<uint32_t>(s.count));
  for (int k = 0; k < 6; ++k) {
    out->add_mean(s.mean(k));
    out->add_std(s.std(k));
    out->add_rms(s.rms(k));
    out->add_p05(s.p05(k));
    out->add_p95(s.p95(k));
  }
}

}  // namespace

void WriteHangingToCalibration(const HangingResult& result, calibration::Calibration* out) {
  out->set_hanging_uncertainty(calibration::CYCLE_SPREAD);
  out->mutable_solver()->set_exact_hanging_rotations(result.exact_rotations);
  out->clear_hanging_residual();
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string name(kLegNames[k]);
    calibration::LegCalibration* leg = nullptr;
    for (auto& l : *out->mutable_leg()) {
      if (l.name() == name) leg = &l;
    }
    if (leg == nullptr) {
      leg = out->add_leg();
      leg->set_name(name);
    }
    const LegHangingResult& r = result.leg[k];
    SetVec3(r.with_s.force_offset_n, leg->mutable_force_offset_n());
    SetVec3(r.with_s.torque_offset_nm, leg->mutable_torque_offset_nm());
    SetScalar(r.with_s.weight_n, leg->mutable_leg_weight_n());
    calibration::LegCom* com = leg->mutable_com();
    com->Clear();
    SetSinusoid(r.com.model.x, r.com.sigma_x, com->mutable_x());
    SetSinusoid(r.com.model.z, r.com.sigma_z, com->mutable_z());
    SetScalar({r.com.model.y, r.com.sigma_y_m}, com->mutable_y_m());
    for (size_t b = 0; b < r.com_bins.phase.size(); ++b) {
      com->add_bin_phase(r.com_bins.phase[b]);
      com->add_bin_x_m(r.com_bins.median_m[b].x());
      com->add_bin_y_m(r.com_bins.median_m[b].y());
      com->add_bin_z_m(r.com_bins.median_m[b].z());
      com->add_bin_sigma_x_m(r.com_bins.sigma_m[b].x());
      com->add_bin_sigma_y_m(r.com_bins.sigma_m[b].y());
      com->add_bin_sigma_z_m(r.com_bins.sigma_m[b].z());
    }
    leg->clear_hanging();
    for (const HangingPairResult& p : r.with_s.pair) {
      calibration::HangingPair* hp = leg->add_hanging();
      hp->set_axis(std::string(1, p.axis));
      SetVec3(p.s_plus_rad, hp->mutable_s_plus_rad());
      SetVec3(p.s_minus_rad, hp->mutable_s_minus_rad());
      SetScalar(p.weight_n, hp->mutable_leg_weight_n());
      SetVec3(p.force_offset_n, hp->mutable_force_offset_n());
      SetVec3(p.torque_offset_nm, hp->mutable_torque_offset_nm());
      hp->set_matched_samples(static_cast<uint32_t>(p.matched_samples));
    }
    leg->clear_naive_offset();
    for (int i = 0; i < 6; ++i) leg->add_naive_offset(r.naive_offset(i));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    SetStats(result.leg[k].with_s.residual, out->add_hanging_residual());
    SetStats(result.leg[k].without_s.residual, out->add_hanging_residual());
    SetStats(result.leg[k].naive_residual, out->add_hanging_residual());
  }
}

}  // namespace ftcal
