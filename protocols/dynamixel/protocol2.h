// ROBOTIS Dynamixel Protocol 2.0 codec for the MX-106(2.0): CRC, byte stuffing, instruction
// packets, a streaming status-packet parser and the control-table block the bridge reads.
//
// Pure bytes in, structs out: no serial port here, so the bridge and the simulator's servo
// bus emulation share it. Wire facts: docs/device-protocols.md section 2 (§2.x below).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace ftcal::dxl {

// Invalid arguments to a builder or decoder; the message names the field and value.
class DxlError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

constexpr std::uint8_t kBroadcastId = 0xFE;
constexpr std::uint8_t kMaxId = 252;
// Header FF FF FD, reserved 00, id, length (2): the bytes the length field does not count.
constexpr std::size_t kHeaderBytes = 7;

enum Instruction : std::uint8_t {
  kPing = 0x01,
  kRead = 0x02,
  kWrite = 0x03,
  kRegWrite = 0x04,
  kAction = 0x05,
  kFactoryReset = 0x06,
  kReboot = 0x08,
  kClear = 0x10,
  kStatus = 0x55,
  kSyncRead = 0x82,
  kSyncWrite = 0x83,
  kBulkRead = 0x92,
  kBulkWrite = 0x93,
};

// MX-106(2.0) control-table addresses the bridge uses (§2.7).
constexpr std::uint16_t kAddrOperatingMode = 11;  // EEPROM: written only while torque is off
constexpr std::uint16_t kAddrTorqueEnable = 64;
constexpr std::uint16_t kAddrHardwareErrorStatus = 70;
constexpr std::uint16_t kAddrGoalPosition = 116;
constexpr std::uint16_t kAddrPresentBlock = 120;  // Realtime Tick ... Present Temperature
constexpr std::uint16_t kPresentBlockBytes = 28;  // addresses 120-147
// The servo's own limits (EEPROM, written only while torque is off; 4 bytes each) and the
// profile that drives every position goal (RAM). Min/Max Position Limit bind only in Position
// mode (3); Extended Position mode ignores them (docs/device-protocols.md §2.7).
constexpr std::uint16_t kAddrAccelerationLimit = 40;     // 214.577 rev/min^2, 0-32767
constexpr std::uint16_t kAddrVelocityLimit = 44;         // 0.229 rpm, 0-1023
constexpr std::uint16_t kAddrMaxPositionLimit = 48;      // counts, 0-4095
constexpr std::uint16_t kAddrMinPositionLimit = 52;      // counts, 0-4095
constexpr std::uint16_t kAddrProfileAcceleration = 108;  // <= Acceleration Limit; 0 = none
constexpr std::uint16_t kAddrProfileVelocity = 112;      // <= Velocity Limit; 0 = none
constexpr std::int32_t kMaxVelocityLimit = 1023;
constexpr std::int32_t kMaxAccelerationLimit = 32767;
constexpr double kAccelerationUnitRevPerMin2 = 214.577;
// Bus Watchdog (98, RAM, 1 byte): 1-127 in 20 ms units arms it, 0 disarms it and clears an
// expiry, 0xFF (-1) is the expired state, in which goal writes answer Data Range Error.
constexpr std::uint16_t kAddrBusWatchdog = 98;
constexpr double kBusWatchdogUnitS = 0.02;
constexpr std::uint8_t kBusWatchdogExpired = 0xFF;

// Bytes on the wire of a status packet with `params` parameter bytes at most (header, id,
// length, instruction, error, params, CRC; stuffing can add one byte per three of params).
constexpr std::size_t MaxStatusPacketBytes(std::size_t params) {
  return kHeaderBytes + 2 + params + params / 3 + 2;
}
// Seconds `bytes` take on a UART at `baud` (start + 8 data + stop bits each).
constexpr double WireSeconds(std::size_t bytes, std::uint32_t baud) {
  return 10.0 * static_cast<double>(bytes) / static_cast<double>(baud);
}
// Return Delay Time (address 9): 2 us per unit, factory default 250 (500 us).
constexpr std::uint16_t kAddrReturnDelayTime = 9;
constexpr double kReturnDelayUnitS = 2e-6;

// CRC-16/UMTS (poly 0x8005, init 0, MSB first, no reflection, no final XOR) over `n` bytes,
// continuing from `crc`.
std::uint16_t Crc16(const std::uint8_t* data, std::size_t n, std::uint16_t crc = 0);

// Inserts FD after every FF FF FD (§2.4). `bytes` is the instruction + parameter region.
std::vector<std::uint8_t> Stuff(const std::vector<std::uint8_t>& bytes);
// Removes the FD after every FF FF FD. Throws DxlError when an FF FF FD is not followed by
// the stuffing FD (the sender did not stuff: the bytes cannot be trusted).
std::vector<std::uint8_t> Unstuff(const std::vector<std::uint8_t>& bytes);

// A whole packet: header, id, length, stuffed instruction + params, CRC. Throws DxlError for
// an id outside 0-252 / FE or a packet longer than the 16-bit length allows.
std::vector<std::uint8_t> BuildPacket(std::uint8_t id, std::uint8_t instruction,
                                      const std::vector<std::uint8_t>& params);

std::vector<std::uint8_t> BuildPing(std::uint8_t id);
std::vector<std::uint8_t> BuildRead(std::uint8_t id, std::uint16_t address, std::uint16_t length);
std::vector<std::uint8_t> BuildWrite(std::uint8_t id, std::uint16_t address,
                                     const std::vector<std::uint8_t>& data);
std::vector<std::uint8_t> BuildTorqueEnable(std::uint8_t id, bool enable);
std::vector<std::uint8_t> BuildReboot(std::uint8_t id);
// Broadcast; one status per id, in list order. Ids must be distinct and 0-252.
std::vector<std::uint8_t> BuildSyncRead(std::uint16_t address, std::uint16_t length,
                                        const std::vector<std::uint8_t>& ids);
// Broadcast; every data block must be exactly `length` bytes; ids distinct and 0-252.
std::vector<std::uint8_t> BuildSyncWrite(
    std::uint16_t address, std::uint16_t length,
    const std::vector<std::pair<std::uint8_t, std::vector<std::uint8_t>>>& data);
// SYNC WRITE of Goal Position (4 bytes, signed LE) to several servos.
std::vector<std::uint8_t> BuildSyncWriteGoalPosition(
    const std::vector<std::pair<std::uint8_t, std::int32_t>>& goals);

// A status packet (§2.5) as a servo sends it; used by the simulator and the tests.
std::vector<std::uint8_t> BuildStatus(std::uint8_t id, std::uint8_t error,
                                      const std::vector<std::uint8_t>& params);

// An instruction packet as a servo would parse it (for the simulator's bus emulation).
struct InstructionPacket {
  std::uint8_t id = 0;
  std::uint8_t instruction = 0;
  std::vector<std::uint8_t> params;  // unstuffed
};

struct StatusPacket {
  std::uint8_t id = 0;
  std::uint8_t error = 0;            // bit 7 alert, bits 0-6 error number (§2.5)
  std::vector<std::uint8_t> params;  // unstuffed
  bool alert() const { return (error & 0x80) != 0; }
  std::uint8_t error_number() const { return error & 0x7F; }
};

// Text for a status error byte ("ok", "alert", "CRC error", ...).
std::string DescribeStatusError(std::uint8_t error);

// Streaming packet parser for a half-duplex byte stream (§2.4, §2.9). Feed() whatever the
// port returned; Next() yields each complete packet that passes the checks, in order.
//
// Resynchronisation: bytes before a header FF FF FD 00 are noise and skipped. A candidate
// packet whose CRC fails, or that is malformed, costs only its first byte, so a false header
// inside noise cannot swallow a real packet that follows. Stuffing guarantees a real header
// never appears inside a packet.
class PacketParser {
 public:
  struct Stats {
    std::uint64_t packets = 0;  // valid packets returned
    std::uint64_t crc_errors = 0;
    std::uint64_t malformed = 0;    // bad length, id, stuffing, or not the expected kind
    std::uint64_t timeouts = 0;     // Timeout() calls that found a reply missing or partial
    std::uint64_t noise_bytes = 0;  // bytes skipped while looking for a header
  };

  // `max_length`: largest length field accepted; anything larger is malformed (a corrupted
  // length would otherwise make the parser wait for bytes that never come).
  explicit PacketParser(std::size_t max_length = 1024);

  void Feed(const std::uint8_t* data, std::size_t n);
  // Next valid status packet (instruction 0x55). Instruction packets (e.g. the echo of an
  // adapter that does not suppress its own transmission) are skipped and counted malformed.
  std::optional<StatusPacket> NextStatus();
  // Next valid instruction packet; status packets are skipped and counted malformed.
  std::optional<InstructionPacket> NextInstruction();

  // The caller's reply deadline passed: count a timeout and discard any partial packet.
  void Timeout();
  // Bytes held waiting for the rest of a packet.
  std::size_t buffered() const { return buffer_.size(); }
  const Stats& stats() const { return stats_; }

 private:
  // Finds the next packet passing framing and CRC checks; returns its unstuffed
  // instruction + params region and its id.
  bool NextRaw(std::uint8_t* id, std::vector<std::uint8_t>* body);

  std::size_t max_length_;
  std::deque<std::uint8_t> buffer_;
  Stats stats_;
};

// The 28-byte block at addresses 120-147 (§2.7), values as the servo reports them.
struct PresentState {
  std::uint16_t realtime_tick_ms = 0;       // 120, wraps at 32768
  std::uint8_t moving = 0;                  // 122
  std::uint8_t moving_status = 0;           // 123
  std::int16_t present_pwm = 0;             // 124
  std::int16_t present_current = 0;         // 126, ~3.36 mA units
  std::int32_t present_velocity = 0;        // 128, 0.229 rpm units
  std::int32_t present_position = 0;        // 132, counts
  std::int32_t velocity_trajectory = 0;     // 136
  std::int32_t position_trajectory = 0;     // 140
  std::uint16_t present_input_voltage = 0;  // 144, 0.1 V units
  std::uint8_t present_temperature = 0;     // 146, deg C
};
// Throws DxlError unless `n` is exactly kPresentBlockBytes.
PresentState DecodePresentBlock(const std::uint8_t* data, std::size_t n);
std::vector<std::uint8_t> EncodePresentBlock(const PresentState& s);

// Operating Mode values (address 11) and the goal range each takes (§2.7): Position mode within
// the Min/Max Position Limits (0-4095 by default), Extended Position mode +-256 turns.
constexpr std::uint8_t kPositionMode = 3;
constexpr std::uint8_t kExtendedPositionMode = 4;
constexpr std::int32_t kPositionModeMinCount = 0;
constexpr std::int32_t kPositionModeMaxCount = 4095;
constexpr std::int32_t kExtendedModeMaxCount = 1048575;  // and -1048575

// Unit conversions (§2.7).
constexpr double kCountsPerRev = 4096.0;
constexpr double kVelocityUnitRpm = 0.229;
constexpr double kCurrentUnitA = 0.00336;
constexpr double kVoltageUnitV = 0.1;
// theta = direction * (count - zero_count) * 2 pi / 4096; direction must be +1 or -1.
double PositionToRad(std::int32_t count, std::int32_t zero_count, int direction);
// Inverse, rounded to the nearest count (for Goal Position and the simulator).
std::int32_t RadToPosition(double angle_rad, std::int32_t zero_count, int direction);
double VelocityToRadPerS(std::int32_t value);
double CurrentToA(std::int16_t value);
double VoltageToV(std::uint16_t value);

// Unwraps the 15-bit Realtime Tick (0-32767 ms) into a monotonic ms count. Assumes reads are
// less than 32.768 s apart; the first value is taken as is.
class TickUnwrapper {
 public:
  std::int64_t Update(std::uint16_t tick_ms);
  void Reset() { started_ = false; }

 private:
  bool started_ = false;
  std::uint16_t last_ = 0;
  std::int64_t total_ = 0;
};

}  // namespace ftcal::dxl
