#include "ftcal/aligner.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace ftcal {
namespace {

// The short way round: the servo's angle may be wrapped to (-pi, pi] by its bridge.
double WrapToPi(double a) { return a - 2.0 * M_PI * std::floor((a + M_PI) / (2.0 * M_PI)); }

int64_t SecondsToUs(double s, const char* what) {
  if (!(s > 0) || !std::isfinite(s)) {
    throw std::invalid_argument(std::string("Aligner: ") + what + " must be > 0 s, got " +
                                std::to_string(s));
  }
  return static_cast<int64_t>(std::llround(s * 1e6));
}

}  // namespace

ServoHistory::ServoHistory(size_t capacity) : capacity_(std::max<size_t>(capacity, 2)) {}

bool ServoHistory::Add(const ServoInput& state) {
  if (!states_.empty() && state.utime <= states_.back().utime) return false;
  states_.push_back(state);
  if (states_.size() > capacity_) states_.pop_front();
  return true;
}

std::optional<ServoHistory::Lookup> ServoHistory::At(int64_t utime) const {
  if (states_.empty()) return std::nullopt;
  Lookup out;
  if (utime <= states_.front().utime) {
    out.angle_rad = states_.front().angle_rad;
    out.age_s = 1e-6 * static_cast<double>(states_.front().utime - utime);
    return out;
  }
  if (utime >= states_.back().utime) {
    out.angle_rad = states_.back().angle_rad;
    out.age_s = 1e-6 * static_cast<double>(utime - states_.back().utime);
    return out;
  }
  // The wanted time is almost always near the newest state: search from the back.
  size_t i = states_.size() - 1;
  while (states_[i - 1].utime > utime) --i;
  const ServoInput& s0 = states_[i - 1];
  const ServoInput& s1 = states_[i];
  const double span = static_cast<double>(s1.utime - s0.utime);
  const double alpha = static_cast<double>(utime - s0.utime) / span;
  for (int k = 0; k < kNumLegs; ++k) {
    out.angle_rad[k] = s0.angle_rad[k] + alpha * WrapToPi(s1.angle_rad[k] - s0.angle_rad[k]);
  }
  out.age_s = 1e-6 * static_cast<double>(std::min(utime - s0.utime, s1.utime - utime));
  out.interpolated = true;
  return out;
}

Aligner::Aligner(const AlignerOptions& options, Callback on_sample)
    : options_(options),
      max_servo_age_us_(SecondsToUs(options.max_servo_age_s, "max_servo_age_s")),
      max_mocap_age_us_(SecondsToUs(options.max_mocap_age_s, "max_mocap_age_s")),
      servo_delay_us_(std::llround(options.servo_delay_s * 1e6)),
      on_sample_(std::move(on_sample)),
      newest_ft_utime_(INT64_MIN) {
  if (!(std::abs(options.servo_delay_s) < options.max_servo_age_s)) {
    throw std::invalid_argument("Aligner: servo_delay_s " + std::to_string(options.servo_delay_s) +
                                " s: its magnitude must be below max_servo_age_s " +
                                std::to_string(options.max_servo_age_s) + " s");
  }
  last_ft_utime_.fill(INT64_MIN);
}

bool Aligner::AddFt(const FtInput& in) {
  if (in.leg < 0 || in.leg >= kNumLegs) {
    throw std::invalid_argument("Aligner::AddFt: leg index " + std::to_string(in.leg) +
                                " outside [0, " + std::to_string(kNumLegs) + ")");
  }
  ++counters_.ft_in;
  if (!in.wrench.allFinite()) {
    ++counters_.non_finite;
    return false;
  }
  if (in.utime <= last_ft_utime_[in.leg]) {
    ++counters_.out_of_order;
    return false;
  }
  last_ft_utime_[in.leg] = in.utime;
  newest_ft_utime_ = std::max(newest_ft_utime_, in.utime);
  std::deque<FtInput>& q = queue_[in.leg];
  q.push_back(in);
  if (q.size() > kMaxQueued) {
    q.pop_front();
    ++counters_.unaligned;
  }
  FormSamples();
  Resolve(newest_ft_utime_);
  return true;
}

void Aligner::FormSamples() {
  std::deque<FtInput>& pace = queue_[0];
  while (!pace.empty()) {
    const int64_t t = pace.front().utime;
    for (const auto& q : queue_) {
      if (q.empty() || q.back().utime < t) return;  // a nearer reading may still come
    }
    Pending p;
    p.out.sample.utime = t;
    for (int k = 0; k < kNumLegs; ++k) {
      std::deque<FtInput>& q = queue_[k];
      // Readings before one that is at or before t can be no instant's nearest any more.
      while (q.size() >= 2 && q[1].utime <= t) q.pop_front();
      const FtInput* use = &q[0];
      if (q.size() >= 2 && q[0].utime < t && q[1].utime - t < t - q[0].utime) use = &q[1];
      p.out.sample.wrench[k] = use->wrench;
      p.out.flags |= use->flags;
    }
    pending_.push_back(p);
    pace.pop_front();
  }
}

bool Aligner::AddServo(const ServoInput& in) {
  // On the transducers' time base: the state describes the shaft servo_delay_s before its stamp.
  ServoInput shifted = in;
  shifted.utime -= servo_delay_us_;
  if (!AcceptServo(shifted, &servo_, &counters_)) return false;
  Resolve(newest_ft_utime_);
  return true;
}

bool Aligner::AddMocap(const MocapInput& in) {
  if (!AcceptMocap(in, &mocap_, &counters_)) return false;
  mocap_history_.push_back(in);
  // A second of frames at 100-300 Hz: more than any sample waits for.
  if (mocap_history_.size() > 512) mocap_history_.pop_front();
  Resolve(newest_ft_utime_);
  return true;
}

const MocapInput* Aligner::MocapNearest(int64_t utime) const {
  if (mocap_history_.empty()) return nullptr;
  // From the newest back while the one before is no farther (the earlier of two as near).
  size_t i = mocap_history_.size() - 1;
  auto distance = [&](size_t at) { return std::llabs(mocap_history_[at].utime - utime); };
  while (i > 0 && distance(i - 1) <= distance(i)) --i;
  return &mocap_history_[i];
}

void Aligner::Resolve(int64_t newest_ft_utime) {
  while (!pending_.empty()) {
    AlignedSample& out = pending_.front().out;
    const int64_t t = out.sample.utime;
    // Wait for a later servo state and a later mocap frame while the transducers are less
    // than each one's max age ahead: until then a later input could still change the sample.
    const bool servo_later = !servo_.empty() && servo_.newest().utime >= t;
    const bool mocap_later = !mocap_history_.empty() && mocap_history_.back().utime >= t;
    if ((!servo_later && newest_ft_utime - t <= max_servo_age_us_) ||
        (!mocap_later && newest_ft_utime - t <= max_mocap_age_us_)) {
      return;
    }
    if (servo_later) {
      const auto angles = servo_.At(t);
      if (!angles->interpolated && angles->age_s * 1e6 > static_cast<double>(max_servo_age_us_)) {
        ++counters_.stale_servo;  // only states long after it: the stream just started
      } else {
        Emit(out, *angles);
      }
    } else if (!servo_.empty() && t - servo_.newest().utime <= max_servo_age_us_) {
      ++counters_.servo_held;
      Emit(out, *servo_.At(t));
    } else {
      ++counters_.stale_servo;
    }
    pending_.pop_front();
  }
}

void Aligner::Emit(AlignedSample& out, const ServoHistory::Lookup& angles) {
  SyncSample& s = out.sample;
  s.angle_rad = angles.angle_rad;
  const MocapInput* m = MocapNearest(s.utime);
  const bool fresh = m != nullptr && std::llabs(s.utime - m->utime) <= max_mocap_age_us_;
  s.R_WC = (m != nullptr && m->tracked) ? m->R_WC : Mat3::Identity();
  s.attitude_ok = fresh && m->tracked;
  s.markers_ok = s.attitude_ok && m->markers_ok;
  if (!s.attitude_ok) ++counters_.stale_mocap;
  ++counters_.emitted;
  if (on_sample_) on_sample_(out);
}

}  // namespace ftcal
