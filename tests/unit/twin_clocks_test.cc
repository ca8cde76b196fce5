// The twin's device clocks against the bridges' maps of them (issue 38, items 1 and 4): 90 min of
// session at 100 Hz through TwinDeviceStamps, the clock code ftcal-sim log writes with, with a
// lab's clocks (SimClocks::Lab(): each device tens of ppm off and its own origin, the host
// stalling for up to 25 ms twice a minute) and the log's latencies. The truth is the twin's:
// every sample's instant (twin time), each device's rate and the least latency the test drew.
//
// Goal (issue 38): skew within 2 ppm of the truth, mapped sample times within 0.2 ms of the
// true instant (plus the least latency, which no clock can tell from the offset).
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>

#include "sim/device_stamps.h"
#include "sim/sim_clocks.h"

namespace ftcal {
namespace {

constexpr int64_t kT0 = 1'700'000'000'000'000;
constexpr double kSessionS = 90 * 60.0;
// A map younger than this is not held to the goal: a servo's map needs 30 s of ticks before it
// bounds the bus time (SyncReadClock), and the bound its window.
constexpr double kWarmUpS = 60.0;

// The skew a map of device time onto host time has when the device runs rate_ppm fast.
double TrueSkewPpm(const SimDeviceClock& c) {
  return (1.0 / (1.0 + 1e-6 * c.rate_ppm) - 1.0) * 1e6;
}

struct Errors {
  double max_us = 0, sum_sq = 0;
  int64_t n = 0;
  void Add(double e) {
    max_us = std::max(max_us, std::abs(e));
    sum_sq += e * e;
    ++n;
  }
  double rms_us() const { return n ? std::sqrt(sum_sq / static_cast<double>(n)) : 0.0; }
};

struct ClockRun {
  std::array<Errors, kNumLegs> ft;
  Errors servo, mocap;
  std::array<double, kNumLegs> ft_skew_error_ppm{}, servo_skew_error_ppm{};
  double mocap_skew_error_ppm = 0;
  int64_t stalls = 0;
};

// servo_timer_s: the servo replies' extra wait, uniform in [0, servo_timer_s): a USB-serial
// adapter's latency timer (0: the log's own 1.5 ms of jitter only).
ClockRun Simulate(const SimClocks& clocks, double servo_timer_s, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::array<int64_t, kNumLegs> count0{}, tick0{};
  std::array<double, kNumLegs> ft_least_s{};
  for (int k = 0; k < kNumLegs; ++k) {
    count0[k] = static_cast<int64_t>(rng() >> 33);
    tick0[k] = static_cast<int64_t>(u(rng) * 32768.0);
    ft_least_s[k] = 0.0005 + 0.0003 * u(rng);  // the log writer's ranges (log_writer.cc)
  }
  constexpr double kServoLeastS = 0.002, kMocapLeastS = 0.004;
  TwinDeviceStamps stamps(clocks, seed, kT0, count0, tick0);
  ClockRun run;
  const auto frames = static_cast<int64_t>(kSessionS * 100.0);
  for (int64_t i = 0; i < frames; ++i) {
    const double t = 0.01 * static_cast<double>(i);
    const int64_t truth = kT0 + std::llround(t * 1e6);
    const bool judged = t >= kWarmUpS;
    for (int k = 0; k < kNumLegs; ++k) {
      const int64_t receipt =
          stamps.HostStamp(truth + std::llround((ft_least_s[k] + 0.001 * u(rng)) * 1e6));
      const auto s = stamps.FtSample(k, t, receipt);
      if (judged) {
        run.ft[k].Add(static_cast<double>(s.sample_utime - truth) - ft_least_s[k] * 1e6);
      }
    }
    const int64_t completion = stamps.HostStamp(
        truth + std::llround((kServoLeastS + 0.0015 * u(rng) + servo_timer_s * u(rng)) * 1e6));
    const auto& servo = stamps.ServoSample(t, completion);
    if (judged) run.servo.Add(static_cast<double>(servo.sample_utime - truth) - kServoLeastS * 1e6);
    const int64_t receipt =
        stamps.HostStamp(truth + std::llround((kMocapLeastS + 0.0015 * u(rng)) * 1e6));
    const auto frame = stamps.MocapSample(t, receipt);
    if (judged) run.mocap.Add(static_cast<double>(frame.sample_utime - truth) - kMocapLeastS * 1e6);
  }
  for (int k = 0; k < kNumLegs; ++k) {
    run.ft_skew_error_ppm[k] = stamps.ft_clock(k).skew_ppm() - TrueSkewPpm(clocks.ft[k]);
    run.servo_skew_error_ppm[k] =
        stamps.servo_clock().clock(k).skew_ppm() - TrueSkewPpm(clocks.servo[k]);
  }
  run.mocap_skew_error_ppm = stamps.mocap_clock().skew_ppm() - TrueSkewPpm(clocks.mocap);
  run.stalls = stamps.stalls();
  return run;
}

void Print(const char* what, const ClockRun& r) {
  for (int k = 0; k < kNumLegs; ++k) {
    std::printf(
        "[ clocks ] %s FT_%s: skew error %+.3f ppm, mapped time error max %.1f us rms %.1f\n", what,
        std::string(kLegNames[k]).c_str(), r.ft_skew_error_ppm[k], r.ft[k].max_us,
        r.ft[k].rms_us());
  }
  for (int k = 0; k < kNumLegs; ++k) {
    std::printf("[ clocks ] %s servo %s tick: skew error %+.3f ppm\n", what,
                std::string(kLegNames[k]).c_str(), r.servo_skew_error_ppm[k]);
  }
  std::printf("[ clocks ] %s SERVO_STATE read instant: mapped time error max %.1f us rms %.1f\n",
              what, r.servo.max_us, r.servo.rms_us());
  std::printf(
      "[ clocks ] %s MOCAP_BODY: skew error %+.3f ppm, mapped time error max %.1f us "
      "rms %.1f; %lld stamps in host stalls\n",
      what, r.mocap_skew_error_ppm, r.mocap.max_us, r.mocap.rms_us(),
      static_cast<long long>(r.stalls));
}

void ExpectWithinGoal(const ClockRun& r) {
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_LT(std::abs(r.ft_skew_error_ppm[k]), 2.0) << "FT_" << kLegNames[k];
    EXPECT_LT(r.ft[k].max_us, 200.0) << "FT_" << kLegNames[k];
    EXPECT_LT(std::abs(r.servo_skew_error_ppm[k]), 2.0) << "servo " << kLegNames[k];
  }
  EXPECT_LT(r.servo.max_us, 200.0);
  EXPECT_LT(std::abs(r.mocap_skew_error_ppm), 2.0);
  EXPECT_LT(r.mocap.max_us, 200.0);
  EXPECT_GT(r.stalls, 0);  // the host did stall: the maps were held to the goal through it
}

TEST(TwinClocks, NinetyMinutesOfALabsClocksMapWithinGoal) {
  const ClockRun r = Simulate(SimClocks::Lab(), 0.0, 11);
  Print("lab", r);
  ExpectWithinGoal(r);
}

// A servo bus behind a USB-serial adapter's 16 ms latency timer (not the twin's default): so few
// replies come through undelayed that a tick's millisecond is rarely pinned by its map. The
// rates are still held to 2 ppm; the read's instant only in the mean (rms under 0.2 ms; its
// largest error is printed, up to most of a millisecond: docs/method.md).
TEST(TwinClocks, ServoBehindALatencyTimerKeepsItsRatesAndMeanInstant) {
  const ClockRun r = Simulate(SimClocks::Lab(), 0.016, 12);
  Print("16 ms timer", r);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_LT(std::abs(r.servo_skew_error_ppm[k]), 2.0) << "servo " << kLegNames[k];
  }
  EXPECT_LT(r.servo.rms_us(), 200.0);
}

// The stamps themselves: a stall delays a host stamp to its end, and only while it lasts.
TEST(TwinClocks, HostStallsDelayStampsToTheirEnd) {
  SimClocks c = SimClocks::Ideal();
  c.stall_every_s = 2.0;
  c.stall_max_s = 0.02;
  TwinDeviceStamps stamps(c, 3, kT0, {}, {});
  int64_t delayed = 0, longest = 0, last = 0;
  for (int64_t i = 0; i < 60'000; ++i) {  // 60 s at 1 kHz
    const int64_t due = kT0 + 1000 * i;
    const int64_t stamped = stamps.HostStamp(due);
    ASSERT_GE(stamped, due);
    ASSERT_GE(stamped, last);  // rising stamps stay rising
    ASSERT_LE(stamped - due, 20'000);
    delayed += stamped > due;
    longest = std::max(longest, stamped - due);
    last = stamped;
  }
  // Stalls of 4-20 ms about every 2 s (at least 1 s apart): 20-30 of them, each delaying the
  // stamps due in it.
  EXPECT_GT(delayed, 20 * 4);
  EXPECT_LT(delayed, 60 * 20);
  EXPECT_GT(longest, 4'000);
}

TEST(TwinClocks, ImpossibleClocksAreRefusedNamingTheField) {
  SimClocks c = SimClocks::Lab();
  c.servo[2].rate_ppm = 5000;
  try {
    c.Validate();
    FAIL() << "accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("servo[2]"), std::string::npos) << e.what();
  }
  c = SimClocks::Lab();
  c.stall_max_s = 0.5;
  EXPECT_THROW(c.Validate(), std::invalid_argument);
}

}  // namespace
}  // namespace ftcal
