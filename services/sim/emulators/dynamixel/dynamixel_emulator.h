// The twin's Dynamixel bus: six MX-106(2.0) servos (model 321) answering Protocol 2.0 on a
// pseudo-terminal, so the real ftcal-dynamixel-bridge runs against it unchanged.
//
// Two layers. DynamixelBusEmulator is bytes in, bytes out (no file descriptors): a test or a
// benchmark can drive it directly. PtyBus puts it on a pseudo-terminal whose slave path is
// symlinked where the bridge's config points, and can vanish and come back (an unplugged USB
// adapter).
//
// Each servo has a control table (docs/device-protocols.md §2.7). Positions either follow Goal
// Position with first-order dynamics while torque is on, no faster than a non-zero Profile
// Velocity, or are driven from outside (the
// twin's shaft angles) through a StateSource called whenever the table is read.
//
// Faults are injected on the servos' replies: per-packet rates (drop, corrupt CRC, noise bytes
// before the packet) drawn from a seeded generator, so a run is repeatable for the same
// sequence of requests, and scheduled events (a servo missing, the whole bus silent, a
// hardware error). Every reply, with its fate, goes to a ReplyObserver: that is the truth a
// test compares the bridge with.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "protocol2.h"

namespace ftcal::sim {

inline constexpr std::uint16_t kMx106ModelNumber = 321;
inline constexpr std::uint8_t kMx106FirmwareVersion = 45;
inline constexpr std::size_t kControlTableBytes = 662;  // through Indirect Data 56

struct DxlFaultRates {
  std::uint64_t seed = 1;
  double drop_reply = 0.0;   // probability per status packet
  double corrupt_crc = 0.0;  // probability per status packet (one CRC byte flipped)
  double noise = 0.0;        // probability per status packet of a noise burst before it
  int max_noise_bytes = 6;   // burst length 1..max; bytes are never FF, so never a false header
};

enum class DxlFaultKind {
  kMissingServo,   // `id` does not answer anything in [start_s, end_s)
  kSilent,         // no servo answers in [start_s, end_s)
  kHardwareError,  // at start_s: `id` raises `hw_error_bits` (torque off, alert) until REBOOT
};

struct DxlFaultEvent {
  DxlFaultKind kind = DxlFaultKind::kSilent;
  double start_s = 0.0;
  double end_s = 0.0;
  std::uint8_t id = 0;
  std::uint8_t hw_error_bits = 0x20;  // overload
};

// A register of one servo that acknowledges writes without taking them: the servo then
// reports a value other than the one it was told (a firmware that lacks the item, a table
// edited behind the bridge's back). What a bridge's read-back must catch.
struct DxlIgnoredWrite {
  std::uint8_t id = 0;
  std::uint16_t address = 0;
};

struct DxlEmulatorOptions {
  std::vector<std::uint8_t> ids = {1, 2, 3, 4, 5, 6};
  double time_constant_s = 0.05;      // first-order response to Goal Position
  std::uint16_t initial_tick_ms = 0;  // Realtime Tick at t = 0 (wraps at 32768)
  // Each servo's own crystal, one per id (same order; missing: exact): its Realtime Tick runs
  // tick_rate_ppm fast and is tick_phase_ms into its millisecond at t = 0 (a servo booted
  // apart from the others). docs/method.md, "Clocks and delays".
  std::vector<double> tick_rate_ppm;
  std::vector<double> tick_phase_ms;
  std::int32_t initial_position = 2048;  // counts, for every servo
  // When given, one per id (same order): each servo's own initial position, counts.
  std::vector<std::int32_t> initial_positions;
  // Operating Mode (address 11) at power-up: 3 (position) from the factory; a bridge writes 4
  // (extended position, multi-turn) with torque off. In mode 3 Goal Position must lie within
  // the Min/Max Position Limits (0-4095), in modes 4 and 5 within +-1,048,575 (Data Limit Error
  // otherwise), and Present Position follows the shaft over any number of turns.
  std::uint8_t operating_mode = 3;
  DxlFaultRates rates;
  std::vector<DxlFaultEvent> events;
  std::vector<DxlIgnoredWrite> ignored_writes;
};

// Present values supplied from outside for one servo (the twin's shaft angle as counts).
struct DxlDrivenState {
  double position_counts = 2048.0;  // continuous; the table holds it rounded
  double velocity_counts_s = 0.0;
  double current_a = 0.0;
};

enum class DxlReplyFate { kSent, kDropped, kCorrupted, kMissing, kSilent };
const char* DxlReplyFateName(DxlReplyFate fate);

// One status packet a servo produced (or would have, for kMissing/kSilent).
struct DxlReplyRecord {
  double t_s = 0.0;
  std::uint8_t id = 0;
  std::uint8_t instruction = 0;  // the request it answers
  std::uint16_t address = 0;     // for READ / SYNC READ
  std::uint16_t length = 0;
  DxlReplyFate fate = DxlReplyFate::kSent;
  std::uint8_t error = 0;
  std::size_t noise_bytes = 0;
  // Table contents when the reply was made (what the packet carried).
  std::uint16_t tick_ms = 0;
  std::int32_t position = 0;
  std::int32_t velocity = 0;
  std::int16_t current = 0;
  std::uint8_t torque_enable = 0;
  std::uint8_t hardware_error = 0;
  double position_exact_counts = 0.0;  // the continuous position behind `position`
};

struct DxlFaultCounts {
  std::int64_t dropped = 0;
  std::int64_t corrupted = 0;
  std::int64_t noise_bursts = 0;
  std::int64_t noise_bytes = 0;
  std::int64_t missing = 0;  // replies not given by a missing servo
  std::int64_t silent = 0;   // replies not given while the bus was silent
  std::int64_t hardware_errors = 0;
  std::int64_t bus_watchdog_expiries = 0;  // a servo with torque on heard nothing in time
};

class DynamixelBusEmulator {
 public:
  // Throws std::invalid_argument for duplicate or out-of-range ids or a bad option.
  explicit DynamixelBusEmulator(DxlEmulatorOptions options);

  // Bytes from the bus master arriving at `now_s` (seconds on the emulator's clock); returns
  // the bytes the servos put on the bus in answer, faults applied.
  std::vector<std::uint8_t> Receive(const std::uint8_t* data, std::size_t n, double now_s);

  // Moves the servos to `now_s` (dynamics, scheduled hardware errors, the state source).
  void Advance(double now_s);

  // While set, positions come from here (called at every Advance for each servo; returning
  // nullopt leaves that servo to the dynamics).
  using StateSource = std::function<std::optional<DxlDrivenState>(std::uint8_t id, double now_s)>;
  void SetStateSource(StateSource source) { source_ = std::move(source); }
  using ReplyObserver = std::function<void(const DxlReplyRecord&)>;
  void SetReplyObserver(ReplyObserver observer) { observer_ = std::move(observer); }

  // Direct access for tests and the driver. Throws std::out_of_range for an unknown id.
  std::uint8_t TableByte(std::uint8_t id, std::uint16_t address) const;
  std::int32_t TableI32(std::uint8_t id, std::uint16_t address) const;
  double ExactPosition(std::uint8_t id) const;
  // When `id` last heard an instruction packet addressed to it (its id or broadcast), and when
  // its Bus Watchdog last expired (-1: never); seconds on the emulator's clock.
  double LastInstruction(std::uint8_t id) const;
  double LastWatchdogExpiry(std::uint8_t id) const;
  const DxlFaultCounts& fault_counts() const { return counts_; }
  const std::vector<std::uint8_t>& ids() const { return options_.ids; }
  const dxl::PacketParser::Stats& parser_stats() const { return parser_.stats(); }

 private:
  struct Servo {
    std::uint8_t id = 0;
    std::vector<std::uint8_t> table;
    double position = 2048.0;  // counts, continuous
    double velocity = 0.0;     // counts/s
    double current_a = 0.0;
    double tick_zero_s = 0.0;  // REBOOT restarts the Realtime Tick
    std::uint16_t tick_base_ms = 0;
    double tick_rate = 1.0, tick_phase_ms = 0.0;  // its crystal
    double last_instruction_s = 0.0;              // what feeds the Bus Watchdog
    double watchdog_expired_s = -1.0;
  };

  Servo* Find(std::uint8_t id);
  const Servo& Get(std::uint8_t id) const;
  bool Present(std::uint8_t id, double now_s) const;
  bool Silent(double now_s) const;
  void UpdateTable(Servo& s, double now_s);
  // Moves servo s over [from_s, to_s] (its goal dynamics, or the state source at to_s).
  void Move(Servo& s, double from_s, double to_s);
  // The moment s's Bus Watchdog runs out, if it is armed and torque is on; -1 otherwise.
  double WatchdogDeadline(const Servo& s) const;
  // Applies a WRITE (or one servo's part of a SYNC WRITE); returns the status error byte.
  std::uint8_t ApplyWrite(Servo& s, std::uint16_t address, const std::uint8_t* data, std::size_t n);
  std::uint8_t AlertBit(const Servo& s) const;
  void Handle(const dxl::InstructionPacket& p, double now_s, std::vector<std::uint8_t>* out);
  // Emits one status packet through the fault layer.
  void Reply(Servo& s, const dxl::InstructionPacket& request, std::uint16_t address,
             std::uint16_t length, std::uint8_t error, const std::vector<std::uint8_t>& params,
             double now_s, std::vector<std::uint8_t>* out);

  DxlEmulatorOptions options_;
  std::vector<Servo> servos_;
  std::vector<bool> event_fired_;
  dxl::PacketParser parser_;
  std::mt19937_64 rng_;
  StateSource source_;
  ReplyObserver observer_;
  DxlFaultCounts counts_;
  double last_advance_s_ = 0.0;
};

// A pseudo-terminal carrying the emulated bus. The slave side is set raw and kept open by
// the emulator too, so the master never sees a hang-up while no bridge is attached; the slave
// path is symlinked at `link_path` (replaced atomically), which is what a config names.
class PtyBus {
 public:
  // Throws std::runtime_error naming the failing step.
  PtyBus(DynamixelBusEmulator& emulator, std::string link_path);
  ~PtyBus();
  PtyBus(const PtyBus&) = delete;
  PtyBus& operator=(const PtyBus&) = delete;

  void Open();   // a new pseudo-terminal, linked at link_path
  void Close();  // the port vanishes: the bridge's fd hangs up; the link is removed
  bool is_open() const { return master_fd_ >= 0; }
  int master_fd() const { return master_fd_; }
  const std::string& slave_path() const { return slave_path_; }

  // Waits up to `timeout_ms` for bytes from the bridge, hands them to the emulator at the time
  // `clock_s()` gives when they arrived (seconds on the emulator's clock) and writes its answer
  // back. Returns false when closed.
  bool ServeOnce(int timeout_ms, const std::function<double()>& clock_s);

 private:
  DynamixelBusEmulator& emulator_;
  std::string link_path_;
  std::string slave_path_;
  int master_fd_ = -1;
  int slave_fd_ = -1;
};

}  // namespace ftcal::sim
