// The twin's device clocks and its host's scheduling, as a lab has them (issue 38, item 4).
//
// A device clock reads  device_s(t) = offset_s + (1 + rate_ppm 1e-6) t  at twin time t: its own
// crystal (tens of ppm off, each device its own) and its own origin (a counter's power-up value,
// a measurement's start). The bridges never see these numbers: they estimate them from the
// stamps (DeviceClock), and the tests hold the estimate to them.
//
// The host stalls now and then (a scheduling burst: another process, a page fault storm):
// every host stamp that falls inside a stall is taken when it ends. Stalls start at
// exponentially distributed intervals of mean `stall_every_s` and last up to `stall_max_s`.
// A stall never reaches a scenario's gap in ftcal-sim log (at least 50 ms, longer than
// kMaxStallS plus the latencies), so the log's events stay in order.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "ftcal/legs.h"

namespace ftcal {

struct SimDeviceClock {
  double rate_ppm = 0.0;  // the clock's rate error: + runs fast
  double offset_s = 0.0;  // the clock's reading at twin time 0
  double DeviceSeconds(double t_s) const { return offset_s + (1.0 + 1e-6 * rate_ppm) * t_s; }
};

inline constexpr double kMaxStallS = 0.04;

struct SimClocks {
  std::array<SimDeviceClock, kNumLegs> ft{};     // each Net F/T box's 7 kHz counter
  std::array<SimDeviceClock, kNumLegs> servo{};  // each servo's Realtime Tick
  SimDeviceClock mocap{};                        // the motion-capture system's frame clock
  double stall_every_s = 0.0;                    // mean interval between host stalls; 0: none
  double stall_max_s = 0.0;                      // a stall lasts U(0.2, 1) of this, s

  // A lab's: Net F/T boxes and servos tens of ppm off, each its own, the mocap clock a few;
  // counters at arbitrary power-up values; the host stalls for up to 25 ms twice a minute.
  static SimClocks Lab() {
    SimClocks c;
    constexpr std::array<double, kNumLegs> kFtPpm{38.0, -52.0, 17.0, -29.0, 61.0, -44.0};
    constexpr std::array<double, kNumLegs> kServoPpm{85.0, -63.0, 41.0, -92.0, 27.0, -70.0};
    for (int k = 0; k < kNumLegs; ++k) {
      c.ft[k] = {kFtPpm[k], 0.0};  // the power-up count is the writer's seeded draw
      // The servos booted at different instants: their millisecond edges fall apart.
      c.servo[k] = {kServoPpm[k], 0.1373 * (k + 1)};
    }
    c.mocap = {12.0, 37.25};  // the measurement started 37.25 s before the session
    c.stall_every_s = 30.0;
    c.stall_max_s = 0.025;
    return c;
  }
  // Every clock exact and the host never stalls (the twin before issue 38).
  static SimClocks Ideal() { return SimClocks{}; }

  // Throws std::invalid_argument naming the field.
  void Validate() const {
    auto check = [](const SimDeviceClock& c, const std::string& what) {
      if (!(std::abs(c.rate_ppm) <= 1000.0) || !std::isfinite(c.offset_s) || c.offset_s < 0) {
        throw std::invalid_argument("sim clocks: " + what +
                                    ": rate within +-1000 ppm and a finite offset >= 0 expected");
      }
    };
    for (int k = 0; k < kNumLegs; ++k) {
      check(ft[k], "ft[" + std::to_string(k) + "]");
      check(servo[k], "servo[" + std::to_string(k) + "]");
    }
    check(mocap, "mocap");
    if (!(stall_every_s >= 0) || !std::isfinite(stall_every_s) ||
        (stall_every_s > 0 && stall_every_s < 1.0)) {
      throw std::invalid_argument("sim clocks: stall_every_s " + std::to_string(stall_every_s) +
                                  ": 0 (no stalls) or at least 1 s");
    }
    if (!(stall_max_s >= 0 && stall_max_s <= kMaxStallS)) {
      throw std::invalid_argument("sim clocks: stall_max_s " + std::to_string(stall_max_s) +
                                  ": 0 to " + std::to_string(kMaxStallS) + " s");
    }
  }
};

}  // namespace ftcal
