// The servo-vs-transducer delay from the hanging series (latency.h states the model).
#include "ftcal/latency.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>

#include <Eigen/Dense>
#include <ceres/ceres.h>

#include "ftcal/legs.h"
#include "hanging_internal.h"

namespace ftcal {
namespace {

using hanging_detail::kTwoPi;
using hanging_detail::WrapPi;
// Gaussian noise passes 6 robust scales once in 5e8 samples.
constexpr double kOutlierScales = 6.0;

std::string Where(const HangingRecording& r, int leg) {
  return std::string("servo delay: hanging series ") + HangSeriesName(r.series) + ", leg " +
         std::string(kLegNames[static_cast<size_t>(leg)]) + ": ";
}

// The shaft angle unwrapped along the series (the bridge wraps it to (-pi, pi]).
std::vector<double> Unwrap(const std::vector<double>& a) {
  std::vector<double> out(a.size());
  for (size_t i = 0; i < a.size(); ++i)
    out[i] = i == 0 ? a[0] : out[i - 1] + WrapPi(a[i] - a[i - 1]);
  return out;
}

// One leg in one series: the regressors, the torque, and the scale of each torque component
// (its rms misfit at tau = 0) so that legs and series of different noise weigh alike.
struct Group {
  Eigen::VectorXd theta, omega;
  Eigen::MatrixXd y;  // n x 3, scaled
  int harmonics = 0;
  int Coefficients() const { return 2 * harmonics + 1; }
  long n() const { return theta.size(); }
};

// Fourier basis [1, sin(h phi), cos(h phi)...] of phi = theta + tau omega, and its derivative in
// tau, row by row.
void Basis(const Group& g, double tau, Eigen::MatrixXd* B, Eigen::MatrixXd* dB) {
  const long n = g.n();
  const int p = g.Coefficients();
  B->resize(n, p);
  if (dB != nullptr) dB->resize(n, p);
  for (long i = 0; i < n; ++i) {
    const double phi = g.theta[i] + tau * g.omega[i];
    (*B)(i, 0) = 1.0;
    if (dB != nullptr) (*dB)(i, 0) = 0.0;
    for (int h = 1; h <= g.harmonics; ++h) {
      const double s = std::sin(h * phi), c = std::cos(h * phi);
      (*B)(i, 2 * h - 1) = s;
      (*B)(i, 2 * h) = c;
      if (dB != nullptr) {
        (*dB)(i, 2 * h - 1) = h * g.omega[i] * c;
        (*dB)(i, 2 * h) = -h * g.omega[i] * s;
      }
    }
  }
}

// Variable projection: for a given tau the coefficients are the linear least-squares solution,
// the residual is the part of y outside the basis' span, and its derivative in tau (Kaufman's
// form) is minus the part of dB C outside that span.
void Project(const Group& g, double tau, Eigen::MatrixXd* residual, Eigen::MatrixXd* jacobian) {
  Eigen::MatrixXd B, dB;
  Basis(g, tau, &B, jacobian != nullptr ? &dB : nullptr);
  const Eigen::MatrixXd G = B.transpose() * B;
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(G);
  const Eigen::MatrixXd C = ldlt.solve(B.transpose() * g.y);
  *residual = g.y - B * C;
  if (jacobian != nullptr) {
    const Eigen::MatrixXd V = dB * C;
    *jacobian = -(V - B * ldlt.solve(B.transpose() * V));
  }
}

class GroupCost final : public ceres::CostFunction {
 public:
  explicit GroupCost(const Group* g) : g_(g) {
    set_num_residuals(static_cast<int>(3 * g->n()));
    mutable_parameter_block_sizes()->push_back(1);
  }
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const bool want_j = jacobians != nullptr && jacobians[0] != nullptr;
    Eigen::MatrixXd r, j;
    Project(*g_, parameters[0][0], &r, want_j ? &j : nullptr);
    Eigen::Map<Eigen::MatrixXd>(residuals, g_->n(), 3) = r;
    if (want_j) Eigen::Map<Eigen::MatrixXd>(jacobians[0], g_->n(), 3) = j;
    return true;
  }

 private:
  const Group* g_;
};

double Rss(const std::vector<Group>& groups, double tau) {
  double rss = 0.0;
  for (const Group& g : groups) {
    Eigen::MatrixXd r;
    Project(g, tau, &r, nullptr);
    rss += r.squaredNorm();
  }
  return rss;
}

// tau minimising the summed residual over `groups` (Ceres, trust region), and its covariance
// (unit weights: the caller scales it).
double Solve(const std::vector<const Group*>& groups, double bound, double* variance) {
  double tau = 0.0;
  ceres::Problem problem;
  for (const Group* g : groups) problem.AddResidualBlock(new GroupCost(g), nullptr, &tau);
  problem.SetParameterLowerBound(&tau, 0, -bound);
  problem.SetParameterUpperBound(&tau, 0, bound);
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_NORMAL_CHOLESKY;
  options.max_num_iterations = 50;
  options.function_tolerance = 1e-12;
  options.parameter_tolerance = 1e-12;
  options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  if (variance != nullptr) {
    *variance = std::numeric_limits<double>::quiet_NaN();
    ceres::Covariance::Options co;
    co.algorithm_type = ceres::DENSE_SVD;
    ceres::Covariance covariance(co);
    std::vector<std::pair<const double*, const double*>> blocks{{&tau, &tau}};
    if (covariance.Compute(blocks, &problem)) covariance.GetCovarianceBlock(&tau, &tau, variance);
  }
  return tau;
}

}  // namespace

double HangSweepAngle(double t_s, double cycle_s, int cycles, double depth) {
  const double duration = cycles * cycle_s;
  const double t = std::clamp(t_s, 0.0, duration);
  const double rate = kTwoPi / cycle_s;
  // A whole number of modulation periods in the sweep, about 1.5 per cycle: cycles j and j + 1
  // pass each angle at different speeds.
  const int periods = std::max(1, (3 * cycles + 1) / 2);
  const double w = kTwoPi * periods / duration;
  return rate * t + depth * rate / w * (1.0 - std::cos(w * t));
}

double HangSweepPeakRate(double cycle_s, double depth) { return (1.0 + depth) * kTwoPi / cycle_s; }

ServoDelayEstimate EstimateServoDelay(const std::vector<HangingRecording>& recordings,
                                      const ServoDelayOptions& options) {
  if (options.harmonics < 1 || options.harmonics > 20) {
    throw std::invalid_argument("servo delay: harmonics must be in [1, 20], got " +
                                std::to_string(options.harmonics));
  }
  if (!(options.derivative_window_s > 0.0) || !(options.max_delay_s > 0.0)) {
    throw std::invalid_argument("servo delay: derivative_window_s and max_delay_s must be > 0");
  }
  std::vector<Group> groups;
  for (const HangingRecording& rec : recordings) {
    for (int k = 0; k < kNumLegs; ++k) {
      const LegSamples& s = rec.legs[static_cast<size_t>(k)];
      const size_t n = s.t_s.size();
      if (s.angle_rad.size() != n || s.wrench.size() != n) {
        throw std::invalid_argument(Where(rec, k) + "times, angles and wrenches differ in length");
      }
      Group g;
      g.harmonics = options.harmonics;
      // Too short to say anything.
      if (n < 20 * static_cast<size_t>(g.Coefficients())) continue;
      for (size_t i = 0; i < n; ++i) {
        if (!std::isfinite(s.t_s[i]) || !std::isfinite(s.angle_rad[i]) ||
            !s.wrench[i].allFinite()) {
          throw std::invalid_argument(Where(rec, k) + "sample " + std::to_string(i) +
                                      " is not finite");
        }
        if (i > 0 && !(s.t_s[i] > s.t_s[i - 1])) {
          throw std::invalid_argument(Where(rec, k) + "sample " + std::to_string(i) +
                                      " does not follow the previous one in time");
        }
      }
      const std::vector<double> theta = Unwrap(s.angle_rad);
      const double dt = (s.t_s.back() - s.t_s.front()) / static_cast<double>(n - 1);
      const long half = std::max(1L, std::lround(0.5 * options.derivative_window_s / dt));
      g.theta.resize(static_cast<long>(n));
      g.omega.resize(static_cast<long>(n));
      g.y.resize(static_cast<long>(n), 3);
      for (long i = 0; i < static_cast<long>(n); ++i) {
        const auto lo = static_cast<size_t>(std::max(0L, i - half));
        const auto hi = static_cast<size_t>(std::min(static_cast<long>(n) - 1, i + half));
        g.theta[i] = theta[static_cast<size_t>(i)];
        g.omega[i] = (theta[hi] - theta[lo]) / (s.t_s[hi] - s.t_s[lo]);
        g.y.row(i) = s.wrench[static_cast<size_t>(i)].tail<3>().transpose();
      }
      // A stray sample (one from another series that the aligner completed late, a glitch)
      // would outweigh thousands: samples beyond kOutlierScales robust scales (1.4826 MAD of
      // the misfit at tau = 0) in any component are left out.
      Eigen::MatrixXd r;
      Project(g, 0.0, &r, nullptr);
      std::vector<bool> keep(static_cast<size_t>(g.n()), true);
      for (int c = 0; c < 3; ++c) {
        std::vector<double> a(static_cast<size_t>(g.n()));
        for (long i = 0; i < g.n(); ++i) a[static_cast<size_t>(i)] = std::abs(r(i, c));
        std::nth_element(a.begin(), a.begin() + static_cast<long>(a.size() / 2), a.end());
        const double scale = 1.4826 * a[a.size() / 2];
        for (long i = 0; i < g.n(); ++i) {
          if (std::abs(r(i, c)) > kOutlierScales * scale) keep[static_cast<size_t>(i)] = false;
        }
      }
      long kept = 0;
      for (long i = 0; i < g.n(); ++i) {
        if (!keep[static_cast<size_t>(i)]) continue;
        g.theta[kept] = g.theta[i];
        g.omega[kept] = g.omega[i];
        g.y.row(kept) = g.y.row(i);
        ++kept;
      }
      g.theta.conservativeResize(kept);
      g.omega.conservativeResize(kept);
      g.y.conservativeResize(kept, 3);
      if (kept < 20 * g.Coefficients()) continue;
      // Each component scaled by its own misfit at tau = 0.
      Project(g, 0.0, &r, nullptr);
      const double dof = static_cast<double>(g.n() - g.Coefficients());
      for (int c = 0; c < 3; ++c) {
        const double scale = std::sqrt(r.col(c).squaredNorm() / dof);
        g.y.col(c) /= std::max(scale, 1e-12);
      }
      groups.push_back(std::move(g));
    }
  }
  ServoDelayEstimate out;
  out.groups = static_cast<int>(groups.size());
  if (groups.size() < 2) return out;
  std::vector<const Group*> all;
  for (const Group& g : groups) {
    all.push_back(&g);
    out.residuals += 3 * g.n();
    out.parameters_without += 3 * g.Coefficients();
  }
  double variance = 0.0;
  out.delay_s = Solve(all, options.max_delay_s, &variance);
  out.rss_without = Rss(groups, 0.0);
  out.rss_with = Rss(groups, out.delay_s);
  const auto N = static_cast<double>(out.residuals);
  const double p0 = out.parameters_without;
  out.bic_without = N * std::log(out.rss_without / N) + p0 * std::log(N);
  out.bic_with = N * std::log(out.rss_with / N) + (p0 + 1.0) * std::log(N);
  out.delta_bic = out.bic_with - out.bic_without;
  out.selected = out.delta_bic < 0.0;
  // The covariance assumes unit-variance residuals: scale by the reduced chi^2.
  const double chi2 = out.rss_with / (N - p0 - 1.0);
  out.sigma_covariance_s = std::sqrt(std::max(0.0, variance * chi2));
  // Each leg and series alone: their spread covers what the shared model misses (a leg's own
  // transducer latency, a misfit of the torque model).
  std::vector<double> each;
  each.reserve(all.size());
  for (const Group* g : all) each.push_back(Solve({g}, options.max_delay_s, nullptr));
  out.group_delay_s = each;
  double mean = 0.0;
  for (double v : each) mean += v;
  mean /= static_cast<double>(each.size());
  double ss = 0.0;
  for (double v : each) ss += (v - mean) * (v - mean);
  out.sigma_spread_s =
      std::sqrt(ss / static_cast<double>(each.size() - 1) / static_cast<double>(each.size()));
  out.sigma_s = std::max(out.sigma_covariance_s, out.sigma_spread_s);
  out.estimated = std::isfinite(out.delay_s) && std::isfinite(out.sigma_s);
  if (!out.estimated) out.selected = false;
  return out;
}

std::vector<HangingRecording> ShiftServoAngles(const std::vector<HangingRecording>& recordings,
                                               double delay_s) {
  std::vector<HangingRecording> out = recordings;
  for (HangingRecording& rec : out) {
    for (LegSamples& s : rec.legs) {
      const size_t n = s.t_s.size();
      if (n < 2 || s.angle_rad.size() != n) continue;
      const std::vector<double> theta = Unwrap(s.angle_rad);
      size_t j = 0;  // t_s[j] <= target < t_s[j + 1] as far as the ends allow
      for (size_t i = 0; i < n; ++i) {
        const double target = s.t_s[i] + delay_s;
        while (j + 2 < n && s.t_s[j + 1] <= target) ++j;
        while (j > 0 && s.t_s[j] > target) --j;
        const double alpha = (target - s.t_s[j]) / (s.t_s[j + 1] - s.t_s[j]);
        s.angle_rad[i] = WrapPi(theta[j] + alpha * (theta[j + 1] - theta[j]));
      }
    }
  }
  return out;
}

}  // namespace ftcal
