// The aligner: sync rule, angle interpolation (hand-computed), waiting and holding, drops,
// attitude freshness, determinism.
#include "ftcal/aligner.h"

#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <vector>

#include <gtest/gtest.h>

namespace ftcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

struct Collect {
  std::vector<AlignedSample> out;
  Aligner::Callback cb() {
    return [this](const AlignedSample& s) { out.push_back(s); };
  }
};

Vec6 WrenchOf(int leg, double base) {
  Vec6 w;
  w << base + leg, base - leg, 10 * base, 0.1 * leg, -0.1 * base, 0.01 * (leg + base);
  return w;
}

ServoInput Servo(int64_t utime, const std::array<double, kNumLegs>& a) { return {utime, a}; }

MocapInput LevelMocap(int64_t utime, bool tracked = true, bool markers = true) {
  return {utime, tracked, Mat3::Identity(), markers};
}

void AllLegs(Aligner& a, int64_t utime, double base, int32_t flags = 0) {
  for (int k = 0; k < kNumLegs; ++k) ASSERT_TRUE(a.AddFt({utime, k, WrenchOf(k, base), flags}));
}

TEST(ServoHistory, InterpolatesUnwrappedAgainstHandComputedValues) {
  ServoHistory h;
  // Leg 0 moves 1.0 -> 1.2; leg 1 crosses the wrap: 3.1 -> -3.1 is +0.0831853 rad the short
  // way; leg 2 crosses it the other way; leg 3 is continuous (not wrapped) past 2 pi.
  ASSERT_TRUE(h.Add(Servo(1'000'000, {1.0, 3.1, -3.1, 6.2, 0.0, -0.5})));
  ASSERT_TRUE(h.Add(Servo(1'010'000, {1.2, -3.1, 3.1, 6.4, 0.0, -0.7})));
  const auto at = h.At(1'004'000);  // alpha = 0.4
  ASSERT_TRUE(at);
  EXPECT_TRUE(at->interpolated);
  const double short_way = 2 * M_PI - 6.2;  // 0.0831853...
  EXPECT_NEAR(at->angle_rad[0], 1.08, 1e-12);
  EXPECT_NEAR(at->angle_rad[1], 3.1 + 0.4 * short_way, 1e-12);
  EXPECT_NEAR(at->angle_rad[2], -3.1 - 0.4 * short_way, 1e-12);
  EXPECT_NEAR(at->angle_rad[3], 6.28, 1e-12);
  EXPECT_NEAR(at->angle_rad[4], 0.0, 1e-15);
  EXPECT_NEAR(at->angle_rad[5], -0.58, 1e-12);
  EXPECT_NEAR(at->age_s, 0.004, 1e-12);
  // Exactly at a state: that state's values, bit for bit.
  EXPECT_EQ(h.At(1'010'000)->angle_rad[1], -3.1);
  // After the newest: held, with its age.
  const auto late = h.At(1'030'000);
  EXPECT_FALSE(late->interpolated);
  EXPECT_EQ(late->angle_rad[0], 1.2);
  EXPECT_NEAR(late->age_s, 0.02, 1e-12);
  // Not newer than the newest: refused.
  EXPECT_FALSE(h.Add(Servo(1'010'000, {})));
}

TEST(Aligner, EmitsAtThePaceLegsTimeWithInterpolatedAnglesWhenTheLaterServoStateArrives) {
  Collect c;
  Aligner a({}, c.cb());
  a.AddMocap(LevelMocap(990'000));
  a.AddServo(Servo(1'000'000, {0.1, 0.2, 0.3, 0.4, 0.5, 0.6}));
  // Legs stamped 1.001 .. 1.006 s: every leg has a reading at or after the pace leg's 1.001 s
  // once the sixth has come.
  for (int k = 0; k < kNumLegs; ++k) a.AddFt({1'001'000 + 1000 * k, k, WrenchOf(k, 1.0), 0});
  a.AddMocap(LevelMocap(1'020'000));
  EXPECT_TRUE(c.out.empty()) << "must wait for a servo state after the sync time";
  EXPECT_EQ(a.pending(), 1u);
  a.AddServo(Servo(1'010'000, {0.2, 0.2, 0.1, 0.4, 0.5, 1.6}));
  ASSERT_EQ(c.out.size(), 1u);
  const SyncSample& s = c.out[0].sample;
  EXPECT_EQ(s.utime, 1'001'000);
  // alpha = 0.1: 0.1 + 0.01, 0.3 - 0.02, 0.6 + 0.1.
  EXPECT_NEAR(s.angle_rad[0], 0.11, 1e-12);
  EXPECT_NEAR(s.angle_rad[1], 0.2, 1e-12);
  EXPECT_NEAR(s.angle_rad[2], 0.28, 1e-12);
  EXPECT_NEAR(s.angle_rad[5], 0.7, 1e-12);
  for (int k = 0; k < kNumLegs; ++k) EXPECT_EQ(s.wrench[k], WrenchOf(k, 1.0)) << k;
  EXPECT_TRUE(s.attitude_ok);  // the nearer frame, 11 ms before
  EXPECT_TRUE(s.markers_ok);
  EXPECT_EQ(a.counters().emitted, 1);
}

TEST(Aligner, ASampleTakesEachLegsReadingNearestThePaceLegsInstant) {
  Collect c;
  Aligner a({}, c.cb());
  a.AddServo(Servo(0, {}));
  a.AddServo(Servo(1'000'000, {}));
  a.AddMocap(LevelMocap(0));
  a.AddMocap(LevelMocap(1'000'000));
  AllLegs(a, 100'000, 1.0);
  ASSERT_EQ(c.out.size(), 1u);
  // Five legs report again; the sixth is still at the old time: nothing yet (its next reading
  // may be nearer 110 ms than its 100 ms one).
  for (int k = 0; k < kNumLegs - 1; ++k) a.AddFt({110'000, k, WrenchOf(k, 2.0), 0});
  EXPECT_EQ(c.out.size(), 1u);
  // Leg 0 reports again before the sixth does: the instant stays 110 ms, and leg 0's reading
  // there is used, not its latest.
  a.AddFt({120'000, 0, WrenchOf(0, 3.0), 4});
  a.AddFt({112'000, kNumLegs - 1, WrenchOf(kNumLegs - 1, 2.0), 1});
  ASSERT_EQ(c.out.size(), 2u);
  EXPECT_EQ(c.out[1].sample.utime, 110'000);
  EXPECT_EQ(c.out[1].sample.wrench[0], WrenchOf(0, 2.0));
  EXPECT_EQ(c.out[1].sample.wrench[1], WrenchOf(1, 2.0));
  EXPECT_EQ(c.out[1].flags, 1);  // OR of the readings used
  // The 120 ms instant: leg 5's nearest is its 112 ms reading until one at or after 120 ms
  // comes; 127 ms is nearer than 112 ms.
  for (int k = 1; k < kNumLegs - 1; ++k) a.AddFt({121'000, k, WrenchOf(k, 4.0), 0});
  EXPECT_EQ(c.out.size(), 2u);
  a.AddFt({127'000, kNumLegs - 1, WrenchOf(kNumLegs - 1, 5.0), 0});
  ASSERT_EQ(c.out.size(), 3u);
  EXPECT_EQ(c.out[2].sample.utime, 120'000);
  EXPECT_EQ(c.out[2].sample.wrench[0], WrenchOf(0, 3.0));
  EXPECT_EQ(c.out[2].sample.wrench[kNumLegs - 1], WrenchOf(kNumLegs - 1, 5.0));
  EXPECT_EQ(c.out[2].flags, 4);
}

// A transducer's readings come a datagram at a time, and the six legs' datagrams in any
// order, on clocks up to 60 us apart (under half the 143 us period): the samples are those of the
// readings one at a time, leg after leg, whichever order the batches arrive in.
TEST(Aligner, BatchedLegsInAnyOrderGiveTheSamplesOfInterleavedReadings) {
  auto reading = [](int k, int j) {
    return FtInput{1'000'000 + 143 * j + 12 * k, k, WrenchOf(k, 0.5 * j), j % 5 == 0 ? 2 : 0};
  };
  constexpr int kBatch = 7, kBatches = 30;
  auto run = [&](const std::vector<int>& order_of_batch, bool batched) {
    Collect c;
    Aligner a({}, c.cb());
    a.AddServo(Servo(0, {0.1, 0.2, 0.3, 0.4, 0.5, 0.6}));
    a.AddServo(Servo(2'000'000, {0.2, 0.2, 0.3, 0.4, 0.5, 0.6}));
    a.AddMocap(LevelMocap(0));
    a.AddMocap(LevelMocap(2'000'000));
    for (int b = 0; b < kBatches; ++b) {
      if (batched) {
        for (int k : order_of_batch) {
          for (int j = b * kBatch; j < (b + 1) * kBatch; ++j) a.AddFt(reading(k, j));
        }
      } else {
        for (int j = b * kBatch; j < (b + 1) * kBatch; ++j) {
          for (int k = 0; k < kNumLegs; ++k) a.AddFt(reading(k, j));
        }
      }
    }
    return c.out;
  };
  const auto one_at_a_time = run({}, false);
  // Every pace-leg instant gives a sample (the other legs stamp later than leg 0).
  ASSERT_EQ(one_at_a_time.size(), static_cast<size_t>(kBatch * kBatches));
  for (size_t j = 0; j < one_at_a_time.size(); ++j) {
    const AlignedSample& s = one_at_a_time[j];
    EXPECT_EQ(s.sample.utime, reading(0, static_cast<int>(j)).utime);
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_EQ(s.sample.wrench[k], reading(k, static_cast<int>(j)).wrench) << j << " " << k;
    }
  }
  for (const std::vector<int>& order :
       {std::vector<int>{0, 1, 2, 3, 4, 5}, {5, 4, 3, 2, 1, 0}, {3, 0, 5, 1, 4, 2}}) {
    const auto batched = run(order, true);
    ASSERT_EQ(batched.size(), one_at_a_time.size());
    for (size_t j = 0; j < batched.size(); ++j) {
      EXPECT_EQ(batched[j].sample.utime, one_at_a_time[j].sample.utime);
      EXPECT_EQ(batched[j].flags, one_at_a_time[j].flags);
      EXPECT_EQ(batched[j].sample.angle_rad, one_at_a_time[j].sample.angle_rad);
      for (int k = 0; k < kNumLegs; ++k) {
        EXPECT_EQ(batched[j].sample.wrench[k], one_at_a_time[j].sample.wrench[k]);
      }
    }
  }
}

TEST(Aligner, HoldsTheNewestServoStateOnlyWithinItsMaxAgeAndNeverExtrapolates) {
  Collect c;
  AlignerOptions opt;
  opt.max_servo_age_s = 0.05;
  Aligner a(opt, c.cb());
  a.AddServo(Servo(1'000'000, {0.5, 0.5, 0.5, 0.5, 0.5, 0.5}));
  AllLegs(a, 1'020'000, 1.0);  // waits
  AllLegs(a, 1'060'000, 1.0);  // 40 ms later: still within the wait
  EXPECT_TRUE(c.out.empty());
  AllLegs(a, 1'080'000, 1.0);  // the first waited 60 ms > 50: held (20 ms old state)
  ASSERT_EQ(c.out.size(), 1u);
  EXPECT_EQ(c.out[0].sample.utime, 1'020'000);
  EXPECT_EQ(c.out[0].sample.angle_rad[0], 0.5);
  EXPECT_EQ(a.counters().servo_held, 1);
  AllLegs(a, 1'200'000, 1.0);  // the 1.06 and 1.08 s samples: 60 and 80 ms from the state
  EXPECT_EQ(c.out.size(), 1u);
  EXPECT_EQ(a.counters().stale_servo, 2);
  EXPECT_EQ(a.pending(), 1u);
}

TEST(Aligner, DropsOutOfOrderAndNonFiniteInputsWithoutChangingTheOutput) {
  Collect clean, dirty;
  Aligner a({}, clean.cb()), b({}, dirty.cb());
  for (Aligner* x : {&a, &b}) {
    x->AddServo(Servo(0, {0.1, 0.1, 0.1, 0.1, 0.1, 0.1}));
    x->AddMocap(LevelMocap(0));
  }
  for (int i = 1; i <= 5; ++i) {
    const int64_t t = 10'000 * i;
    for (Aligner* x : {&a, &b}) {
      x->AddServo(Servo(t, {0.1 * i, 0.1, 0.1, 0.1, 0.1, 0.1}));
      x->AddMocap(LevelMocap(t));
      AllLegs(*x, t, i);
    }
    // Only b sees the garbage: a stale reading, a NaN wrench, a NaN angle, an old servo
    // state, an old and a non-finite mocap frame.
    EXPECT_FALSE(b.AddFt({t - 5'000, 2, WrenchOf(2, 99.0), 0}));
    Vec6 bad = WrenchOf(3, 1.0);
    bad[4] = kNaN;
    EXPECT_FALSE(b.AddFt({t + 1, 3, bad, 0}));
    EXPECT_FALSE(b.AddServo(Servo(t + 1, {kNaN, 0, 0, 0, 0, 0})));
    EXPECT_FALSE(b.AddServo(Servo(t - 1, {9, 9, 9, 9, 9, 9})));
    EXPECT_FALSE(b.AddMocap(LevelMocap(t - 1)));
    MocapInput m = LevelMocap(t + 1);
    m.R_WC(0, 0) = kNaN;
    EXPECT_FALSE(b.AddMocap(m));
  }
  EXPECT_EQ(b.counters().out_of_order, 3 * 5);
  EXPECT_EQ(b.counters().non_finite, 3 * 5);
  ASSERT_EQ(clean.out.size(), dirty.out.size());
  ASSERT_EQ(clean.out.size(), 5u);  // servo state and readings share each time stamp
  for (size_t i = 0; i < clean.out.size(); ++i) {
    EXPECT_EQ(clean.out[i].sample.utime, dirty.out[i].sample.utime);
    EXPECT_EQ(clean.out[i].sample.angle_rad, dirty.out[i].sample.angle_rad);
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_EQ(clean.out[i].sample.wrench[k], dirty.out[i].sample.wrench[k]);
    }
  }
}

TEST(Aligner, AttitudeIsOkOnlyWhenTrackedAndFreshAndMarkersFollowTheFrame) {
  Collect c;
  AlignerOptions opt;
  opt.max_mocap_age_s = 0.03;
  Aligner a(opt, c.cb());
  const Mat3 R = RotationFromRollPitchYaw(0.1, -0.05, 0.0);
  a.AddServo(Servo(0, {}));
  a.AddServo(Servo(10'000'000, {}));
  AllLegs(a, 100'000, 1.0);  // no frame comes within 30 ms of transducer time: none at all
  AllLegs(a, 131'000, 1.0);
  a.AddMocap({140'000, true, R, false});  // the nearest to 131 ms: fresh, a marker missing
  AllLegs(a, 180'000, 1.0);
  a.AddMocap({221'000, false, Mat3::Identity(), false});  // 180 ms: 140 is nearer, 40 ms old
  AllLegs(a, 230'000, 1.0);                               // 230 ms: 221 is nearer, untracked
  a.AddMocap({260'000, true, R, true});
  AllLegs(a, 262'000, 1.0);  // all good
  a.AddMocap({280'000, true, R, true});
  ASSERT_EQ(c.out.size(), 5u);
  EXPECT_FALSE(c.out[0].sample.attitude_ok);
  EXPECT_TRUE(c.out[0].sample.R_WC.isIdentity());
  EXPECT_TRUE(c.out[1].sample.attitude_ok);
  EXPECT_FALSE(c.out[1].sample.markers_ok);
  EXPECT_TRUE(c.out[1].sample.R_WC.isApprox(R, 1e-15));
  EXPECT_FALSE(c.out[2].sample.attitude_ok);
  EXPECT_FALSE(c.out[3].sample.attitude_ok);
  EXPECT_TRUE(c.out[4].sample.attitude_ok);
  EXPECT_TRUE(c.out[4].sample.markers_ok);
  EXPECT_EQ(a.counters().stale_mocap, 3);
}

// Jittered, interleaved streams as a real bus delivers them: the same input order gives the
// same output, every time, and the sync times increase strictly.
TEST(Aligner, SameInputOrderGivesIdenticalOutput) {
  std::mt19937_64 rng(7);
  std::uniform_int_distribution<int> jitter(0, 3000);
  struct Event {
    int kind;  // 0 ft, 1 servo, 2 mocap
    FtInput ft;
    ServoInput servo;
    MocapInput mocap;
  };
  std::vector<Event> events;
  for (int i = 0; i < 2000; ++i) {
    const int64_t t = 1'000'000 + 10'000 * static_cast<int64_t>(i);
    std::vector<Event> frame;
    for (int k = 0; k < kNumLegs; ++k) {
      Event e{0, {t + jitter(rng), k, WrenchOf(k, std::sin(0.01 * i)), 0}, {}, {}};
      frame.push_back(e);
    }
    Event s{1, {}, {}, {}};
    s.servo.utime = t + jitter(rng);
    for (int k = 0; k < kNumLegs; ++k) s.servo.angle_rad[k] = std::sin(0.003 * i + k);
    frame.push_back(s);
    Event m{2,
            {},
            {},
            {t + jitter(rng), i % 50 != 0,
             RotationFromRollPitchYaw(0.01 * std::sin(0.02 * i), 0, 0), i % 7 != 0}};
    frame.push_back(m);
    std::shuffle(frame.begin(), frame.end(), rng);
    events.insert(events.end(), frame.begin(), frame.end());
  }
  auto run = [&events] {
    Collect c;
    Aligner a({}, c.cb());
    for (const Event& e : events) {
      if (e.kind == 0) a.AddFt(e.ft);
      if (e.kind == 1) a.AddServo(e.servo);
      if (e.kind == 2) a.AddMocap(e.mocap);
    }
    return c.out;
  };
  const auto first = run();
  const auto second = run();
  ASSERT_GT(first.size(), 1900u);
  ASSERT_EQ(first.size(), second.size());
  for (size_t i = 0; i < first.size(); ++i) {
    const SyncSample& x = first[i].sample;
    const SyncSample& y = second[i].sample;
    ASSERT_EQ(x.utime, y.utime);
    ASSERT_EQ(x.angle_rad, y.angle_rad);
    ASSERT_EQ(x.R_WC, y.R_WC);
    ASSERT_EQ(x.attitude_ok, y.attitude_ok);
    ASSERT_EQ(x.markers_ok, y.markers_ok);
    for (int k = 0; k < kNumLegs; ++k) ASSERT_EQ(x.wrench[k], y.wrench[k]);
    if (i > 0) {
      ASSERT_GT(x.utime, first[i - 1].sample.utime);
    }
  }
}

}  // namespace
}  // namespace ftcal

namespace ftcal {
namespace {

// A servo bus 16 ms late (docs/method.md "Latencies"): with servo_delay_s set, a transducer
// sample takes the angle the servo stream reports 16 ms after it, hand-computed; an option at or
// beyond the wait for a servo state is refused.
TEST(Aligner, ServoDelayTakesTheAngleReportedThatMuchLater) {
  AlignerOptions options;
  options.servo_delay_s = 0.016;
  Collect c;
  Aligner a(options, c.cb());
  // The shaft turns 1 rad/s; the servo stamps it 16 ms late: the state stamped u + 16 ms holds
  // the angle of instant u.
  for (int i = 0; i <= 10; ++i) {
    const int64_t instant = 1'000'000 + 10'000 * i;
    std::array<double, kNumLegs> angle;
    angle.fill(1e-6 * static_cast<double>(instant - 1'000'000));
    ASSERT_TRUE(a.AddServo(Servo(instant + 16'000, angle)));
    ASSERT_TRUE(a.AddMocap(LevelMocap(instant)));
  }
  AllLegs(a, 1'025'000, 1.0);
  AllLegs(a, 1'055'000, 2.0);
  AllLegs(a, 1'200'000, 3.0);  // moves the transducers' clock past every wait
  ASSERT_GE(c.out.size(), 2u);
  EXPECT_NEAR(c.out[0].sample.angle_rad[0], 0.025, 1e-12);
  EXPECT_NEAR(c.out[1].sample.angle_rad[3], 0.055, 1e-12);

  AlignerOptions too_late;
  too_late.servo_delay_s = 0.05;
  EXPECT_THROW(Aligner(too_late, nullptr), std::invalid_argument);
}

}  // namespace
}  // namespace ftcal
