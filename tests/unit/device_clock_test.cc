// DeviceClock (libcal/include/ftcal/device_clock.h) against clocks whose truth the test makes:
// a device counter at its own rate (tens of ppm off nominal, drifting), receipts behind it by a
// constant least delay plus one-sided queuing delay with host stalls. The goals are issue 38's:
// the skew within 2 ppm, mapped sample times within 0.2 ms of the truth over a 90-minute session.
#include "ftcal/device_clock.h"

#include <cmath>
#include <cstdint>
#include <iostream>
#include <random>
#include <stdexcept>
#include <string>

#include <gtest/gtest.h>

namespace ftcal {
namespace {

constexpr int64_t kHostStartUs = 1'765'000'000'000'000;  // a December 2025 Unix time

TEST(DeviceClock, ThreePointsOnALineGiveItsRate) {
  DeviceClockOptions o;
  o.nominal_hz = 1;
  o.min_span_s = 0;
  DeviceClock clock(o);
  EXPECT_EQ(clock.Observe(100, kHostStartUs), kHostStartUs);
  EXPECT_EQ(clock.Observe(101, kHostStartUs + 1'000'010), kHostStartUs + 1'000'010);
  // The third point 5 us late: on or above the line through the first two (10 ppm).
  EXPECT_EQ(clock.Observe(102, kHostStartUs + 2'000'025), kHostStartUs + 2'000'020);
  EXPECT_NEAR(clock.skew_ppm(), 10.0, 1e-6);
  EXPECT_EQ(clock.Map(110), kHostStartUs + 10'000'100);
}

TEST(DeviceClock, BelowTheMinimumSpanTheRateIsNominalAndTheLineUnderEveryPoint) {
  DeviceClockOptions o;
  o.nominal_hz = 1000;
  o.min_span_s = 2;
  DeviceClock clock(o);
  clock.Observe(0, kHostStartUs + 700);
  clock.Observe(500, kHostStartUs + 500'300);  // 0.4 ms earlier relative to the first
  const int64_t mapped = clock.Observe(1000, kHostStartUs + 1'000'900);
  EXPECT_EQ(clock.skew_ppm(), 0.0);
  EXPECT_EQ(mapped, kHostStartUs + 1'000'300);
}

struct Session {
  double nominal_hz;
  double minutes;
  double skew_start_ppm, skew_end_ppm;  // host seconds per device second, minus 1, in ppm
  double least_delay_s = 0.0004;
  double mean_queue_s = 0.0005;
  double latency_timer_s = 0;  // > 0: the queuing is uniform in [0, this) (a USB-serial adapter)
  double stall_every_s = 30, stall_s = 0.1, stall_max_s = 0.02;
  uint32_t seed = 1;
};

struct Errors {
  double max_time_error_s = 0;    // |mapped - (sample time + least delay)|, after the first 10 s
  double max_skew_error_ppm = 0;  // |skew - truth|, once the fit spans its window (100 s)
  double late_mapped = 0;         // mapped later than received (must never happen)
  int64_t samples = 0;
};

Errors RunSession(const Session& s, DeviceClock& clock) {
  std::mt19937_64 rng(s.seed);
  std::exponential_distribution<double> queue(1.0 / s.mean_queue_s);
  std::uniform_real_distribution<double> unit(0, 1);
  Errors e;
  const int64_t n = static_cast<int64_t>(s.minutes * 60 * s.nominal_hz);
  const int64_t tick0 = 4'000'000'000;  // far from 0: the map must not depend on the origin
  double host_s = 0;                    // the sample's true host time since the start
  double next_stall_s = s.stall_every_s * unit(rng);
  for (int64_t i = 0; i < n; ++i) {
    const double frac = static_cast<double>(i) / static_cast<double>(n);
    const double skew_ppm = s.skew_start_ppm + (s.skew_end_ppm - s.skew_start_ppm) * frac;
    if (i > 0) host_s += (1.0 + skew_ppm * 1e-6) / s.nominal_hz;
    double receipt_s = host_s + s.least_delay_s +
                       (s.latency_timer_s > 0 ? s.latency_timer_s * unit(rng) : queue(rng));
    if (host_s >= next_stall_s) {  // the host did not run the receiver: everything waits
      if (host_s < next_stall_s + s.stall_s) {
        receipt_s = std::max(receipt_s, next_stall_s + s.stall_s + s.stall_max_s * unit(rng));
      } else {
        next_stall_s += s.stall_every_s;
      }
    }
    const int64_t receipt_us = kHostStartUs + std::llround(receipt_s * 1e6);
    const int64_t mapped_us = clock.Observe(tick0 + i, receipt_us);
    if (mapped_us > receipt_us) ++e.late_mapped;
    const double t = static_cast<double>(i) / s.nominal_hz;
    if (t < 10) continue;
    ++e.samples;
    const double truth_us = static_cast<double>(kHostStartUs) + (host_s + s.least_delay_s) * 1e6;
    e.max_time_error_s =
        std::max(e.max_time_error_s, std::abs(static_cast<double>(mapped_us) - truth_us) * 1e-6);
    if (clock.fit_span_s() >= 100) {
      e.max_skew_error_ppm = std::max(e.max_skew_error_ppm, std::abs(clock.skew_ppm() - skew_ppm));
    }
  }
  return e;
}

// Runs `s` on a clock at its nominal rate, checks issue 38's goals and prints the figures;
// returns the clock for checks of its own.
DeviceClock ExpectWithinGoals(const Session& s, const std::string& what) {
  DeviceClockOptions o;
  o.nominal_hz = s.nominal_hz;
  DeviceClock clock(o);
  const Errors e = RunSession(s, clock);
  EXPECT_EQ(e.late_mapped, 0) << what;
  EXPECT_LT(e.max_time_error_s, 0.0002) << what;
  EXPECT_LT(e.max_skew_error_ppm, 2.0) << what;
  std::cout << what << ": max mapped-time error " << e.max_time_error_s * 1e6
            << " us, max skew error " << e.max_skew_error_ppm << " ppm over " << e.samples
            << " samples\n";
  return clock;
}

TEST(DeviceClock, ANinetyMinuteSessionWithDriftingSkewAndStallsMapsWithinGoal) {
  // A servo bus's Realtime Tick (1 ms), 35 ppm fast drifting to 45 ppm as the board warms up.
  Session s{1000, 90, 35, 45};
  const DeviceClock clock = ExpectWithinGoals(s, "90 min at 1 kHz, skew 35 -> 45 ppm");
  EXPECT_EQ(clock.restarts(), 0);
}

TEST(DeviceClock, ANetFtCounterAt7kHzWithASlowClockAndHeavyQueuing) {
  // A Net F/T's 7 kHz sample counter 60 ppm slow; receipts queued 2 ms on average (heavy-tailed).
  Session s{7000, 10, -60, -60};
  s.mean_queue_s = 0.002;
  s.stall_every_s = 5;
  ExpectWithinGoals(s, "10 min at 7 kHz, skew -60 ppm, 2 ms mean queuing");
}

TEST(DeviceClock, AServoBusAt100HzBehindA16msLatencyTimer) {
  // The bus's 100 Hz cycle stamped at its end, behind an FTDI adapter that holds each reply up
  // to its 16 ms latency timer: few receipts come near the least delay.
  Session s{100, 90, 20, 20};
  s.latency_timer_s = 0.016;
  s.seed = 7;
  ExpectWithinGoals(s, "90 min at 100 Hz behind a 16 ms latency timer");
}

TEST(DeviceClock, ACounterThatFallsOrAHostClockThatStepsBackStartsAfresh) {
  DeviceClockOptions o;
  o.nominal_hz = 1000;
  DeviceClock clock(o);
  int64_t us = kHostStartUs;
  for (int i = 0; i < 5000; ++i) clock.Observe(1000 + i, us + i * 1000);
  // The device rebooted: its counter starts near 0.
  EXPECT_EQ(clock.Observe(3, us + 5'000'000), us + 5'000'000);
  EXPECT_EQ(clock.restarts(), 1);
  for (int i = 1; i < 5000; ++i) {
    EXPECT_EQ(clock.Observe(3 + i, us + 5'000'000 + i * 1000), us + 5'000'000 + i * 1000);
  }
  // The host's clock stepped back by a second (an NTP step): no queuing explains it.
  const int64_t stepped = us + 5'000'000 + 5000 * 1000 - 1'000'000;
  EXPECT_EQ(clock.Observe(3 + 5000, stepped), stepped);
  EXPECT_EQ(clock.restarts(), 2);
  EXPECT_EQ(clock.Observe(3 + 5001, stepped + 1000), stepped + 1000);
}

TEST(DeviceClock, ACounterThatStandsStillWhileTimeGoesOnStartsAfreshAfterASecond) {
  // ftcal-sim's log between two scenarios: the devices fall silent for 2 s and resume where
  // their counters stopped. Every later sample is 2 s late by the old map: not a stall that
  // drains.
  DeviceClockOptions o;
  o.nominal_hz = 100;
  DeviceClock clock(o);
  const int64_t us = kHostStartUs;
  for (int i = 0; i < 1000; ++i) clock.Observe(i, us + i * 10'000);
  int64_t late = 0;
  for (int i = 1000; i < 2000; ++i) {
    const int64_t receipt = us + 2'000'000 + i * 10'000;
    late += clock.Observe(i, receipt) < receipt - 1'000'000;
  }
  EXPECT_EQ(clock.restarts(), 1);
  EXPECT_EQ(late, 100);  // the second of them before the map gave up on its line
  EXPECT_EQ(clock.Map(1999), us + 2'000'000 + 1999 * 10'000);
}

TEST(DeviceClock, RefusesANominalRateThatIsNotPositive) {
  DeviceClockOptions o;
  o.nominal_hz = 0;
  EXPECT_THROW(DeviceClock{o}, std::invalid_argument);
}

}  // namespace
}  // namespace ftcal
