// The leg CoM of step 1 (docs/method.md "Step 1"): tau- = -[f-] r per matched sample, smoothed
// over the samples of each pair (Kalman filter + RTS smoother, random-walk r), the null space
// r + p f- of each sample resolved between the x and z pairs, and the sinusoid fit
// r_x, r_z = A sin(2 pi phi + C) + D, r_y = const, with its sigmas from the per-cycle fits and
// the per-bin medians the report plots (Fig. 4/7).
#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>

#include <Eigen/Cholesky>

#include "hanging_internal.h"

namespace ftcal {

using hanging_detail::kTwoPi;
using hanging_detail::OrthonormalComplement;

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

namespace hanging_detail {

std::vector<Vec3> ResolveLegCom(const PairData& px, const PairData& pz,
                                const HangingOptions& options) {
  const int n = static_cast<int>(px.f_minus.size());
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
  return r;
}

namespace {

// The CoM model on the matched samples [lo, hi): sinusoids in x and z, the mean in y.
void FitRange(const LegMatched& m, const std::vector<Vec3>& r, int lo, int hi, LegComModel* model) {
  model->x = FitSinusoidRange(m.phase, lo, hi, [&](int i) { return r[i].x(); });
  model->z = FitSinusoidRange(m.phase, lo, hi, [&](int i) { return r[i].z(); });
  double y = 0.0;
  for (int i = lo; i < hi; ++i) y += r[i].y();
  model->y = y / (hi - lo);
}

}  // namespace

ComFitResult FitLegCom(const LegMatched& m, const std::vector<Vec3>& r) {
  const int n = static_cast<int>(m.phase.size());
  ComFitResult com;
  FitRange(m, r, 0, n, &com.model);
  std::vector<Vec3> cx, cz;
  std::vector<double> cy;
  for (const auto& [lo, hi] : m.cycles) {
    LegComModel c;
    FitRange(m, r, lo, hi, &c);
    // Phases relative to the full fit, so a wrap at +-pi does not inflate the spread.
    cx.emplace_back(c.x.a, com.model.x.c + WrapPi(c.x.c - com.model.x.c), c.x.d);
    cz.emplace_back(c.z.a, com.model.z.c + WrapPi(c.z.c - com.model.z.c), c.z.d);
    cy.push_back(c.y);
  }
  com.sigma_x = StdError3(cx);
  com.sigma_z = StdError3(cz);
  com.sigma_y_m = StdError(cy);
  return com;
}

ComBins BinLegCom(const LegMatched& m, const std::vector<Vec3>& r, int bins) {
  const int n = static_cast<int>(m.phase.size());
  ComBins out;
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
      sigma(k) =
          c.size() > 1 ? std::sqrt(ss / (c.size() - 1)) : std::numeric_limits<double>::quiet_NaN();
      std::sort(c.begin(), c.end());
      const size_t h = c.size() / 2;
      median(k) = c.size() % 2 ? c[h] : 0.5 * (c[h - 1] + c[h]);
    }
    out.phase.push_back((b + 0.5) / bins);
    out.median_m.push_back(median);
    out.sigma_m.push_back(sigma);
  }
  return out;
}

}  // namespace hanging_detail
}  // namespace ftcal
