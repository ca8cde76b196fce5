// Qualisys QTM real-time (RT) protocol codec, little-endian binary port (base port + 1):
// packet framing, a TCP stream deframer, commands, text/event replies, data frames with the
// 3D, 3DRes, 6D and 6DRes components, and the 6D/3D parameter XML.
//
// Pure bytes in, structs out: no sockets here, so the bridge and the simulator's QTM server
// share it. Wire facts: docs/device-protocols.md section 3 (§3.x below).
#pragma once

#include <Eigen/Core>

#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace ftcal::qtm {

// Bad bytes or XML; the message names what was wrong and where.
class QtmError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

constexpr std::uint16_t kLittleEndianPort = 22223;
constexpr std::size_t kPacketHeaderBytes = 8;  // i32 size (whole packet), i32 type
constexpr std::string_view kWelcomePrefix = "QTM RT Interface connected";

enum class PacketType : std::int32_t {
  kError = 0,
  kCommand = 1,  // also command responses
  kXml = 2,
  kData = 3,
  kNoMoreData = 4,
  kC3dFile = 5,
  kEvent = 6,
  kDiscover = 7,
  kQtmFile = 8,
};

// One packet. `type` is kept raw: a newer server may send types this code does not know,
// and the caller decides to skip them.
struct Packet {
  std::int32_t type = 0;
  std::vector<std::uint8_t> payload;  // the size - 8 bytes after the header
  bool is(PacketType t) const { return type == static_cast<std::int32_t>(t); }
};

std::vector<std::uint8_t> EncodePacket(std::int32_t type, const std::vector<std::uint8_t>& payload);
// A command packet (type 1) carrying `text` and its terminating NUL. Throws QtmError if the
// text holds a NUL itself.
std::vector<std::uint8_t> EncodeCommand(std::string_view text);
// Error, command-response or XML packet as the server sends them (NUL-terminated).
std::vector<std::uint8_t> EncodeText(PacketType type, std::string_view text);

// Reassembles packets from a TCP byte stream read in arbitrary pieces (§3.2). A size field
// below 8 or above max_packet_bytes means the stream is out of step and cannot be recovered:
// Next() throws QtmError then and on every later call until Reset() (reconnect first).
class Deframer {
 public:
  static constexpr std::size_t kDefaultMaxPacketBytes = 16u << 20;
  explicit Deframer(std::size_t max_packet_bytes = kDefaultMaxPacketBytes);

  void Feed(const std::uint8_t* data, std::size_t n);
  std::optional<Packet> Next();
  void Reset();
  std::size_t buffered() const { return buffer_.size() - read_; }

 private:
  std::size_t max_packet_bytes_;
  std::vector<std::uint8_t> buffer_;
  std::size_t read_ = 0;
  std::string failure_;
};

// Text of an error (0), command (1) or XML (2) packet, up to its first NUL (the NUL is
// optional). Throws QtmError for other types.
std::string DecodeText(const Packet& packet);
// The server's greeting: compare the prefix only (the documents differ on the final '.').
bool IsWelcome(std::string_view text);
// True when `reply` is the server's acceptance of `Version <version>`.
bool IsVersionAccepted(std::string_view reply, std::string_view version);

// Event number of an Event packet (§3.7); throws QtmError unless the payload is 1 byte.
std::uint8_t DecodeEvent(const Packet& packet);
constexpr std::uint8_t kEventCaptureStarted = 3;
constexpr std::uint8_t kEventRtFromFileStarted = 8;
constexpr std::uint8_t kEventCameraSettingsChanged = 11;
constexpr std::uint8_t kEventQtmShuttingDown = 12;
std::string EventName(std::uint8_t event);

// Component types (§3.6) this codec decodes.
constexpr std::int32_t kComponent3D = 1;
constexpr std::int32_t kComponent6D = 5;
constexpr std::int32_t kComponent3DRes = 9;
constexpr std::int32_t kComponent6DRes = 11;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// A labelled marker, in QTM's global frame G. Untracked: position NaN (§3.6).
struct Marker {
  Eigen::Vector3d p_GoM_G_mm = Eigen::Vector3d::Constant(kNaN);
  double residual_mm = kNaN;  // NaN when the component carries none
  bool tracked() const { return !p_GoM_G_mm.array().isNaN().any(); }
};

// A rigid body's pose: R_GB rotates body coordinates into G. Untracked: NaN fields.
struct Body {
  Eigen::Vector3d p_GoBo_G_mm = Eigen::Vector3d::Constant(kNaN);
  Eigen::Matrix3d R_GB = Eigen::Matrix3d::Constant(kNaN);
  double residual_mm = kNaN;
  bool tracked() const { return !p_GoBo_G_mm.array().isNaN().any() && !R_GB.array().isNaN().any(); }
};

struct DataFrame {
  std::int64_t timestamp_us = 0;  // since the start of the measurement
  std::int32_t frame_number = 0;
  // 3D or 3DRes: markers in the order of the 3D labels.
  bool has_markers = false;
  bool markers_have_residuals = false;
  std::uint16_t markers_drop_rate_permille = 0;
  std::uint16_t markers_out_of_sync_permille = 0;
  std::vector<Marker> markers;
  // 6D or 6DRes: bodies in the order of the 6D parameters.
  bool has_bodies = false;
  bool bodies_have_residuals = false;
  std::uint16_t bodies_drop_rate_permille = 0;
  std::uint16_t bodies_out_of_sync_permille = 0;
  std::vector<Body> bodies;
  // Types of the components present but not decoded here (skipped by their size).
  std::vector<std::int32_t> skipped_component_types;
};

// Decodes a Data packet (type 3). Throws QtmError naming the component and the sizes when
// any size disagrees with the counts, components overrun the packet, bytes are left over,
// or two components fill the same slot (e.g. both 3D and 3DRes).
DataFrame DecodeData(const Packet& packet);
// The inverse for the simulator: 3D/3DRes and 6D/6DRes by the has_* and *_have_residuals
// flags (skipped_component_types is ignored). Values are narrowed to f32 as on the wire.
std::vector<std::uint8_t> EncodeData(const DataFrame& frame);

// What the bridge needs from `GetParameters General 3D 6D` (§3.4).
struct Parameters {
  std::optional<double> frequency_hz;  // General/Frequency
  bool has_3d = false;
  std::vector<std::string> labels_3d;  // The_3D/Label/Name, in data order
  bool has_6d = false;
  std::vector<std::string> body_names;  // The_6D/Body/Name, in data order
};
// Throws QtmError on malformed XML, a root other than QTM_Parameters_Ver_*, the protocol
// <= 1.20 6D layout (<Bodies>), a body or label without a name, or a duplicate name.
Parameters ParseParameters(std::string_view xml);

}  // namespace ftcal::qtm
