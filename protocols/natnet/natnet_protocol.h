// OptiTrack Motive NatNet codec: the packets of docs/natnet-protocol.md, for bitstream versions
// 3.0 to 4.x, shared by ftcal-natnet-bridge and the simulator's Motive server.
//
// Written by hand because no Debian package decodes NatNet (the vendor's libNatNet is a closed
// binary). Every decoder takes the negotiated version explicitly, never guesses it, and
// refuses a packet it did not consume exactly (§6 "version mismatch"): a wrong version yields
// plausible garbage otherwise. From 4.1 on every frame section and every description carries a
// byte count; a section whose records do not fill exactly that count is refused too.
//
// Plain C++ with no dependency: vectors are float arrays as on the wire (Motive's own units
// and axes). Converting to ftcal's frames and units is the bridge's job (natnet_bridge.h).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace ftcal::natnet {

// A malformed or unsupported packet; the message names the field and its byte offset.
class NatNetError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

inline constexpr uint16_t kCommandPort = 1510;
inline constexpr uint16_t kDataPort = 1511;
inline constexpr char kMulticastGroup[] = "239.255.42.99";
inline constexpr size_t kHeaderBytes = 4;
// 65535 - 20 (IP) - 8 (UDP) - 4 (header): the 4.x SDK's limit (§2.2).
inline constexpr size_t kMaxPayloadBytes = 65503;
// The vendor rejects more markers per rigid body (§6); the same cap bounds every count here.
inline constexpr int32_t kMaxCount = 16000;

enum MessageId : uint16_t {
  kConnect = 0,
  kServerInfo = 1,
  kRequest = 2,
  kResponse = 3,
  kRequestModelDef = 4,
  kModelDef = 5,
  kRequestFrameOfData = 6,
  kFrameOfData = 7,
  kMessageString = 8,
  kDisconnect = 9,
  kKeepAlive = 10,
  kDisconnectByTimeout = 11,
  kEchoRequest = 12,
  kEchoResponse = 13,
  kDiscovery = 14,
  kUnrecognizedRequest = 100,
  kUnrecognizedRequestAlt = 0x100,  // python_natnet saw this (§8 item 2): accept both
};

// A NatNet bitstream version (major.minor; build and revision never change the layout).
struct Version {
  int major = 0;
  int minor = 0;
  bool AtLeast(int ma, int mi) const { return major > ma || (major == ma && minor >= mi); }
  bool operator==(const Version& o) const { return major == o.major && minor == o.minor; }
  bool operator!=(const Version& o) const { return !(*this == o); }
  std::string ToString() const { return std::to_string(major) + "." + std::to_string(minor); }
};
// The versions this codec reads and writes: 3.0 to 4.x (§1).
bool Supported(const Version& v);
// "3.1" or "4.1.0.0" -> Version; nullopt when not numbers.
std::optional<Version> ParseVersion(const std::string& text);

struct Packet {
  uint16_t id = 0;
  std::vector<uint8_t> payload;
};

// One datagram -> a packet. Throws NatNetError when the datagram is shorter than its header
// or its length differs from nDataBytes + 4 (a truncated or padded datagram, §6).
Packet DecodePacket(const uint8_t* data, size_t size);
std::vector<uint8_t> EncodePacket(uint16_t id, const std::vector<uint8_t>& payload);

// ---- Handshake (§2.3) ----

// NAT_SERVERINFO (sSender_Server, 279 bytes from 3.0 on).
struct ServerInfo {
  std::string app_name = "Motive";
  std::array<uint8_t, 4> app_version{3, 1, 0, 0};
  std::array<uint8_t, 4> natnet_version{4, 1, 0, 0};
  uint64_t clock_frequency_hz = 0;  // HighResClockFrequency: ticks per second
  uint16_t data_port = kDataPort;
  bool multicast = true;
  std::array<uint8_t, 4> multicast_group{239, 255, 42, 99};
  Version version() const { return {natnet_version[0], natnet_version[1]}; }
};
inline constexpr size_t kServerInfoBytes = 279;
ServerInfo DecodeServerInfo(const std::vector<uint8_t>& payload);
std::vector<uint8_t> EncodeServerInfo(const ServerInfo& info);

// NAT_CONNECT as the 4.x PacketClient sends it (sSender + sConnectionOptions): our name, and
// the bitstream version we ask for (nullopt: the server's own).
std::vector<uint8_t> EncodeConnect(const std::string& client_name,
                                   std::optional<Version> bitstream);
// What a server reads from any NAT_CONNECT variant of §2.3 (0, 5, 264, 269, 271, 273 bytes):
// the bitstream version asked for, nullopt when none (or all zero).
std::optional<Version> DecodeConnectRequest(const std::vector<uint8_t>& payload);

// NAT_REQUEST / NAT_MESSAGESTRING: a NUL-terminated string.
std::vector<uint8_t> EncodeString(const std::string& text);
std::string DecodeString(const std::vector<uint8_t>& payload);

// NAT_ECHOREQUEST: u64 opaque client time. NAT_ECHORESPONSE: u64 echoed, u64 server ticks.
struct Echo {
  uint64_t request_time = 0;
  uint64_t server_ticks = 0;
};
std::vector<uint8_t> EncodeEchoResponse(const Echo& echo);
Echo DecodeEchoResponse(const std::vector<uint8_t>& payload);

// ---- Data descriptions (NAT_MODELDEF, §3) ----

using Vec3f = std::array<float, 3>;
using Quatf = std::array<float, 4>;  // x, y, z, w: NatNet's order

struct MarkerSetDescription {
  std::string name;
  std::vector<std::string> marker_names;
};

struct RigidBodyDescription {
  std::string name;
  int32_t id = 0;  // the streaming id frames carry
  int32_t parent_id = -1;
  Vec3f offset{0, 0, 0};                // relative to the parent (skeleton bones)
  Quatf rotation_offset{0, 0, 0, 1};    // v >= 4.2
  std::vector<Vec3f> marker_positions;  // v >= 3.0, body (pivot) frame
  std::vector<int32_t> marker_required_labels;
  std::vector<std::string> marker_names;  // v >= 4.0
};

struct SkeletonDescription {
  std::string name;
  int32_t id = 0;
  std::vector<RigidBodyDescription> bones;
};

struct Descriptions {
  std::vector<MarkerSetDescription> marker_sets;
  std::vector<RigidBodyDescription> rigid_bodies;
  std::vector<SkeletonDescription> skeletons;
  // Force plates, devices, cameras and assets: read (or skipped by their byte count) and
  // counted, not kept; the bridge has no use for them.
  int other = 0;
};

// Throws NatNetError naming the description and byte offset: a count out of range, a string
// without its NUL, a description whose body differs from its byte count (v >= 4.1), a type it
// cannot skip (v < 4.1), bytes left over.
Descriptions DecodeDescriptions(const std::vector<uint8_t>& payload, Version v);
// Writes marker sets, rigid bodies and skeletons (no other types).
std::vector<uint8_t> EncodeDescriptions(const Descriptions& d, Version v);

// ---- Frame of data (NAT_FRAMEOFDATA, §4) ----

struct RigidBodyData {
  int32_t id = 0;
  Vec3f position{0, 0, 0};
  Quatf orientation{0, 0, 0, 1};  // x, y, z, w
  float mean_error = 0;           // metres
  int16_t params = 0;
  bool tracked() const { return (params & 0x01) != 0; }
};

struct MarkerSetData {
  std::string name;
  std::vector<Vec3f> markers;
};

struct SkeletonData {
  int32_t id = 0;
  std::vector<RigidBodyData> bones;
};

struct AssetRigidBody {
  int32_t id = 0;
  Vec3f position{0, 0, 0};
  Quatf orientation{0, 0, 0, 1};
  float mean_error = 0;
  int16_t params = 0;
};
struct AssetMarker {
  int32_t id = 0;
  Vec3f position{0, 0, 0};
  float size = 0;
  int16_t params = 0;
  float residual = 0;
};
struct AssetData {
  int32_t id = 0;
  std::vector<AssetRigidBody> rigid_bodies;
  std::vector<AssetMarker> markers;
};

struct LabeledMarker {
  int32_t id = 0;  // rigid-body members: asset id << 16 | member id (1-based), §4.3
  Vec3f position{0, 0, 0};
  float size = 0;
  int16_t params = 0;
  float residual = 0;
  bool occluded() const { return (params & 0x01) != 0; }
};

struct AnalogData {  // force plates and devices
  int32_t id = 0;
  std::vector<std::vector<float>> channels;  // per channel, its sub-frames
};

// Frame params bits (§4.4, the 4.x header's meaning; §8 item 1).
inline constexpr int16_t kFrameRecording = 0x01;
inline constexpr int16_t kFrameModelListChanged = 0x02;
inline constexpr int16_t kFrameEditMode = 0x04;
inline constexpr int16_t kFrameBitstreamChanged = 0x08;

struct FrameOfData {
  int32_t frame_number = 0;
  std::vector<MarkerSetData> marker_sets;
  std::vector<Vec3f> other_markers;
  std::vector<RigidBodyData> rigid_bodies;
  std::vector<SkeletonData> skeletons;
  std::vector<AssetData> assets;  // v >= 4.1
  std::vector<LabeledMarker> labeled_markers;
  std::vector<AnalogData> force_plates;
  std::vector<AnalogData> devices;
  uint32_t timecode = 0;
  uint32_t timecode_subframe = 0;
  double timestamp_s = 0;           // since Motive started
  uint64_t mid_exposure_ticks = 0;  // 0 when unavailable
  uint64_t data_received_ticks = 0;
  uint64_t transmit_ticks = 0;
  uint32_t precision_s = 0;  // v >= 4.1
  uint32_t precision_fraction = 0;
  int16_t params = 0;

  bool model_list_changed() const { return (params & kFrameModelListChanged) != 0; }
  bool edit_mode() const { return (params & kFrameEditMode) != 0; }
  bool bitstream_changed() const { return (params & kFrameBitstreamChanged) != 0; }
};

// Throws NatNetError naming the section and byte offset (a count out of range, a section whose
// records differ from its byte count, a missing end tag, bytes left over).
FrameOfData DecodeFrame(const std::vector<uint8_t>& payload, Version v);
std::vector<uint8_t> EncodeFrame(const FrameOfData& f, Version v);

// The frame params read from the suffix without decoding the rest (§4.4: the last 6 bytes
// are params and the end tag); nullopt when the payload is too short.
std::optional<int16_t> PeekFrameParams(const std::vector<uint8_t>& payload);

}  // namespace ftcal::natnet
