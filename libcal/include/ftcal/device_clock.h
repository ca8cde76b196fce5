// A device's clock mapped onto the host's, from the times its messages arrive (docs/method.md,
// "Clocks and delays").
//
// Model: a sample stamped with device time x (its counter over the nominal rate, seconds) left
// the device at host time  t = a + b x  and arrived at  r = t + d_min + q,  with d_min a constant
// (the transport's least delay) and q >= 0 a one-sided queuing delay (the bus, the kernel, the
// host's scheduler). Unknowns: a + d_min (offset) and b (the rate ratio; skew = b - 1). d_min
// cannot be told from a apart by any clock: what the map gives is the sample's time plus the
// least transport delay; a constant delay inside the device (a filter's group delay, an
// adapter's latency timer) is the calibration's job (docs/method.md, "Latencies").
//
// Estimate: every point (x, r) lies on or above the line, so the line is a lower envelope. Of
// the lines under all points, the one closest to them in the mean (min sum of r_i - a - b x_i, a
// linear program; Moon, Skelly & Towsley, "Estimation and removal of clock skew from network
// delay measurements", 1999) is the edge of the points' lower convex hull above their mean
// device time. Unlike a least-squares fit it is not pulled up by queuing delay, however
// heavy-tailed, and only the hull's few vertices are kept. Written here because no Debian
// library fits a clock this way (PTP and NTP daemons do it inside their own protocols).
//
// Where few samples come through undelayed (a 100 Hz bus behind a USB adapter's 16 ms latency
// timer), the hull edge above the mean can be short and its two ends' delays set the rate; so
// once the fit spans two slices the rate is taken instead from the least delayed sample of each
// half of the window (least r - b x, iterated: a baseline of half the window), and the offset
// from the line of that rate under every point.
//
// Online: the samples are kept as the lower hulls of slices of a quarter epoch of device time
// (x only rises: Andrew's monotone chain, O(1) a sample); the fit spans the last one to two
// epochs, so it follows a rate that drifts slowly (a board warming up) and forgets what is older.
#pragma once

#include <cstdint>
#include <deque>
#include <memory>
#include <utility>
#include <vector>

namespace ftcal {

struct DeviceClockOptions {
  double nominal_hz = 1.0;  // device counter ticks per second, as the device's manual states
  // Of device time; the fit spans one to two epochs. Short enough that a rate drifting as a
  // board warms (10 ppm in 90 min) costs the newest sample under 20 us of extrapolation, long
  // enough that the envelope holds many near-undelayed samples.
  double epoch_s = 120.0;
  // Below this span of device time the rate is taken as nominal (b = 1): too short to tell.
  double min_span_s = 2.0;
  // A sample that arrives this much earlier than the line says it can is not a queuing effect:
  // the host's clock stepped back or the device restarted its counter. The map starts afresh.
  double step_s = 0.05;
  // Samples later than the line by more than step_s for this long of device time: not a stall
  // that drains, the device's counter stood still while time went on (a device paused, a
  // recording with its devices silent between scenarios) or the host's clock stepped forward.
  // The map starts afresh.
  double step_persist_s = 1.0;
};

class DeviceClock {
 public:
  explicit DeviceClock(const DeviceClockOptions& options);

  // Takes a sample's device counter (unwrapped, rising; a fall means the device restarted) and
  // the host time it was received (us since the Unix epoch), and returns the host time (us) the
  // map gives that sample now: never later than its receipt.
  int64_t Observe(int64_t ticks, int64_t receipt_us);

  // The host time (us) of device counter `ticks` by the current map; only after an Observe.
  int64_t Map(int64_t ticks) const;

  bool started() const { return started_; }
  // The device's rate relative to the host's, in parts per million (b - 1), by the current map.
  double skew_ppm() const { return (rate_ - 1.0) * 1e6; }
  // How often the map started afresh (a counter that fell or stood still, a host clock that
  // stepped).
  int64_t restarts() const { return restarts_; }
  // The device time the current fit spans (s).
  double fit_span_s() const;

 private:
  struct Point {
    double x, y;  // device seconds, receipt seconds, both since the map's origin
  };
  struct Slice {
    std::vector<Point> hull;  // lower convex hull of the slice's samples, x rising
    double sum_x = 0;
    int64_t n = 0;
    double first_x = 0, last_x = 0;
  };
  static void AddToHull(std::vector<Point>& hull, const Point& p);
  void Restart(int64_t ticks, int64_t receipt_us);
  void Refit();
  double LineAt(double x) const { return intercept_ + rate_ * x; }

  DeviceClockOptions options_;
  bool started_ = false;
  int64_t origin_ticks_ = 0, origin_us_ = 0, last_ticks_ = 0;
  std::deque<Slice> slices_;           // oldest first; the last one takes the new samples
  std::vector<Point> merged_;          // scratch: the hull of the window
  double intercept_ = 0, rate_ = 1.0;  // the map: y = intercept_ + rate_ * x
  double next_refit_x_ = 0;
  double late_since_x_ = -1;  // device time of the first of a run of samples over step_s late
  int64_t restarts_ = 0;
};

// The instant one Sync Read sampled a bus of servos, on the host clock (docs/method.md, "Clocks
// and delays"). Each servo's Realtime Tick (ms) is its own crystal, so each has its own
// DeviceClock against the read's completion. A tick says only which millisecond of its clock
// the servo read in: its map gives the interval [map(tick), map(tick + 1)). The servos of one
// read answer within one bus transaction (well under a millisecond apart at 1 Mbit/s and
// more), and their millisecond edges fall at unrelated instants, so the intervals' intersection
// is a fraction of a millisecond wide, but only as narrow as the six edges happen to fall: when
// they bunch (each servo's crystal drifts against the others) it widens to most of a ms.
//
// So the bridge also stamps the instant it sent the read (host clock, before the write): the
// servos sample a constant bus time c after it, plus a small one-sided USB scheduling delay.
// Every read's interval bounds c from above (c <= hi - request, strictly, whatever the
// queuing), and over a window of reads the least of these bounds comes down to c: the read's
// instant is then request + c, to within the USB delay's jitter. Only maps that span 30 s give
// bounds (a younger one's rate is not known to the ppm a millisecond tick needs), and each read
// gives its second lowest (one map gone early must not hold the bound down for a window). Without a
// request stamp, or before a bound is known, the middle of the intersection stands in (where the
// intervals do not meet, a map young or just restarted, the median of their middles). Never later
// than the completion.
class SyncReadClock {
 public:
  // `servos` clocks of ticks in ms (options.nominal_hz is set to 1000).
  SyncReadClock(int servos, DeviceClockOptions options);

  // ticks[i] is servo i's unwrapped Realtime Tick, answered[i] whether it answered this read
  // (a silent servo's tick says nothing about this one). Returns the host time (us) of the
  // read's instant; with no servo answering, the completion itself.
  // request_us: the host time the read was sent (kNoRequest: not known).
  static constexpr int64_t kNoRequest = INT64_MIN;
  int64_t Observe(const int64_t* ticks, const bool* answered, int64_t completion_us,
                  int64_t request_us = kNoRequest);
  // Servo i's tick started afresh (its port reopened, the servo rebooted): a new map.
  void Reset(int servo);
  const DeviceClock& clock(int servo) const { return *clocks_[static_cast<size_t>(servo)]; }
  int servos() const { return static_cast<int>(clocks_.size()); }

 private:
  DeviceClockOptions options_;
  std::vector<std::unique_ptr<DeviceClock>> clocks_;
  // Scratch: this read's intervals, the upper edges of the mature maps, the middles.
  std::vector<std::pair<double, double>> intervals_;
  std::vector<double> mature_highs_, middles_;
  // Sliding minimum of (hi - request) over the last kBoundWindowS of requests: (request, bound),
  // bounds rising, oldest first.
  std::deque<std::pair<int64_t, double>> bounds_;
};

}  // namespace ftcal
