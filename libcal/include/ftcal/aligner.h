// Stream alignment: six asynchronous transducer streams, the servo state and motion capture
// into SyncSamples at the transducers' rate (the pose segmenter's and the calibrator's input).
//
// Rule. A sample is taken at each reading time t of the pace leg (leg 0, HL), from every leg's
// reading nearest t (the earlier of two as near), once every leg has a reading at or after t:
// then no later reading can be nearer, so the sample does not depend on how the legs' messages
// interleave on arrival (a transducer's records come a datagram at a time, and six datagrams
// arrive in any order). The sync time is t; it is strictly increasing. The readings of one
// instant are within half a sample period of each other; no wrench is resampled (interpolating
// a wrench would smear the settling the segmenter looks for). While a leg is silent nothing is
// emitted; each leg keeps at most kMaxQueued readings waiting (the oldest go first, counted).
//
// Shaft angles are interpolated linearly to the sync time between the two servo states that
// bracket it, the later one unwrapped against the earlier (a step of more than pi between two
// states is taken the short way round). When no later state has arrived yet the sample waits
// for one, at most max_servo_age_s of transducer time; after that it takes the newest state as
// is (counted as servo_held) when that is within max_servo_age_s of the sync time, and is
// dropped (stale_servo) otherwise. Angles are never extrapolated.
//
// Attitude: R_WC of the motion-capture frame nearest the sync time (the earlier of two as
// near), once a frame at or after it has arrived (or, none coming, after max_mocap_age_s of
// transducer time: then the nearest of those received); attitude_ok is false when the body was
// untracked or that frame is more than max_mocap_age_s from the sync time.
//
// Everything is keyed on the inputs' own utime stamps, never on a clock, and a sample is made
// only once no input still to come could change it: the same streams give the same samples
// whatever the order their messages interleave in, live or on replay (unless a servo state or
// mocap frame comes more than its max age of transducer time late: then it is held, as said).
// Inputs older than the previous one of their stream (per leg for the transducers) and non-finite
// inputs are counted and dropped.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <deque>
#include <functional>
#include <optional>

#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/segmenter.h"

namespace ftcal {

struct FtInput {
  int64_t utime = 0;
  int leg = 0;  // index in kLegNames (config order)
  Vec6 wrench = Vec6::Zero();
  int32_t flags = 0;  // ft_batch_t FLAG_* bits, passed through (OR over the six legs)
};

struct ServoInput {
  int64_t utime = 0;
  std::array<double, kNumLegs> angle_rad{};  // by leg index
};

struct MocapInput {
  int64_t utime = 0;
  bool tracked = false;
  Mat3 R_WC = Mat3::Identity();
  bool markers_ok = false;  // every chassis marker tracked in this frame
};

// Servo states in time order, for angles at a given time (the aligner and the corrector).
class ServoHistory {
 public:
  struct Lookup {
    std::array<double, kNumLegs> angle_rad{};
    // |t - time of the state held| when held; the distance to the nearer bracketing state when
    // interpolated. Seconds.
    double age_s = 0.0;
    bool interpolated = false;
  };
  explicit ServoHistory(size_t capacity = 16);

  // Returns false (and keeps nothing) for a state not newer than the newest one.
  bool Add(const ServoInput& state);
  bool empty() const { return states_.empty(); }
  const ServoInput& newest() const { return states_.back(); }
  // Interpolated between the bracketing states when there are two; else the nearest state
  // held (before the first or after the last). nullopt when empty.
  std::optional<Lookup> At(int64_t utime) const;

 private:
  size_t capacity_;
  std::deque<ServoInput> states_;
};

struct AlignerOptions {
  double max_servo_age_s = 0.05;
  double max_mocap_age_s = 0.05;
  // The servo stream's delay relative to the transducers' (a calibration's
  // latencies.applied_servo_delay_s, docs/method.md "Latencies"): a servo state stamped u is
  // taken as the shaft at u - servo_delay_s. |servo_delay_s| must stay below max_servo_age_s.
  double servo_delay_s = 0.0;
};

struct AlignedSample {
  SyncSample sample;
  int32_t flags = 0;  // OR of the six readings' flags
};

// The input checks the aligner and the corrector share: count the input, refuse a non-finite
// one and one that is not newer than the last of its stream, keep the newest. `Counters` has
// servo_in / mocap_in / non_finite / out_of_order.
template <class Counters>
bool AcceptServo(const ServoInput& in, ServoHistory* history, Counters* counters) {
  ++counters->servo_in;
  for (double a : in.angle_rad) {
    if (!std::isfinite(a)) {
      ++counters->non_finite;
      return false;
    }
  }
  if (!history->Add(in)) {
    ++counters->out_of_order;
    return false;
  }
  return true;
}

template <class Counters>
bool AcceptMocap(const MocapInput& in, std::optional<MocapInput>* latest, Counters* counters) {
  ++counters->mocap_in;
  if (in.tracked && !in.R_WC.allFinite()) {
    ++counters->non_finite;
    return false;
  }
  if (*latest && in.utime <= (*latest)->utime) {
    ++counters->out_of_order;
    return false;
  }
  *latest = in;
  return true;
}

struct AlignerCounters {
  int64_t ft_in = 0, servo_in = 0, mocap_in = 0;
  int64_t emitted = 0;
  int64_t out_of_order = 0;  // an input not newer than the previous one of its stream
  int64_t non_finite = 0;    // a NaN/inf wrench, angle or tracked attitude
  int64_t servo_held = 0;    // emitted with the newest servo state held (no later state came)
  int64_t stale_servo = 0;   // dropped: no servo state within max_servo_age_s
  int64_t stale_mocap = 0;   // emitted with attitude_ok false (none, untracked or old)
  int64_t unaligned = 0;     // readings dropped unused while another leg was silent
};

class Aligner {
 public:
  using Callback = std::function<void(const AlignedSample&)>;
  Aligner(const AlignerOptions& options, Callback on_sample);

  // Each returns false when the input was dropped (counted).
  bool AddFt(const FtInput& in);
  bool AddServo(const ServoInput& in);
  bool AddMocap(const MocapInput& in);

  const AlignerCounters& counters() const { return counters_; }
  // Samples complete but still waiting for a later servo state.
  size_t pending() const { return pending_.size(); }

 private:
  struct Pending {
    AlignedSample out;
  };
  // Resolves pending samples in order; `newest_ft_utime` is the transducer clock that bounds
  // the wait for a later servo state.
  void Resolve(int64_t newest_ft_utime);
  void Emit(AlignedSample& out, const ServoHistory::Lookup& angles);
  // The frame nearest `utime` among mocap_history_; nullptr when there is none.
  const MocapInput* MocapNearest(int64_t utime) const;

  AlignerOptions options_;
  int64_t max_servo_age_us_;
  int64_t max_mocap_age_us_;
  int64_t servo_delay_us_;
  Callback on_sample_;
  // Forms the samples whose every leg has a reading at or after the pace leg's instant.
  void FormSamples();

  static constexpr size_t kMaxQueued = 4096;  // 0.6 s of a 7 kHz transducer
  std::array<std::deque<FtInput>, kNumLegs> queue_;
  std::array<int64_t, kNumLegs> last_ft_utime_;  // each leg's last accepted reading
  int64_t newest_ft_utime_;
  ServoHistory servo_;
  std::optional<MocapInput> mocap_;       // the newest frame (AcceptMocap's order check)
  std::deque<MocapInput> mocap_history_;  // the latest frames, for the nearest
  std::deque<Pending> pending_;
  AlignerCounters counters_;
};

}  // namespace ftcal
