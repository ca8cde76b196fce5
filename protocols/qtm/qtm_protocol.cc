#include "qtm_protocol.h"

#include <pugixml.hpp>

#include <cmath>
#include <cstring>
#include <set>
#include <sstream>

namespace ftcal::qtm {
namespace {

std::uint16_t GetU16(const std::uint8_t* p) {
  return static_cast<std::uint16_t>(p[0] | (p[1] << 8));
}
std::uint32_t GetU32(const std::uint8_t* p) {
  return std::uint32_t{p[0]} | (std::uint32_t{p[1]} << 8) | (std::uint32_t{p[2]} << 16) |
         (std::uint32_t{p[3]} << 24);
}
std::int32_t GetI32(const std::uint8_t* p) { return static_cast<std::int32_t>(GetU32(p)); }
std::int64_t GetI64(const std::uint8_t* p) {
  return static_cast<std::int64_t>(std::uint64_t{GetU32(p)} | (std::uint64_t{GetU32(p + 4)} << 32));
}
double GetF32(const std::uint8_t* p) {
  const std::uint32_t bits = GetU32(p);
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
}

void PutU16(std::uint16_t v, std::vector<std::uint8_t>* out) {
  out->push_back(static_cast<std::uint8_t>(v));
  out->push_back(static_cast<std::uint8_t>(v >> 8));
}
void PutU32(std::uint32_t v, std::vector<std::uint8_t>* out) {
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<std::uint8_t>(v >> (8 * i)));
}
void PutI64(std::int64_t v, std::vector<std::uint8_t>* out) {
  const auto u = static_cast<std::uint64_t>(v);
  PutU32(static_cast<std::uint32_t>(u), out);
  PutU32(static_cast<std::uint32_t>(u >> 32), out);
}
void PutF32(double v, std::vector<std::uint8_t>* out) {
  const float f = static_cast<float>(v);
  std::uint32_t bits;
  std::memcpy(&bits, &f, sizeof bits);
  PutU32(bits, out);
}

std::string ComponentName(std::int32_t type) {
  switch (type) {
    case kComponent3D:
      return "3D";
    case kComponent3DRes:
      return "3DRes";
    case kComponent6D:
      return "6D";
    case kComponent6DRes:
      return "6DRes";
    default:
      return "type " + std::to_string(type);
  }
}

// Per-item sizes of the decoded components (§3.6).
std::size_t ItemBytes(std::int32_t type) {
  switch (type) {
    case kComponent3D:
      return 12;
    case kComponent3DRes:
      return 16;
    case kComponent6D:
      return 48;
    case kComponent6DRes:
      return 52;
    default:
      return 0;
  }
}

}  // namespace

std::vector<std::uint8_t> EncodePacket(std::int32_t type,
                                       const std::vector<std::uint8_t>& payload) {
  const std::size_t size = kPacketHeaderBytes + payload.size();
  if (size > static_cast<std::size_t>(std::numeric_limits<std::int32_t>::max())) {
    throw QtmError("packet of " + std::to_string(size) + " bytes exceeds the i32 size field");
  }
  std::vector<std::uint8_t> out;
  out.reserve(size);
  PutU32(static_cast<std::uint32_t>(size), &out);
  PutU32(static_cast<std::uint32_t>(type), &out);
  out.insert(out.end(), payload.begin(), payload.end());
  return out;
}

std::vector<std::uint8_t> EncodeText(PacketType type, std::string_view text) {
  if (text.find('\0') != std::string_view::npos) {
    throw QtmError("packet text holds a NUL at offset " + std::to_string(text.find('\0')));
  }
  std::vector<std::uint8_t> payload(text.begin(), text.end());
  payload.push_back(0);
  return EncodePacket(static_cast<std::int32_t>(type), payload);
}

std::vector<std::uint8_t> EncodeCommand(std::string_view text) {
  return EncodeText(PacketType::kCommand, text);
}

Deframer::Deframer(std::size_t max_packet_bytes) : max_packet_bytes_(max_packet_bytes) {
  if (max_packet_bytes_ < kPacketHeaderBytes) {
    throw QtmError("Deframer: max_packet_bytes " + std::to_string(max_packet_bytes) + " < 8");
  }
}

void Deframer::Feed(const std::uint8_t* data, std::size_t n) {
  // Drop consumed bytes before growing, so the buffer stays about one packet long.
  if (read_ > 0 && (read_ == buffer_.size() || read_ > 4096)) {
    buffer_.erase(buffer_.begin(), buffer_.begin() + static_cast<std::ptrdiff_t>(read_));
    read_ = 0;
  }
  buffer_.insert(buffer_.end(), data, data + n);
}

std::optional<Packet> Deframer::Next() {
  if (!failure_.empty()) throw QtmError(failure_);
  if (buffered() < kPacketHeaderBytes) return std::nullopt;
  const std::uint8_t* p = buffer_.data() + read_;
  const std::int32_t size = GetI32(p);
  if (size < static_cast<std::int32_t>(kPacketHeaderBytes) ||
      static_cast<std::size_t>(size) > max_packet_bytes_) {
    failure_ = "QTM stream: packet size field " + std::to_string(size) + " outside 8-" +
               std::to_string(max_packet_bytes_) + " bytes; the stream is out of step";
    throw QtmError(failure_);
  }
  if (buffered() < static_cast<std::size_t>(size)) return std::nullopt;
  Packet packet;
  packet.type = GetI32(p + 4);
  packet.payload.assign(p + kPacketHeaderBytes, p + size);
  read_ += static_cast<std::size_t>(size);
  return packet;
}

void Deframer::Reset() {
  buffer_.clear();
  read_ = 0;
  failure_.clear();
}

std::string DecodeText(const Packet& packet) {
  if (!packet.is(PacketType::kError) && !packet.is(PacketType::kCommand) &&
      !packet.is(PacketType::kXml)) {
    throw QtmError("packet of type " + std::to_string(packet.type) + " carries no text");
  }
  const auto* begin = reinterpret_cast<const char*>(packet.payload.data());
  const std::string_view all(begin, packet.payload.size());
  return std::string(all.substr(0, all.find('\0')));
}

bool IsWelcome(std::string_view text) {
  return text.substr(0, kWelcomePrefix.size()) == kWelcomePrefix;
}

bool IsVersionAccepted(std::string_view reply, std::string_view version) {
  return reply == "Version set to " + std::string(version);
}

std::uint8_t DecodeEvent(const Packet& packet) {
  if (!packet.is(PacketType::kEvent)) {
    throw QtmError("packet of type " + std::to_string(packet.type) + " is not an event");
  }
  if (packet.payload.size() != 1) {
    throw QtmError("event packet: payload of " + std::to_string(packet.payload.size()) +
                   " bytes, expected 1");
  }
  return packet.payload[0];
}

std::string EventName(std::uint8_t event) {
  static const char* const kNames[] = {nullptr,
                                       "Connected",
                                       "Connection Closed",
                                       "Capture Started",
                                       "Capture Stopped",
                                       nullptr,
                                       "Calibration Started",
                                       "Calibration Stopped",
                                       "RT From File Started",
                                       "RT From File Stopped",
                                       "Waiting For Trigger",
                                       "Camera Settings Changed",
                                       "QTM Shutting Down",
                                       "Capture Saved",
                                       nullptr,
                                       nullptr,
                                       "Trigger"};
  if (event < sizeof kNames / sizeof kNames[0] && kNames[event]) return kNames[event];
  return "event " + std::to_string(event);
}

DataFrame DecodeData(const Packet& packet) {
  if (!packet.is(PacketType::kData)) {
    throw QtmError("packet of type " + std::to_string(packet.type) + " is not a data packet");
  }
  const std::uint8_t* p = packet.payload.data();
  const std::size_t n = packet.payload.size();
  // Offsets below are within the payload (packet offset - 8).
  if (n < 16) {
    throw QtmError("data packet: payload of " + std::to_string(n) +
                   " bytes, needs 16 for its header");
  }
  DataFrame frame;
  frame.timestamp_us = GetI64(p);
  frame.frame_number = GetI32(p + 8);
  const std::int32_t count = GetI32(p + 12);
  if (count < 0) throw QtmError("data packet: negative component count " + std::to_string(count));

  std::size_t at = 16;
  for (std::int32_t c = 0; c < count; ++c) {
    const std::string where = "data packet frame " + std::to_string(frame.frame_number) +
                              ", component " + std::to_string(c + 1) + "/" + std::to_string(count);
    if (n - at < 8) throw QtmError(where + ": truncated component header");
    const std::int32_t size = GetI32(p + at);
    const std::int32_t type = GetI32(p + at + 4);
    if (size < 8 || static_cast<std::size_t>(size) > n - at) {
      throw QtmError(where + " (" + ComponentName(type) + "): size " + std::to_string(size) +
                     " outside 8-" + std::to_string(n - at));
    }
    const std::uint8_t* body = p + at + 8;
    const std::size_t body_bytes = static_cast<std::size_t>(size) - 8;
    at += static_cast<std::size_t>(size);

    const std::size_t item = ItemBytes(type);
    if (item == 0) {
      frame.skipped_component_types.push_back(type);
      continue;
    }
    if (body_bytes < 8) {
      throw QtmError(where + " (" + ComponentName(type) + "): " + std::to_string(body_bytes) +
                     " payload bytes, needs 8 for count and rates");
    }
    const std::uint32_t items = GetU32(body);
    const std::uint16_t drop = GetU16(body + 4);
    const std::uint16_t out_of_sync = GetU16(body + 6);
    // 64-bit product: a hostile count cannot wrap around to a plausible size.
    if (std::uint64_t{items} * item != body_bytes - 8) {
      throw QtmError(where + " (" + ComponentName(type) + "): " + std::to_string(items) +
                     " items of " + std::to_string(item) + " bytes do not fill " +
                     std::to_string(body_bytes - 8) + " payload bytes");
    }
    const std::uint8_t* q = body + 8;
    if (type == kComponent3D || type == kComponent3DRes) {
      if (frame.has_markers) throw QtmError(where + ": a second 3D component");
      frame.has_markers = true;
      frame.markers_have_residuals = type == kComponent3DRes;
      frame.markers_drop_rate_permille = drop;
      frame.markers_out_of_sync_permille = out_of_sync;
      frame.markers.resize(items);
      for (Marker& m : frame.markers) {
        m.p_GoM_G_mm = {GetF32(q), GetF32(q + 4), GetF32(q + 8)};
        if (frame.markers_have_residuals) m.residual_mm = GetF32(q + 12);
        q += item;
      }
    } else {
      if (frame.has_bodies) throw QtmError(where + ": a second 6D component");
      frame.has_bodies = true;
      frame.bodies_have_residuals = type == kComponent6DRes;
      frame.bodies_drop_rate_permille = drop;
      frame.bodies_out_of_sync_permille = out_of_sync;
      frame.bodies.resize(items);
      for (Body& b : frame.bodies) {
        b.p_GoBo_G_mm = {GetF32(q), GetF32(q + 4), GetF32(q + 8)};
        // Column-major: R(i, j) = m[3 j + i], R rotating body into global (§3.6, [S]; Qualisys's
        // own Unity plugin reads the nine floats the same way and takes positions in mm).
        for (int j = 0; j < 3; ++j) {
          for (int i = 0; i < 3; ++i) b.R_GB(i, j) = GetF32(q + 12 + 4 * (3 * j + i));
        }
        if (frame.bodies_have_residuals) b.residual_mm = GetF32(q + 48);
        q += item;
      }
    }
  }
  if (at != n) {
    throw QtmError("data packet frame " + std::to_string(frame.frame_number) + ": " +
                   std::to_string(n - at) + " bytes after the last of " + std::to_string(count) +
                   " components");
  }
  return frame;
}

std::vector<std::uint8_t> EncodeData(const DataFrame& frame) {
  std::vector<std::uint8_t> payload;
  PutI64(frame.timestamp_us, &payload);
  PutU32(static_cast<std::uint32_t>(frame.frame_number), &payload);
  PutU32(static_cast<std::uint32_t>((frame.has_markers ? 1 : 0) + (frame.has_bodies ? 1 : 0)),
         &payload);
  if (frame.has_markers) {
    const std::int32_t type = frame.markers_have_residuals ? kComponent3DRes : kComponent3D;
    const std::size_t size = 16 + ItemBytes(type) * frame.markers.size();
    PutU32(static_cast<std::uint32_t>(size), &payload);
    PutU32(static_cast<std::uint32_t>(type), &payload);
    PutU32(static_cast<std::uint32_t>(frame.markers.size()), &payload);
    PutU16(frame.markers_drop_rate_permille, &payload);
    PutU16(frame.markers_out_of_sync_permille, &payload);
    for (const Marker& m : frame.markers) {
      for (int i = 0; i < 3; ++i) PutF32(m.p_GoM_G_mm(i), &payload);
      if (frame.markers_have_residuals) PutF32(m.residual_mm, &payload);
    }
  }
  if (frame.has_bodies) {
    const std::int32_t type = frame.bodies_have_residuals ? kComponent6DRes : kComponent6D;
    const std::size_t size = 16 + ItemBytes(type) * frame.bodies.size();
    PutU32(static_cast<std::uint32_t>(size), &payload);
    PutU32(static_cast<std::uint32_t>(type), &payload);
    PutU32(static_cast<std::uint32_t>(frame.bodies.size()), &payload);
    PutU16(frame.bodies_drop_rate_permille, &payload);
    PutU16(frame.bodies_out_of_sync_permille, &payload);
    for (const Body& b : frame.bodies) {
      for (int i = 0; i < 3; ++i) PutF32(b.p_GoBo_G_mm(i), &payload);
      for (int j = 0; j < 3; ++j) {
        for (int i = 0; i < 3; ++i) PutF32(b.R_GB(i, j), &payload);
      }
      if (frame.bodies_have_residuals) PutF32(b.residual_mm, &payload);
    }
  }
  return EncodePacket(static_cast<std::int32_t>(PacketType::kData), payload);
}

Parameters ParseParameters(std::string_view xml) {
  pugi::xml_document doc;
  const pugi::xml_parse_result parsed = doc.load_buffer(xml.data(), xml.size());
  if (!parsed) {
    std::ostringstream os;
    os << "QTM parameters: malformed XML at byte " << parsed.offset << ": " << parsed.description();
    throw QtmError(os.str());
  }
  const pugi::xml_node root = doc.document_element();
  if (std::string_view(root.name()).rfind("QTM_Parameters_Ver_", 0) != 0) {
    throw QtmError(std::string("QTM parameters: root element <") + root.name() +
                   ">, expected <QTM_Parameters_Ver_...>");
  }
  Parameters out;
  if (const pugi::xml_node general = root.child("General")) {
    if (const pugi::xml_node f = general.child("Frequency")) {
      const char* text = f.child_value();
      char* end = nullptr;
      const double hz = std::strtod(text, &end);
      if (end == text || *end != '\0' || !std::isfinite(hz) || hz <= 0) {
        throw QtmError(std::string("QTM parameters: General/Frequency '") + text +
                       "' is not a positive number");
      }
      out.frequency_hz = hz;
    }
  }
  auto names = [](pugi::xml_node section, const char* item, const char* what,
                  std::vector<std::string>* into) {
    std::set<std::string> seen;
    for (const pugi::xml_node n : section.children(item)) {
      const std::string name = n.child("Name").child_value();
      const std::string where =
          std::string("QTM parameters: ") + what + " " + std::to_string(into->size() + 1);
      if (name.empty()) throw QtmError(where + " has no <Name>");
      if (!seen.insert(name).second) throw QtmError(where + ": duplicate name '" + name + "'");
      into->push_back(name);
    }
  };
  if (const pugi::xml_node six = root.child("The_6D")) {
    if (six.child("Bodies")) {
      throw QtmError(
          "QTM parameters: The_6D is in the protocol <= 1.20 layout (<Bodies>); request "
          "protocol version 1.21 or later");
    }
    out.has_6d = true;
    names(six, "Body", "6D body", &out.body_names);
  }
  if (const pugi::xml_node three = root.child("The_3D")) {
    out.has_3d = true;
    names(three, "Label", "3D label", &out.labels_3d);
    if (const pugi::xml_node count = three.child("Labels")) {
      const std::string text = count.child_value();
      if (text != std::to_string(out.labels_3d.size())) {
        throw QtmError("QTM parameters: The_3D/Labels says '" + text + "' but " +
                       std::to_string(out.labels_3d.size()) + " <Label> elements follow");
      }
    }
  }
  return out;
}

}  // namespace ftcal::qtm
