// The twin's device clocks and host stamps, and the bridges' maps of them (issue 38, items 1
// and 4), for ftcal-sim log.
//
// For a sample the twin takes at twin time t, each device's clock reads what SimClocks says it
// reads then (a Net F/T box's 7 kHz counter, each servo's Realtime Tick in ms, the mocap
// system's frame clock in us); the host stamp the caller drew (t plus a latency) is taken late
// when the host stalls; and the sample time a bridge would publish is that clock mapped onto the
// host's by the bridge's own estimator (DeviceClock, SyncReadClock), run here on the same
// stamps in the same order. So a log holds what a bridge would have published from such
// devices, and a test holds the maps to SimClocks' truth.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <random>

#include "ftcal/device_clock.h"
#include "ftcal/legs.h"
#include "sim/sim_clocks.h"

namespace ftcal {

class TwinDeviceStamps {
 public:
  // t0_utime: the host time of twin time 0. ft_count0: each box's counter at its power-up
  // (added to its clock's reading); tick0_ms: each servo's tick at twin time 0 before its
  // clock's offset. Throws std::invalid_argument (SimClocks::Validate) for impossible clocks.
  TwinDeviceStamps(const SimClocks& clocks, uint64_t seed, int64_t t0_utime,
                   const std::array<int64_t, kNumLegs>& ft_count0,
                   const std::array<int64_t, kNumLegs>& tick0_ms);

  // The host's stamp for an event due at `utime`: later when it falls in a stall. Events must
  // come in rising twin time, frame by frame (a frame's stamps within 40 ms of its instant).
  int64_t HostStamp(int64_t utime);

  struct Ft {
    int64_t counter;  // the box's 7 kHz counter, unwrapped (the wire carries its low 32 bits)
    int64_t sample_utime;
  };
  // Leg k's box sampled at t_s and its datagram was stamped receipt_utime.
  Ft FtSample(int k, double t_s, int64_t receipt_utime);

  struct Servo {
    std::array<int64_t, kNumLegs> tick_ms;  // unwrapped Realtime Ticks
    int64_t request_utime;  // the bridge's stamp of the read's request: kReadLeadUs before t_s,
                            // less up to kReadJitterUs (a USB frame's wait)
    int64_t sample_utime;
  };
  static constexpr int64_t kReadLeadUs = 250, kReadJitterUs = 125;
  // The bus was read at t_s; the read completed at completion_utime.
  const Servo& ServoSample(double t_s, int64_t completion_utime);

  struct Mocap {
    int64_t device_utime;
    int64_t sample_utime;
  };
  Mocap MocapSample(double t_s, int64_t receipt_utime);

  const SimClocks& clocks() const { return clocks_; }
  const DeviceClock& ft_clock(int k) const { return *ft_map_[static_cast<size_t>(k)]; }
  const SyncReadClock& servo_clock() const { return servo_map_; }
  const DeviceClock& mocap_clock() const { return mocap_map_; }
  int64_t stalls() const { return stalls_; }

 private:
  void NextStall(int64_t after_utime);

  SimClocks clocks_;
  int64_t t0_utime_;
  std::mt19937_64 rng_;  // the stalls' own: a log without stalls keeps its other draws
  std::array<int64_t, kNumLegs> ft_count0_{};
  std::array<int64_t, kNumLegs> tick0_ms_{};
  std::array<std::unique_ptr<DeviceClock>, kNumLegs> ft_map_;
  SyncReadClock servo_map_;
  DeviceClock mocap_map_;
  Servo servo_{};
  std::array<bool, kNumLegs> all_answered_{};
  int64_t stall_begin_ = 0, stall_end_ = 0;  // the current or next stall, host us
  int64_t stalls_ = 0;
};

}  // namespace ftcal
