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
//
// This file runs the step (RunHanging) and checks its input; the phase matching is in
// hanging_match.cc, the pair equations (s+, m g, s-, offsets) in hanging_pair.cc, the leg CoM
// (smoother, null space, sinusoid fit) in leg_com.cc, the calibration-file output in
// hanging_output.cc. Their shared declarations: hanging_internal.h.
#include "ftcal/hanging.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>

#include "hanging_internal.h"
#include "parallel.h"

namespace ftcal {
namespace hanging_detail {

std::string Where(HangSeries series, int leg) {
  std::ostringstream s;
  s << "hanging series " << HangSeriesName(series) << ", leg " << kLegNames[leg] << ": ";
  return s.str();
}

[[noreturn]] void Fail(const std::string& what) { throw std::invalid_argument(what); }

std::string LegWhere(int leg) {
  return std::string("hanging, leg ") + std::string(kLegNames[leg]) + ": ";
}

}  // namespace hanging_detail

using hanging_detail::BinLegCom;
using hanging_detail::Combine;
using hanging_detail::Fail;
using hanging_detail::FitLegCom;
using hanging_detail::kRadToDeg;
using hanging_detail::kSlotXDown;
using hanging_detail::kSlotXUp;
using hanging_detail::kSlotZDown;
using hanging_detail::kSlotZUp;
using hanging_detail::LegMatched;
using hanging_detail::LegWhere;
using hanging_detail::MakePair;
using hanging_detail::MatchLeg;
using hanging_detail::PairData;
using hanging_detail::PairEstimate;
using hanging_detail::PairResult;
using hanging_detail::PairSolve;
using hanging_detail::ResolveLegCom;
using hanging_detail::RotApply;
using hanging_detail::StudentWidening;
using hanging_detail::Where;
using hanging_detail::WrapPi;

// ---------------------------------------------------------------- names and options

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

namespace {

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

// force_offset's sigma carries step 1's Student-t widening (`widening`, StdError): the prior
// weighs by the spread itself, not by the interval the report states.
HangingGravityObservation GravityObservation(const HangingRecording& rec, int leg,
                                             const Pose3& X_B_ft, const Vec3Sigma& force_offset,
                                             double widening) {
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
  const double sigma_offset = force_offset.sigma.norm() / widening / std::sqrt(3.0) / f_mean.norm();
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

// ---------------------------------------------------------------- the step, in named parts

using SeriesArray = std::array<const HangingRecording*, kNumHangSeries>;

// Exactly one recording per series.
SeriesArray OneRecordingPerSeries(const std::vector<HangingRecording>& recordings) {
  SeriesArray by_series{};
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
  return by_series;
}

// Saturated samples (beyond the rated range) out, counted per leg: a copy only of the
// recordings that have any, kept in *unsaturated (reserved up front, so *by_series can point
// into it).
std::array<int, kNumLegs> LeaveOutSaturated(const HangingOptions& options, SeriesArray* by_series,
                                            std::vector<HangingRecording>* unsaturated) {
  std::array<int, kNumLegs> saturated{};
  unsaturated->reserve(kNumHangSeries);
  for (int s = 0; s < kNumHangSeries; ++s) {
    const HangingRecording& rec = *(*by_series)[s];
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
    unsaturated->push_back(std::move(copy));
    (*by_series)[s] = &unsaturated->back();
  }
  return saturated;
}

// Slot of each series for one leg: which transducer axis each has along gravity, each slot
// taken exactly once.
std::array<int, 4> SlotsOfLeg(const SeriesArray& by_series,
                              const std::array<Vec3, kNumHangSeries>& g_b, const Pose3& X_B_ft,
                              int leg, const HangingOptions& options) {
  const std::string leg_where = LegWhere(leg);
  std::array<int, 4> series_of_slot = {-1, -1, -1, -1};
  for (int s = 0; s < kNumHangSeries; ++s) {
    const int slot = SeriesSlot(*by_series[s], g_b[s], X_B_ft, leg, options);
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
  return series_of_slot;
}

// r(phi) of the fitted CoM at every raw sample of the four series (by slot), shared by both
// variants' residuals. LegComModel::At with one sin/cos of the shaft angle per sample:
// a sin(theta + c) + d = a (sin theta cos c + cos theta sin c) + d (2 pi phi = theta mod 2 pi).
std::array<std::vector<Vec3>, 4> ComAtRawSamples(const LegComModel& com,
                                                 const SeriesArray& by_series,
                                                 const std::array<int, 4>& series_of_slot,
                                                 int leg) {
  std::array<std::vector<Vec3>, 4> com_raw;
  const double xs = com.x.a * std::cos(com.x.c), xc = com.x.a * std::sin(com.x.c);
  const double zs = com.z.a * std::cos(com.z.c), zc = com.z.a * std::sin(com.z.c);
  for (int slot = 0; slot < 4; ++slot) {
    const LegSamples& ls = by_series[series_of_slot[slot]]->legs[leg];
    com_raw[slot].resize(ls.angle_rad.size());
    for (size_t i = 0; i < ls.angle_rad.size(); ++i) {
      const double sn = std::sin(ls.angle_rad[i]), cs = std::cos(ls.angle_rad[i]);
      com_raw[slot][i] = Vec3(xs * sn + xc * cs + com.x.d, com.y, zs * sn + zc * cs + com.z.d);
    }
  }
  return com_raw;
}

// One leg's inputs to the pair solves, as RunHanging has them at that point.
struct LegPairs {
  int leg = 0;
  const SeriesArray* by_series = nullptr;
  std::array<int, 4> series_of_slot{};
  const LegMatched* matched = nullptr;
  std::array<const PairData*, 2> pairs{};                     // x pair, z pair
  const std::vector<Vec3>* r_fit = nullptr;                   // fitted CoM at each matched sample
  const std::array<std::vector<Vec3>, 4>* com_raw = nullptr;  // fitted CoM at each raw sample
};

// The report's two hanging variants: the mounting rotation s estimated, or taken as zero.
enum class Variant { kWithS, kWithoutS };

// One variant of a leg: both pairs, their inverse-variance combination, and the residual over
// every raw sample of the four series (report Fig. 5).

HangingVariant SolveVariant(const LegPairs& in, Variant variant, const HangingOptions& options) {
  const bool use_s = variant == Variant::kWithS;
  const int leg = in.leg;
  const SeriesArray& by_series = *in.by_series;
  const std::array<int, 4>& series_of_slot = in.series_of_slot;
  const std::string leg_where = LegWhere(leg);
  HangingVariant v;
  std::array<PairEstimate, 2> est;
  for (int p = 0; p < 2; ++p) {
    const int down = series_of_slot[p == 0 ? kSlotXDown : kSlotZDown];
    const int up = series_of_slot[p == 0 ? kSlotXUp : kSlotZUp];
    const std::string where = leg_where + (p == 0 ? "x" : "z") + " pair (" +
                              HangSeriesName(static_cast<HangSeries>(down)) + ", " +
                              HangSeriesName(static_cast<HangSeries>(up)) + "): ";
    PairSolve how;
    how.use_s = use_s;
    how.exact_rotations = options.exact_rotations;
    how.refine_s_plus = options.refine_s_plus;
    v.pair[p] = PairResult(*in.pairs[p], *in.r_fit, *in.matched, how, where, &est[p]);
    v.pair[p].down_series = static_cast<HangSeries>(down);
    v.pair[p].up_series = static_cast<HangSeries>(up);
  }
  v.weight_n = Combine(v.pair[0].weight_n, v.pair[1].weight_n);
  v.force_offset_n = Combine(v.pair[0].force_offset_n, v.pair[1].force_offset_n);
  v.torque_offset_nm = Combine(v.pair[0].torque_offset_nm, v.pair[1].torque_offset_nm);
  std::vector<Vec6> residual;
  size_t samples = 0;
  for (int slot = 0; slot < 4; ++slot) samples += (*in.com_raw)[slot].size();
  residual.reserve(samples);  // once: a reserve per slot reallocated (and copied) each time
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
          (*in.com_raw)[slot][i].cross(f_leg) + v.torque_offset_nm.value;
      residual.push_back(ls.wrench[i] - model);
    }
  }
  v.residual = Stats(std::string(kLegNames[leg]) + (use_s ? " with s" : " without s"), residual);
  return v;
}

// Naive tare: the upright reading near theta = 0, no leg gravity model; its residual over every
// sample of the four series.
void NaiveTare(const SeriesArray& by_series, int upright, int leg, const HangingOptions& options,
               LegHangingResult* out) {
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
  out->naive_offset = sum / count;
  std::vector<Vec6> residual;
  size_t samples = 0;
  for (int s = 0; s < kNumHangSeries; ++s) samples += by_series[s]->legs[leg].wrench.size();
  residual.reserve(samples);
  for (int s = 0; s < kNumHangSeries; ++s) {
    for (const Vec6& w : by_series[s]->legs[leg].wrench) residual.push_back(w - out->naive_offset);
  }
  out->naive_residual = Stats(std::string(kLegNames[leg]) + " naive tare", residual);
}

}  // namespace

// ---------------------------------------------------------------- the step

// Step 1 as docs/method.md states it: per leg, the four series matched at equal leg phase; the
// CoM from the pairs' torque half-differences; each pair's s+, m g, s- and offsets, the two
// pairs combined; the baselines beside them.
HangingResult RunHanging(const std::vector<HangingRecording>& recordings,
                         const std::array<Pose3, kNumLegs>& X_B_ft, const HangingOptions& options) {
  ValidateOptions(options);
  SeriesArray by_series = OneRecordingPerSeries(recordings);
  std::vector<HangingRecording> unsaturated;
  const std::array<int, kNumLegs> saturated = LeaveOutSaturated(options, &by_series, &unsaturated);
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

  HangingResult result;
  result.exact_rotations = options.exact_rotations;
  result.phase_bins = options.phase_bins;
  for (int leg = 0; leg < kNumLegs; ++leg) result.leg[leg].saturated_samples = saturated[leg];
  // The legs are independent: each on a worker of its own (parallel.h). A leg that fails
  // throws; the first in leg order is the one reported, as when they ran one after another.
  std::array<std::vector<HangingGravityObservation>, kNumLegs> observations;
  ParallelFor(kNumLegs, [&](size_t leg_index) {
    const int leg = static_cast<int>(leg_index);
    LegHangingResult& out = result.leg[leg];
    const std::array<int, 4> series_of_slot = SlotsOfLeg(by_series, g_b, X_B_ft[leg], leg, options);
    const LegMatched m = MatchLeg(by_series, series_of_slot, leg, options);
    const PairData px = MakePair(m, kSlotXDown, kSlotXUp, 0);
    const PairData pz = MakePair(m, kSlotZDown, kSlotZUp, 2);

    const std::vector<Vec3> r = ResolveLegCom(px, pz, options);
    out.com = FitLegCom(m, r);
    out.com_bins = BinLegCom(m, r, options.phase_bins);
    std::vector<Vec3> r_fit(m.phase.size());
    for (size_t i = 0; i < r_fit.size(); ++i) r_fit[i] = out.com.model.At(m.phase[i]);
    const std::array<std::vector<Vec3>, 4> com_raw =
        ComAtRawSamples(out.com.model, by_series, series_of_slot, leg);

    const LegPairs pairs{leg, &by_series, series_of_slot, &m, {&px, &pz}, &r_fit, &com_raw};
    out.with_s = SolveVariant(pairs, Variant::kWithS, options);
    out.without_s = SolveVariant(pairs, Variant::kWithoutS, options);
    NaiveTare(by_series, upright, leg, options, &out);

    if (has_attitude) {
      for (int s = 0; s < kNumHangSeries; ++s) {
        observations[leg].push_back(
            GravityObservation(*by_series[s], leg, X_B_ft[leg], out.with_s.force_offset_n,
                               StudentWidening(static_cast<int>(m.cycles.size()))));
      }
    }
  });
  for (const auto& leg_observations : observations) {
    result.gravity_observations.insert(result.gravity_observations.end(), leg_observations.begin(),
                                       leg_observations.end());
  }
  return result;
}

}  // namespace ftcal
