#include "dynamixel_bridge/command_gate.h"

#include <algorithm>
#include <type_traits>
#include <cmath>
#include <set>
#include <stdexcept>

#include "common/bus.h"

namespace ftcal {

const char* CommandGate::ModeName(Mode mode) {
  switch (mode) {
    case Mode::kDisarmed:
      return "disarmed";
    case Mode::kArmed:
      return "armed";
    case Mode::kHold:
      return "hold";
    case Mode::kFault:
      return "fault";
  }
  return "?";
}

CommandGate::CommandGate(const config::Config& config, ServiceStats& stats, double start_s)
    : stats_(stats),
      start_s_(start_s),
      quiet_s_(config.dynamixel().start_quiet_s()),
      deadman_s_(config.dynamixel().deadman_s()),
      max_velocity_rad_s_(config.dynamixel().max_velocity_rad_s()) {
  const double margin = config.dynamixel().limit_margin_rad();
  for (const auto& leg : config.robot().leg()) {
    Servo s;
    s.id = static_cast<int>(leg.servo().id());
    s.min_rad = leg.servo().min_angle_rad() + margin;
    s.max_rad = leg.servo().max_angle_rad() - margin;
    if (!(s.min_rad <= s.max_rad)) {
      throw std::invalid_argument("servo " + std::to_string(s.id) + " (" + leg.name() +
                                  "): angle limits closer than twice dynamixel.limit_margin_rad");
    }
    by_id_[s.id] = servos_.size();
    servos_.push_back(s);
  }
  stats_.Counter("mode") = static_cast<int>(mode_);
}

void CommandGate::Refuse(const std::string& kind, const std::string& why) {
  ++stats_.Counter("refused_" + kind);
  throw BadInput("servo command " + kind, why);
}

void CommandGate::SetMode(Mode mode, const std::string& why) {
  if (mode == mode_) return;
  stats_.log().warn("servo commands: {} -> {} ({})", ModeName(mode_), ModeName(mode), why);
  mode_ = mode;
  stats_.Counter("mode") = static_cast<int>(mode_);
}

void CommandGate::OnState(const servo_state_t& state) {
  for (size_t i = 0; i < std::extent_v<decltype(state.id)>; ++i) {
    const auto it = by_id_.find(state.id[i]);
    if (it == by_id_.end() || (state.flags[i] & servo_state_t::FLAG_STALE) ||
        !std::isfinite(state.angle_rad[i])) {
      continue;
    }
    Servo& s = servos_[it->second];
    s.measured_rad = state.angle_rad[i];
    s.measured = true;
  }
}

void CommandGate::OnCommand(const std::string& signer, const servo_command_t& cmd, double now_s) {
  if (now_s - start_s_ < quiet_s_) {
    Refuse("ignored_at_start", "from " + signer + " within dynamixel.start_quiet_s of the start");
  }
  const bool is_commander = (mode_ == Mode::kArmed || mode_ == Mode::kHold) && signer == commander_;
  switch (cmd.action) {
    case servo_command_t::ARM: {
      if (mode_ == Mode::kFault) Refuse("in_fault", "ARM from " + signer + " while in FAULT");
      if (!arm_block_.empty())
        Refuse("limits_unverified", "ARM from " + signer + ": " + arm_block_);
      if (mode_ == Mode::kArmed && signer != commander_) {
        Refuse("not_commander", "ARM from " + signer + " while armed by " + commander_);
      }
      for (const Servo& s : servos_) {
        if (!s.measured) {
          Refuse("unmeasured",
                 "ARM from " + signer + " before servo " + std::to_string(s.id) + " was measured");
        }
      }
      for (Servo& s : servos_) {
        s.goal_rad = std::clamp(s.measured_rad, s.min_rad, s.max_rad);
        s.target_rad = s.goal_rad;
      }
      commander_ = signer;
      last_contact_s_ = now_s;
      torque_enable_ = true;
      ++stats_.Counter("arms");
      SetMode(Mode::kArmed, "ARM from " + signer);
      return;
    }
    case servo_command_t::DISARM:
      if (!is_commander) Refuse("not_commander", "DISARM from " + signer);
      hold_pending_ = true;
      SetMode(Mode::kDisarmed, "DISARM from " + signer);
      return;
    case servo_command_t::HEARTBEAT:
      if (mode_ != Mode::kArmed) Refuse("not_armed", "HEARTBEAT from " + signer);
      if (!is_commander) Refuse("not_commander", "HEARTBEAT from " + signer);
      last_contact_s_ = now_s;
      return;
    case servo_command_t::MOVE:
      break;
    default:
      Refuse("bad_action", "action " + std::to_string(cmd.action) + " from " + signer);
  }
  if (mode_ != Mode::kArmed) {
    Refuse("not_armed", std::string("MOVE from ") + signer + " while " + ModeName(mode_));
  }
  if (!is_commander) Refuse("not_commander", "MOVE from " + signer + ", armed by " + commander_);
  // Exactly the configured servos, each once, finite goals: taken whole or not at all.
  if (cmd.num_servos != static_cast<int>(servos_.size()) || cmd.id.size() != servos_.size() ||
      cmd.goal_angle_rad.size() != servos_.size()) {
    Refuse("wrong_servos", "MOVE names " + std::to_string(cmd.num_servos) + " servos, the config " +
                               std::to_string(servos_.size()));
  }
  std::set<int> seen;
  for (size_t i = 0; i < servos_.size(); ++i) {
    if (by_id_.count(cmd.id[i]) == 0 || !seen.insert(cmd.id[i]).second) {
      Refuse("wrong_servos",
             "MOVE names servo id " + std::to_string(cmd.id[i]) + " (unknown or twice)");
    }
    if (cmd.torque_enable && !std::isfinite(cmd.goal_angle_rad[i])) {
      Refuse("non_finite", "MOVE goal for servo " + std::to_string(cmd.id[i]) + " is not finite");
    }
  }
  last_contact_s_ = now_s;
  torque_enable_ = cmd.torque_enable;
  if (!cmd.torque_enable) return;
  for (size_t i = 0; i < servos_.size(); ++i) {
    Servo& s = servos_[by_id_.at(cmd.id[i])];
    const double goal = cmd.goal_angle_rad[i];
    s.target_rad = std::clamp(goal, s.min_rad, s.max_rad);
    if (s.target_rad != goal) ++stats_.Counter("goals_clamped_to_margin");
  }
  ++stats_.Counter("moves");
}

void CommandGate::Hold(const std::string& why) {
  ++stats_.Counter("external_holds");
  if (mode_ != Mode::kArmed) return;  // held, disarmed or in fault: nothing is moving already
  hold_pending_ = true;
  SetMode(Mode::kHold, why);
}

servo_command_t CommandGate::HoldMeasured() {
  servo_command_t cmd{};
  cmd.action = servo_command_t::MOVE;
  // A hold keeps the torque as the commander left it. Held with torque on, the legs stay where
  // they are (torque off would drop a standing robot). But a commander that turned the torque
  // off (the sequencer's SAFE_TORQUE_OFF, for an operator at the robot) and then went silent
  // or disarmed must not have the bridge stiffen the legs again behind its back: that undid
  // the safe action.
  cmd.torque_enable = torque_enable_;
  for (Servo& s : servos_) {
    if (s.measured) s.goal_rad = s.target_rad = std::clamp(s.measured_rad, s.min_rad, s.max_rad);
    cmd.id.push_back(s.id);
    cmd.goal_angle_rad.push_back(s.goal_rad);
  }
  cmd.num_servos = static_cast<int32_t>(cmd.id.size());
  return cmd;
}

std::optional<servo_command_t> CommandGate::Tick(double now_s, bool degraded) {
  const double dt = last_tick_s_ < 0 ? 0.0 : std::clamp(now_s - last_tick_s_, 0.0, 0.1);
  last_tick_s_ = now_s;
  // One stale cycle (a late reply on a loaded bus) is not a fault; a servo silent or in error,
  // or the port down, for longer than the dead-man time is.
  if (!degraded) {
    degraded_since_s_ = -1;
  } else if (degraded_since_s_ < 0) {
    degraded_since_s_ = now_s;
  }
  if (degraded_since_s_ >= 0 && now_s - degraded_since_s_ > deadman_s_) {
    // Nothing moves further; the goals already written stay (they are inside the limits).
    hold_pending_ = false;
    SetMode(Mode::kFault, "the bridge degraded for more than dynamixel.deadman_s");
    return std::nullopt;
  }
  if (mode_ == Mode::kFault) {
    if (degraded) return std::nullopt;
    SetMode(Mode::kDisarmed, "the bridge recovered; ARM again");
  }
  if (mode_ == Mode::kArmed && now_s - last_contact_s_ > deadman_s_) {
    ++stats_.Counter("deadman_holds");
    hold_pending_ = true;
    SetMode(Mode::kHold, commander_ + " silent for more than dynamixel.deadman_s");
  }
  if (hold_pending_) {
    hold_pending_ = false;
    return HoldMeasured();
  }
  if (mode_ != Mode::kArmed) return std::nullopt;
  servo_command_t cmd{};
  cmd.action = servo_command_t::MOVE;
  cmd.torque_enable = torque_enable_;
  bool moved = false;
  const double step = max_velocity_rad_s_ * dt;
  for (Servo& s : servos_) {
    const double next = s.goal_rad + std::clamp(s.target_rad - s.goal_rad, -step, step);
    moved = moved || next != s.goal_rad;
    s.goal_rad = next;
    cmd.id.push_back(s.id);
    cmd.goal_angle_rad.push_back(s.goal_rad);
  }
  cmd.num_servos = static_cast<int32_t>(cmd.id.size());
  // Torque off, or a goal that changed; at rest nothing is written.
  if (!moved && torque_enable_) return std::nullopt;
  return cmd;
}

}  // namespace ftcal
