// The Dynamixel bridge's work, without LCM's loop: open the bus, ping the servos, and run one
// read-write cycle at a time (pending torque/goal writes, SYNC READ of the present block,
// Hardware Error Status now and then), turning the replies into a servo_state_t.
//
// Rules (docs/device-protocols.md §2.9): replies are matched to their request by id (never by
// position), by length (a reply of another request's size is a late one) and by a Realtime Tick
// that moves forward; the rest are counted and dropped. Each read waits only as long as the
// replies take on the wire at the bus's baud rate, plus each servo's Return Delay Time, plus
// the config's reply_timeout_s for adapter and OS latency. A servo that does not answer this
// cycle is flagged STALE with its last good values (NaN before it ever answered); after
// lost_after_misses cycles in a row it is LOST: left out of the reads (so it no longer costs the
// other five a timeout each cycle) and PINGed every reprobe_every_s until it answers. CRC
// errors, timeouts, malformed packets, status errors and hardware errors are counted and logged
// once per kind; a port that vanishes is reopened with back-off. Nothing a servo did not say
// is ever published as a value.
//
// Operating Mode (dynamixel.operating_mode): each servo's address 11 is read when it is first
// found (at start, after a reopen, after a lost servo answers again) and written, with torque
// off, when it differs (it is EEPROM: the servo keeps it). A servo whose mode cannot be set
// (torque on, which switching would drop, or a refused write) is logged and its goals are
// refused until the bridge restarts. In Extended Position mode Present Position is multi-turn,
// so the published shaft angle is unbounded (a turn is 2 pi, never wrapped); goals stay within
// the configured angle limits either way, and within the mode's count range.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/service_stats.h"
#include "ftcal/servo_command_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "proto/config.pb.h"
#include "protocol2.h"
#include "serial_port.h"

namespace ftcal {

struct DynamixelBridgeOptions {
  std::string device;          // serial device; empty: the config's
  int hardware_error_every = 10;  // read address 64-70 every n-th cycle (and after an alert)
  int lost_after_misses = 5;   // consecutive cycles without a valid reply before a servo is lost
  double reprobe_every_s = 1.0;  // a lost servo is PINGed this often
  double reopen_min_s = 0.1;   // back-off between attempts to reopen a vanished port
  double reopen_max_s = 2.0;
};

class DynamixelBridge {
 public:
  using Publisher = std::function<void(const servo_state_t&)>;
  using Clock = std::chrono::steady_clock;

  // Throws std::invalid_argument when the config has no dynamixel section or a servo's
  // direction is not +-1.
  DynamixelBridge(const config::Config& config, DynamixelBridgeOptions options,
                  ServiceStats& stats, Publisher publish, std::function<int64_t()> now_utime);

  // Opens the port and pings every configured servo; logs each one that does not answer or is
  // not an MX-106(2.0). Returns false (and schedules a retry) when the port cannot be opened.
  bool Connect();
  bool connected() const { return port_ != nullptr; }
  // The device fd to poll between cycles, -1 while disconnected.
  int fd() const { return port_ ? port_->fd() : -1; }

  // One cycle: reconnects when due, sends pending writes, reads the servos, publishes one
  // servo_state_t. Takes at most about two reply timeouts.
  void Cycle();
  // The device fd is readable between cycles: bytes nobody asked for (counted as noise), or a
  // hang-up (the port is closed and reopened later).
  void OnDeviceReadable();
  // SERVO_CMD. Throws BadInput (unknown id, NaN goal) without applying any of it.
  void OnCommand(const servo_command_t& cmd);

  // True while a servo is missing, stale, in hardware error, or the port is down; `why` says
  // which.
  bool Degraded(std::string* why = nullptr) const;
  // Servos currently lost (left out of the reads, re-probed now and then).
  std::vector<std::uint8_t> lost() const;
  // Ids that did not answer the start-up PING.
  const std::vector<std::uint8_t>& missing_at_start() const { return missing_at_start_; }
  std::int64_t cycles() const { return cycles_; }
  // Servos whose Operating Mode is checked and not the configured one (their goals are refused).
  std::vector<std::uint8_t> wrong_mode() const;

 private:
  struct ServoSlot {
    std::string leg;
    std::uint8_t id = 0;
    std::int32_t zero_count = 2048;
    int direction = 1;
    double min_angle_rad = 0, max_angle_rad = 0;
    // Last good values.
    bool ever_read = false;
    double angle_rad = 0, velocity_rad_s = 0, current_a = 0;
    dxl::TickUnwrapper ticks;
    std::int64_t tick_ms = 0;
    std::uint16_t last_raw_tick = 0;
    bool tick_known = false;  // last_raw_tick is from this port session and this find
    double return_delay_s = 500e-6;  // factory default until read from the servo
    std::int32_t hardware_error = 0;
    int torque_enable = -1;  // -1 unknown
    bool alert = false;
    int consecutive_misses = 0;
    bool lost = false;
    bool probe_outstanding = false;  // a PING sent, its answer not seen yet
    Clock::time_point next_probe{};
    Clock::time_point last_read{};
    // Pending from SERVO_CMD.
    std::optional<bool> pending_torque;
    std::optional<std::int32_t> goal_count;
    // Operating Mode: checked since this servo was last found; and whether it is the configured.
    bool mode_checked = false;
    bool mode_ok = false;
    int mode = -1;  // as read, -1 unknown
  };

  // Sends `packet` and collects one status per servo in `slots` (indices into servos_) until
  // all came or the deadline passed: the wire time of the request and of the replies of
  // `reply_params` bytes each, the servos' return delays, and reply_timeout_s. A reply from a
  // servo not asked, or a second one, is counted unexpected; one without error whose size is
  // not `reply_params` answers another request (late) and is counted mismatched. `on_reply`
  // gets each matched status (with its index into `slots`) and returns false to reject it (an
  // error byte): that servo stays unanswered. Returns, per slot, whether it answered.
  std::vector<bool> Transact(
      const std::vector<std::uint8_t>& packet, const std::vector<std::size_t>& slots,
      std::size_t reply_params,
      const std::function<bool(std::size_t, const dxl::StatusPacket&)>& on_reply);
  // The slots not lost, and their ids.
  std::vector<std::size_t> ActiveSlots() const;
  std::vector<std::uint8_t> IdsOf(const std::vector<std::size_t>& slots) const;
  void ReadReturnDelays(const std::vector<std::size_t>& slots);
  // Reads (and when needed writes) the Operating Mode of each of `slots` not yet checked.
  void CheckOperatingModes(const std::vector<std::size_t>& slots);
  // One byte of slot i's control table; nullopt when it did not answer or answered an error.
  std::optional<std::uint8_t> ReadByte(std::size_t i, std::uint16_t address);
  // Sends a PING to at most one lost servo whose probe is due (without waiting for it).
  void Reprobe();
  // True when `status` answers an outstanding probe: that servo is found (read again).
  bool ProbeAnswered(const dxl::StatusPacket& status);
  void ReadPresent(std::vector<bool>* fresh);
  // Reads what is waiting; complete status packets are late replies (counted, dropped). Throws
  // dxl::SerialError.
  void DrainLate();
  void ReadHardwareErrors();
  void SendPendingWrites();
  void Publish(std::int64_t utime, const std::vector<bool>& fresh);
  void PortLost(const std::string& why);
  void SyncParserStats();
  ServoSlot* FindId(std::uint8_t id);

  config::Config config_;
  DynamixelBridgeOptions options_;
  ServiceStats& stats_;
  Publisher publish_;
  std::function<int64_t()> now_utime_;
  std::string device_;
  std::uint32_t baud_;
  double reply_timeout_s_;
  std::uint8_t operating_mode_;  // dynamixel.operating_mode's code
  std::int32_t min_goal_count_, max_goal_count_;  // the mode's range

  std::unique_ptr<dxl::SerialPort> port_;
  dxl::PacketParser parser_;
  dxl::PacketParser::Stats synced_{};  // parser counts already moved into stats_
  std::vector<ServoSlot> servos_;
  std::vector<std::uint8_t> missing_at_start_;
  std::vector<bool> last_fresh_;
  bool force_error_read_ = true;
  std::int64_t cycles_ = 0;
  double reopen_delay_s_;
  Clock::time_point next_reopen_{};
  std::string down_reason_;
};

}  // namespace ftcal
