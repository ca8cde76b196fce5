#include "ftcal/device_clock.h"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <stdexcept>
#include <string>

namespace ftcal {

namespace {

// How often (device seconds) the map is refitted: the hull changes with every sample, the line
// it gives only slowly (a sample below it in between is mapped to its receipt). More often while
// the map is young and each second of data moves it.
constexpr double kRefitEveryS = 0.5;
constexpr double kYoungRefitEveryS = 0.05;
constexpr double kYoungS = 10.0;
constexpr size_t kSlicesPerEpoch = 4;
// SyncReadClock: the window over which the least bound on the bus time is taken (long enough for
// the servos' millisecond edges to fall close to many reads' instants, short enough to follow a
// change of the bus's timing), and how far outside the intervals' intersection an estimate may
// fall (the maps' own error, tens of us) before the intersection's middle is preferred.
constexpr double kBoundWindowS = 30.0;
constexpr double kBoundSlackUs = 250.0;
// A map's rate is known to a ppm only once its fit spans this much: a tick resolves a
// millisecond, so a younger map extrapolates early or late by hundreds of us, and one early
// bound would hold for the whole window.
constexpr double kMatureSpanS = 30.0;

// > 0 when o -> a -> b turns counter-clockwise (b above the line through o and a).
double Cross(double ox, double oy, double ax, double ay, double bx, double by) {
  return (ax - ox) * (by - oy) - (ay - oy) * (bx - ox);
}

}  // namespace

DeviceClock::DeviceClock(const DeviceClockOptions& options) : options_(options) {
  if (!(options.nominal_hz > 0) || !std::isfinite(options.nominal_hz)) {
    throw std::invalid_argument("device clock: nominal rate " + std::to_string(options.nominal_hz) +
                                " Hz is not positive");
  }
  if (!(options.epoch_s > 0) || !(options.min_span_s >= 0) || !(options.step_s > 0) ||
      !(options.step_persist_s > 0)) {
    throw std::invalid_argument(
        "device clock: epoch, minimum span, step and step persistence must be positive");
  }
}

void DeviceClock::AddToHull(std::vector<Point>& hull, const Point& p) {
  if (!hull.empty() && hull.back().x == p.x) {
    if (p.y >= hull.back().y) return;  // the same device instant, received later: not a vertex
    hull.pop_back();
  }
  while (hull.size() >= 2) {
    const Point& o = hull[hull.size() - 2];
    const Point& a = hull.back();
    if (Cross(o.x, o.y, a.x, a.y, p.x, p.y) > 0) break;
    hull.pop_back();
  }
  hull.push_back(p);
}

void DeviceClock::Restart(int64_t ticks, int64_t receipt_us) {
  started_ = true;
  origin_ticks_ = last_ticks_ = ticks;
  origin_us_ = receipt_us;
  slices_.clear();
  slices_.emplace_back();
  slices_.back().hull.push_back({0, 0});
  slices_.back().n = 1;
  intercept_ = 0;
  rate_ = 1.0;
  next_refit_x_ = 0;
  late_since_x_ = -1;
}

double DeviceClock::fit_span_s() const {
  return slices_.empty() ? 0.0 : slices_.back().last_x - slices_.front().first_x;
}

void DeviceClock::Refit() {
  merged_.clear();
  double sum_x = 0, n = 0;
  for (const Slice& s : slices_) {
    for (const Point& p : s.hull) AddToHull(merged_, p);
    sum_x += s.sum_x;
    n += static_cast<double>(s.n);
  }
  const double first_x = slices_.front().first_x, last_x = slices_.back().last_x;
  if (merged_.size() < 2 || last_x - first_x < options_.min_span_s) {
    // The nominal rate, as low as every sample allows: y - x is least at a lower-hull vertex.
    rate_ = 1.0;
    intercept_ = merged_.front().y - merged_.front().x;
    for (const Point& p : merged_) intercept_ = std::min(intercept_, p.y - p.x);
    return;
  }
  // Halves by slice: the split is the first slice whose middle is past the window's.
  const double mid_x = 0.5 * (first_x + last_x);
  size_t split = 1;
  while (split + 1 < slices_.size() &&
         0.5 * (slices_[split].first_x + slices_[split].last_x) < mid_x) {
    ++split;
  }
  // Until the newer half spans half a slice, its least delayed sample may still be well above
  // the line: the edge is the better guess then.
  const double slice_s = options_.epoch_s / kSlicesPerEpoch;
  if (slices_.size() < 2 || last_x - slices_[split].first_x < 0.5 * slice_s) {
    // The hull edge above the mean device time (the first vertex at or past it, and the one
    // before): the line under every point that is highest there, i.e. nearest them in the mean.
    const double mean_x = sum_x / n;
    auto after = std::lower_bound(merged_.begin(), merged_.end(), mean_x,
                                  [](const Point& p, double x) { return p.x < x; });
    if (after == merged_.begin()) ++after;
    if (after == merged_.end()) --after;
    const Point& a = *(after - 1);
    const Point& b = *after;
    rate_ = (b.y - a.y) / (b.x - a.x);
    intercept_ = a.y - rate_ * a.x;
    return;
  }
  // The least delayed sample of each half of the window (least y - rate x is a vertex of its
  // slice's hull), twice, as which sample is least delayed depends on the rate.
  auto least = [&](size_t from, size_t to, double rate) {
    Point best = slices_[from].hull.front();
    for (size_t i = from; i < to; ++i) {
      for (const Point& p : slices_[i].hull) {
        if (p.y - rate * p.x < best.y - rate * best.x) best = p;
      }
    }
    return best;
  };
  for (int pass = 0; pass < 2; ++pass) {
    const Point a = least(0, split, rate_);
    const Point b = least(split, slices_.size(), rate_);
    if (b.x - a.x <= 0) break;
    rate_ = (b.y - a.y) / (b.x - a.x);
  }
  intercept_ = merged_.front().y - rate_ * merged_.front().x;
  for (const Point& p : merged_) intercept_ = std::min(intercept_, p.y - rate_ * p.x);
}

int64_t DeviceClock::Observe(int64_t ticks, int64_t receipt_us) {
  if (!started_) {
    Restart(ticks, receipt_us);
    return receipt_us;
  }
  if (ticks < last_ticks_) {  // the device's counter started again
    ++restarts_;
    Restart(ticks, receipt_us);
    return receipt_us;
  }
  const Point p{static_cast<double>(ticks - origin_ticks_) / options_.nominal_hz,
                static_cast<double>(receipt_us - origin_us_) * 1e-6};
  if (p.y < LineAt(p.x) - options_.step_s) {  // earlier than possible: the host clock stepped
    ++restarts_;
    Restart(ticks, receipt_us);
    return receipt_us;
  }
  if (p.y - LineAt(p.x) > options_.step_s) {
    if (late_since_x_ < 0) {
      late_since_x_ = p.x;
    } else if (p.x - late_since_x_ >= options_.step_persist_s) {
      ++restarts_;
      Restart(ticks, receipt_us);
      return receipt_us;
    }
  } else {
    late_since_x_ = -1;
  }
  last_ticks_ = ticks;
  const double slice_s = options_.epoch_s / kSlicesPerEpoch;
  if (p.x - slices_.back().first_x >= slice_s) {
    slices_.emplace_back();
    slices_.back().first_x = p.x;
    // The window: the slices of the last two epochs, and the one being filled.
    while (slices_.size() > 2 * kSlicesPerEpoch + 1) slices_.pop_front();
  }
  Slice& slice = slices_.back();
  AddToHull(slice.hull, p);
  slice.sum_x += p.x;
  ++slice.n;
  slice.last_x = p.x;
  if (p.x >= next_refit_x_) {
    Refit();
    next_refit_x_ = p.x + (fit_span_s() < kYoungS ? kYoungRefitEveryS : kRefitEveryS);
  }
  const double mapped = std::min(LineAt(p.x), p.y);
  return origin_us_ + std::llround(mapped * 1e6);
}

int64_t DeviceClock::Map(int64_t ticks) const {
  const double x = static_cast<double>(ticks - origin_ticks_) / options_.nominal_hz;
  return origin_us_ + std::llround(LineAt(x) * 1e6);
}

SyncReadClock::SyncReadClock(int servos, DeviceClockOptions options) : options_(options) {
  if (servos < 1) {
    throw std::invalid_argument("sync read clock: " + std::to_string(servos) + " servos");
  }
  options_.nominal_hz = 1000.0;  // the Realtime Tick counts milliseconds
  for (int i = 0; i < servos; ++i) clocks_.push_back(std::make_unique<DeviceClock>(options_));
}

void SyncReadClock::Reset(int servo) {
  clocks_.at(static_cast<size_t>(servo)) = std::make_unique<DeviceClock>(options_);
}

int64_t SyncReadClock::Observe(const int64_t* ticks, const bool* answered, int64_t completion_us,
                               int64_t request_us) {
  double lo = -std::numeric_limits<double>::infinity();
  double hi = std::numeric_limits<double>::infinity();
  intervals_.clear();
  mature_highs_.clear();
  middles_.clear();
  for (size_t i = 0; i < clocks_.size(); ++i) {
    if (!answered[i]) continue;
    DeviceClock& c = *clocks_[i];
    c.Observe(ticks[i], completion_us);
    const auto a = static_cast<double>(c.Map(ticks[i]));
    const auto b = static_cast<double>(c.Map(ticks[i] + 1));
    lo = std::max(lo, a);
    hi = std::min(hi, b);
    intervals_.emplace_back(a, b);
    if (c.fit_span_s() >= kMatureSpanS) mature_highs_.push_back(b);
    middles_.push_back(0.5 * (a + b));
  }
  if (middles_.empty()) return completion_us;
  if (request_us != kNoRequest && !mature_highs_.empty()) {
    // A host clock stepped back: bounds from before say nothing now.
    if (!bounds_.empty() && request_us < bounds_.back().first) bounds_.clear();
    // The second lowest upper edge when there are three or more: one map that slipped early
    // (its rate misjudged over a short span) must not pull the bound for a whole window.
    std::sort(mature_highs_.begin(), mature_highs_.end());
    const double high = mature_highs_[mature_highs_.size() >= 3 ? 1 : 0];
    const double bound = high - static_cast<double>(request_us);
    while (!bounds_.empty() && bounds_.back().second >= bound) bounds_.pop_back();
    bounds_.emplace_back(request_us, bound);
    while (bounds_.front().first < request_us - std::llround(kBoundWindowS * 1e6)) {
      bounds_.pop_front();
    }
    // Used when most of this read's intervals hold it (within the maps' own error): else the
    // bound has gone stale (the bus's timing changed) and the intervals decide.
    const double t = static_cast<double>(request_us) + bounds_.front().second;
    size_t holding = 0;
    for (const auto& [a, b] : intervals_) {
      holding += t >= a - kBoundSlackUs && t <= b + kBoundSlackUs;
    }
    if (2 * holding > intervals_.size()) {
      return std::min(completion_us, static_cast<int64_t>(std::llround(t)));
    }
  }
  double t = 0.5 * (lo + hi);
  if (!(lo <= hi)) {
    const auto mid = middles_.begin() + static_cast<std::ptrdiff_t>(middles_.size() / 2);
    std::nth_element(middles_.begin(), mid, middles_.end());
    t = *mid;
  }
  return std::min(completion_us, static_cast<int64_t>(std::llround(t)));
}

}  // namespace ftcal
