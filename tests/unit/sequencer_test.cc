// The sequencer: plan -> schedule (Gray order, limits, timing), the safety rules against the
// twin's own readings, and whole runs in simulated time with the BigAnt twin as the robot: the
// servos follow the commands (first-order), the transducers and motion capture are the twin's
// standing frames (BigAntTwin::Driven). The bus here is a manual clock: publications loop back
// to the subscribers, and the test decides what time it is (holds of seconds in microseconds of
// test time, and the abort rules at exact times). The commands pass through the Dynamixel
// bridge's own command gate (signed envelopes opened with the config's trusted keys, ARM, the
// dead-man), so the sequencer is tested against the rules the real bridge enforces.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <set>
#include <unistd.h>

#include <gtest/gtest.h>
#include <sodium.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/envelope.h"
#include "dynamixel_bridge/command_gate.h"
#include "ftcal/config.h"
#include "ftcal/service_status_t.hpp"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/servo_command_t.hpp"
#include "sequencer/plan.h"
#include "sequencer/safety.h"
#include "sequencer/sequencer.h"
#include "sim/twin.h"

namespace ftcal::sequencer {
namespace {

constexpr double kDeg = M_PI / 180.0;

std::string ShippedConfigText(const std::string& name) {
  std::ifstream in(std::string(FTCAL_SOURCE_DIR) + "/config/" + name, std::ios::binary);
  EXPECT_TRUE(in.good()) << name;
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// The sequencer's key for these tests: made at test time, never a committed one.
auth::Signer& TestSigner() {
  static auth::Signer signer = [] {
    auth::InitSodium();
    std::array<uint8_t, auth::kSeedBytes> seed{};
    randombytes_buf(seed.data(), seed.size());
    return auth::Signer::FromSeed(seed);
  }();
  return signer;
}

// sim.pbtxt with `extra` and the test key trusted on SERVO_CMD and EXPERIMENT.
config::Config SimConfig(const std::string& extra = "", bool allow_unsigned = true) {
  const auth::PublicKey& key = TestSigner().public_key();
  std::string text = ShippedConfigText("sim.pbtxt") + extra;
  const std::string open = "\nauth {\n";
  const size_t at = text.find(open);
  EXPECT_NE(at, std::string::npos) << "sim.pbtxt has no auth section";
  text.insert(at + open.size(), "  trusted_key { name: \"sequencer\" public_key_hex: \"" +
                                    auth::ToHex(key.data(), key.size()) +
                                    "\" channel: \"SERVO_CMD\" channel: \"EXPERIMENT\" }\n");
  config::Config c = LoadConfigText(text, "sim.pbtxt+test");
  c.mutable_auth()->set_allow_unsigned(allow_unsigned);
  return c;
}

// ---- plan -> schedule ----

TEST(GrayGrid, EveryPoseOnceAndOneLegOneStepApart) {
  const std::vector<double> grid = {-36 * kDeg, 0.0, 36 * kDeg};
  const auto poses = GrayGrid(grid);
  ASSERT_EQ(poses.size(), 729u);
  std::set<Angles> unique(poses.begin(), poses.end());
  EXPECT_EQ(unique.size(), 729u);
  for (size_t i = 1; i < poses.size(); ++i) {
    int changed = 0;
    for (int k = 0; k < kNumLegs; ++k) {
      const double d = std::abs(poses[i][k] - poses[i - 1][k]);
      if (d > 1e-12) {
        ++changed;
        EXPECT_NEAR(d, 36 * kDeg, 1e-12) << "pose " << i << " leg " << k;
      }
    }
    EXPECT_EQ(changed, 1) << "pose " << i;
  }
}

TEST(Expand, ShortStandingPlanTimesEveryMoveUnderTheSpeedLimit) {
  config::Config c = SimConfig(R"(
plan { name: "grid" phase { kind: PHASE_STANDING_GRID pose_stride: 81 dwell_s: 2 } }
)");
  c.mutable_sequencer()->set_max_velocity_rad_s(0.5);
  const Schedule s = Expand(c, "grid");
  int holds = 0, starts = 0, stops = 0;
  std::vector<Angles> poses;
  for (const Step& st : s.steps) {
    if (st.kind == StepKind::kHold) {
      ++holds;
      EXPECT_DOUBLE_EQ(st.duration_s, 2.0);
      poses.push_back(st.to);
    }
    if (st.kind == StepKind::kMarkerStart) ++starts;
    if (st.kind == StepKind::kMarkerStop) ++stops;
    if (st.kind == StepKind::kMove) {
      // Peak speed of the smooth blend: pi/2 * distance / duration, sampled too.
      for (double u = 0.0; u < st.duration_s; u += 0.01) {
        const Angles a = GoalAt(st, u), b = GoalAt(st, u + 0.01);
        for (int k = 0; k < kNumLegs; ++k) EXPECT_LE(std::abs(b[k] - a[k]) / 0.01, 0.5 + 1e-6);
      }
    }
  }
  EXPECT_EQ(holds, 9);  // 729 / 81
  EXPECT_EQ(starts, 1);
  EXPECT_EQ(stops, 1);
  const auto all = GrayGrid({-36 * kDeg, 0.0, 36 * kDeg});
  for (size_t j = 0; j < poses.size(); ++j) EXPECT_EQ(poses[j], all[j * 81]);
  EXPECT_EQ(s.steps.back().kind, StepKind::kMove);  // back to 0 at the end
  EXPECT_EQ(s.steps.back().to, Angles{});
}

TEST(Expand, RefusesGoalsBeyondTheServoLimitsNamingThem) {
  // The sim config's servos stay within +-pi: ten full hanging cycles do not fit.
  const config::Config c = SimConfig(R"(
plan { name: "hang" phase { kind: PHASE_HANG orientation: HANG_X_POS cycles: 10 } }
)");
  try {
    Expand(c, "hang");
    FAIL() << "expected a refusal";
  } catch (const std::invalid_argument& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("phase 0 (PHASE_HANG HANG_X_POS)"), std::string::npos) << what;
    EXPECT_NE(what.find("62.83"), std::string::npos) << what;
    EXPECT_NE(what.find("max_angle_rad"), std::string::npos) << what;
  }
}

TEST(Expand, HangingTurnsAtTheCycleRateAndStatesTheBodyAxis) {
  config::Config c = SimConfig(R"(
plan { name: "hang" phase { kind: PHASE_HANG orientation: HANG_Z_NEG cycles: 2 cycle_s: 10 } }
)");
  // Servos in multi-turn mode: limits wide enough for two turns.
  for (auto& leg : *c.mutable_robot()->mutable_leg()) leg.mutable_servo()->set_max_angle_rad(20.0);
  const Schedule s = Expand(c, "hang");
  ASSERT_GE(s.steps.size(), 5u);
  EXPECT_EQ(s.steps[0].kind, StepKind::kConfirm);  // the operator re-hangs the robot
  EXPECT_EQ(s.steps[1].kind, StepKind::kPrecheck);
  EXPECT_EQ(s.steps[1].precheck, Precheck::kAirborne);
  const Step* turn = nullptr;
  for (const Step& st : s.steps) {
    if (st.kind == StepKind::kTurn) turn = &st;
  }
  ASSERT_NE(turn, nullptr);
  EXPECT_EQ(turn->marker, +experiment_marker_t::HANG_Z_NEG);
  EXPECT_DOUBLE_EQ(turn->duration_s, 20.0);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_NEAR(GoalAt(*turn, 2.5)[k], M_PI / 2, 1e-12);
    EXPECT_NEAR(GoalAt(*turn, 20.0)[k], 4 * M_PI, 1e-12);
  }
  // The sim config's leg 0 transducer is aligned with B: -z of the transducer is -z of B.
  EXPECT_EQ(s.phase_gravity_b[0], (std::array<double, 3>{0.0, 0.0, -1.0}));
  // The unwind to straight down happens after the marker closed.
  EXPECT_EQ(s.steps.back().kind, StepKind::kMove);
  EXPECT_EQ(s.steps.back().to, Angles{});
  EXPECT_EQ(s.steps[s.steps.size() - 2].kind, StepKind::kMarkerStop);
}

TEST(Expand, BigAntsReportPlanIsTheReportsExperiment) {
  config::Config c = LoadConfigText(ShippedConfigText("bigant.pbtxt"), "bigant.pbtxt");
  // As shipped: multi-turn mode with limits wide enough for the ten hanging cycles and the walk.
  EXPECT_EQ(c.dynamixel().operating_mode(), config::EXTENDED_POSITION_MODE);
  const Schedule s = Expand(c, "");
  {
    // Single-turn limits (position mode's): the full cycles do not fit.
    config::Config narrow = c;
    for (auto& leg : *narrow.mutable_robot()->mutable_leg()) {
      leg.mutable_servo()->set_min_angle_rad(-M_PI);
      leg.mutable_servo()->set_max_angle_rad(M_PI);
    }
    EXPECT_THROW(Expand(narrow, ""), std::invalid_argument);
  }
  EXPECT_EQ(s.plan_name, "report");
  std::vector<int8_t> phases;
  int standing_holds = 0, turns = 0, tripod_lifts = 0, walks = 0;
  for (const Step& st : s.steps) {
    if (st.kind == StepKind::kMarkerStart) phases.push_back(st.marker);
    if (st.kind == StepKind::kHold && st.marker == experiment_marker_t::STANDING) {
      ++standing_holds;
      EXPECT_DOUBLE_EQ(st.duration_s, 5.0);
    }
    if (st.kind == StepKind::kTurn) {
      ++turns;
      EXPECT_DOUBLE_EQ(st.duration_s, 200.0);  // ten cycles of 20 s
    }
    if (st.kind == StepKind::kHold && st.marker == experiment_marker_t::TRIPOD &&
        st.duration_s == 5.0) {
      ++tripod_lifts;
      for (int k = 0; k < kNumLegs; ++k) {
        // The lifted tripod alternates; its legs are past the calibrator's 90 deg.
        const bool lifted = kTripodOf[k] == (st.unit % 2);
        EXPECT_NEAR(st.to[k], lifted ? 150.0 * kDeg : 0.0, 1e-12);
      }
    }
    if (st.kind == StepKind::kWalk) {
      ++walks;
      EXPECT_DOUBLE_EQ(st.duration_s, 120.0);
    }
  }
  EXPECT_EQ(phases,
            (std::vector<int8_t>{experiment_marker_t::TARE, +experiment_marker_t::HANG_X_POS,
                                 experiment_marker_t::HANG_X_NEG, experiment_marker_t::HANG_Z_POS,
                                 experiment_marker_t::HANG_Z_NEG, experiment_marker_t::STANDING,
                                 experiment_marker_t::TRIPOD, experiment_marker_t::WALKING}));
  EXPECT_EQ(standing_holds, 729);
  EXPECT_EQ(turns, 4);
  EXPECT_EQ(tripod_lifts, 20);
  EXPECT_EQ(walks, 1);
  // 729 poses of 5 s, four 200 s series, 20 stances of 6 s, the walk and the tare, plus moves.
  const double holds = 2.0 + 729 * 5.0 + 4 * 200.0 + 20 * 6.0 + 120.0;
  EXPECT_GT(s.duration_s, holds);
  EXPECT_LT(s.duration_s, holds + 729 * 1.0 + 4 * 60.0 + 300.0);
}

TEST(Expand, UnknownPlanNamesTheOnesThereAre) {
  const config::Config c = SimConfig(R"(
plan { name: "a" phase { kind: PHASE_TARE } }
plan { name: "b" phase { kind: PHASE_TARE } }
)");
  try {
    Expand(c, "c");
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("a, b"), std::string::npos) << e.what();
  }
}

TEST(Expand, WalkFasterThanTheSpeedLimitIsRefused) {
  const config::Config c = SimConfig(R"(
plan { name: "w" phase { kind: PHASE_TRIPOD_WALK clock_hz: 1.0 walk_s: 2 } }
)");
  try {
    Expand(c, "w");
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("max_velocity_rad_s"), std::string::npos) << e.what();
  }
}

TEST(PlanConfig, BadPhasesAndLimitsAreRefusedWithTheFieldNamed) {
  auto error_of = [](const std::string& extra) -> std::string {
    try {
      SimConfig(extra);
    } catch (const ConfigError& e) {
      return e.what();
    }
    return "";
  };
  // sim.pbtxt ships three plans (short, experiment, quick): the one added here is plan[3].
  std::string e = error_of("plan { name: \"x\" phase { kind: PHASE_HANG } }");
  EXPECT_NE(e.find("plan[3].phase[0].orientation: a hanging phase needs"), std::string::npos) << e;
  e = error_of("plan { name: \"short\" phase { kind: PHASE_TARE } }");
  EXPECT_NE(e.find("plan[3].name: duplicate plan name 'short'"), std::string::npos) << e;
  e = error_of(
      "plan { name: \"g\" phase { kind: PHASE_STANDING_GRID grid_angles_deg: [0, 120] } }");
  EXPECT_NE(e.find("plan[3].phase[0].grid_angles_deg[1]: a standing angle must be within +-90 deg"),
            std::string::npos)
      << e;
  e = error_of("plan { name: \"w\" phase { kind: PHASE_TRIPOD_WALK duty: 1.5 } }");
  EXPECT_NE(e.find("plan[3].phase[0].duty: must be in (0, 1), got 1.5"), std::string::npos) << e;
  e = error_of("plan { name: \"empty\" }");
  EXPECT_NE(e.find("plan[3]: a plan needs at least one phase"), std::string::npos) << e;
}

// ---- safety rules against the twin's own readings ----

Inputs FromFrame(const TwinFrame& f, int64_t utime) {
  Inputs in;
  for (int k = 0; k < kNumLegs; ++k) {
    FtInput ft;
    ft.utime = utime;
    ft.leg = k;
    ft.wrench = f.reading[k];
    in.ft[k] = ft;
  }
  ServoInput sv;
  sv.utime = utime;
  sv.angle_rad = f.angle_rad;
  in.servo = sv;
  MocapInput m;
  m.utime = utime;
  m.tracked = true;
  m.R_WC = f.R_WC;
  in.mocap = m;
  return in;
}

class SafetyTest : public ::testing::Test {
 protected:
  config::Config config_ = SimConfig();
  BigAntTwin twin_{config_, TwinOptions{}};
};

TEST_F(SafetyTest, StandingTwinPassesTheStandingCheckAndFailsTheAirborneOne) {
  BigAntTwin::Driven driven(twin_);
  const TwinFrame& f = driven.Frame(0.0, Angles{});
  const Inputs in = FromFrame(f, 1'000'000);
  const Safety safety(config_);
  EXPECT_EQ(safety.Standing(in), std::nullopt);
  const auto airborne = safety.Airborne(in, Vec3::Zero());
  ASSERT_TRUE(airborne.has_value());
  EXPECT_NE(airborne->find("not in the air"), std::string::npos) << *airborne;
  EXPECT_NE(airborne->find("airborne_max_support_n 25"), std::string::npos) << *airborne;
  EXPECT_EQ(safety.Stale(in, 1'000'000, true), std::nullopt);
  EXPECT_EQ(safety.OverRange(in), std::nullopt);
}

TEST_F(SafetyTest, HangingTwinPassesTheAirborneCheckOnlyForItsOwnAxis) {
  std::optional<TwinFrame> first;
  twin_.Hanging(HangSeries::kXPos, RunOptions{}, [&](const TwinFrame& f) {
    if (!first) first = f;
  });
  ASSERT_TRUE(first.has_value());
  const Inputs in = FromFrame(*first, 5'000'000);
  const Safety safety(config_);
  const Vec3 stated = twin_.StatedGravityB(HangSeries::kXPos);
  EXPECT_EQ(safety.Airborne(in, stated), std::nullopt);
  // Stated the other way round, the legs' weight looks like support.
  const auto reversed = safety.Airborne(in, -stated);
  ASSERT_TRUE(reversed.has_value());
  EXPECT_NE(reversed->find("not in the air"), std::string::npos) << *reversed;
  // The twin hangs 1-3 deg off the stated axis; motion capture 30 deg further off is refused.
  Inputs tilted = in;
  const Vec3 g_C = in.mocap->R_WC.transpose() * Vec3(0.0, 0.0, -1.0);
  tilted.mocap->R_WC =
      in.mocap->R_WC * Eigen::AngleAxisd(30.0 * kDeg, g_C.unitOrthogonal()).toRotationMatrix();
  const auto wrong = safety.Airborne(tilted, stated);
  ASSERT_TRUE(wrong.has_value());
  EXPECT_NE(wrong->find("hang_axis_tolerance_deg 10"), std::string::npos) << *wrong;
  EXPECT_TRUE(safety.Standing(in).has_value());
}

TEST_F(SafetyTest, StaleOverRangeSaturatedAndFailedBridgeAreNamed) {
  BigAntTwin::Driven driven(twin_);
  Inputs in = FromFrame(driven.Frame(0.0, Angles{}), 10'000'000);
  const Safety safety(config_);
  in.ft[1]->utime = 10'000'000 - 600'000;
  auto stale = safety.Stale(in, 10'000'000, false);
  ASSERT_TRUE(stale.has_value());
  EXPECT_NE(stale->find("FT_ML is 0.6 s old, above sequencer.max_input_age_s 0.5"),
            std::string::npos)
      << *stale;
  in.ft[1]->utime = 10'000'000;
  in.mocap.reset();
  EXPECT_EQ(safety.Stale(in, 10'000'000, false), std::nullopt);
  EXPECT_TRUE(safety.Stale(in, 10'000'000, true).has_value());

  in.ft[4]->wrench[2] = 401.0;  // sim.pbtxt rates Fz to 400 N
  auto over = safety.OverRange(in);
  ASSERT_TRUE(over.has_value());
  EXPECT_NE(over->find("FT_MR Fz = 401 is beyond the rated range 400"), std::string::npos) << *over;
  in.ft[4]->wrench[2] = 10.0;
  in.ft[4]->flags = ft_batch_t::FLAG_SATURATED;
  over = safety.OverRange(in);
  ASSERT_TRUE(over.has_value());
  EXPECT_NE(over->find("FT_MR is flagged saturated"), std::string::npos) << *over;
  in.ft[4]->flags = 0;

  in.status["ftcal-ati-bridge"] =
      StatusReading{10'000'000, service_status_t::DEGRADED, "box 3 refuses"};
  auto failed = safety.Stale(in, 10'000'000, false);
  ASSERT_TRUE(failed.has_value());
  EXPECT_NE(failed->find("ftcal-ati-bridge reports state 2 (box 3 refuses)"), std::string::npos)
      << *failed;
  // Issue 36, finding 7: an entry never heard again expires after kStatusExpiryS (its data's age
  // says whether the process is gone).
  for (const int64_t after_us : {-1000, 1000}) {
    const int64_t now = 10'000'000 + static_cast<int64_t>(kStatusExpiryS * 1e6) + after_us;
    Inputs later = FromFrame(driven.Frame(0.0, Angles{}), now);
    later.status = in.status;
    const auto verdict = safety.Stale(later, now, false);
    EXPECT_EQ(verdict.has_value(), after_us < 0) << verdict.value_or("");
  }
}

TEST_F(SafetyTest, TheSequencersOwnStallDoesNotAgeItsInputsButAStallOnlyTakesOutItsSpan) {
  BigAntTwin::Driven driven(twin_);
  Inputs in = FromFrame(driven.Frame(0.0, Angles{}), 10'000'000);
  const Safety safety(config_);  // sim.pbtxt: max_input_age_s 0.5
  OwnStalls own;
  // Ticking every 20 ms with ordinary jitter (up to 90 ms) is no stall.
  int64_t t = 10'000'000;
  for (int i = 0; i < 10; ++i) EXPECT_EQ(own.Awake(t += (i == 5 ? 90'000 : 20'000)), 0);
  // Then the sequencer blocks 3 s, its inputs last seen as the stall began.
  const int64_t stall_from = t;
  for (auto& ft : in.ft) ft->utime = t;
  in.servo->utime = t;
  EXPECT_EQ(own.Awake(t + 3'000'000), 3'000'000);
  t += 3'000'000;
  EXPECT_EQ(own.StalledUs(t - 3'000'000, t), 3'000'000);
  EXPECT_EQ(own.StalledUs(t - 1'000'000, t), 1'000'000);  // clipped to the asked span
  EXPECT_EQ(safety.Stale(in, t, false, own), std::nullopt);
  // Without the account the same inputs are 3 s old.
  EXPECT_TRUE(safety.Stale(in, t, false).has_value());
  // Having listened 0.49 s since (ticking every 10 ms), they still pass; at 0.6 s FT_HL is named,
  // with the stall.
  auto listen_until = [&](int64_t until) {
    for (int64_t u = t + 10'000; u <= until; u += 10'000) EXPECT_EQ(own.Awake(u), 0);
  };
  listen_until(t + 490'000);
  EXPECT_EQ(safety.Stale(in, t + 490'000, false, own), std::nullopt);
  listen_until(t + 600'000);
  auto stale = safety.Stale(in, t + 600'000, false, own);
  ASSERT_TRUE(stale.has_value());
  EXPECT_NE(stale->find("FT_HL is 0.6 s old, above sequencer.max_input_age_s 0.5 (not counting 3 "
                        "s in which the sequencer itself did not run)"),
            std::string::npos)
      << *stale;
  // An input that went quiet before the stall is charged for the time around it: last seen
  // 0.4 s before the stall began, it is 0.4 + 0.6 = 1.0 s old.
  for (auto& ft : in.ft) ft->utime = t + 600'000;
  in.servo->utime = t + 600'000;
  in.ft[3]->utime = stall_from - 400'000;
  stale = safety.Stale(in, t + 600'000, false, own);
  ASSERT_TRUE(stale.has_value());
  EXPECT_NE(stale->find("FT_HR is 1 s old"), std::string::npos) << *stale;
}

TEST_F(SafetyTest, TiltBeyondTheLimitIsRefused) {
  BigAntTwin::Driven driven(twin_);
  Inputs in = FromFrame(driven.Frame(0.0, Angles{}), 1);
  in.mocap->R_WC = Eigen::AngleAxisd(20.0 * kDeg, Vec3::UnitX()).toRotationMatrix();
  const auto tilted = Safety(config_).Tilted(in);
  ASSERT_TRUE(tilted.has_value());
  EXPECT_NE(tilted->find("tilted 20 deg, above sequencer.max_tilt_deg 15"), std::string::npos)
      << *tilted;
}

// ---- whole runs in simulated time, the twin as the robot ----

// A bus on a manual clock: publications are recorded and looped back to the subscribers.
class ManualBus : public Bus {
 public:
  explicit ManualBus(ServiceStats& stats) : Bus(stats) {}
  int64_t NowUtime() const override { return now_; }
  void Run(const std::function<void()>&, int64_t) override {}
  bool IsReplay() const override { return false; }
  void SetNow(int64_t utime) { now_ = utime; }

  template <class Msg>
  void Deliver(const std::string& channel, const Msg& msg) {
    std::vector<uint8_t> bytes(msg.getEncodedSize());
    msg.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
    DeliverRaw(channel, bytes);
  }
  struct Publication {
    int64_t utime;
    std::string channel;
    std::vector<uint8_t> bytes;
  };
  std::vector<Publication> published;

 protected:
  void TransportSubscribe(size_t, const std::string&) override {}
  void TransportPublish(const std::string& channel, const void* data, int size) override {
    const auto* p = static_cast<const uint8_t*>(data);
    published.push_back({now_, channel, std::vector<uint8_t>(p, p + size)});
    DeliverRaw(channel, published.back().bytes);
  }

 private:
  void DeliverRaw(const std::string& channel, const std::vector<uint8_t>& bytes) {
    const std::vector<size_t> subs = HandlersFor(channel);
    for (size_t s : subs) Dispatch(s, channel, now_, bytes.data(), static_cast<int>(bytes.size()));
  }
  // Every bus starts a day after the one before: the tests share TestSigner(), whose sequences
  // follow its clock, and receivers refuse a sequence ahead of their time (issue 36).
  static int64_t NextStart() {
    static int64_t next = 1'700'000'000'000'000;
    next += 86'400'000'000;
    return next;
  }
  int64_t now_ = NextStart();
};

template <class Msg>
Msg Decode(const uint8_t* data, int size) {
  Msg m;
  EXPECT_EQ(m.decode(data, 0, size), size);
  return m;
}
// The message inside a signed publication (every SERVO_CMD and EXPERIMENT is one).
template <class Msg>
Msg Decode(const ManualBus::Publication& p) {
  const auto e = Decode<signed_envelope_t>(p.bytes.data(), static_cast<int>(p.bytes.size()));
  EXPECT_EQ(e.inner_fingerprint, static_cast<int64_t>(Msg::getHash())) << p.channel;
  return Decode<Msg>(e.payload.data(), e.size);
}
bool IsMove(const ManualBus::Publication& p) {
  return p.channel == "SERVO_CMD" && Decode<servo_command_t>(p).action == servo_command_t::MOVE;
}

// The robot: the Dynamixel bridge's command gate takes the signed commands, the servos follow
// the goals it writes as a first-order lag, the twin's standing frames at those angles every
// 10 ms, and the bridge's FTCAL_STATUS (its gate mode) once a second.
class Robot {
 public:
  // `bridge_up_s`: how long the bridge has been running at t = 0 (its start_quiet_s applies).
  Robot(const config::Config& config, ManualBus& bus, double bridge_up_s = 5.0)
      : config_(config),
        bus_(bus),
        twin_(config, TwinOptions{}),
        driven_(twin_),
        bridge_stats_(QuietBridgeLog()),
        verifier_(auth::Verifier::FromConfig(config)),
        gate_(config, bridge_stats_, -bridge_up_s),
        t0_(bus.NowUtime()) {}

  // Runs `seconds` of robot time; `sequencer` ticks every 20 ms as the loop would.
  void Run(Sequencer& sequencer, double seconds, const std::function<void(double)>& each = {}) {
    const int n = static_cast<int>(std::lround(seconds / kDt));
    for (int i = 0; i < n; ++i) {
      t_ += kDt;
      bus_.SetNow(t0_ + std::llround(t_ * 1e6));
      if (each) each(t_);
      // The bridge: commands through the gate, the goals it writes followed by the servos.
      for (size_t j = seen_; j < bus_.published.size(); ++j) {
        const auto& p = bus_.published[j];
        if (p.channel != "SERVO_CMD" || cut_) continue;
        auto [opened, refused] =
            verifier_.Open(p.channel, p.bytes.data(), static_cast<int>(p.bytes.size()),
                           static_cast<uint64_t>(servo_command_t::getHash()), p.utime, 250'000);
        if (refused) {
          ++refusals_[refused->kind];
          continue;
        }
        try {
          gate_.OnCommand(*opened->signer, Decode<servo_command_t>(opened->payload, opened->size),
                          t_);
        } catch (const BadInput& e) {
          ++refusals_[e.kind()];
        }
      }
      seen_ = bus_.published.size();
      if (const auto written = gate_.Tick(t_, /*degraded=*/false)) {
        for (int k = 0; k < kNumLegs; ++k) goal_[k] = written->goal_angle_rad[k];
      }
      for (int k = 0; k < kNumLegs; ++k) angle_[k] += (goal_[k] - angle_[k]) * (kDt / kTau);
      const TwinFrame& f = driven_.Frame(t_, angle_);
      for (int k = 0; k < kNumLegs; ++k) {
        if (silent_leg_ == k) continue;
        const FtInput ft{bus_.NowUtime(), k, f.reading[k], 0};
        FtBatch batch = BatchOf(ft, ft.utime);
        if (spike_leg_ == k) {
          // A datagram of three records whose middle one is a spike of 10 kN on Fz.
          batch.n = 3;
          for (int r = 0; r < 3; ++r) {
            batch.records[static_cast<size_t>(r)].in = ft;
            batch.records[static_cast<size_t>(r)].in.utime = ft.utime - 2 + r;
          }
          batch.records[1].in.wrench[2] = 1e4;
        }
        bus_.Deliver("FT_" + std::string(kLegNames[k]), ToLcm(batch));
      }
      mocap_body_t m{};
      m.utime = m.sample_utime = bus_.NowUtime();
      m.body = config_.mocap().body_name();
      m.tracked = true;
      const Eigen::Vector4d q = RotationToQuaternion(f.R_WC);
      for (int a = 0; a < 4; ++a) m.q_wc[a] = q[a];
      m.num_markers = 0;
      bus_.Deliver("MOCAP_BODY", m);
      servo_state_t s{};
      s.utime = s.sample_utime = bus_.NowUtime();
      for (int k = 0; k < kNumLegs; ++k) {
        s.leg[k] = std::string(kLegNames[k]);
        s.id[k] = k + 1;
        s.angle_rad[k] = angle_[k];
        s.velocity_rad_s[k] = 0.0;
        s.current_a[k] = 0.0;
        s.hardware_error[k] = 0;
        s.device_tick_ms[k] = 0;
        s.flags[k] = 0;
      }
      gate_.OnState(s);
      bus_.Deliver("SERVO_STATE", s);
      if (i % 100 == 0) {
        service_status_t st{};
        st.utime = bus_.NowUtime();
        st.name = "ftcal-dynamixel-bridge";
        st.state = service_status_t::RUNNING;
        st.counter_name = {"mode"};
        st.counter_value = {static_cast<int64_t>(gate_.mode())};
        st.num_counters = 1;
        bus_.Deliver("FTCAL_STATUS", st);
      }
      if (i % 2 == 0) sequencer.Tick();
      if (sequencer.state() == Sequencer::State::kDone ||
          sequencer.state() == Sequencer::State::kStopped) {
        return;
      }
    }
  }
  void Silence(int leg) { silent_leg_ = leg; }
  void Spike(int leg) { spike_leg_ = leg; }
  // The link from the sequencer to the bridge is cut (commands lost) or mended.
  void Cut(bool cut) { cut_ = cut; }
  const Angles& angles() const { return angle_; }
  double t() const { return t_; }
  CommandGate& gate() { return gate_; }
  // Commands the bridge did not act on, by reason.
  const std::map<std::string, int>& refusals() const { return refusals_; }

 private:
  static constexpr double kDt = 0.01, kTau = 0.05;
  const config::Config& config_;
  ManualBus& bus_;
  BigAntTwin twin_;
  BigAntTwin::Driven driven_;
  static std::shared_ptr<spdlog::logger> QuietBridgeLog() {
    static auto log =
        std::make_shared<spdlog::logger>("bridge", std::make_shared<spdlog::sinks::null_sink_mt>());
    return log;
  }
  ServiceStats bridge_stats_;
  auth::Verifier verifier_;
  CommandGate gate_;
  std::map<std::string, int> refusals_;
  Angles angle_{}, goal_{};
  size_t seen_ = 0;
  int silent_leg_ = -1;
  int spike_leg_ = -1;
  bool cut_ = false;
  double t_ = 0.0;
  const int64_t t0_;
};

std::shared_ptr<spdlog::logger> QuietLog() {
  static auto log = std::make_shared<spdlog::logger>(
      "sequencer_test", std::make_shared<spdlog::sinks::null_sink_mt>());
  return log;
}

// The marker edges (a start repeated while its phase is open is not an edge), and the times of
// the repeats.
struct Markers {
  std::vector<experiment_marker_t> all;
  std::vector<int64_t> repeat_utimes;
};
Markers MarkersOf(const ManualBus& bus) {
  Markers m;
  bool open = false;
  for (const auto& p : bus.published) {
    if (p.channel != "EXPERIMENT") continue;
    const auto marker = Decode<experiment_marker_t>(p);
    if (open && marker.start && marker.phase == m.all.back().phase &&
        marker.session_id == m.all.back().session_id) {
      m.repeat_utimes.push_back(marker.utime);
      continue;
    }
    open = marker.start;
    m.all.push_back(marker);
  }
  return m;
}

// The goals held in each hold of the run: the last command published before each STANDING
// hold ended, grouped by value.
std::vector<Angles> HeldPoses(const ManualBus& bus) {
  std::vector<Angles> poses;
  for (const auto& p : bus.published) {
    if (!IsMove(p)) continue;
    const auto cmd = Decode<servo_command_t>(p);
    Angles a;
    for (int k = 0; k < kNumLegs; ++k) a[k] = cmd.goal_angle_rad[k];
    if (poses.empty() || poses.back() != a) poses.push_back(a);
  }
  return poses;
}

constexpr char kGridPlan[] = R"(
plan { name: "grid" phase { kind: PHASE_STANDING_GRID pose_stride: 100 dwell_s: 1.5 } }
)";

std::string TempPath(const std::string& name) {
  return (std::filesystem::temp_directory_path() / (name + "." + std::to_string(::getpid())))
      .string();
}

TEST(SequencerRun, StandingGridOnTheTwinVisitsEveryPoseInsideOneMarker) {
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", /*yes=*/true, "", "s1"});
  robot.Run(seq, 120.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kDone) << seq.stop_reason();
  const Markers m = MarkersOf(bus);
  ASSERT_EQ(m.all.size(), 2u);
  EXPECT_EQ(m.all[0].phase, +experiment_marker_t::STANDING);
  EXPECT_TRUE(m.all[0].start);
  EXPECT_FALSE(m.all[1].start);
  EXPECT_EQ(m.all[0].session_id, "s1");
  // While the phase ran, its start went out again once a second (a restarted stage learns it
  // is inside the phase from the repeat).
  const double phase_s = (m.all[1].utime - m.all[0].utime) * 1e-6;
  EXPECT_NEAR(static_cast<double>(m.repeat_utimes.size()), std::floor(phase_s), 1.0) << phase_s;
  int64_t previous = m.all[0].utime;
  for (int64_t t : m.repeat_utimes) {
    EXPECT_NEAR((t - previous) * 1e-6, 1.0, 0.021);
    previous = t;
  }
  // Every 100th pose of the Gray order, each held: the commands dwell on exactly those goals.
  const auto all = GrayGrid({-36 * kDeg, 0.0, 36 * kDeg});
  const auto held = HeldPoses(bus);
  for (size_t j = 0; j * 100 < all.size(); ++j) {
    EXPECT_NE(std::find(held.begin(), held.end(), all[j * 100]), held.end()) << "pose " << j;
  }
  // Every move kept under the speed limit: consecutive commands 20 ms apart.
  double fastest = 0.0;
  std::optional<std::pair<int64_t, Angles>> last;
  for (const auto& p : bus.published) {
    if (!IsMove(p)) continue;
    const auto cmd = Decode<servo_command_t>(p);
    Angles a;
    for (int k = 0; k < kNumLegs; ++k) a[k] = cmd.goal_angle_rad[k];
    if (last && p.utime > last->first) {
      for (int k = 0; k < kNumLegs; ++k) {
        fastest =
            std::max(fastest, std::abs(a[k] - last->second[k]) / ((p.utime - last->first) * 1e-6));
      }
    }
    last = {p.utime, a};
  }
  EXPECT_LE(fastest, c.sequencer().max_velocity_rad_s() * 1.01);
  EXPECT_GT(fastest, 0.1);
}

TEST(ProgressSaverTest, TheLatestSaveReachesTheFileAndAFailedWriteIsReportedOnce) {
  const std::string path = TempPath("saver_progress");
  std::filesystem::remove(path);
  {
    ProgressSaver saver(path);
    for (int i = 0; i <= 200; ++i) saver.Save(Progress{"grid", i, "s9"});
    EXPECT_EQ(saver.Flush(), "");
    const auto saved = LoadProgress(path);
    ASSERT_TRUE(saved.has_value());
    EXPECT_EQ(saved->next_step, 200);
    EXPECT_EQ(saved->session_id, "s9");
    saver.Save(Progress{"grid", 201, "s9"});  // pending as the saver goes away
  }
  EXPECT_EQ(LoadProgress(path)->next_step, 201);
  std::filesystem::remove(path);

  const std::string nowhere = TempPath("no_such_dir") + "/progress";
  ProgressSaver bad(nowhere);
  bad.Save(Progress{"grid", 3, "s9"});
  const std::string error = bad.Flush();
  EXPECT_NE(error.find(nowhere), std::string::npos) << error;
  EXPECT_EQ(bad.TakeError(), "");
}

TEST(SequencerRun, SilentTransducerStopsTheMotionClosesTheMarkerAndResumesAtThatPose) {
  const std::string progress = TempPath("sequencer_progress");
  std::filesystem::remove(progress);
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  int interrupted_pose = -1;
  double silenced_at = -1.0;
  {
    Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, progress, "s2"});
    robot.Run(seq, 120.0, [&](double t) {
      // Silence the ATI of ML in the middle of the fourth pose's dwell.
      if (silenced_at < 0 && seq.ProgressLine().find("STANDING_GRID 4/") != std::string::npos &&
          seq.schedule().steps[seq.step_index()].kind == StepKind::kHold) {
        silenced_at = t;
        robot.Silence(1);
        interrupted_pose = 3;
      }
    });
    ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
    EXPECT_NE(seq.stop_reason().find("FT_ML is"), std::string::npos) << seq.stop_reason();
    EXPECT_NE(seq.stop_reason().find("above sequencer.max_input_age_s 0.5"), std::string::npos);
    // Stopped within the age limit and one loop tick of the silence.
    EXPECT_LE(robot.t() - silenced_at, 0.5 + 0.03);
    EXPECT_GE(robot.t() - silenced_at, 0.49);
  }
  // The last command holds the measured angles; the marker is closed.
  const auto last_cmd = [&] {
    for (auto it = bus.published.rbegin(); it != bus.published.rend(); ++it) {
      if (IsMove(*it)) return Decode<servo_command_t>(*it);
    }
    return servo_command_t{};
  }();
  for (int k = 0; k < kNumLegs; ++k)
    EXPECT_DOUBLE_EQ(last_cmd.goal_angle_rad[k], robot.angles()[k]);
  EXPECT_TRUE(last_cmd.torque_enable);
  const Markers m = MarkersOf(bus);
  ASSERT_EQ(m.all.size(), 2u);
  EXPECT_FALSE(m.all.back().start);

  // A restart resumes at the interrupted pose: the first pose held is pose 3, not pose 0, and
  // the marker opens again in the same session.
  const auto progress_saved = LoadProgress(progress);
  ASSERT_TRUE(progress_saved.has_value());
  EXPECT_EQ(progress_saved->plan, "grid");
  EXPECT_EQ(progress_saved->session_id, "s2");
  ServiceStats stats2(QuietLog());
  ManualBus bus2(stats2);
  Robot robot2(c, bus2);
  Sequencer again(c, bus2, TestSigner(), Sequencer::Options{"grid", true, progress, ""});
  robot2.Run(again, 120.0);
  ASSERT_EQ(again.state(), Sequencer::State::kDone) << again.stop_reason();
  const Markers m2 = MarkersOf(bus2);
  ASSERT_EQ(m2.all.size(), 2u);
  EXPECT_TRUE(m2.all[0].start);
  EXPECT_EQ(m2.all[0].session_id, "s2");
  const auto all = GrayGrid({-36 * kDeg, 0.0, 36 * kDeg});
  const auto held = HeldPoses(bus2);
  EXPECT_EQ(std::find(held.begin(), held.end(), all[0]), held.end()) << "pose 0 repeated";
  EXPECT_EQ(std::find(held.begin(), held.end(), all[100]), held.end()) << "pose 1 repeated";
  EXPECT_NE(std::find(held.begin(), held.end(), all[interrupted_pose * 100]), held.end());
  EXPECT_NE(std::find(held.begin(), held.end(), all[700]), held.end());
  std::filesystem::remove(progress);
}

// A transducer's message carries a datagram of records: one beyond the rated range in the
// middle of it stops the run, though the message's last record is in range.
TEST(SequencerRun, ARecordBeyondTheRatedRangeInsideADatagramStopsTheRun) {
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "s9"});
  robot.Run(seq, 120.0, [&](double t) {
    if (t > 5.0) robot.Spike(2);
  });
  ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(seq.stop_reason().find("FT_FL Fz = 1e+04 is beyond the rated range 400"),
            std::string::npos)
      << seq.stop_reason();
  EXPECT_LT(robot.t(), 5.1);
}

TEST(SequencerRun, HangingIsRefusedWhileTheFeetCarryTheRobot) {
  config::Config c = SimConfig(R"(
plan { name: "hang" phase { kind: PHASE_HANG orientation: HANG_X_POS cycles: 1 cycle_s: 10 } }
)");
  for (auto& leg : *c.mutable_robot()->mutable_leg()) leg.mutable_servo()->set_max_angle_rad(20.0);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);  // the twin stands on its six feet
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"hang", true, "", "s3"});
  robot.Run(seq, 5.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(
      seq.stop_reason().find("PHASE_HANG HANG_X_POS cannot start: the robot is not in the air"),
      std::string::npos)
      << seq.stop_reason();
  EXPECT_TRUE(MarkersOf(bus).all.empty());
  for (int k = 0; k < kNumLegs; ++k) EXPECT_NEAR(robot.angles()[k], 0.0, 1e-9);
}

TEST(SequencerRun, OperatorStopOverLcmAndConfirmation) {
  const config::Config c = SimConfig(R"(
plan { name: "grid" phase { kind: PHASE_STANDING_GRID confirm: true pose_stride: 100 dwell_s: 1.5 } }
)");
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  std::vector<std::string> prompts;
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", /*yes=*/false, "", "s4"});
  seq.OnPrompt([&](const std::string& p) { prompts.push_back(p); });
  robot.Run(seq, 3.0);
  EXPECT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  ASSERT_EQ(prompts.size(), 1u);
  EXPECT_TRUE(MarkersOf(bus).all.empty());
  sequencer_control_t confirm{};
  confirm.action = sequencer_control_t::CONFIRM;
  confirm.step = 0;
  confirm.nonce = seq.confirm_nonce();
  bus.Deliver("SEQUENCER_CONTROL", confirm);
  robot.Run(seq, 5.0);
  EXPECT_EQ(seq.state(), Sequencer::State::kRunning);
  ASSERT_EQ(MarkersOf(bus).all.size(), 1u);
  sequencer_control_t stop{};
  stop.action = sequencer_control_t::STOP;
  stop.step = -1;
  stop.note = "hand on the e-stop";
  bus.Deliver("SEQUENCER_CONTROL", stop);
  EXPECT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(seq.stop_reason().find("operator STOP"), std::string::npos);
  EXPECT_NE(seq.stop_reason().find("hand on the e-stop"), std::string::npos);
  ASSERT_EQ(MarkersOf(bus).all.size(), 2u);
  EXPECT_FALSE(MarkersOf(bus).all.back().start);
}

// ---- the servo side: the sequencer against the bridge's command gate ----

TEST(SequencerRun, ArmsTheBridgeBeforeTheFirstMoveAndDisarmsAtTheEnd) {
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  // The bridge started just now: the first ARM falls in its start_quiet_s and is ignored, so
  // the sequencer must ARM again before anything moves.
  Robot robot(c, bus, /*bridge_up_s=*/0.0);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "s5"});
  robot.Run(seq, 120.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kDone) << seq.stop_reason();
  robot.Run(seq, 0.1);  // the bridge takes the last command (DISARM)
  std::vector<int8_t> actions;
  for (const auto& p : bus.published) {
    if (p.channel != "SERVO_CMD") continue;
    const int8_t a = Decode<servo_command_t>(p).action;
    if (actions.empty() || actions.back() != a) actions.push_back(a);
  }
  ASSERT_GE(actions.size(), 3u);
  EXPECT_EQ(actions.front(), +servo_command_t::ARM);
  EXPECT_EQ(actions.back(), +servo_command_t::DISARM);
  // The first ARM fell in the bridge's start_quiet_s; the second was taken, and the sequencer
  // saw it taken in the bridge's status: no third.
  EXPECT_EQ(std::count(actions.begin(), actions.end(), +servo_command_t::ARM), 2);
  EXPECT_GE(robot.refusals().count("servo command ignored_at_start"), 1u);
  EXPECT_EQ(robot.gate().mode(), CommandGate::Mode::kDisarmed);
  // Nothing else was refused: no MOVE before the bridge was armed, none from a stranger. (The
  // HEARTBEATs sent while waiting for the status after the first ARM are refused as not armed.)
  for (const auto& [why, n] : robot.refusals()) {
    EXPECT_TRUE(why == "servo command ignored_at_start" || why == "servo command not_armed")
        << why << " x" << n;
  }
  // The poses were reached through the gate: every pose of the plan was held, and the legs end
  // where the last MOVE sent them.
  const auto all = GrayGrid({-36 * kDeg, 0.0, 36 * kDeg});
  const auto held = HeldPoses(bus);
  for (size_t j = 0; j * 100 < all.size(); ++j) {
    EXPECT_NE(std::find(held.begin(), held.end(), all[j * 100]), held.end()) << "pose " << j;
  }
  ASSERT_FALSE(held.empty());
  // (The plan ends when the legs are within arrival_tolerance_rad of the last goal; on DISARM the
  // bridge holds them where they are measured.)
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_NEAR(robot.angles()[k], held.back()[k], c.sequencer().arrival_tolerance_rad()) << k;
  }
}

TEST(SequencerRun, ABridgeThatHoldsStopsTheRun) {
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "s6"});
  double cut_at = -1.0;
  robot.Run(seq, 120.0, [&](double t) {
    if (cut_at < 0 && seq.ProgressLine().find("STANDING_GRID 3/") != std::string::npos) {
      cut_at = t;
      robot.Cut(true);  // the bridge's dead-man holds after dynamixel.deadman_s
    }
  });
  ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(seq.stop_reason().find("ftcal-dynamixel-bridge left armed mode: it is in hold"),
            std::string::npos)
      << seq.stop_reason();
  EXPECT_EQ(robot.gate().mode(), CommandGate::Mode::kHold);
  // Seen at the bridge's next status (1 Hz) after the dead-man (0.25 s).
  EXPECT_LE(robot.t() - cut_at, c.dynamixel().deadman_s() + 1.0 + 0.05);
  const Markers m = MarkersOf(bus);
  ASSERT_EQ(m.all.size(), 2u);
  EXPECT_FALSE(m.all.back().start);
}

TEST(SequencerRun, AnUntrustedKeyNeverMovesTheRobot) {
  const config::Config trusted = SimConfig(kGridPlan);
  config::Config c = trusted;
  c.mutable_auth()->clear_trusted_key();  // the bridge trusts nobody on SERVO_CMD
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "s7"});
  robot.Run(seq, 30.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(seq.stop_reason().find("did not arm after 4 ARMs"), std::string::npos)
      << seq.stop_reason();
  EXPECT_NE(seq.stop_reason().find("auth.trusted_key"), std::string::npos) << seq.stop_reason();
  EXPECT_GE(robot.refusals().count("untrusted signer"), 1u);
  for (int k = 0; k < kNumLegs; ++k) EXPECT_DOUBLE_EQ(robot.angles()[k], 0.0);
  EXPECT_TRUE(MarkersOf(bus).all.empty() || !MarkersOf(bus).all.back().start);
}

TEST(SequencerRun, AnUnsignedConfirmIsRefusedOnALabNetwork) {
  const config::Config c = SimConfig(R"(
plan { name: "grid" phase { kind: PHASE_STANDING_GRID confirm: true pose_stride: 100 dwell_s: 1.5 } }
)",
                                     /*allow_unsigned=*/false);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", /*yes=*/false, "", "s8"});
  robot.Run(seq, 2.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  sequencer_control_t confirm{};
  confirm.action = sequencer_control_t::CONFIRM;
  confirm.step = 0;
  bus.Deliver("SEQUENCER_CONTROL", confirm);
  robot.Run(seq, 2.0);
  EXPECT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  EXPECT_EQ(stats.kinds().count("unsigned on SEQUENCER_CONTROL"), 1u);
}

// ---- issue 36: a signature says who, not when nor for which prompt ----

// The operator's key, trusted on SEQUENCER_CONTROL only.
auth::Signer& OperatorSigner() {
  static auth::Signer signer = [] {
    std::array<uint8_t, auth::kSeedBytes> seed{};
    randombytes_buf(seed.data(), seed.size());
    return auth::Signer::FromSeed(seed);
  }();
  return signer;
}

config::Config SignedControlConfig() {
  config::Config c = SimConfig(R"(
plan { name: "grid" phase { kind: PHASE_STANDING_GRID confirm: true pose_stride: 100 dwell_s: 1.5 } }
)",
                               /*allow_unsigned=*/false);
  auto* key = c.mutable_auth()->add_trusted_key();
  key->set_name("operator");
  const auth::PublicKey& pk = OperatorSigner().public_key();
  key->set_public_key_hex(auth::ToHex(pk.data(), pk.size()));
  key->add_channel("SEQUENCER_CONTROL");
  return c;
}

template <class Msg>
void DeliverSigned(ManualBus& bus, const Msg& msg, int64_t signed_utime) {
  bus.Deliver("SEQUENCER_CONTROL", OperatorSigner().Seal("SEQUENCER_CONTROL", msg, signed_utime));
}

TEST(SequencerControl, AConfirmMustCarryTheNonceOfThePromptItAnswers) {
  const config::Config c = SignedControlConfig();
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", /*yes=*/false, "", "n1"});
  robot.Run(seq, 2.0);
  ASSERT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  const int64_t nonce = seq.confirm_nonce();
  ASSERT_NE(nonce, 0);
  EXPECT_EQ(stats.counters().at("confirm_nonce"), nonce);  // what ftcal-sequencer-control reads
  sequencer_control_t confirm{};
  confirm.action = sequencer_control_t::CONFIRM;
  confirm.step = -1;
  confirm.nonce = 0;  // as an old ftcal-sequencer-control, or a capture of another prompt, sends
  DeliverSigned(bus, confirm, bus.NowUtime());
  confirm.nonce = nonce + 1;
  DeliverSigned(bus, confirm, bus.NowUtime());
  robot.Run(seq, 1.0);
  EXPECT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  EXPECT_EQ(stats.kinds().at("confirm of another prompt"), 2);
  confirm.nonce = nonce;
  DeliverSigned(bus, confirm, bus.NowUtime());
  robot.Run(seq, 1.0);
  EXPECT_EQ(seq.state(), Sequencer::State::kRunning);
  EXPECT_EQ(stats.counters().at("confirms"), 1);
  EXPECT_EQ(seq.confirm_nonce(), 0);
  EXPECT_EQ(stats.counters().at("confirm_nonce"), 0);
}

TEST(SequencerControl, EachPromptDrawsAFreshNonce) {
  // Two sequencers at the same prompt of the same plan (a run and its resume): different nonces,
  // so a CONFIRM of the one cannot answer the other.
  const config::Config c = SignedControlConfig();
  std::set<int64_t> nonces;
  for (int run = 0; run < 4; ++run) {
    ServiceStats stats(QuietLog());
    ManualBus bus(stats);
    Robot robot(c, bus);
    Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", false, "", "n2"});
    robot.Run(seq, 1.0);
    ASSERT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
    nonces.insert(seq.confirm_nonce());
  }
  EXPECT_EQ(nonces.size(), 4u);
}

TEST(SequencerControl, AStopSignedSecondsAgoIsRefused) {
  const config::Config c = SignedControlConfig();
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", false, "", "n3"});
  robot.Run(seq, 1.0);
  sequencer_control_t stop{};
  stop.action = sequencer_control_t::STOP;
  stop.step = -1;
  // Captured 20 s ago (the finding's replay), and one just outside auth.control_window_s.
  DeliverSigned(bus, stop, bus.NowUtime() - 20'000'000);
  DeliverSigned(bus, stop,
                bus.NowUtime() - static_cast<int64_t>(c.auth().control_window_s() * 1e6) - 1000);
  EXPECT_EQ(seq.state(), Sequencer::State::kWaitingForOperator);
  EXPECT_EQ(stats.kinds().at("stale from operator on SEQUENCER_CONTROL"), 2);
  DeliverSigned(bus, stop, bus.NowUtime() - 1'000'000);  // a second in transit: taken
  EXPECT_EQ(seq.state(), Sequencer::State::kStopped);
}

// Issue 36, finding 7: one unsigned FTCAL_STATUS from an invented process name containing
// "bridge", state DEGRADED, stopped a moving run.
TEST(SequencerStatusWatch, AStatusFromAnInventedBridgeDoesNotStopARun) {
  const config::Config c = SimConfig(kGridPlan);
  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "w1"});
  bool forged = false;
  robot.Run(seq, 120.0, [&](double) {
    if (forged || seq.ProgressLine().find("STANDING_GRID 3/") == std::string::npos) return;
    forged = true;
    service_status_t st{};
    st.utime = bus.NowUtime();
    st.name = "ftcal-evil-bridge";
    st.state = service_status_t::DEGRADED;
    st.last_error = "forged";
    bus.Deliver("FTCAL_STATUS", st);
  });
  ASSERT_TRUE(forged);
  EXPECT_EQ(seq.state(), Sequencer::State::kDone) << seq.stop_reason();
  EXPECT_GE(stats.counters().at("status_ignored"), 1);
}

TEST(SequencerStatusWatch, AWatchedBridgeThatIsDegradedStopsTheRunUntilItsEntryExpires) {
  const config::Config c = SimConfig(kGridPlan);
  EXPECT_EQ(
      WatchedStatusNames(c),
      (std::set<std::string>{"ftcal-ati-bridge", "ftcal-dynamixel-bridge", "ftcal-mocap-bridge"}));
  // A config whose launch group runs the sequencer: its bridges, by their heartbeat names.
  const config::Config lab = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/bigant.pbtxt");
  const std::set<std::string> watched = WatchedStatusNames(lab);
  EXPECT_EQ(watched.count("ftcal-dynamixel-bridge"), 1u);
  EXPECT_EQ(watched.count("ftcal-corrector"), 0u);
  for (const std::string& n : watched) EXPECT_NE(n.find("-bridge"), std::string::npos) << n;
  // Another bridge the sequencer's group launches is watched too; the mocap bridge follows
  // mocap.system.
  config::Config more = lab;
  ASSERT_EQ(more.launch().group(0).name(), "lab");
  auto* plate = more.mutable_launch()->mutable_group(0)->add_process();
  plate->set_name("plate");
  plate->set_command("/opt/lab/ftcal-plate-bridge");
  more.mutable_mocap()->set_system(config::OPTITRACK);
  const std::set<std::string> more_watched = WatchedStatusNames(more);
  EXPECT_EQ(more_watched.count("ftcal-plate-bridge"), 1u);
  EXPECT_EQ(more_watched.count("ftcal-natnet-bridge"), 1u);

  ServiceStats stats(QuietLog());
  ManualBus bus(stats);
  Robot robot(c, bus);
  Sequencer seq(c, bus, TestSigner(), Sequencer::Options{"grid", true, "", "w2"});
  bool sent = false;
  robot.Run(seq, 120.0, [&](double) {
    if (sent || seq.ProgressLine().find("STANDING_GRID 3/") == std::string::npos) return;
    sent = true;
    service_status_t st{};
    st.utime = bus.NowUtime() - static_cast<int64_t>((kStatusExpiryS + 0.5) * 1e6);
    st.name = "ftcal-ati-bridge";
    st.state = service_status_t::DEGRADED;
    bus.Deliver("FTCAL_STATUS", st);  // long expired when it comes: nothing
    st.utime = bus.NowUtime();
    st.last_error = "box 3 refuses";
    bus.Deliver("FTCAL_STATUS", st);
  });
  ASSERT_TRUE(sent);
  ASSERT_EQ(seq.state(), Sequencer::State::kStopped);
  EXPECT_NE(seq.stop_reason().find("ftcal-ati-bridge reports state 2 (box 3 refuses)"),
            std::string::npos)
      << seq.stop_reason();
}

}  // namespace
}  // namespace ftcal::sequencer
