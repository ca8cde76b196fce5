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
// The servo set-up (servo_setup.h: model, Return Delay Time, Operating Mode, the servos' own
// limits and Bus Watchdog) is done when a servo is found (at start, after a reopen, after a lost
// servo answers again), before it takes a goal; a servo whose mode or limits are not as
// configured has its goals refused or blocks arming, and an expired Bus Watchdog found is
// cleared and reported once (TakeWatchdogExpiry), so that the gate holds until a new ARM.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/service_stats.h"
#include "ftcal/device_clock.h"
#include "ftcal/legs.h"
#include "ftcal/servo_command_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "proto/config.pb.h"
#include "protocol2.h"
#include "serial_port.h"
#include "servo_setup.h"

namespace ftcal {

struct DynamixelBridgeOptions {
  std::string device;             // serial device; empty: the config's
  int hardware_error_every = 10;  // read address 64-70 every n-th cycle (and after an alert)
  int lost_after_misses = 5;      // consecutive cycles without a valid reply before a servo is lost
  double reprobe_every_s = 1.0;   // a lost servo is PINGed this often
  double reopen_min_s = 0.1;      // back-off between attempts to reopen a vanished port
  double reopen_max_s = 2.0;
};

class DynamixelBridge : private ServoSetup::Link {
 public:
  using Publisher = std::function<void(const servo_state_t&)>;
  using Clock = std::chrono::steady_clock;

  // Throws std::invalid_argument when the config has no dynamixel section or a servo's
  // direction is not +-1.
  DynamixelBridge(const config::Config& config, DynamixelBridgeOptions options, ServiceStats& stats,
                  Publisher publish, std::function<int64_t()> now_utime);

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
  // Why arming must wait, empty when it need not: a servo whose limits are not yet written and
  // read back, or read back different from the config.
  std::string ArmBlocker() const { return setup_->ArmBlocker(); }
  // A servo's Bus Watchdog was found expired and cleared since the last call: what happened.
  std::optional<std::string> TakeWatchdogExpiry() { return setup_->TakeWatchdogExpiry(); }
  // Servos currently lost (left out of the reads, re-probed now and then).
  std::vector<std::uint8_t> lost() const;
  // Ids that did not answer the start-up PING.
  const std::vector<std::uint8_t>& missing_at_start() const { return missing_at_start_; }
  std::int64_t cycles() const { return cycles_; }
  // Servos whose Operating Mode is checked and not the configured one (their goals are refused).
  std::vector<std::uint8_t> wrong_mode() const { return setup_->wrong_mode(); }

 private:
  // A servo: who it is and what its set-up found (SetupServo), and what the run loop keeps.
  struct ServoSlot : SetupServo {
    explicit ServoSlot(SetupServo who) : SetupServo(std::move(who)) {}
    // Last good values.
    bool ever_read = false;
    double angle_rad = 0, velocity_rad_s = 0, current_a = 0;
    dxl::TickUnwrapper ticks;
    std::int64_t tick_ms = 0;
    std::uint16_t last_raw_tick = 0;
    bool tick_known = false;  // last_raw_tick is from this port session and this find
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
    bool watchdog_expired = false;  // seen in the error block: cleared at the end of the cycle
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
  // ServoSetup::Link: the servos, and Transact to one of them.
  std::size_t size() const override { return servos_.size(); }
  SetupServo& servo(std::size_t i) override { return servos_[i]; }
  std::vector<std::size_t> active() const override { return ActiveSlots(); }
  bool Request(std::size_t i, const std::vector<std::uint8_t>& packet, std::size_t reply_params,
               const std::function<bool(const dxl::StatusPacket&)>& on_reply) override;
  bool port_open() const override { return port_ != nullptr; }
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
  // Each servo's Realtime Tick mapped onto the host clock, one instant per read (SERVO_STATE's
  // sample_utime; docs/method.md, "Clocks and delays").
  SyncReadClock sample_clock_{kNumLegs, DeviceClockOptions{}};
  std::int64_t read_request_utime_ = SyncReadClock::kNoRequest;  // this cycle's Sync Read sent
  std::string device_;
  std::uint32_t baud_;
  double reply_timeout_s_;
  std::optional<ServoSetup> setup_;   // made once the config's checks before it passed
  Clock::time_point last_traffic_{};  // the last instruction packet sent

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
