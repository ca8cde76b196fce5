// The Dynamixel bridge as the last line: what a verified SERVO_CMD may make the servos do.
//
// The envelope's signature says who sent a command (common/envelope.h); this gate decides
// whether to act on it:
//   - commands in the first dynamixel.start_quiet_s after start are ignored: a commander that
//     kept sending to a bridge that died must not move the legs the moment it is back;
//   - goals are taken only while armed, and only from the commander that armed the bridge
//     (ARM from a trusted signer while disarmed or held; one commander at a time);
//   - a MOVE must name exactly the configured servos, each once, with finite goals;
//   - goals are clamped to each servo's angle limits minus dynamixel.limit_margin_rad, and the
//     goal written moves towards the commanded one by at most dynamixel.max_velocity_rad_s per
//     second, from the measured position at arming;
//   - dead-man: while armed, a MOVE or HEARTBEAT from the commander at least every
//     dynamixel.deadman_s, or the gate writes the measured positions as goals and goes to
//     HOLD (a new ARM resumes); torque stays on, since torque off drops a standing robot;
//   - while the bridge has been degraded (a servo silent or in hardware error, the port down)
//     for longer than dynamixel.deadman_s the gate is in FAULT: nothing is moved until it
//     clears and a commander arms again (one stale cycle on a loaded bus is not a fault);
//   - ARM is refused while the bridge says the servos' own limits are not as configured (not
//     yet read back, or different: SetArmBlock), and a servo whose Bus Watchdog expired (the
//     bridge hung) takes the gate to HOLD (Hold): motion resumes only after a new ARM.
// Mode and refusal counts are counters of the process's FTCAL_STATUS.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "common/service_stats.h"
#include "ftcal/servo_command_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "proto/config.pb.h"

namespace ftcal {

class CommandGate {
 public:
  enum class Mode : int { kDisarmed = 0, kArmed = 1, kHold = 2, kFault = 3 };

  // `start_s`: the bridge's start on the clock the other calls use (steady, s).
  CommandGate(const config::Config& config, ServiceStats& stats, double start_s);

  // A command whose envelope verified, from the trusted key `signer`. Throws BadInput (kind
  // names the reason) for one that is not acted on.
  void OnCommand(const std::string& signer, const servo_command_t& cmd, double now_s);
  // What the bridge measured (its SERVO_STATE).
  void OnState(const servo_state_t& state);
  // Once per bridge cycle: the dead-man, the fault state and the velocity limit. Returns the
  // command to hand to the bridge this cycle, if any.
  std::optional<servo_command_t> Tick(double now_s, bool degraded);
  // Why ARM must be refused now (the bridge's ArmBlocker); empty: it need not be.
  void SetArmBlock(std::string why) { arm_block_ = std::move(why); }
  // Something outside the commander stopped the servos (`why`): armed becomes HOLD, the
  // measured positions are written at the next tick, and only a new ARM moves them again.
  void Hold(const std::string& why);

  Mode mode() const { return mode_; }
  const std::string& commander() const { return commander_; }
  static const char* ModeName(Mode mode);

 private:
  struct Servo {
    int id = 0;
    double min_rad = 0, max_rad = 0;  // limits minus the margin
    double measured_rad = 0;
    bool measured = false;
    double goal_rad = 0;    // written
    double target_rad = 0;  // commanded
  };
  void SetMode(Mode mode, const std::string& why);
  servo_command_t HoldMeasured();
  [[noreturn]] void Refuse(const std::string& kind, const std::string& why);

  ServiceStats& stats_;
  double start_s_;
  double quiet_s_, deadman_s_, max_velocity_rad_s_;
  std::vector<Servo> servos_;
  std::map<int, size_t> by_id_;
  Mode mode_ = Mode::kDisarmed;
  std::string commander_;
  double last_contact_s_ = 0;
  double last_tick_s_ = -1;
  bool torque_enable_ = true;
  bool hold_pending_ = false;  // write the measured positions at the next tick
  double degraded_since_s_ = -1;
  std::string arm_block_;
};

}  // namespace ftcal
