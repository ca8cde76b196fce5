#include "ftcal/offset_tracker.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

namespace ftcal {
namespace {

double WrapToPi(double a) { return a - 2.0 * M_PI * std::floor((a + M_PI) / (2.0 * M_PI)); }

int64_t FloorDiv(int64_t a, int64_t b) { return a / b - ((a % b != 0) && ((a < 0) != (b < 0))); }

void Require(bool ok, const std::string& what) {
  if (!ok) throw std::invalid_argument("offset tracker: " + what);
}

int64_t Us(double s) { return static_cast<int64_t>(std::llround(s * 1e6)); }

bool Hanging(ExperimentPhase p) {
  return p == ExperimentPhase::kHangXPos || p == ExperimentPhase::kHangXNeg ||
         p == ExperimentPhase::kHangZPos || p == ExperimentPhase::kHangZNeg ||
         p == ExperimentPhase::kTare;
}

constexpr int kAllLegs = (1 << kNumLegs) - 1;
// Bin instants kept waiting for a silent leg's bin before they are given up (bins).
constexpr int64_t kMaxSlotLag = 200;
constexpr size_t kMocapHistory = 512;

// The unloaded reading given X_C_ft (see UnloadedReading): the leg's weight in ft_k and its
// moment about the transducer's origin, r_k(phi) being in ft_k already.
Vec6 Unloaded(const Pose3& X_C_ft, const LegCalibration& leg, double angle_rad, const Mat3& R_WC,
              double g0) {
  const Vec3 f_ft = X_C_ft.R.transpose() * (leg.weight_n / g0 * GravityInC(R_WC, g0));
  Vec6 w;
  w << f_ft, leg.com.At(LegPhase(angle_rad)).cross(f_ft);
  return w;
}

}  // namespace

double BalanceStats::ForceRmsN(int tracked) const {
  return count > 0 ? std::sqrt(sq_force[tracked] / static_cast<double>(count)) : 0.0;
}
double BalanceStats::TorqueRmsNm(int tracked) const {
  return count > 0 ? std::sqrt(sq_torque[tracked] / static_cast<double>(count)) : 0.0;
}
void BalanceStats::Add(const BalanceStats& o) {
  count += o.count;
  for (int i = 0; i < 2; ++i) {
    sq_force[i] += o.sq_force[i];
    sq_torque[i] += o.sq_torque[i];
  }
}

Vec6 UnloadedReading(const RobotCalibration& cal, int k, double angle_rad, const Mat3& R_WC) {
  return Unloaded(cal.X_C_ft(k), cal.leg[k], angle_rad, R_WC, cal.g0);
}

int DriftBeyondCalibration(const LegDrift& d, const Vec6& calibration_sigma, double factor,
                           const Vec6& min_change) {
  int bits = 0;
  for (int i = 0; i < 6; ++i) {
    const double limit = std::max(factor * calibration_sigma[i], min_change[i]);
    const double a = std::abs(d.change[i]);
    if (a > limit && a > 3.0 * d.sigma[i]) bits |= 1 << i;
  }
  return bits;
}

int DriftSignificant(const LegDrift& d, const Vec6& calibration_sigma, double factor,
                     const Vec6& min_change) {
  int bits = 0;
  for (int i = 0; i < 6; ++i) {
    const double a = std::abs(d.change[i]);
    if (a > factor * d.sigma[i] && a > std::max(calibration_sigma[i], min_change[i])) {
      bits |= 1 << i;
    }
  }
  return bits;
}

int LegsToApply(const std::array<LegDrift, kNumLegs>& drift,
                const std::array<Vec6, kNumLegs>& calibration_sigma, const DriftApplyPolicy& policy,
                int64_t utime, int64_t last_apply_utime) {
  if (last_apply_utime > 0 &&
      static_cast<double>(utime - last_apply_utime) < policy.min_interval_s * 1e6) {
    return 0;
  }
  int legs = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    if (drift[k].windows > 0 &&
        DriftSignificant(drift[k], calibration_sigma[k], policy.factor, policy.min_change) != 0) {
      legs |= 1 << k;
    }
  }
  return legs;
}

OffsetTracker::OffsetTracker(const OffsetTrackerOptions& o, const RobotCalibration& cal)
    : options_(o), cal_(cal) {
  auto positive = [](double v, const char* name) {
    Require(std::isfinite(v) && v > 0.0,
            std::string(name) + " must be finite and > 0, got " + std::to_string(v));
  };
  auto non_negative = [](double v, const char* name) {
    Require(std::isfinite(v) && v >= 0.0,
            std::string(name) + " must be finite and >= 0, got " + std::to_string(v));
  };
  positive(o.bin_s, "bin_s");
  positive(o.max_foot_force_n, "max_foot_force_n");
  positive(o.max_shaft_accel_rad_s2, "max_shaft_accel_rad_s2");
  non_negative(o.max_shaft_speed_rad_s, "max_shaft_speed_rad_s");
  positive(o.accel_baseline_s, "accel_baseline_s");
  positive(o.min_window_s, "min_window_s");
  positive(o.max_window_s, "max_window_s");
  non_negative(o.edge_trim_s, "edge_trim_s");
  positive(o.max_servo_age_s, "max_servo_age_s");
  positive(o.max_mocap_age_s, "max_mocap_age_s");
  Require(o.max_window_s >= o.min_window_s, "max_window_s must be >= min_window_s");
  for (int i = 0; i < 6; ++i) {
    non_negative(o.process_noise[i], "process_noise");
    positive(o.initial_sigma[i], "initial_sigma");
    non_negative(o.window_floor[i], "window_floor");
  }
  Require(std::isfinite(cal.g0) && cal.g0 > 0.0, "the calibration's g0 must be > 0");
  bin_us_ = std::max<int64_t>(1, Us(o.bin_s));
  baseline_us_ = Us(o.accel_baseline_s);
  max_servo_age_us_ = Us(o.max_servo_age_s);
  max_mocap_age_us_ = Us(o.max_mocap_age_s);
  for (int k = 0; k < kNumLegs; ++k) {
    X_C_ft_[k] = cal.X_C_ft(k);
    Require(X_C_ft_[k].R.allFinite() && X_C_ft_[k].p.allFinite() && cal.leg[k].offset.allFinite() &&
                std::isfinite(cal.leg[k].weight_n),
            "the calibration of leg " + std::string(kLegNames[k]) + " is not finite");
    leg_[k].P = o.initial_sigma.cwiseAbs2().asDiagonal();
  }
}

bool OffsetTracker::AddFt(const FtInput& in) {
  Require(in.leg >= 0 && in.leg < kNumLegs,
          "AddFt: leg index " + std::to_string(in.leg) + " outside [0, 6)");
  ++counters_.ft_in;
  if (!in.wrench.allFinite()) {
    ++counters_.non_finite;
    return false;
  }
  Leg& leg = leg_[in.leg];
  if (in.utime <= leg.last_ft_utime) {
    ++counters_.out_of_order;
    return false;
  }
  leg.last_ft_utime = in.utime;
  newest_utime_ = std::max(newest_utime_, in.utime);
  const int64_t index = FloorDiv(in.utime, bin_us_);
  if (leg.open.n > 0 && leg.open.index != index) CloseBin(in.leg);
  leg.open.index = index;
  leg.open.utime_sum += in.utime - index * bin_us_;
  leg.open.sum += in.wrench;
  ++leg.open.n;
  JudgePending(in.leg, false);
  return true;
}

bool OffsetTracker::AddServo(const ServoInput& in) {
  if (!AcceptServo(in, &servo_, &counters_)) return false;
  newest_utime_ = std::max(newest_utime_, in.utime);
  for (int k = 0; k < kNumLegs; ++k) JudgePending(k, false);
  return true;
}

bool OffsetTracker::AddMocap(const MocapInput& in) {
  if (!AcceptMocap(in, &mocap_, &counters_)) return false;
  mocap_history_.push_back(in);
  if (mocap_history_.size() > kMocapHistory) mocap_history_.pop_front();
  for (int k = 0; k < kNumLegs; ++k) JudgePending(k, false);
  return true;
}

void OffsetTracker::Finish() {
  for (int k = 0; k < kNumLegs; ++k) {
    if (leg_[k].open.n > 0) CloseBin(k);
    JudgePending(k, true);
    // The input ended, not the window: no touch-down to trim.
    if (!leg_[k].window.empty()) CloseWindow(k, false);
  }
}

void OffsetTracker::CloseBin(int k) {
  Leg& leg = leg_[k];
  leg.pending.push_back(leg.open);
  leg.open = Bin{};
  ++counters_.bins;
}

void OffsetTracker::JudgePending(int k, bool input_ended) {
  Leg& leg = leg_[k];
  // A bin is judged once the servo states bracket its instant +- the baseline and a mocap frame
  // at or after it has come, or, those not coming, once this leg's samples are well past it.
  const int64_t hold_us = baseline_us_ + std::max(max_servo_age_us_, max_mocap_age_us_) + 100000;
  while (!leg.pending.empty()) {
    const Bin& b = leg.pending.front();
    const int64_t t = b.index * bin_us_ + b.utime_sum / b.n;
    const bool servo_past = !servo_.empty() && servo_.newest().utime >= t + baseline_us_;
    const bool mocap_past = mocap_ && mocap_->utime >= t;
    if (!(input_ended || (servo_past && mocap_past) || leg.last_ft_utime - t > hold_us)) break;
    JudgeBin(k, b);
    leg.pending.pop_front();
  }
}

const MocapInput* OffsetTracker::MocapNearest(int64_t utime) const {
  const MocapInput* best = nullptr;
  int64_t best_d = INT64_MAX;
  for (auto it = mocap_history_.rbegin(); it != mocap_history_.rend(); ++it) {
    const int64_t d = std::llabs(it->utime - utime);
    if (d <= best_d) {
      best_d = d;
      best = &*it;
    } else if (it->utime < utime) {
      break;  // older frames only get farther
    }
  }
  return best != nullptr && best_d <= max_mocap_age_us_ ? best : nullptr;
}

void OffsetTracker::JudgeBin(int k, const Bin& b) {
  Leg& leg = leg_[k];
  const int64_t t = b.index * bin_us_ + b.utime_sum / b.n;
  const Vec6 w = b.sum / b.n;
  const auto before = servo_.At(t - baseline_us_);
  const auto at = servo_.At(t);
  const auto after = servo_.At(t + baseline_us_);
  auto fresh = [this](const std::optional<ServoHistory::Lookup>& l) {
    return l && l->interpolated && l->age_s * 1e6 <= static_cast<double>(max_servo_age_us_);
  };
  const bool servo_ok = fresh(before) && fresh(at) && fresh(after);
  const MocapInput* mocap = MocapNearest(t);
  const bool attitude_ok = mocap != nullptr && mocap->tracked;
  bool qualifies = servo_ok && attitude_ok;
  bool loaded = false;
  Vec6 y = Vec6::Zero();
  Mat3 R_WC = Mat3::Identity();
  if (!servo_ok) {
    ++counters_.bins_no_servo;
  } else if (!attitude_ok) {
    ++counters_.bins_no_attitude;
  } else {
    R_WC = mocap->R_WC;
    const double angle = at->angle_rad[k];
    y = w - cal_.leg[k].offset - Unloaded(X_C_ft_[k], cal_.leg[k], angle, R_WC, cal_.g0);
    const double h = 1e-6 * static_cast<double>(baseline_us_);
    const double d1 = WrapToPi(angle - before->angle_rad[k]);
    const double d2 = WrapToPi(after->angle_rad[k] - angle);
    const double accel = (d2 - d1) / (h * h);
    const double speed = (d1 + d2) / (2.0 * h);
    loaded = (y.head<3>() - leg.x.head<3>()).norm() >= options_.max_foot_force_n;
    const bool moving =
        std::abs(accel) > options_.max_shaft_accel_rad_s2 ||
        (options_.max_shaft_speed_rad_s > 0.0 && std::abs(speed) > options_.max_shaft_speed_rad_s);
    if (loaded) {
      ++counters_.bins_loaded;
    } else if (moving) {
      ++counters_.bins_moving;
    }
    qualifies = !loaded && !moving;
  }
  AddToBalance(b.index, k, servo_ok && attitude_ok, loaded, y, R_WC);
  if (!qualifies) {
    if (!leg.window.empty()) CloseWindow(k, true);
    leg.window_trim_start = true;
    return;
  }
  ++counters_.bins_air;
  // A gap in the samples (lost records, a silent transducer) ends the window as a load would:
  // what happened in it is unknown.
  if (!leg.window.empty() && t - leg.window.back().utime > 10 * bin_us_) {
    CloseWindow(k, true);
    leg.window_trim_start = true;
  }
  leg.window.push_back({t, y});
  if (t - leg.window.front().utime >= Us(options_.max_window_s)) {
    CloseWindow(k, false);
    leg.window_trim_start = false;  // the next window continues this one: no edge between
  }
}

void OffsetTracker::CloseWindow(int k, bool trim_end) {
  Leg& leg = leg_[k];
  const int64_t trim = Us(options_.edge_trim_s);
  const int64_t from = leg.window.front().utime + (leg.window_trim_start ? trim : 0);
  const int64_t to = leg.window.back().utime - (trim_end ? trim : 0);
  Vec6 sum = Vec6::Zero(), sq = Vec6::Zero();
  int64_t n = 0, t_sum = 0;
  const int64_t t_ref = leg.window.front().utime;
  for (const Judged& j : leg.window) {
    if (j.utime < from || j.utime > to) continue;
    sum += j.y;
    ++n;
    t_sum += j.utime - t_ref;
  }
  const double seconds = static_cast<double>(n) * options_.bin_s;
  if (n < 2 || seconds < options_.min_window_s) {
    ++counters_.windows_short;
    leg.window.clear();
    return;
  }
  DriftWindow win;
  win.leg = k;
  win.utime = t_ref + t_sum / n;
  win.seconds = seconds;
  win.mean = sum / static_cast<double>(n);
  for (const Judged& j : leg.window) {
    if (j.utime < from || j.utime > to) continue;
    sq += (j.y - win.mean).cwiseAbs2();
  }
  // The scatter of the bins over their number: the window mean's variance when the bins are
  // independent (they are bin_s apart, longer than the transducers' own correlation).
  const Vec6 var = sq / static_cast<double>(n - 1) / static_cast<double>(n);
  win.sigma = (var + options_.window_floor.cwiseAbs2()).cwiseSqrt();
  leg.window.clear();
  Update(k, win);
}

void OffsetTracker::Update(int k, const DriftWindow& w) {
  Leg& leg = leg_[k];
  if (leg.updated_utime != 0 && w.utime > leg.updated_utime) {
    const double dt = 1e-6 * static_cast<double>(w.utime - leg.updated_utime);
    leg.P.diagonal() += options_.process_noise.cwiseAbs2() * dt;
  }
  const Mat6 R = w.sigma.cwiseAbs2().asDiagonal();
  const Mat6 K = leg.P * (leg.P + R).inverse();
  leg.x += K * (w.mean - leg.x);
  const Mat6 I_K = Mat6::Identity() - K;
  leg.P = I_K * leg.P * I_K.transpose() + K * R * K.transpose();  // Joseph: stays symmetric
  leg.updated_utime = std::max(leg.updated_utime, w.utime);
  ++leg.windows;
  leg.window_seconds += w.seconds;
  ++counters_.windows_used;
  windows_.push_back(w);
}

void OffsetTracker::AddToBalance(int64_t index, int k, bool ok, bool loaded, const Vec6& y,
                                 const Mat3& R_WC) {
  Slot& s = slots_[index];
  s.have |= 1 << k;
  s.ok = s.ok && ok;
  if (loaded) ++s.loaded;
  if (ok) {
    // y - d is the reading less its offset and its leg's gravity: X(X_C_ft)^-1 w_gc (eq. 3).
    const Pose3 R(R_WC, Vec3::Zero());
    s.sum[0] += TransformWrench(R, TransformWrench(X_C_ft_[k], y));
    s.sum[1] += TransformWrench(R, TransformWrench(X_C_ft_[k], y - leg_[k].x));
  }
  if (s.have == kAllLegs) {
    if (s.ok && s.loaded >= 3 && !Hanging(phase_)) {
      Vec6 target = Vec6::Zero();
      target[2] = cal_.TotalWeightN();
      for (int i = 0; i < 2; ++i) {
        const Vec6 r = s.sum[i] - target;
        balance_.sq_force[i] += r.head<3>().squaredNorm();
        balance_.sq_torque[i] += r.tail<3>().squaredNorm();
      }
      ++balance_.count;
      BalanceStats one;
      one.count = 1;
      for (int i = 0; i < 2; ++i) {
        const Vec6 r = s.sum[i] - target;
        one.sq_force[i] = r.head<3>().squaredNorm();
        one.sq_torque[i] = r.tail<3>().squaredNorm();
      }
      balance_total_.Add(one);
    }
    slots_.erase(index);
  }
  // A leg silent for long: its instants will not complete.
  while (!slots_.empty() && slots_.begin()->first < index - kMaxSlotLag) {
    slots_.erase(slots_.begin());
  }
}

LegDrift OffsetTracker::Drift(int k, int64_t utime) const {
  Require(k >= 0 && k < kNumLegs, "Drift: leg index " + std::to_string(k) + " outside [0, 6)");
  const Leg& leg = leg_[k];
  LegDrift d;
  d.change = leg.x;
  Vec6 var = leg.P.diagonal();
  if (leg.updated_utime != 0 && utime > leg.updated_utime) {
    var += options_.process_noise.cwiseAbs2() *
           (1e-6 * static_cast<double>(utime - leg.updated_utime));
  }
  d.sigma = var.cwiseSqrt();
  d.windows = leg.windows;
  d.window_seconds = leg.window_seconds;
  d.last_window_utime = leg.updated_utime;
  return d;
}

RobotCalibration OffsetTracker::TrackedCalibration() const {
  RobotCalibration out = cal_;
  for (int k = 0; k < kNumLegs; ++k) out.leg[k].offset += leg_[k].x;
  return out;
}

std::vector<DriftWindow> OffsetTracker::TakeWindows() {
  std::vector<DriftWindow> out;
  out.swap(windows_);
  return out;
}

BalanceStats OffsetTracker::TakeBalance() {
  const BalanceStats out = balance_;
  balance_ = BalanceStats{};
  return out;
}

}  // namespace ftcal
