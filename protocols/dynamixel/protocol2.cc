#include "protocol2.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <set>

namespace ftcal::dxl {
namespace {

// Written by hand: CRC-16/UMTS is a few lines, and no Debian library packages this variant
// (boost's crc_optimal would do it, but pulling in Boost for one function is not worth it).
// The table is generated at compile time from the bitwise definition in §2.3, so there are
// no magic numbers to mistype.
constexpr std::array<std::uint16_t, 256> MakeCrcTable() {
  std::array<std::uint16_t, 256> table{};
  for (int i = 0; i < 256; ++i) {
    std::uint16_t r = static_cast<std::uint16_t>(i << 8);
    for (int b = 0; b < 8; ++b) {
      r = static_cast<std::uint16_t>((r & 0x8000) ? (r << 1) ^ 0x8005 : (r << 1));
    }
    table[i] = r;
  }
  return table;
}
constexpr std::array<std::uint16_t, 256> kCrcTable = MakeCrcTable();

void PutU16Le(std::uint16_t v, std::vector<std::uint8_t>* out) {
  out->push_back(static_cast<std::uint8_t>(v));
  out->push_back(static_cast<std::uint8_t>(v >> 8));
}
void PutU32Le(std::uint32_t v, std::vector<std::uint8_t>* out) {
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<std::uint8_t>(v >> (8 * i)));
}
std::uint16_t GetU16Le(const std::uint8_t* p) {
  return static_cast<std::uint16_t>(p[0] | (p[1] << 8));
}
std::uint32_t GetU32Le(const std::uint8_t* p) {
  return std::uint32_t{p[0]} | (std::uint32_t{p[1]} << 8) | (std::uint32_t{p[2]} << 16) |
         (std::uint32_t{p[3]} << 24);
}

void CheckUnicastId(std::uint8_t id, const char* what) {
  if (id > kMaxId) {
    throw DxlError(std::string(what) + ": servo id " + std::to_string(id) + " is outside 0-252");
  }
}

void CheckDistinctIds(const std::vector<std::uint8_t>& ids, const char* what) {
  std::set<std::uint8_t> seen;
  for (std::uint8_t id : ids) {
    CheckUnicastId(id, what);
    if (!seen.insert(id).second) {
      throw DxlError(std::string(what) + ": servo id " + std::to_string(id) + " listed twice");
    }
  }
}

}  // namespace

std::uint16_t Crc16(const std::uint8_t* data, std::size_t n, std::uint16_t crc) {
  for (std::size_t i = 0; i < n; ++i) {
    const std::uint8_t index = static_cast<std::uint8_t>((crc >> 8) ^ data[i]);
    crc = static_cast<std::uint16_t>((crc << 8) ^ kCrcTable[index]);
  }
  return crc;
}

std::vector<std::uint8_t> Stuff(const std::vector<std::uint8_t>& bytes) {
  std::vector<std::uint8_t> out;
  out.reserve(bytes.size() + bytes.size() / 3 + 1);
  for (std::size_t i = 0; i < bytes.size(); ++i) {
    out.push_back(bytes[i]);
    if (i >= 2 && bytes[i] == 0xFD && bytes[i - 1] == 0xFF && bytes[i - 2] == 0xFF) {
      out.push_back(0xFD);
    }
  }
  return out;
}

std::vector<std::uint8_t> Unstuff(const std::vector<std::uint8_t>& bytes) {
  std::vector<std::uint8_t> out;
  out.reserve(bytes.size());
  for (std::size_t i = 0; i < bytes.size(); ++i) {
    out.push_back(bytes[i]);
    // The pattern is looked for in the stuffed input, whose stuffing FD we are about to skip.
    if (i >= 2 && bytes[i] == 0xFD && bytes[i - 1] == 0xFF && bytes[i - 2] == 0xFF) {
      if (i + 1 >= bytes.size() || bytes[i + 1] != 0xFD) {
        throw DxlError("byte stuffing: FF FF FD at offset " + std::to_string(i - 2) +
                       " is not followed by the stuffing byte FD");
      }
      ++i;
    }
  }
  return out;
}

std::vector<std::uint8_t> BuildPacket(std::uint8_t id, std::uint8_t instruction,
                                      const std::vector<std::uint8_t>& params) {
  if (id > kMaxId && id != kBroadcastId) {
    throw DxlError("instruction packet: id " + std::to_string(id) +
                   " is neither 0-252 nor broadcast (254)");
  }
  std::vector<std::uint8_t> body;
  body.reserve(params.size() + 1);
  body.push_back(instruction);
  body.insert(body.end(), params.begin(), params.end());
  const std::vector<std::uint8_t> stuffed = Stuff(body);
  const std::size_t length = stuffed.size() + 2;  // + CRC
  if (length > 0xFFFF) {
    throw DxlError("packet: " + std::to_string(length) +
                   " bytes after stuffing exceed the 16-bit length field");
  }
  std::vector<std::uint8_t> out = {0xFF, 0xFF, 0xFD, 0x00, id};
  PutU16Le(static_cast<std::uint16_t>(length), &out);
  out.insert(out.end(), stuffed.begin(), stuffed.end());
  PutU16Le(Crc16(out.data(), out.size()), &out);
  return out;
}

std::vector<std::uint8_t> BuildPing(std::uint8_t id) { return BuildPacket(id, kPing, {}); }

std::vector<std::uint8_t> BuildRead(std::uint8_t id, std::uint16_t address, std::uint16_t length) {
  if (length == 0) throw DxlError("READ: length 0");
  std::vector<std::uint8_t> p;
  PutU16Le(address, &p);
  PutU16Le(length, &p);
  return BuildPacket(id, kRead, p);
}

std::vector<std::uint8_t> BuildWrite(std::uint8_t id, std::uint16_t address,
                                     const std::vector<std::uint8_t>& data) {
  if (data.empty()) throw DxlError("WRITE: no data");
  // Sized up front: GCC 12 warns falsely (-Warray-bounds) on insert after two push_backs.
  std::vector<std::uint8_t> p(2 + data.size());
  p[0] = static_cast<std::uint8_t>(address);
  p[1] = static_cast<std::uint8_t>(address >> 8);
  std::copy(data.begin(), data.end(), p.begin() + 2);
  return BuildPacket(id, kWrite, p);
}

std::vector<std::uint8_t> BuildTorqueEnable(std::uint8_t id, bool enable) {
  return BuildWrite(id, kAddrTorqueEnable, {static_cast<std::uint8_t>(enable ? 1 : 0)});
}

std::vector<std::uint8_t> BuildReboot(std::uint8_t id) { return BuildPacket(id, kReboot, {}); }

std::vector<std::uint8_t> BuildSyncRead(std::uint16_t address, std::uint16_t length,
                                        const std::vector<std::uint8_t>& ids) {
  if (ids.empty()) throw DxlError("SYNC READ: no servo ids");
  if (length == 0) throw DxlError("SYNC READ: length 0");
  CheckDistinctIds(ids, "SYNC READ");
  std::vector<std::uint8_t> p;
  PutU16Le(address, &p);
  PutU16Le(length, &p);
  p.insert(p.end(), ids.begin(), ids.end());
  return BuildPacket(kBroadcastId, kSyncRead, p);
}

std::vector<std::uint8_t> BuildSyncWrite(
    std::uint16_t address, std::uint16_t length,
    const std::vector<std::pair<std::uint8_t, std::vector<std::uint8_t>>>& data) {
  if (data.empty()) throw DxlError("SYNC WRITE: no servos");
  if (length == 0) throw DxlError("SYNC WRITE: length 0");
  std::vector<std::uint8_t> ids;
  for (const auto& [id, bytes] : data) {
    ids.push_back(id);
    if (bytes.size() != length) {
      throw DxlError("SYNC WRITE: servo " + std::to_string(id) + " has " +
                     std::to_string(bytes.size()) + " data bytes, expected " +
                     std::to_string(length));
    }
  }
  CheckDistinctIds(ids, "SYNC WRITE");
  std::vector<std::uint8_t> p;
  PutU16Le(address, &p);
  PutU16Le(length, &p);
  for (const auto& [id, bytes] : data) {
    p.push_back(id);
    p.insert(p.end(), bytes.begin(), bytes.end());
  }
  return BuildPacket(kBroadcastId, kSyncWrite, p);
}

std::vector<std::uint8_t> BuildSyncWriteGoalPosition(
    const std::vector<std::pair<std::uint8_t, std::int32_t>>& goals) {
  std::vector<std::pair<std::uint8_t, std::vector<std::uint8_t>>> data;
  for (const auto& [id, count] : goals) {
    std::vector<std::uint8_t> bytes;
    PutU32Le(static_cast<std::uint32_t>(count), &bytes);
    data.emplace_back(id, std::move(bytes));
  }
  return BuildSyncWrite(kAddrGoalPosition, 4, data);
}

std::vector<std::uint8_t> BuildStatus(std::uint8_t id, std::uint8_t error,
                                      const std::vector<std::uint8_t>& params) {
  CheckUnicastId(id, "status packet");
  std::vector<std::uint8_t> p;
  p.reserve(params.size() + 1);
  p.push_back(error);
  p.insert(p.end(), params.begin(), params.end());
  return BuildPacket(id, kStatus, p);
}

std::string DescribeStatusError(std::uint8_t error) {
  static const char* const kNames[] = {"ok",
                                       "result fail",
                                       "instruction error",
                                       "CRC error",
                                       "data range error",
                                       "data length error",
                                       "data limit error",
                                       "access error"};
  const std::uint8_t number = error & 0x7F;
  std::string text = number < 8 ? kNames[number] : "unknown error " + std::to_string(number);
  if (error & 0x80) text = (number == 0 ? std::string("alert") : "alert, " + text);
  return text;
}

PacketParser::PacketParser(std::size_t max_length) : max_length_(max_length) {
  if (max_length_ < 3 || max_length_ > 0xFFFF) {
    throw DxlError("PacketParser: max_length " + std::to_string(max_length) + " outside 3-65535");
  }
}

void PacketParser::Feed(const std::uint8_t* data, std::size_t n) {
  buffer_.insert(buffer_.end(), data, data + n);
}

bool PacketParser::NextRaw(std::uint8_t* id, std::vector<std::uint8_t>* body) {
  static constexpr std::uint8_t kHeader[4] = {0xFF, 0xFF, 0xFD, 0x00};
  while (true) {
    // Skip to the next full header; keep a partial one at the end for the next Feed().
    std::size_t skip = 0;
    while (skip < buffer_.size()) {
      std::size_t k = 0;
      while (k < 4 && skip + k < buffer_.size() && buffer_[skip + k] == kHeader[k]) ++k;
      if (k == 4 || skip + k == buffer_.size()) break;
      ++skip;
    }
    stats_.noise_bytes += skip;
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(skip));
    if (buffer_.size() < kHeaderBytes) return false;

    const std::uint8_t packet_id = buffer_[4];
    const std::size_t length = static_cast<std::size_t>(buffer_[5] | (buffer_[6] << 8));
    // 0xFD and 0xFF are never ids (§2.2); length covers at least instruction + CRC.
    if (packet_id == 0xFD || packet_id == 0xFF || length < 3 || length > max_length_) {
      ++stats_.malformed;
      buffer_.pop_front();
      continue;
    }
    const std::size_t total = kHeaderBytes + length;
    if (buffer_.size() < total) return false;

    std::vector<std::uint8_t> packet(buffer_.begin(),
                                     buffer_.begin() + static_cast<std::ptrdiff_t>(total));
    const std::uint16_t crc = Crc16(packet.data(), total - 2);
    if (crc != GetU16Le(packet.data() + total - 2)) {
      ++stats_.crc_errors;
      buffer_.pop_front();
      continue;
    }
    try {
      *body = Unstuff(std::vector<std::uint8_t>(packet.begin() + kHeaderBytes, packet.end() - 2));
    } catch (const DxlError&) {
      ++stats_.malformed;
      buffer_.pop_front();
      continue;
    }
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(total));
    *id = packet_id;
    return true;
  }
}

std::optional<StatusPacket> PacketParser::NextStatus() {
  std::uint8_t id = 0;
  std::vector<std::uint8_t> body;
  while (NextRaw(&id, &body)) {
    // A status needs instruction + error byte and comes from a unicast id.
    if (body[0] != kStatus || body.size() < 2 || id > kMaxId) {
      ++stats_.malformed;
      continue;
    }
    ++stats_.packets;
    StatusPacket s;
    s.id = id;
    s.error = body[1];
    s.params.assign(body.begin() + 2, body.end());
    return s;
  }
  return std::nullopt;
}

std::optional<InstructionPacket> PacketParser::NextInstruction() {
  std::uint8_t id = 0;
  std::vector<std::uint8_t> body;
  while (NextRaw(&id, &body)) {
    if (body[0] == kStatus) {
      ++stats_.malformed;
      continue;
    }
    ++stats_.packets;
    InstructionPacket p;
    p.id = id;
    p.instruction = body[0];
    p.params.assign(body.begin() + 1, body.end());
    return p;
  }
  return std::nullopt;
}

void PacketParser::Timeout() {
  ++stats_.timeouts;
  buffer_.clear();
}

PresentState DecodePresentBlock(const std::uint8_t* data, std::size_t n) {
  if (data == nullptr || n != kPresentBlockBytes) {
    throw DxlError("present block (addresses 120-147): " + std::to_string(n) +
                   " bytes, expected 28");
  }
  // Offsets are address - 120.
  PresentState s;
  s.realtime_tick_ms = GetU16Le(data + 0);
  s.moving = data[2];
  s.moving_status = data[3];
  s.present_pwm = static_cast<std::int16_t>(GetU16Le(data + 4));
  s.present_current = static_cast<std::int16_t>(GetU16Le(data + 6));
  s.present_velocity = static_cast<std::int32_t>(GetU32Le(data + 8));
  s.present_position = static_cast<std::int32_t>(GetU32Le(data + 12));
  s.velocity_trajectory = static_cast<std::int32_t>(GetU32Le(data + 16));
  s.position_trajectory = static_cast<std::int32_t>(GetU32Le(data + 20));
  s.present_input_voltage = GetU16Le(data + 24);
  s.present_temperature = data[26];
  return s;
}

std::vector<std::uint8_t> EncodePresentBlock(const PresentState& s) {
  std::vector<std::uint8_t> out;
  out.reserve(kPresentBlockBytes);
  PutU16Le(s.realtime_tick_ms, &out);
  out.push_back(s.moving);
  out.push_back(s.moving_status);
  PutU16Le(static_cast<std::uint16_t>(s.present_pwm), &out);
  PutU16Le(static_cast<std::uint16_t>(s.present_current), &out);
  PutU32Le(static_cast<std::uint32_t>(s.present_velocity), &out);
  PutU32Le(static_cast<std::uint32_t>(s.present_position), &out);
  PutU32Le(static_cast<std::uint32_t>(s.velocity_trajectory), &out);
  PutU32Le(static_cast<std::uint32_t>(s.position_trajectory), &out);
  PutU16Le(s.present_input_voltage, &out);
  out.push_back(s.present_temperature);
  out.push_back(0);  // 147: not an item of the MX-106(2.0) table
  return out;
}

namespace {
constexpr double kPi = 3.14159265358979323846;

void CheckDirection(int direction) {
  if (direction != 1 && direction != -1) {
    throw DxlError("servo direction must be +1 or -1, got " + std::to_string(direction));
  }
}
}  // namespace

double PositionToRad(std::int32_t count, std::int32_t zero_count, int direction) {
  CheckDirection(direction);
  const double delta = static_cast<double>(count) - static_cast<double>(zero_count);
  return direction * delta * (2.0 * kPi / kCountsPerRev);
}

std::int32_t RadToPosition(double angle_rad, std::int32_t zero_count, int direction) {
  CheckDirection(direction);
  const double count = static_cast<double>(zero_count) +
                       std::round(direction * angle_rad * kCountsPerRev / (2.0 * kPi));
  if (!std::isfinite(count) || count < std::numeric_limits<std::int32_t>::min() ||
      count > std::numeric_limits<std::int32_t>::max()) {
    throw DxlError("angle " + std::to_string(angle_rad) + " rad has no position count");
  }
  return static_cast<std::int32_t>(count);
}

double VelocityToRadPerS(std::int32_t value) { return value * kVelocityUnitRpm * 2.0 * kPi / 60.0; }

double CurrentToA(std::int16_t value) { return value * kCurrentUnitA; }

double VoltageToV(std::uint16_t value) { return value * kVoltageUnitV; }

std::int64_t TickUnwrapper::Update(std::uint16_t tick_ms) {
  const std::uint16_t tick = tick_ms & 0x7FFF;
  if (!started_) {
    started_ = true;
    total_ = tick;
  } else {
    total_ += (tick - last_ + 0x8000) & 0x7FFF;
  }
  last_ = tick;
  return total_;
}

}  // namespace ftcal::dxl
