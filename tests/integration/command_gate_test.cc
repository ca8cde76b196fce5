// CommandGate (services/dynamixel_bridge/command_gate.h), the bridge's last line, driven with
// a hand-made clock: the start's quiet period, arming by one commander, exactly the configured
// servos with finite goals, the margin clamp, the velocity limit, the dead-man's hold at the
// measured position, and FAULT while the bridge is degraded.
#include <cmath>
#include <limits>

#include <gtest/gtest.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/bus.h"
#include "dynamixel_bridge/command_gate.h"
#include "ftcal/config.h"

namespace ftcal {
namespace {

using Mode = CommandGate::Mode;

constexpr double kStartS = 100.0;

class CommandGateTest : public ::testing::Test {
 protected:
  CommandGateTest()
      : config_(MakeConfig()),
        stats_(std::make_shared<spdlog::logger>("gate",
                                                std::make_shared<spdlog::sinks::null_sink_mt>())),
        gate_(config_, stats_, kStartS) {
    for (const auto& leg : config_.robot().leg())
      ids_.push_back(static_cast<int>(leg.servo().id()));
    measured_.assign(ids_.size(), 0.0);
    for (size_t i = 0; i < ids_.size(); ++i) measured_[i] = 0.1 * static_cast<double>(i);
    Measure();
  }
  static config::Config MakeConfig() {
    config::Config c = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    auto* d = c.mutable_dynamixel();
    d->set_start_quiet_s(1.0);
    d->set_deadman_s(0.25);
    d->set_limit_margin_rad(0.05);
    d->set_max_velocity_rad_s(2.0);
    for (auto& leg : *c.mutable_robot()->mutable_leg()) {
      leg.mutable_servo()->set_min_angle_rad(-1.0);
      leg.mutable_servo()->set_max_angle_rad(1.0);
    }
    return c;
  }
  void Measure() {
    servo_state_t s{};
    for (size_t i = 0; i < ids_.size(); ++i) {
      s.id[i] = ids_[i];
      s.angle_rad[i] = measured_[i];
    }
    gate_.OnState(s);
  }
  servo_command_t Cmd(int8_t action, double goal = 0.0) {
    servo_command_t c{};
    c.action = action;
    c.torque_enable = true;
    c.num_servos = static_cast<int32_t>(ids_.size());
    for (int id : ids_) {
      c.id.push_back(id);
      c.goal_angle_rad.push_back(goal);
    }
    return c;
  }
  // The refusal's kind, "" when accepted.
  std::string Send(const std::string& signer, const servo_command_t& c, double t) {
    try {
      gate_.OnCommand(signer, c, t);
      return "";
    } catch (const BadInput& e) {
      return e.kind();
    }
  }

  config::Config config_;
  ServiceStats stats_;
  CommandGate gate_;
  std::vector<int> ids_;
  std::vector<double> measured_;
};

TEST_F(CommandGateTest, CommandsInTheFirstMomentsAreIgnored) {
  EXPECT_EQ(Send("op", Cmd(servo_command_t::ARM), kStartS + 0.5), "servo command ignored_at_start");
  EXPECT_EQ(gate_.mode(), Mode::kDisarmed);
  EXPECT_EQ(Send("op", Cmd(servo_command_t::ARM), kStartS + 1.01), "");
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
}

TEST_F(CommandGateTest, GoalsOnlyFromTheOneCommanderThatArmed) {
  const double t = kStartS + 2;
  EXPECT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.5), t), "servo command not_armed");
  EXPECT_FALSE(gate_.Tick(t, false));
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  EXPECT_EQ(Send("other", Cmd(servo_command_t::ARM), t), "servo command not_commander");
  EXPECT_EQ(Send("other", Cmd(servo_command_t::MOVE, 0.5), t), "servo command not_commander");
  EXPECT_EQ(Send("other", Cmd(servo_command_t::HEARTBEAT), t), "servo command not_commander");
  EXPECT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.5), t), "");
  EXPECT_EQ(gate_.commander(), "op");
  EXPECT_EQ(stats_.counters().at("refused_not_commander"), 3);
}

TEST_F(CommandGateTest, AMoveMustNameExactlyTheConfiguredServosWithFiniteGoals) {
  const double t = kStartS + 2;
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  auto missing = Cmd(servo_command_t::MOVE, 0.2);
  missing.id.pop_back();
  missing.goal_angle_rad.pop_back();
  missing.num_servos -= 1;
  EXPECT_EQ(Send("op", missing, t), "servo command wrong_servos");
  auto twice = Cmd(servo_command_t::MOVE, 0.2);
  twice.id[1] = twice.id[0];
  EXPECT_EQ(Send("op", twice, t), "servo command wrong_servos");
  auto unknown = Cmd(servo_command_t::MOVE, 0.2);
  unknown.id[2] = 99;
  EXPECT_EQ(Send("op", unknown, t), "servo command wrong_servos");
  auto nan = Cmd(servo_command_t::MOVE, 0.2);
  nan.goal_angle_rad[3] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(Send("op", nan, t), "servo command non_finite");
  // None of them moved anything.
  EXPECT_FALSE(gate_.Tick(t + 0.01, false));
}

TEST_F(CommandGateTest, GoalsAreClampedToTheMarginAndMoveAtMostTheVelocityLimit) {
  double t = kStartS + 2;
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  EXPECT_FALSE(gate_.Tick(t, false));  // at rest at the measured position: nothing to write
  ASSERT_EQ(Send("op", Cmd(servo_command_t::MOVE, 5.0), t), "");
  EXPECT_EQ(stats_.counters().at("goals_clamped_to_margin"), static_cast<int64_t>(ids_.size()));
  std::vector<double> last = measured_;
  constexpr double kDt = 0.01;
  for (int step = 1; step <= 100; ++step) {
    t += kDt;
    if (step % 10 == 0) {
      ASSERT_EQ(Send("op", Cmd(servo_command_t::HEARTBEAT), t), "");
    }
    const auto cmd = gate_.Tick(t, false);
    if (!cmd) {
      for (size_t i = 0; i < ids_.size(); ++i) EXPECT_DOUBLE_EQ(last[i], 0.95);
      continue;
    }
    ASSERT_EQ(cmd->num_servos, static_cast<int>(ids_.size()));
    for (size_t i = 0; i < ids_.size(); ++i) {
      EXPECT_LE(cmd->goal_angle_rad[i] - last[i], 2.0 * kDt + 1e-12);  // max_velocity_rad_s
      EXPECT_LE(cmd->goal_angle_rad[i], 0.95 + 1e-12);                 // limit 1.0 - margin
      last[i] = cmd->goal_angle_rad[i];
    }
  }
  // 0.95 rad from 0.0 at 2 rad/s: reached after 0.475 s, well within the second.
  for (size_t i = 0; i < ids_.size(); ++i) EXPECT_DOUBLE_EQ(last[i], 0.95) << i;
}

TEST_F(CommandGateTest, TheDeadManHoldsTheMeasuredPositionWhenTheCommanderFallsSilent) {
  double t = kStartS + 2;
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  ASSERT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.9), t), "");
  for (int i = 0; i < 20; ++i) gate_.Tick(t += 0.01, false);  // 0.2 s: still inside deadman_s
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
  // The servos got somewhere; the commander stops.
  for (size_t i = 0; i < ids_.size(); ++i) measured_[i] = 0.3 + 0.01 * static_cast<double>(i);
  Measure();
  std::optional<servo_command_t> hold;
  while (!hold || gate_.mode() != Mode::kHold) {
    hold = gate_.Tick(t += 0.01, false);
    ASSERT_LT(t, kStartS + 2.3) << "no hold within the dead-man time";
  }
  EXPECT_GT(t - (kStartS + 2), 0.25);
  for (size_t i = 0; i < ids_.size(); ++i) EXPECT_EQ(hold->goal_angle_rad[i], measured_[i]);
  EXPECT_TRUE(hold->torque_enable);  // torque off would drop a standing robot
  EXPECT_EQ(stats_.counters().at("deadman_holds"), 1);
  EXPECT_EQ(stats_.counters().at("mode"), static_cast<int>(Mode::kHold));
  // Held: nothing more is written, a MOVE is refused, a new ARM resumes from the hold.
  EXPECT_FALSE(gate_.Tick(t += 0.01, false));
  EXPECT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.9), t), "servo command not_armed");
  EXPECT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
}

// The sequencer's SAFE_TORQUE_OFF: a MOVE with the torque off, then silence or DISARM. The hold
// that follows keeps the torque off; until now it wrote torque on at the measured position.
TEST_F(CommandGateTest, AHoldAfterTheCommanderTurnedTheTorqueOffKeepsItOff) {
  for (const bool disarm : {false, true}) {
    double t = kStartS + 2;
    ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
    servo_command_t off = Cmd(servo_command_t::MOVE, 0.0);
    off.torque_enable = false;
    ASSERT_EQ(Send("op", off, t), "");
    const auto written = gate_.Tick(t += 0.01, false);
    ASSERT_TRUE(written);
    EXPECT_FALSE(written->torque_enable);
    if (disarm) {
      ASSERT_EQ(Send("op", Cmd(servo_command_t::DISARM), t), "");
    }
    // Torque off is written every cycle while armed; the hold is what the tick that leaves
    // the armed mode writes.
    std::optional<servo_command_t> hold;
    do {
      hold = gate_.Tick(t += 0.01, false);
      ASSERT_LT(t, kStartS + 3) << "no hold";
    } while (gate_.mode() == Mode::kArmed);
    ASSERT_TRUE(hold);
    EXPECT_EQ(gate_.mode(), disarm ? Mode::kDisarmed : Mode::kHold);
    EXPECT_FALSE(hold->torque_enable) << (disarm ? "DISARM" : "dead-man") << " turned torque on";
    // A new ARM turns it on again: the commander's own, explicit step.
    ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
    const auto armed = gate_.Tick(t += 0.01, false);
    if (armed) {
      EXPECT_TRUE(armed->torque_enable);
    }
  }
}

TEST_F(CommandGateTest, ADegradedBridgeIsAFaultUntilItRecoversAndIsArmedAgain) {
  double t = kStartS + 2;
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  ASSERT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.9), t), "");
  EXPECT_FALSE(gate_.Tick(t, false));  // the first tick starts the clock
  // One degraded cycle (a late reply) is not a fault: the motion goes on.
  EXPECT_TRUE(gate_.Tick(t += 0.01, true));
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
  EXPECT_TRUE(gate_.Tick(t += 0.01, false));
  // Degraded for longer than deadman_s is (the commander still talking).
  const double degraded_from = t + 0.01;
  while (gate_.mode() != Mode::kFault) {
    ASSERT_EQ(Send("op", Cmd(servo_command_t::HEARTBEAT), t), "");
    gate_.Tick(t += 0.01, true);
    ASSERT_LT(t, degraded_from + 0.5);
  }
  EXPECT_GT(t - degraded_from, 0.25 - 1e-9);
  EXPECT_LT(t - degraded_from, 0.25 + 0.02);
  EXPECT_FALSE(gate_.Tick(t += 0.01, true));  // nothing moves in FAULT
  EXPECT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "servo command in_fault");
  EXPECT_FALSE(gate_.Tick(t += 0.01, false));
  EXPECT_EQ(gate_.mode(), Mode::kDisarmed);
  EXPECT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.9), t), "servo command not_armed");
}

// The servos' own limits not read back as configured (the bridge's ArmBlocker): ARM is refused
// with the reason, and taken once it clears.
TEST_F(CommandGateTest, NoArmWhileTheBridgeSaysTheLimitsAreWrong) {
  const double t = kStartS + 2;
  gate_.SetArmBlock("servo 3 (FL): Profile Velocity (112) written 125, read back 0");
  try {
    gate_.OnCommand("op", Cmd(servo_command_t::ARM), t);
    FAIL() << "armed";
  } catch (const BadInput& e) {
    EXPECT_EQ(e.kind(), "servo command limits_unverified");
    EXPECT_NE(std::string(e.what()).find("servo 3 (FL): Profile Velocity (112) written 125"),
              std::string::npos)
        << e.what();
  }
  EXPECT_EQ(gate_.mode(), Mode::kDisarmed);
  gate_.SetArmBlock("");
  EXPECT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
}

// A servo stopped by its Bus Watchdog (the bridge hung): armed becomes HOLD at the measured
// position, MOVEs and HEARTBEATs are refused, and only a new ARM moves the servos again.
TEST_F(CommandGateTest, AnExpiredWatchdogHoldsUntilANewArm) {
  double t = kStartS + 2;
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t), "");
  ASSERT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.5), t), "");
  gate_.Tick(t, false);
  t += 0.05;
  ASSERT_TRUE(gate_.Tick(t, false).has_value());
  measured_.assign(ids_.size(), 0.03);
  Measure();
  gate_.Hold("servo 1 (HL)'s Bus Watchdog had expired");
  EXPECT_EQ(gate_.mode(), Mode::kHold);
  t += 0.01;
  const auto hold = gate_.Tick(t, false);
  ASSERT_TRUE(hold.has_value());
  for (double g : hold->goal_angle_rad) EXPECT_DOUBLE_EQ(g, 0.03);
  EXPECT_EQ(Send("op", Cmd(servo_command_t::MOVE, 0.5), t), "servo command not_armed");
  EXPECT_EQ(Send("op", Cmd(servo_command_t::HEARTBEAT), t), "servo command not_armed");
  EXPECT_FALSE(gate_.Tick(t + 0.01, false).has_value());
  ASSERT_EQ(Send("op", Cmd(servo_command_t::ARM), t + 0.02), "");
  EXPECT_EQ(gate_.mode(), Mode::kArmed);
  // Disarmed, a hold changes nothing.
  ASSERT_EQ(Send("op", Cmd(servo_command_t::DISARM), t + 0.03), "");
  gate_.Tick(t + 0.04, false);
  gate_.Hold("again");
  EXPECT_EQ(gate_.mode(), Mode::kDisarmed);
}
}  // namespace
}  // namespace ftcal
