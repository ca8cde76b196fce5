// One file over 600 lines: the servos' control table, motion and faults are one device.
#include "dynamixel_emulator.h"

#include <fcntl.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace ftcal::sim {
namespace {

// MX-106(2.0) control-table addresses (docs/device-protocols.md §2.7) the emulator gives meaning
// to.
constexpr std::uint16_t kAddrModelNumber = 0;
constexpr std::uint16_t kAddrFirmware = 6;
constexpr std::uint16_t kAddrId = 7;
constexpr std::uint16_t kAddrBaud = 8;
constexpr std::uint16_t kAddrReturnDelay = 9;
constexpr std::uint16_t kAddrOperatingMode = 11;
constexpr std::uint16_t kAddrProtocol = 13;
constexpr std::uint16_t kAddrMovingThreshold = 24;
constexpr std::uint16_t kAddrTemperatureLimit = 31;
constexpr std::uint16_t kAddrMaxVoltage = 32;
constexpr std::uint16_t kAddrMinVoltage = 34;
constexpr std::uint16_t kAddrCurrentLimit = 38;
constexpr std::uint16_t kAddrAccelerationLimit = dxl::kAddrAccelerationLimit;
constexpr std::uint16_t kAddrVelocityLimit = 44;
constexpr std::uint16_t kAddrMaxPosition = 48;
constexpr std::uint16_t kAddrMinPosition = 52;
constexpr std::uint16_t kAddrShutdown = 63;
constexpr std::uint16_t kAddrTorque = dxl::kAddrTorqueEnable;
constexpr std::uint16_t kAddrLed = 65;
constexpr std::uint16_t kAddrStatusReturnLevel = 68;
constexpr std::uint16_t kAddrHwError = dxl::kAddrHardwareErrorStatus;
constexpr std::uint16_t kAddrBusWatchdog = dxl::kAddrBusWatchdog;
constexpr std::uint16_t kAddrGoalPwm = 100;  // the goal values: Goal PWM (100) ... Goal
constexpr std::uint16_t kAddrProfileAcceleration = dxl::kAddrProfileAcceleration;
constexpr std::uint16_t kAddrProfileVelocity = dxl::kAddrProfileVelocity;
constexpr std::uint16_t kAddrGoalPosition = dxl::kAddrGoalPosition;
constexpr std::uint16_t kAddrTick = 120;
constexpr std::uint16_t kAddrMoving = 122;
constexpr std::uint16_t kAddrCurrent = 126;
constexpr std::uint16_t kAddrVelocity = 128;
constexpr std::uint16_t kAddrPosition = 132;
constexpr std::uint16_t kAddrVoltage = 144;
constexpr std::uint16_t kAddrTemperature = 146;
constexpr std::uint16_t kAddrIndirectAddress1 = 168;
constexpr std::uint16_t kAddrIndirectData1 = 224;
constexpr int kIndirectCount = 28;

// Status error numbers (§2.5).
constexpr std::uint8_t kErrInstruction = 2;
constexpr std::uint8_t kErrDataRange = 4;
constexpr std::uint8_t kErrDataLength = 5;
constexpr std::uint8_t kErrDataLimit = 6;
constexpr std::uint8_t kErrAccess = 7;

constexpr double kCountsPerUnitVelocity = dxl::kCountsPerRev * dxl::kVelocityUnitRpm / 60.0;

void PutLe(std::vector<std::uint8_t>& t, std::uint16_t address, std::uint32_t value, int bytes) {
  for (int i = 0; i < bytes; ++i) t[address + i] = static_cast<std::uint8_t>(value >> (8 * i));
}
std::uint32_t GetLe(const std::vector<std::uint8_t>& t, std::uint16_t address, int bytes) {
  std::uint32_t v = 0;
  for (int i = 0; i < bytes; ++i) v |= static_cast<std::uint32_t>(t[address + i]) << (8 * i);
  return v;
}

// Addresses a master may write (RAM items and EEPROM below 64); everything else is read-only
// or undefined and answers Access Error.
bool Writable(std::uint16_t a) {
  return (a >= kAddrId && a < kAddrTorque) || a == kAddrTorque || a == kAddrLed ||
         a == kAddrStatusReturnLevel || (a >= 76 && a < kAddrTick) ||
         (a >= kAddrIndirectAddress1 && a < kAddrIndirectData1 + kIndirectCount);
}

std::int32_t RoundToI32(double v) {
  return static_cast<std::int32_t>(
      std::clamp(std::round(v), static_cast<double>(INT32_MIN), static_cast<double>(INT32_MAX)));
}

}  // namespace

const char* DxlReplyFateName(DxlReplyFate fate) {
  switch (fate) {
    case DxlReplyFate::kSent:
      return "sent";
    case DxlReplyFate::kDropped:
      return "dropped";
    case DxlReplyFate::kCorrupted:
      return "corrupted";
    case DxlReplyFate::kMissing:
      return "missing";
    case DxlReplyFate::kSilent:
      return "silent";
  }
  return "?";
}

DynamixelBusEmulator::DynamixelBusEmulator(DxlEmulatorOptions options)
    : options_(std::move(options)), parser_(1024), rng_(options_.rates.seed) {
  if (options_.ids.empty()) throw std::invalid_argument("Dynamixel emulator: no servo ids");
  if (!(options_.time_constant_s > 0)) {
    throw std::invalid_argument("Dynamixel emulator: time_constant_s must be > 0");
  }
  for (double p : {options_.rates.drop_reply, options_.rates.corrupt_crc, options_.rates.noise}) {
    if (!(p >= 0 && p <= 1)) {
      throw std::invalid_argument("Dynamixel emulator: a fault rate is outside [0, 1]");
    }
  }
  {
    const std::uint8_t m = options_.operating_mode;
    if (m != 0 && m != 1 && m != 3 && m != 4 && m != 5 && m != 16) {
      throw std::invalid_argument("Dynamixel emulator: operating_mode " + std::to_string(m) +
                                  " is not an MX-106 mode (0, 1, 3, 4, 5, 16)");
    }
  }
  if (options_.rates.max_noise_bytes < 1) {
    throw std::invalid_argument("Dynamixel emulator: max_noise_bytes must be >= 1");
  }
  if (!options_.initial_positions.empty() &&
      options_.initial_positions.size() != options_.ids.size()) {
    throw std::invalid_argument("Dynamixel emulator: initial_positions must give one per id");
  }
  for (std::size_t i = 0; i < options_.ids.size(); ++i) {
    const std::uint8_t id = options_.ids[i];
    const std::int32_t initial = options_.initial_positions.empty() ? options_.initial_position
                                                                    : options_.initial_positions[i];
    if (id > dxl::kMaxId) {
      throw std::invalid_argument("Dynamixel emulator: id " + std::to_string(id) +
                                  " outside 0-252");
    }
    for (const Servo& s : servos_) {
      if (s.id == id) {
        throw std::invalid_argument("Dynamixel emulator: duplicate id " + std::to_string(id));
      }
    }
    Servo s;
    s.id = id;
    s.table.assign(kControlTableBytes, 0);
    auto& t = s.table;
    PutLe(t, kAddrModelNumber, kMx106ModelNumber, 2);
    t[kAddrFirmware] = kMx106FirmwareVersion;
    t[kAddrId] = id;
    t[kAddrBaud] = 3;  // 1 Mbit/s
    t[kAddrReturnDelay] = 250;
    t[kAddrOperatingMode] = options_.operating_mode;
    t[kAddrProtocol] = 2;
    PutLe(t, kAddrMovingThreshold, 10, 4);
    t[kAddrTemperatureLimit] = 80;
    PutLe(t, kAddrMaxVoltage, 160, 2);
    PutLe(t, kAddrMinVoltage, 95, 2);
    PutLe(t, kAddrCurrentLimit, 2047, 2);
    PutLe(t, kAddrAccelerationLimit, dxl::kMaxAccelerationLimit, 4);
    PutLe(t, kAddrVelocityLimit, 210, 4);
    PutLe(t, kAddrMaxPosition, 4095, 4);
    PutLe(t, kAddrMinPosition, 0, 4);
    t[kAddrShutdown] = 52;
    t[kAddrStatusReturnLevel] = 2;
    PutLe(t, kAddrGoalPosition, static_cast<std::uint32_t>(initial), 4);
    PutLe(t, kAddrVoltage, 120, 2);
    t[kAddrTemperature] = 35;
    for (int n = 0; n < kIndirectCount; ++n) {
      PutLe(t, static_cast<std::uint16_t>(kAddrIndirectAddress1 + 2 * n),
            static_cast<std::uint32_t>(kAddrIndirectData1 + n), 2);
    }
    s.position = initial;
    s.tick_base_ms = options_.initial_tick_ms & 0x7FFF;
    if (i < options_.tick_rate_ppm.size()) s.tick_rate = 1.0 + 1e-6 * options_.tick_rate_ppm[i];
    if (i < options_.tick_phase_ms.size()) s.tick_phase_ms = options_.tick_phase_ms[i];
    servos_.push_back(std::move(s));
  }
  for (const auto& e : options_.events) {
    if (e.kind != DxlFaultKind::kSilent) Get(e.id);  // throws for an unknown id
    if (e.kind != DxlFaultKind::kHardwareError && !(e.end_s >= e.start_s)) {
      throw std::invalid_argument("Dynamixel emulator: a fault window ends before it starts");
    }
  }
  event_fired_.assign(options_.events.size(), false);
  for (Servo& s : servos_) UpdateTable(s, 0.0);
}

DynamixelBusEmulator::Servo* DynamixelBusEmulator::Find(std::uint8_t id) {
  for (Servo& s : servos_) {
    if (s.id == id) return &s;
  }
  return nullptr;
}

const DynamixelBusEmulator::Servo& DynamixelBusEmulator::Get(std::uint8_t id) const {
  for (const Servo& s : servos_) {
    if (s.id == id) return s;
  }
  throw std::out_of_range("Dynamixel emulator: no servo with id " + std::to_string(id));
}

std::uint8_t DynamixelBusEmulator::TableByte(std::uint8_t id, std::uint16_t address) const {
  return Get(id).table.at(address);
}

std::int32_t DynamixelBusEmulator::TableI32(std::uint8_t id, std::uint16_t address) const {
  const auto& t = Get(id).table;
  if (address + 4u > t.size()) throw std::out_of_range("control-table address out of range");
  return static_cast<std::int32_t>(GetLe(t, address, 4));
}

double DynamixelBusEmulator::ExactPosition(std::uint8_t id) const { return Get(id).position; }
double DynamixelBusEmulator::LastInstruction(std::uint8_t id) const {
  return Get(id).last_instruction_s;
}
double DynamixelBusEmulator::LastWatchdogExpiry(std::uint8_t id) const {
  return Get(id).watchdog_expired_s;
}

double DynamixelBusEmulator::WatchdogDeadline(const Servo& s) const {
  const std::uint8_t w = s.table[kAddrBusWatchdog];
  // Watched only while torque is on (§2.7): a servo at rest with torque off has nothing to stop.
  if (w == 0 || w == dxl::kBusWatchdogExpired || s.table[kAddrTorque] == 0) return -1.0;
  return s.last_instruction_s + w * dxl::kBusWatchdogUnitS;
}

bool DynamixelBusEmulator::Present(std::uint8_t id, double now_s) const {
  for (const auto& e : options_.events) {
    if (e.kind == DxlFaultKind::kMissingServo && e.id == id && now_s >= e.start_s &&
        now_s < e.end_s) {
      return false;
    }
  }
  return true;
}

bool DynamixelBusEmulator::Silent(double now_s) const {
  for (const auto& e : options_.events) {
    if (e.kind == DxlFaultKind::kSilent && now_s >= e.start_s && now_s < e.end_s) return true;
  }
  return false;
}

void DynamixelBusEmulator::UpdateTable(Servo& s, double now_s) {
  auto& t = s.table;
  const double since_boot_ms =
      std::max(0.0, (now_s - s.tick_zero_s) * 1000.0 * s.tick_rate + s.tick_phase_ms);
  const auto tick = static_cast<std::uint32_t>(
      (s.tick_base_ms + static_cast<std::uint64_t>(std::floor(since_boot_ms))) % 32768);
  PutLe(t, kAddrTick, tick, 2);
  const double velocity_units = s.velocity / kCountsPerUnitVelocity;
  const double threshold = GetLe(t, kAddrMovingThreshold, 4);
  t[kAddrMoving] = std::abs(velocity_units) > threshold ? 1 : 0;
  const double current_units =
      std::clamp(std::round(s.current_a / dxl::kCurrentUnitA), -32768.0, 32767.0);
  PutLe(t, kAddrCurrent, static_cast<std::uint16_t>(static_cast<std::int16_t>(current_units)), 2);
  PutLe(t, kAddrVelocity, static_cast<std::uint32_t>(RoundToI32(velocity_units)), 4);
  PutLe(t, kAddrPosition, static_cast<std::uint32_t>(RoundToI32(s.position)), 4);
}

void DynamixelBusEmulator::Advance(double now_s) {
  for (std::size_t i = 0; i < options_.events.size(); ++i) {
    const auto& e = options_.events[i];
    if (e.kind != DxlFaultKind::kHardwareError || event_fired_[i] || now_s < e.start_s) continue;
    event_fired_[i] = true;
    Servo* s = Find(e.id);
    // A shutdown error clears Torque Enable and stays in address 70 until REBOOT (§2.7).
    s->table[kAddrHwError] |= e.hw_error_bits;
    s->table[kAddrTorque] = 0;
    ++counts_.hardware_errors;
  }
  const double from_s = last_advance_s_;
  for (Servo& s : servos_) {
    const double deadline = WatchdogDeadline(s);
    // "larger than" its value (§2.7): a packet exactly at the deadline still feeds it.
    if (deadline >= 0 && deadline < now_s) {
      // It runs to the moment the watchdog ran out, then stops where it is: the goal becomes
      // the present position (the profile applied as 0, an immediate stop), torque stays on,
      // and goal writes are refused until the watchdog is written 0 (§2.7).
      const double at = std::max(deadline, from_s);
      Move(s, from_s, at);
      s.table[kAddrBusWatchdog] = dxl::kBusWatchdogExpired;
      PutLe(s.table, kAddrGoalPosition, static_cast<std::uint32_t>(RoundToI32(s.position)), 4);
      s.velocity = 0.0;
      s.watchdog_expired_s = at;
      ++counts_.bus_watchdog_expiries;
      Move(s, at, now_s);
    } else {
      Move(s, from_s, now_s);
    }
    UpdateTable(s, now_s);
  }
  if (now_s > last_advance_s_) last_advance_s_ = now_s;
}

void DynamixelBusEmulator::Move(Servo& s, double from_s, double to_s) {
  std::optional<DxlDrivenState> driven;
  if (source_) driven = source_(s.id, to_s);
  const double dt = to_s - from_s;
  if (driven) {
    s.position = driven->position_counts;
    s.velocity = driven->velocity_counts_s;
    s.current_a = driven->current_a;
  } else if (dt > 0) {
    if (s.table[kAddrTorque] != 0) {
      const double goal = static_cast<std::int32_t>(GetLe(s.table, kAddrGoalPosition, 4));
      const double alpha = 1.0 - std::exp(-dt / options_.time_constant_s);
      double next = s.position + (goal - s.position) * alpha;
      // A non-zero Profile Velocity caps the speed on the way to every goal (§2.7); the
      // velocity-based profile's acceleration ramp is left to the first-order lag.
      const double profile_counts_s =
          GetLe(s.table, kAddrProfileVelocity, 4) * kCountsPerUnitVelocity;
      if (profile_counts_s > 0) {
        const double reach = profile_counts_s * dt;
        next = std::clamp(next, s.position - reach, s.position + reach);
      }
      s.velocity = (next - s.position) / dt;
      // Holding torque grows with the position error; a stand-in, not a motor model.
      s.current_a = std::clamp(0.002 * (goal - next), -5.0, 5.0);
      s.position = next;
    } else {
      s.velocity = 0.0;
      s.current_a = 0.0;
    }
  }
}

std::uint8_t DynamixelBusEmulator::AlertBit(const Servo& s) const {
  return s.table[kAddrHwError] != 0 ? 0x80 : 0x00;
}

std::uint8_t DynamixelBusEmulator::ApplyWrite(Servo& s, std::uint16_t address,
                                              const std::uint8_t* data, std::size_t n) {
  auto& t = s.table;
  if (n == 0) return kErrDataLength;
  if (address + n > t.size()) return kErrAccess;
  const bool torque_on = t[kAddrTorque] != 0;
  for (std::size_t i = 0; i < n; ++i) {
    const auto a = static_cast<std::uint16_t>(address + i);
    if (!Writable(a)) return kErrAccess;
    if (a < kAddrTorque && torque_on) return kErrAccess;  // EEPROM is locked while torque is on
    // The emulated bus's wiring is fixed: renumbering or re-clocking a servo is not emulated.
    if (a == kAddrId || a == kAddrBaud) return kErrAccess;
  }
  if (address <= kAddrOperatingMode && address + n > kAddrOperatingMode) {
    const std::uint8_t mode = data[kAddrOperatingMode - address];
    // The MX-106(2.0)'s modes: current, velocity, position, extended position,
    // current-based position, PWM (§2.7).
    if (mode != 0 && mode != 1 && mode != 3 && mode != 4 && mode != 5 && mode != 16) {
      return kErrDataRange;
    }
  }
  // The value an item of `size` bytes at `item` would hold after this write, for the range
  // checks below; nullopt when the write does not touch it.
  auto after = [&](std::uint16_t item, int size) -> std::optional<std::uint32_t> {
    if (address >= item + size || address + n <= item) return std::nullopt;
    std::uint32_t v = 0;
    for (int i = 0; i < size; ++i) {
      const std::size_t a = item + static_cast<std::size_t>(i);
      const std::uint8_t byte = (a >= address && a < address + n) ? data[a - address] : t[a];
      v |= static_cast<std::uint32_t>(byte) << (8 * i);
    }
    return v;
  };
  const bool watchdog_expired = t[kAddrBusWatchdog] == dxl::kBusWatchdogExpired;
  if (const auto w = after(kAddrBusWatchdog, 1)) {
    // 0 disarms (and clears an expiry), 1-127 arms; -1 is the servo's own state, not a value
    // to write. While expired only the clearing 0 is taken (an assumption: §2.7).
    if (*w > 127 || (watchdog_expired && *w != 0)) return kErrDataRange;
  }
  // An expired watchdog makes the goal values (Goal PWM 100 ... Goal Velocity 104, Goal
  // Position 116) read-only: a write answers Data Range Error (§2.7).
  if (watchdog_expired && address < kAddrGoalPosition + 4u && address + n > kAddrGoalPwm &&
      !(address >= kAddrProfileAcceleration && address + n <= kAddrGoalPosition)) {
    return kErrDataRange;
  }
  // Each limit within its register's range (Data Range Error), each profile within its limit
  // (Data Limit Error: "value outside its limit item", §2.5).
  if (const auto v = after(kAddrVelocityLimit, 4); v && *v > dxl::kMaxVelocityLimit) {
    return kErrDataRange;
  }
  if (const auto v = after(kAddrAccelerationLimit, 4); v && *v > dxl::kMaxAccelerationLimit) {
    return kErrDataRange;
  }
  for (const std::uint16_t item : {kAddrMaxPosition, kAddrMinPosition}) {
    if (const auto v = after(item, 4);
        v && *v > static_cast<std::uint32_t>(dxl::kPositionModeMaxCount)) {
      return kErrDataRange;
    }
  }
  if (const auto v = after(kAddrProfileVelocity, 4); v && *v > GetLe(t, kAddrVelocityLimit, 4)) {
    return kErrDataLimit;
  }
  if (const auto v = after(kAddrProfileAcceleration, 4);
      v && *v > GetLe(t, kAddrAccelerationLimit, 4)) {
    return kErrDataLimit;
  }
  if (address <= kAddrGoalPosition && address + n >= kAddrGoalPosition + 4u) {
    const std::size_t off = kAddrGoalPosition - address;
    const auto goal =
        static_cast<std::int32_t>(data[off] | (data[off + 1] << 8) | (data[off + 2] << 16) |
                                  (static_cast<std::uint32_t>(data[off + 3]) << 24));
    // Position mode keeps goals within the Min/Max Position Limits; the multi-turn modes (4, 5)
    // ignore those limits and take +-256 turns (§2.7).
    const std::uint8_t mode = t[kAddrOperatingMode];
    const bool multi_turn = mode == dxl::kExtendedPositionMode || mode == 5;
    const auto lo = multi_turn ? -dxl::kExtendedModeMaxCount
                               : static_cast<std::int32_t>(GetLe(t, kAddrMinPosition, 4));
    const auto hi = multi_turn ? dxl::kExtendedModeMaxCount
                               : static_cast<std::int32_t>(GetLe(t, kAddrMaxPosition, 4));
    if (goal < lo || goal > hi) return kErrDataLimit;
  }
  if (address <= kAddrTorque && address + n > kAddrTorque && data[kAddrTorque - address] != 0 &&
      t[kAddrHwError] != 0) {
    return 1;  // Result Fail: torque stays off until REBOOT after a shutdown error
  }
  for (std::size_t i = 0; i < n; ++i) {
    std::uint16_t a = static_cast<std::uint16_t>(address + i);
    if (a >= kAddrIndirectData1 && a < kAddrIndirectData1 + kIndirectCount) {
      a = static_cast<std::uint16_t>(GetLe(
          t, static_cast<std::uint16_t>(kAddrIndirectAddress1 + 2 * (a - kAddrIndirectData1)), 2));
      if (a >= t.size()) return kErrAccess;
    }
    const bool ignored = std::any_of(
        options_.ignored_writes.begin(), options_.ignored_writes.end(),
        [&](const DxlIgnoredWrite& w) { return w.id == s.id && w.address == address + i; });
    if (!ignored) t[a] = data[i];
  }
  return 0;
}

std::vector<std::uint8_t> DynamixelBusEmulator::Receive(const std::uint8_t* data, std::size_t n,
                                                        double now_s) {
  std::vector<std::uint8_t> out;
  parser_.Feed(data, n);
  while (auto p = parser_.NextInstruction()) {
    Advance(now_s);
    // Every instruction packet a servo is addressed by (its id, or broadcast: SYNC and BULK
    // instructions too) feeds its Bus Watchdog (§2.7). Whether packets for other ids do as
    // well is not documented; counting only its own makes the watchdog the stricter.
    for (Servo& s : servos_) {
      if ((p->id == s.id || p->id == dxl::kBroadcastId) && Present(s.id, now_s)) {
        s.last_instruction_s = now_s;
      }
    }
    Handle(*p, now_s, &out);
  }
  return out;
}

void DynamixelBusEmulator::Handle(const dxl::InstructionPacket& p, double now_s,
                                  std::vector<std::uint8_t>* out) {
  auto read_bytes = [](const Servo& s, std::uint16_t address, std::uint16_t length,
                       std::vector<std::uint8_t>* params) -> std::uint8_t {
    if (length == 0 || address + static_cast<std::size_t>(length) > s.table.size()) {
      return kErrAccess;
    }
    for (std::uint16_t i = 0; i < length; ++i) {
      std::uint16_t a = static_cast<std::uint16_t>(address + i);
      if (a >= kAddrIndirectData1 && a < kAddrIndirectData1 + kIndirectCount) {
        a = static_cast<std::uint16_t>(GetLe(
            s.table,
            static_cast<std::uint16_t>(kAddrIndirectAddress1 + 2 * (a - kAddrIndirectData1)), 2));
        if (a >= s.table.size()) return kErrAccess;
      }
      params->push_back(s.table[a]);
    }
    return 0;
  };
  auto u16 = [&p](std::size_t i) {
    return static_cast<std::uint16_t>(p.params[i] | (p.params[i + 1] << 8));
  };
  const bool broadcast = p.id == dxl::kBroadcastId;

  switch (p.instruction) {
    case dxl::kPing:
      for (Servo& s : servos_) {
        if ((broadcast || s.id == p.id) && Present(s.id, now_s)) {
          Reply(s, p, 0, 0, AlertBit(s),
                {static_cast<std::uint8_t>(kMx106ModelNumber & 0xFF),
                 static_cast<std::uint8_t>(kMx106ModelNumber >> 8), kMx106FirmwareVersion},
                now_s, out);
        }
      }
      return;
    case dxl::kSyncRead: {
      if (!broadcast || p.params.size() < 5) return;
      const std::uint16_t address = u16(0), length = u16(2);
      for (std::size_t i = 4; i < p.params.size(); ++i) {
        Servo* s = Find(p.params[i]);
        if (s == nullptr) continue;
        std::vector<std::uint8_t> params;
        const std::uint8_t err = read_bytes(*s, address, length, &params);
        if (err != 0) params.clear();
        Reply(*s, p, address, length, static_cast<std::uint8_t>(err | AlertBit(*s)), params, now_s,
              out);
      }
      return;
    }
    case dxl::kSyncWrite: {
      if (!broadcast || p.params.size() < 4) return;
      const std::uint16_t address = u16(0), length = u16(2);
      if (length == 0 || (p.params.size() - 4) % (1u + length) != 0) return;
      for (std::size_t i = 4; i < p.params.size(); i += 1u + length) {
        Servo* s = Find(p.params[i]);
        if (s != nullptr && Present(s->id, now_s)) {
          ApplyWrite(*s, address, &p.params[i + 1], length);
        }
      }
      Advance(now_s);
      return;
    }
    default:
      break;
  }

  // Unicast (or broadcast WRITE, answered by nobody).
  for (Servo& s : servos_) {
    if (!(broadcast || s.id == p.id) || !Present(s.id, now_s)) continue;
    const std::uint8_t level = s.table[kAddrStatusReturnLevel];
    switch (p.instruction) {
      case dxl::kRead: {
        if (broadcast || level < 1) break;
        std::vector<std::uint8_t> params;
        std::uint8_t err =
            p.params.size() == 4 ? read_bytes(s, u16(0), u16(2), &params) : kErrDataLength;
        if (err != 0) params.clear();
        Reply(s, p, p.params.size() == 4 ? u16(0) : 0, p.params.size() == 4 ? u16(2) : 0,
              static_cast<std::uint8_t>(err | AlertBit(s)), params, now_s, out);
        break;
      }
      case dxl::kWrite: {
        const std::uint8_t err =
            p.params.size() >= 3 ? ApplyWrite(s, u16(0), p.params.data() + 2, p.params.size() - 2)
                                 : kErrDataLength;
        Advance(now_s);
        if (!broadcast && level >= 2) {
          Reply(s, p, 0, 0, static_cast<std::uint8_t>(err | AlertBit(s)), {}, now_s, out);
        }
        break;
      }
      case dxl::kReboot: {
        if (!broadcast && level >= 2) Reply(s, p, 0, 0, AlertBit(s), {}, now_s, out);
        // After a reboot: errors cleared, torque off, the Realtime Tick restarts from 0.
        s.table[kAddrHwError] = 0;
        s.table[kAddrTorque] = 0;
        s.table[kAddrBusWatchdog] = 0;  // a RAM item: back to its initial value
        s.tick_zero_s = now_s;
        s.tick_base_ms = 0;
        PutLe(s.table, kAddrGoalPosition, static_cast<std::uint32_t>(RoundToI32(s.position)), 4);
        UpdateTable(s, now_s);
        break;
      }
      default:
        if (!broadcast && level >= 2) {
          Reply(s, p, 0, 0, static_cast<std::uint8_t>(kErrInstruction | AlertBit(s)), {}, now_s,
                out);
        }
        break;
    }
  }
}

void DynamixelBusEmulator::Reply(Servo& s, const dxl::InstructionPacket& request,
                                 std::uint16_t address, std::uint16_t length, std::uint8_t error,
                                 const std::vector<std::uint8_t>& params, double now_s,
                                 std::vector<std::uint8_t>* out) {
  DxlReplyRecord r;
  r.t_s = now_s;
  r.id = s.id;
  r.instruction = request.instruction;
  r.address = address;
  r.length = length;
  r.error = error;
  r.tick_ms = static_cast<std::uint16_t>(GetLe(s.table, kAddrTick, 2));
  r.position = static_cast<std::int32_t>(GetLe(s.table, kAddrPosition, 4));
  r.velocity = static_cast<std::int32_t>(GetLe(s.table, kAddrVelocity, 4));
  r.current = static_cast<std::int16_t>(GetLe(s.table, kAddrCurrent, 2));
  r.torque_enable = s.table[kAddrTorque];
  r.hardware_error = s.table[kAddrHwError];
  r.position_exact_counts = s.position;

  // Three draws for every packet, whatever happens to it, so a fault's position in the
  // sequence does not shift the ones after it.
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  const double u_drop = uniform(rng_), u_corrupt = uniform(rng_), u_noise = uniform(rng_);
  std::uniform_int_distribution<int> noise_len(1, options_.rates.max_noise_bytes);
  std::uniform_int_distribution<int> noise_byte(0x00, 0xFE);
  const int burst = noise_len(rng_);

  if (!Present(s.id, now_s)) {
    r.fate = DxlReplyFate::kMissing;
    ++counts_.missing;
  } else if (Silent(now_s)) {
    r.fate = DxlReplyFate::kSilent;
    ++counts_.silent;
  } else if (u_drop < options_.rates.drop_reply) {
    r.fate = DxlReplyFate::kDropped;
    ++counts_.dropped;
  } else {
    if (u_noise < options_.rates.noise) {
      for (int i = 0; i < burst; ++i) out->push_back(static_cast<std::uint8_t>(noise_byte(rng_)));
      r.noise_bytes = static_cast<std::size_t>(burst);
      ++counts_.noise_bursts;
      counts_.noise_bytes += burst;
    }
    std::vector<std::uint8_t> packet = dxl::BuildStatus(s.id, error, params);
    if (u_corrupt < options_.rates.corrupt_crc) {
      packet.back() ^= 0x5A;
      r.fate = DxlReplyFate::kCorrupted;
      ++counts_.corrupted;
    }
    out->insert(out->end(), packet.begin(), packet.end());
  }
  if (observer_) observer_(r);
}

// ---- PtyBus ----

PtyBus::PtyBus(DynamixelBusEmulator& emulator, std::string link_path)
    : emulator_(emulator), link_path_(std::move(link_path)) {
  if (link_path_.empty()) throw std::runtime_error("PtyBus: empty link path");
}

PtyBus::~PtyBus() { Close(); }

void PtyBus::Open() {
  if (is_open()) return;
  auto fail = [this](const std::string& step) {
    const std::string why = std::strerror(errno);
    Close();
    throw std::runtime_error("Dynamixel emulator pty: " + step + ": " + why);
  };
  master_fd_ = ::posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK);
  if (master_fd_ < 0) fail("posix_openpt");
  if (::grantpt(master_fd_) != 0) fail("grantpt");
  if (::unlockpt(master_fd_) != 0) fail("unlockpt");
  char name[128] = {};
  if (::ptsname_r(master_fd_, name, sizeof name) != 0) fail("ptsname_r");
  slave_path_ = name;
  // Raw before any bridge opens it: no echo, no line editing, no CR/LF translation of replies.
  slave_fd_ = ::open(name, O_RDWR | O_NOCTTY | O_NONBLOCK);
  if (slave_fd_ < 0) fail("open " + slave_path_);
  termios tio{};
  if (::tcgetattr(slave_fd_, &tio) != 0) fail("tcgetattr");
  ::cfmakeraw(&tio);
  ::cfsetispeed(&tio, B1000000);
  ::cfsetospeed(&tio, B1000000);
  if (::tcsetattr(slave_fd_, TCSANOW, &tio) != 0) fail("tcsetattr");
  const std::string tmp = link_path_ + ".tmp" + std::to_string(::getpid());
  ::unlink(tmp.c_str());
  if (::symlink(name, tmp.c_str()) != 0) fail("symlink " + tmp);
  if (::rename(tmp.c_str(), link_path_.c_str()) != 0) fail("rename onto " + link_path_);
}

void PtyBus::Close() {
  if (!slave_path_.empty()) {
    char target[256] = {};
    const ssize_t n = ::readlink(link_path_.c_str(), target, sizeof target - 1);
    if (n > 0 && slave_path_ == std::string(target, static_cast<std::size_t>(n))) {
      ::unlink(link_path_.c_str());
    }
  }
  if (slave_fd_ >= 0) ::close(slave_fd_);
  if (master_fd_ >= 0) ::close(master_fd_);
  slave_fd_ = master_fd_ = -1;
  slave_path_.clear();
}

bool PtyBus::ServeOnce(int timeout_ms, const std::function<double()>& clock_s) {
  if (!is_open()) return false;
  pollfd pfd{master_fd_, POLLIN, 0};
  const int r = ::poll(&pfd, 1, timeout_ms);
  if (r <= 0) return true;  // timeout, or EINTR: the caller checks its stop flag
  std::uint8_t buf[4096];
  const ssize_t n = ::read(master_fd_, buf, sizeof buf);
  if (n <= 0) return true;
  const std::vector<std::uint8_t> reply =
      emulator_.Receive(buf, static_cast<std::size_t>(n), clock_s());
  std::size_t done = 0;
  int waits = 0;
  while (done < reply.size()) {
    const ssize_t w = ::write(master_fd_, reply.data() + done, reply.size() - done);
    if (w > 0) {
      done += static_cast<std::size_t>(w);
      continue;
    }
    if (w < 0 && errno != EAGAIN && errno != EINTR) break;
    // Nobody reads the slave: like a bus with no listener, the rest is lost.
    if (++waits > 5) break;
    pollfd out{master_fd_, POLLOUT, 0};
    ::poll(&out, 1, 10);
  }
  return true;
}

}  // namespace ftcal::sim
