// The Dynamixel bridge's servo set-up: what it makes sure of in a servo's control table when the
// servo is found (at start, after a reopen, after a lost servo answers again), before it takes a
// goal. The bridge's run loop (dynamixel_bridge.h) asks for it; this does it, one request to one
// servo at a time, through the bridge's port (ServoSetup::Link).
//
// Model: the PING answer names an MX-106(2.0) (model 321); another is logged.
//
// Return Delay Time (address 9) is read, so that each read waits only as long as the servo
// takes (docs/device-protocols.md §2.9).
//
// Operating Mode (dynamixel.operating_mode): each servo's address 11 is read when it is first
// found and written, with torque off, when it differs (it is EEPROM: the servo keeps it). A servo
// whose mode cannot be set (torque on, which switching would drop, or a refused write) is logged
// and its goals are refused until the bridge restarts. In Extended Position mode Present Position
// is multi-turn, so the published shaft angle is unbounded (a turn is 2 pi, never wrapped); goals
// stay within the configured angle limits either way, and within the mode's count range (Goal).
//
// The servos' own limits (docs/device-protocols.md §2.7), when a servo is found, after its
// mode: Acceleration and Velocity Limit (EEPROM) from dynamixel.max_acceleration_rad_s2 and
// max_velocity_rad_s, Min/Max Position Limit from the angle limits in Position mode (Extended
// Position mode ignores them: there the bridge's clamp is the only position limit), then
// Profile Acceleration and Velocity (RAM, at most the limits) and the Bus Watchdog
// (dynamixel.bus_watchdog_s). Each is read first and written only when it differs, EEPROM
// only with torque off (a servo holding its leg is not dropped to rewrite it), and all are
// read back: a servo whose limits are not what the config says blocks arming, with the
// servo, the register and the values named (the bridge's ArmBlocker and Degraded). The
// bridge's every cycle feeds the watchdog; a servo found with it expired (the bridge hung, or
// the port was gone longer than it) is cleared (0, the goal set to where it stopped, then the
// watchdog again) and reported once (TakeWatchdogExpiry), so that the gate holds until a new ARM.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "common/service_stats.h"
#include "proto/config.pb.h"
#include "protocol2.h"

namespace ftcal {

// A PING's status: model number (2 bytes) and firmware version.
constexpr std::size_t kPingParams = 3;

// "servo 3 (HL)": how every line names a servo.
std::string ServoName(std::uint8_t id, const std::string& leg);

// A servo as its set-up knows it: who it is (from the config) and what the set-up found since
// the servo was last found.
struct SetupServo {
  std::string leg;
  std::uint8_t id = 0;
  std::int32_t zero_count = 2048;
  int direction = 1;
  double min_angle_rad = 0, max_angle_rad = 0;
  double return_delay_s = 500e-6;  // factory default until read from the servo
  // Operating Mode: checked since this servo was last found; and whether it is the configured.
  bool mode_checked = false;
  bool mode_ok = false;
  int mode = -1;  // as read, -1 unknown
  // Its limits (LimitsFor): written and read back since it was last found; what differs.
  bool limits_checked = false;
  std::string limits_error;
};

// The servos of the config's legs, in its order. Throws std::invalid_argument when a servo's
// direction is not +-1.
std::vector<SetupServo> ServosFromConfig(const config::Config& config);

class ServoSetup {
 public:
  // What the set-up needs of the bridge: its servos (slots 0..size()-1, and those not lost,
  // which are read); one request to the servo in slot i (the packet sent, its status of
  // `reply_params` bytes handed to `on_reply`, which returns false to reject it; true when the
  // servo answered and was not rejected); and whether the port is still open (a request can
  // lose it: then the set-up stops where it is, and is done again after a reopen).
  class Link {
   public:
    virtual std::size_t size() const = 0;
    virtual SetupServo& servo(std::size_t i) = 0;
    virtual std::vector<std::size_t> active() const = 0;
    virtual bool Request(std::size_t i, const std::vector<std::uint8_t>& packet,
                         std::size_t reply_params,
                         const std::function<bool(const dxl::StatusPacket&)>& on_reply) = 0;
    virtual bool port_open() const = 0;

   protected:
    ~Link() = default;
  };

  // The registers' values from the config's dynamixel section. Throws std::invalid_argument for
  // an operating_mode that is not POSITION_MODE or EXTENDED_POSITION_MODE, or a bus_watchdog_s
  // that is not 1-127 units of 20 ms.
  ServoSetup(const config::Config& config, ServiceStats& stats, Link& link);

  // The answer `p` to the start-up PING of slot i: false when it is not a PING's answer; an
  // answer from another model than the MX-106(2.0) is logged and accepted.
  bool PingAnswered(std::size_t i, const dxl::StatusPacket& p);
  void ReadReturnDelays(const std::vector<std::size_t>& slots);
  // The servos not lost whose mode or limits are not checked since they were found: their
  // Operating Mode (CheckOperatingModes), then the limits of those whose mode is checked
  // (CheckLimits). What did not answer is tried again at the next call.
  void CheckFound();
  // Reads (and when needed writes) the Operating Mode of each of `slots` not yet checked.
  void CheckOperatingModes(const std::vector<std::size_t>& slots);
  // Reads, writes where they differ, and reads back slot i's limits (and clears an expired
  // watchdog); sets limits_checked and limits_error.
  void CheckLimits(std::size_t i);
  // Slot i's Bus Watchdog was seen expired (in the bridge's error read): cleared as ClearWatchdog
  // says; when that fails (the port still open), the servo's limits_error says why, so that it
  // blocks arming.
  void ClearExpiredWatchdog(std::size_t i);
  // A servo's Bus Watchdog was found expired and cleared since the last call: what happened.
  std::optional<std::string> TakeWatchdogExpiry();
  // Why arming must wait, empty when it need not: a servo whose limits are not yet written and
  // read back, or read back different from the config.
  std::string ArmBlocker() const;
  // Servos whose Operating Mode is checked and not the configured one (their goals are refused).
  std::vector<std::uint8_t> wrong_mode() const;

  // The goal count for `goal_rad` (finite): clamped to the servo's angle limits (counted as
  // goals_clamped). Throws BadInput when the servo is in the wrong Operating Mode or the count is
  // outside the mode's range.
  std::int32_t Goal(const SetupServo& s, double goal_rad);

  std::uint8_t operating_mode() const { return operating_mode_; }
  double watchdog_s() const { return watchdog_s_; }

 private:
  // One register the bridge sets in every servo; the value comes from the config.
  struct LimitItem {
    const char* name;
    std::uint16_t address;
    int size;
    bool eeprom;
    std::uint32_t value;
  };
  // Clears slot i's expired Bus Watchdog: 0, the goal at its present position, the value.
  // Returns false when the servo refused or did not answer.
  bool ClearWatchdog(std::size_t i, std::string* why);
  // The registers for slot i, in the order they are written (EEPROM limits before the profile
  // values they bound, the watchdog last).
  std::vector<LimitItem> LimitsFor(std::size_t i);
  std::optional<std::vector<std::uint8_t>> ReadBlock(std::size_t i, std::uint16_t address,
                                                     std::uint16_t length);
  // WRITE to slot i; the status error byte, or nullopt without an answer.
  std::optional<std::uint8_t> WriteItem(std::size_t i, std::uint16_t address, std::uint32_t value,
                                        int size);
  // One byte of slot i's control table; nullopt when it did not answer or answered an error.
  std::optional<std::uint8_t> ReadByte(std::size_t i, std::uint16_t address);

  ServiceStats& stats_;
  Link& link_;
  std::string mode_name_;                              // dynamixel.operating_mode's name
  std::uint8_t operating_mode_;                        // its code
  std::int32_t min_goal_count_, max_goal_count_;       // the mode's range
  std::uint32_t velocity_limit_, acceleration_limit_;  // register units
  std::uint8_t watchdog_units_;
  double watchdog_s_;
  std::optional<std::string> watchdog_expiry_;
};

}  // namespace ftcal
