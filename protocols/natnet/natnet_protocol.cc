#include "natnet_protocol.h"

#include <cstring>
#include <functional>

namespace ftcal::natnet {
namespace {

// Little-endian cursor over one payload; every failure names what was read and where.
class Reader {
 public:
  Reader(const std::vector<uint8_t>& bytes, std::string what)
      : data_(bytes.data()), size_(bytes.size()), what_(std::move(what)) {}

  size_t at() const { return at_; }
  size_t left() const { return size_ - at_; }

  [[noreturn]] void Fail(const std::string& field, const std::string& why) const {
    throw NatNetError(what_ + ": " + field + " at byte " + std::to_string(at_) + ": " + why);
  }
  void Need(size_t n, const std::string& field) const {
    if (left() < n) {
      Fail(field, "needs " + std::to_string(n) + " bytes, " + std::to_string(left()) + " left");
    }
  }
  template <typename T>
  T Get(const std::string& field) {
    Need(sizeof(T), field);
    T v;
    std::memcpy(&v, data_ + at_, sizeof v);  // hosts are little-endian (static_assert below)
    at_ += sizeof v;
    return v;
  }
  int32_t Count(const std::string& field) {
    const int32_t n = Get<int32_t>(field);
    if (n < 0 || n > kMaxCount) {
      at_ -= 4;
      Fail(field, "count " + std::to_string(n) + " outside 0.." + std::to_string(kMaxCount));
    }
    return n;
  }
  std::string CString(const std::string& field) {
    const void* nul = std::memchr(data_ + at_, 0, left());
    if (nul == nullptr) Fail(field, "string without its terminating NUL");
    const size_t n = static_cast<const uint8_t*>(nul) - (data_ + at_);
    std::string s(reinterpret_cast<const char*>(data_ + at_), n);
    at_ += n + 1;
    return s;
  }
  Vec3f Vec3(const std::string& field) {
    return {Get<float>(field), Get<float>(field), Get<float>(field)};
  }
  Quatf Quat(const std::string& field) {
    return {Get<float>(field), Get<float>(field), Get<float>(field), Get<float>(field)};
  }
  void Skip(size_t n, const std::string& field) {
    Need(n, field);
    at_ += n;
  }
  void End() const {
    if (left() != 0) Fail("end", std::to_string(left()) + " bytes left over");
  }

 private:
  const uint8_t* data_;
  size_t size_;
  size_t at_ = 0;
  std::string what_;
};

static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__, "NatNet is little-endian, as is the host");

class Writer {
 public:
  template <typename T>
  void Put(T v) {
    const size_t at = out.size();
    out.resize(at + sizeof v);
    std::memcpy(out.data() + at, &v, sizeof v);
  }
  void Count(size_t n) { Put<int32_t>(static_cast<int32_t>(n)); }
  void CString(const std::string& s) {
    out.insert(out.end(), s.begin(), s.end());
    out.push_back(0);
  }
  void Vec3(const Vec3f& v) {
    for (float x : v) Put(x);
  }
  void Quat(const Quatf& q) {
    for (float x : q) Put(x);
  }
  // An i32 placeholder for a byte count; Patch() fills it with the bytes written since.
  size_t Placeholder() {
    Put<int32_t>(0);
    return out.size();
  }
  void Patch(size_t after_placeholder) {
    const auto n = static_cast<int32_t>(out.size() - after_placeholder);
    std::memcpy(out.data() + after_placeholder - 4, &n, 4);
  }
  std::vector<uint8_t> out;
};

// One list section of a frame: count, [v >= 4.1] byte count, records. The records must fill
// exactly the byte count: the check that catches a stream parsed with the wrong version.
template <typename Record>
void ReadSection(Reader& r, Version v, const std::string& name, std::vector<Record>& out,
                 const std::function<Record(Reader&, const std::string&)>& read_one) {
  const int32_t n = r.Count(name + " count");
  std::optional<int32_t> bytes;
  if (v.AtLeast(4, 1)) {
    bytes = r.Get<int32_t>(name + " byte count");
    if (*bytes < 0 || static_cast<size_t>(*bytes) > r.left()) {
      r.Fail(name + " byte count",
             std::to_string(*bytes) + " with " + std::to_string(r.left()) + " bytes left");
    }
  }
  const size_t start = r.at();
  out.reserve(static_cast<size_t>(n));
  for (int32_t i = 0; i < n; ++i) out.push_back(read_one(r, name + " " + std::to_string(i)));
  if (bytes && r.at() - start != static_cast<size_t>(*bytes)) {
    r.Fail(name, "records took " + std::to_string(r.at() - start) + " bytes, the byte count says " +
                     std::to_string(*bytes));
  }
}

template <typename Record>
void WriteSection(Writer& w, Version v, const std::vector<Record>& records,
                  const std::function<void(Writer&, const Record&)>& write_one) {
  w.Count(records.size());
  size_t mark = 0;
  if (v.AtLeast(4, 1)) mark = w.Placeholder();
  for (const Record& rec : records) write_one(w, rec);
  if (v.AtLeast(4, 1)) w.Patch(mark);
}

RigidBodyData ReadRigidBody(Reader& r, const std::string& where) {
  RigidBodyData b;
  b.id = r.Get<int32_t>(where + " id");
  b.position = r.Vec3(where + " position");
  b.orientation = r.Quat(where + " orientation");
  // v < 3.0 carried a marker list here; Supported() keeps those versions out.
  b.mean_error = r.Get<float>(where + " mean error");
  b.params = r.Get<int16_t>(where + " params");
  return b;
}

void WriteRigidBody(Writer& w, const RigidBodyData& b) {
  w.Put(b.id);
  w.Vec3(b.position);
  w.Quat(b.orientation);
  w.Put(b.mean_error);
  w.Put(b.params);
}

AnalogData ReadAnalog(Reader& r, const std::string& where) {
  AnalogData a;
  a.id = r.Get<int32_t>(where + " id");
  const int32_t n = r.Count(where + " channel count");
  for (int32_t c = 0; c < n; ++c) {
    const int32_t frames = r.Count(where + " channel " + std::to_string(c) + " frame count");
    r.Need(static_cast<size_t>(frames) * 4, where + " channel " + std::to_string(c));
    std::vector<float> values(static_cast<size_t>(frames));
    for (auto& x : values) x = r.Get<float>(where);
    a.channels.push_back(std::move(values));
  }
  return a;
}

void WriteAnalog(Writer& w, const AnalogData& a) {
  w.Put(a.id);
  w.Count(a.channels.size());
  for (const auto& ch : a.channels) {
    w.Count(ch.size());
    for (float x : ch) w.Put(x);
  }
}

// A rigid-body description body (type 1, and a 4.x skeleton's bones).
RigidBodyDescription ReadRigidBodyDescription(Reader& r, Version v, const std::string& where) {
  RigidBodyDescription d;
  d.name = r.CString(where + " name");
  d.id = r.Get<int32_t>(where + " id");
  d.parent_id = r.Get<int32_t>(where + " parent id");
  d.offset = r.Vec3(where + " offset");
  if (v.AtLeast(4, 2)) d.rotation_offset = r.Quat(where + " rotation offset");
  const int32_t n = r.Count(where + " marker count");
  r.Need(static_cast<size_t>(n) * 16, where + " markers");
  // Three separate arrays, not interleaved records (§3).
  for (int32_t i = 0; i < n; ++i) d.marker_positions.push_back(r.Vec3(where + " marker"));
  for (int32_t i = 0; i < n; ++i) d.marker_required_labels.push_back(r.Get<int32_t>(where));
  if (v.AtLeast(4, 0)) {
    for (int32_t i = 0; i < n; ++i) {
      d.marker_names.push_back(r.CString(where + " marker name " + std::to_string(i)));
    }
  }
  return d;
}

void WriteRigidBodyDescription(Writer& w, Version v, const RigidBodyDescription& d) {
  w.CString(d.name);
  w.Put(d.id);
  w.Put(d.parent_id);
  w.Vec3(d.offset);
  if (v.AtLeast(4, 2)) w.Quat(d.rotation_offset);
  w.Count(d.marker_positions.size());
  for (const auto& p : d.marker_positions) w.Vec3(p);
  for (size_t i = 0; i < d.marker_positions.size(); ++i) {
    w.Put<int32_t>(i < d.marker_required_labels.size() ? d.marker_required_labels[i] : 0);
  }
  if (v.AtLeast(4, 0)) {
    for (size_t i = 0; i < d.marker_positions.size(); ++i) {
      w.CString(i < d.marker_names.size() ? d.marker_names[i] : "");
    }
  }
}

// A skeleton's bone: the full rigid-body body in 4.x, the short form (name, id, parent,
// offset) in the 3.x samples (§8 item 8; no 3.x sample reads more).
RigidBodyDescription ReadBone(Reader& r, Version v, const std::string& where) {
  if (v.AtLeast(4, 0)) return ReadRigidBodyDescription(r, v, where);
  RigidBodyDescription d;
  d.name = r.CString(where + " name");
  d.id = r.Get<int32_t>(where + " id");
  d.parent_id = r.Get<int32_t>(where + " parent id");
  d.offset = r.Vec3(where + " offset");
  return d;
}

void WriteBone(Writer& w, Version v, const RigidBodyDescription& d) {
  if (v.AtLeast(4, 0)) return WriteRigidBodyDescription(w, v, d);
  w.CString(d.name);
  w.Put(d.id);
  w.Put(d.parent_id);
  w.Vec3(d.offset);
}

// Types the bridge does not keep, read field by field so that a pre-4.1 stream (no byte
// counts) can go past them.
void ReadOtherDescription(Reader& r, Version v, int32_t type, const std::string& where) {
  auto strings = [&](const std::string& what) {
    const int32_t n = r.Count(where + " " + what + " count");
    for (int32_t i = 0; i < n; ++i) r.CString(where + " " + what);
  };
  switch (type) {
    case 3:  // force plate
      r.Get<int32_t>(where + " id");
      r.CString(where + " serial");
      r.Skip(4 * (2 + 3 + 12 * 12 + 4 * 3) + 4 + 4, where + " geometry");
      strings("channel");
      return;
    case 4:  // device
      r.Get<int32_t>(where + " id");
      r.CString(where + " name");
      r.CString(where + " serial");
      r.Skip(8, where + " types");
      strings("channel");
      return;
    case 5:  // camera
      if (!v.AtLeast(4, 0)) break;
      r.CString(where + " name");
      r.Skip(7 * 4, where + " pose");
      return;
    default:
      break;
  }
  r.Fail(where, "description type " + std::to_string(type) + " is unknown to NatNet " +
                    v.ToString() + ", which has no byte count to skip it");
}

void CheckVersion(Version v, const std::string& what) {
  if (!Supported(v)) {
    throw NatNetError(what + ": NatNet " + v.ToString() + " is not supported (3.0 to 4.x)");
  }
}

}  // namespace

bool Supported(const Version& v) { return v.major == 3 || v.major == 4; }

std::optional<Version> ParseVersion(const std::string& text) {
  Version v;
  char dot = 0;
  size_t used = 0;
  try {
    v.major = std::stoi(text, &used);
    if (used >= text.size() || text[used] != '.') return std::nullopt;
    dot = text[used];
    size_t used2 = 0;
    v.minor = std::stoi(text.substr(used + 1), &used2);
    const std::string rest = text.substr(used + 1 + used2);
    for (char c : rest) {
      if (c != '.' && (c < '0' || c > '9')) return std::nullopt;
    }
  } catch (const std::exception&) {
    return std::nullopt;
  }
  if (dot != '.' || v.major < 0 || v.minor < 0 || v.major > 255 || v.minor > 255) {
    return std::nullopt;
  }
  return v;
}

Packet DecodePacket(const uint8_t* data, size_t size) {
  if (size < kHeaderBytes) {
    throw NatNetError("datagram of " + std::to_string(size) + " bytes is shorter than a header");
  }
  Packet p;
  uint16_t n = 0;
  std::memcpy(&p.id, data, 2);
  std::memcpy(&n, data + 2, 2);
  if (size != n + kHeaderBytes) {
    throw NatNetError("message " + std::to_string(p.id) + ": datagram of " + std::to_string(size) +
                      " bytes, header says " + std::to_string(n) + " + 4 (truncated or padded)");
  }
  p.payload.assign(data + kHeaderBytes, data + size);
  return p;
}

std::vector<uint8_t> EncodePacket(uint16_t id, const std::vector<uint8_t>& payload) {
  if (payload.size() > kMaxPayloadBytes) {
    throw NatNetError("message " + std::to_string(id) + ": payload of " +
                      std::to_string(payload.size()) + " bytes exceeds " +
                      std::to_string(kMaxPayloadBytes));
  }
  Writer w;
  w.Put(id);
  w.Put(static_cast<uint16_t>(payload.size()));
  w.out.insert(w.out.end(), payload.begin(), payload.end());
  return w.out;
}

ServerInfo DecodeServerInfo(const std::vector<uint8_t>& payload) {
  Reader r(payload, "NAT_SERVERINFO");
  if (payload.size() != kServerInfoBytes) {
    r.Fail("size", std::to_string(payload.size()) + " bytes, a NatNet 3.0+ server sends " +
                       std::to_string(kServerInfoBytes));
  }
  ServerInfo s;
  r.Need(256, "application name");
  const char* name = reinterpret_cast<const char*>(payload.data());
  s.app_name.assign(name, strnlen(name, 256));
  r.Skip(256, "application name");
  for (auto& b : s.app_version) b = r.Get<uint8_t>("application version");
  for (auto& b : s.natnet_version) b = r.Get<uint8_t>("NatNet version");
  s.clock_frequency_hz = r.Get<uint64_t>("clock frequency");
  s.data_port = r.Get<uint16_t>("data port");
  s.multicast = r.Get<uint8_t>("is multicast") != 0;
  for (auto& b : s.multicast_group) b = r.Get<uint8_t>("multicast group");
  r.End();
  return s;
}

std::vector<uint8_t> EncodeServerInfo(const ServerInfo& s) {
  Writer w;
  w.out.resize(256, 0);
  std::memcpy(w.out.data(), s.app_name.data(), std::min<size_t>(s.app_name.size(), 255));
  for (uint8_t b : s.app_version) w.Put(b);
  for (uint8_t b : s.natnet_version) w.Put(b);
  w.Put(s.clock_frequency_hz);
  w.Put(s.data_port);
  w.Put<uint8_t>(s.multicast ? 1 : 0);
  for (uint8_t b : s.multicast_group) w.Put(b);
  return w.out;
}

std::vector<uint8_t> EncodeConnect(const std::string& client_name,
                                   std::optional<Version> bitstream) {
  // sSender (name[256], app version[4], NatNet version[4]), then sConnectionOptions
  // (subscribedDataOnly, BitstreamVersion[4]) and 4 spare bytes: 273 bytes, as the 4.x
  // PacketClient sends it.
  std::vector<uint8_t> p(273, 0);
  std::memcpy(p.data(), client_name.data(), std::min<size_t>(client_name.size(), 255));
  p[256] = 4;
  p[257] = 1;
  p[260] = 4;
  p[261] = 1;
  if (bitstream) {
    p[265] = static_cast<uint8_t>(bitstream->major);
    p[266] = static_cast<uint8_t>(bitstream->minor);
  }
  return p;
}

std::optional<Version> DecodeConnectRequest(const std::vector<uint8_t>& payload) {
  // The bitstream version sits at 265..268 in the 269-, 271- and 273-byte variants; the
  // shorter ones (0, 5 "Ping", 264 sSender only) ask for nothing.
  if (payload.size() < 269) return std::nullopt;
  if (payload[265] == 0 && payload[266] == 0) return std::nullopt;
  return Version{payload[265], payload[266]};
}

std::vector<uint8_t> EncodeString(const std::string& text) {
  std::vector<uint8_t> p(text.begin(), text.end());
  p.push_back(0);
  return p;
}

std::string DecodeString(const std::vector<uint8_t>& payload) {
  const char* s = reinterpret_cast<const char*>(payload.data());
  return std::string(s, strnlen(s, payload.size()));
}

std::vector<uint8_t> EncodeEchoResponse(const Echo& e) {
  Writer w;
  w.Put(e.request_time);
  w.Put(e.server_ticks);
  return w.out;
}

Echo DecodeEchoResponse(const std::vector<uint8_t>& payload) {
  Reader r(payload, "NAT_ECHORESPONSE");
  Echo e;
  e.request_time = r.Get<uint64_t>("request time");
  e.server_ticks = r.Get<uint64_t>("server ticks");
  r.End();
  return e;
}

Descriptions DecodeDescriptions(const std::vector<uint8_t>& payload, Version v) {
  CheckVersion(v, "NAT_MODELDEF");
  Reader r(payload, "NAT_MODELDEF (NatNet " + v.ToString() + ")");
  Descriptions d;
  const int32_t n = r.Count("description count");
  for (int32_t i = 0; i < n; ++i) {
    const std::string where = "description " + std::to_string(i);
    const int32_t type = r.Get<int32_t>(where + " type");
    std::optional<size_t> size;
    if (v.AtLeast(4, 1)) {
      const int32_t bytes = r.Get<int32_t>(where + " byte count");
      if (bytes < 0 || static_cast<size_t>(bytes) > r.left()) {
        r.Fail(where + " byte count",
               std::to_string(bytes) + " with " + std::to_string(r.left()) + " bytes left");
      }
      size = static_cast<size_t>(bytes);
    }
    const size_t start = r.at();
    switch (type) {
      case 0: {
        MarkerSetDescription m;
        m.name = r.CString(where + " marker set name");
        const int32_t k = r.Count(where + " marker count");
        for (int32_t j = 0; j < k; ++j) m.marker_names.push_back(r.CString(where + " marker name"));
        d.marker_sets.push_back(std::move(m));
        break;
      }
      case 1:
        d.rigid_bodies.push_back(ReadRigidBodyDescription(r, v, where + " (rigid body)"));
        break;
      case 2: {
        SkeletonDescription s;
        s.name = r.CString(where + " skeleton name");
        s.id = r.Get<int32_t>(where + " skeleton id");
        const int32_t bones = r.Count(where + " bone count");
        for (int32_t j = 0; j < bones; ++j) {
          s.bones.push_back(ReadBone(r, v, where + " bone " + std::to_string(j)));
        }
        d.skeletons.push_back(std::move(s));
        break;
      }
      default:
        ++d.other;
        if (size) {
          r.Skip(*size, where + " (type " + std::to_string(type) + ")");
        } else {
          ReadOtherDescription(r, v, type, where);
        }
        break;
    }
    if (size && r.at() - start != *size) {
      r.Fail(where, "type " + std::to_string(type) + " body took " +
                        std::to_string(r.at() - start) + " bytes, its byte count says " +
                        std::to_string(*size));
    }
  }
  r.End();
  return d;
}

std::vector<uint8_t> EncodeDescriptions(const Descriptions& d, Version v) {
  CheckVersion(v, "NAT_MODELDEF");
  Writer w;
  w.Count(d.marker_sets.size() + d.rigid_bodies.size() + d.skeletons.size());
  auto one = [&](int32_t type, const std::function<void()>& body) {
    w.Put(type);
    size_t mark = 0;
    if (v.AtLeast(4, 1)) mark = w.Placeholder();
    body();
    if (v.AtLeast(4, 1)) w.Patch(mark);
  };
  for (const auto& m : d.marker_sets) {
    one(0, [&] {
      w.CString(m.name);
      w.Count(m.marker_names.size());
      for (const auto& name : m.marker_names) w.CString(name);
    });
  }
  for (const auto& rb : d.rigid_bodies) one(1, [&] { WriteRigidBodyDescription(w, v, rb); });
  for (const auto& s : d.skeletons) {
    one(2, [&] {
      w.CString(s.name);
      w.Put(s.id);
      w.Count(s.bones.size());
      for (const auto& b : s.bones) WriteBone(w, v, b);
    });
  }
  return w.out;
}

FrameOfData DecodeFrame(const std::vector<uint8_t>& payload, Version v) {
  CheckVersion(v, "NAT_FRAMEOFDATA");
  Reader r(payload, "NAT_FRAMEOFDATA (NatNet " + v.ToString() + ")");
  FrameOfData f;
  f.frame_number = r.Get<int32_t>("frame number");
  ReadSection<MarkerSetData>(r, v, "marker set", f.marker_sets,
                             [](Reader& r, const std::string& w) {
                               MarkerSetData m;
                               m.name = r.CString(w + " name");
                               const int32_t n = r.Count(w + " marker count");
                               r.Need(static_cast<size_t>(n) * 12, w + " markers");
                               for (int32_t i = 0; i < n; ++i) m.markers.push_back(r.Vec3(w));
                               return m;
                             });
  ReadSection<Vec3f>(r, v, "unlabeled marker", f.other_markers,
                     [](Reader& r, const std::string& w) { return r.Vec3(w); });
  ReadSection<RigidBodyData>(r, v, "rigid body", f.rigid_bodies, ReadRigidBody);
  ReadSection<SkeletonData>(r, v, "skeleton", f.skeletons, [](Reader& r, const std::string& w) {
    SkeletonData s;
    s.id = r.Get<int32_t>(w + " id");
    const int32_t n = r.Count(w + " bone count");
    for (int32_t i = 0; i < n; ++i) s.bones.push_back(ReadRigidBody(r, w + " bone"));
    return s;
  });
  if (v.AtLeast(4, 1)) {
    ReadSection<AssetData>(r, v, "asset", f.assets, [](Reader& r, const std::string& w) {
      AssetData a;
      a.id = r.Get<int32_t>(w + " id");
      const int32_t nrb = r.Count(w + " rigid body count");
      for (int32_t i = 0; i < nrb; ++i) {
        AssetRigidBody b;
        b.id = r.Get<int32_t>(w + " rigid body id");
        b.position = r.Vec3(w + " rigid body position");
        b.orientation = r.Quat(w + " rigid body orientation");
        b.mean_error = r.Get<float>(w + " rigid body error");
        b.params = r.Get<int16_t>(w + " rigid body params");
        a.rigid_bodies.push_back(b);
      }
      const int32_t nm = r.Count(w + " marker count");
      for (int32_t i = 0; i < nm; ++i) {
        AssetMarker m;
        m.id = r.Get<int32_t>(w + " marker id");
        m.position = r.Vec3(w + " marker position");
        m.size = r.Get<float>(w + " marker size");
        m.params = r.Get<int16_t>(w + " marker params");
        m.residual = r.Get<float>(w + " marker residual");
        a.markers.push_back(m);
      }
      return a;
    });
  }
  ReadSection<LabeledMarker>(r, v, "labeled marker", f.labeled_markers,
                             [](Reader& r, const std::string& w) {
                               LabeledMarker m;
                               m.id = r.Get<int32_t>(w + " id");
                               m.position = r.Vec3(w + " position");
                               m.size = r.Get<float>(w + " size");
                               m.params = r.Get<int16_t>(w + " params");
                               m.residual = r.Get<float>(w + " residual");
                               return m;
                             });
  ReadSection<AnalogData>(r, v, "force plate", f.force_plates, ReadAnalog);
  ReadSection<AnalogData>(r, v, "device", f.devices, ReadAnalog);
  f.timecode = r.Get<uint32_t>("timecode");
  f.timecode_subframe = r.Get<uint32_t>("timecode subframe");
  f.timestamp_s = r.Get<double>("timestamp");
  f.mid_exposure_ticks = r.Get<uint64_t>("mid-exposure ticks");
  f.data_received_ticks = r.Get<uint64_t>("data-received ticks");
  f.transmit_ticks = r.Get<uint64_t>("transmit ticks");
  if (v.AtLeast(4, 1)) {
    f.precision_s = r.Get<uint32_t>("precision timestamp seconds");
    f.precision_fraction = r.Get<uint32_t>("precision timestamp fraction");
  }
  f.params = r.Get<int16_t>("frame params");
  const int32_t tag = r.Get<int32_t>("end-of-data tag");
  if (tag != 0) r.Fail("end-of-data tag", "is " + std::to_string(tag) + ", not 0");
  r.End();
  return f;
}

std::vector<uint8_t> EncodeFrame(const FrameOfData& f, Version v) {
  CheckVersion(v, "NAT_FRAMEOFDATA");
  Writer w;
  w.Put(f.frame_number);
  WriteSection<MarkerSetData>(w, v, f.marker_sets, [](Writer& w, const MarkerSetData& m) {
    w.CString(m.name);
    w.Count(m.markers.size());
    for (const auto& p : m.markers) w.Vec3(p);
  });
  WriteSection<Vec3f>(w, v, f.other_markers, [](Writer& w, const Vec3f& p) { w.Vec3(p); });
  WriteSection<RigidBodyData>(w, v, f.rigid_bodies, WriteRigidBody);
  WriteSection<SkeletonData>(w, v, f.skeletons, [](Writer& w, const SkeletonData& s) {
    w.Put(s.id);
    w.Count(s.bones.size());
    for (const auto& b : s.bones) WriteRigidBody(w, b);
  });
  if (v.AtLeast(4, 1)) {
    WriteSection<AssetData>(w, v, f.assets, [](Writer& w, const AssetData& a) {
      w.Put(a.id);
      w.Count(a.rigid_bodies.size());
      for (const auto& b : a.rigid_bodies) {
        w.Put(b.id);
        w.Vec3(b.position);
        w.Quat(b.orientation);
        w.Put(b.mean_error);
        w.Put(b.params);
      }
      w.Count(a.markers.size());
      for (const auto& m : a.markers) {
        w.Put(m.id);
        w.Vec3(m.position);
        w.Put(m.size);
        w.Put(m.params);
        w.Put(m.residual);
      }
    });
  }
  WriteSection<LabeledMarker>(w, v, f.labeled_markers, [](Writer& w, const LabeledMarker& m) {
    w.Put(m.id);
    w.Vec3(m.position);
    w.Put(m.size);
    w.Put(m.params);
    w.Put(m.residual);
  });
  WriteSection<AnalogData>(w, v, f.force_plates, WriteAnalog);
  WriteSection<AnalogData>(w, v, f.devices, WriteAnalog);
  w.Put(f.timecode);
  w.Put(f.timecode_subframe);
  w.Put(f.timestamp_s);
  w.Put(f.mid_exposure_ticks);
  w.Put(f.data_received_ticks);
  w.Put(f.transmit_ticks);
  if (v.AtLeast(4, 1)) {
    w.Put(f.precision_s);
    w.Put(f.precision_fraction);
  }
  w.Put(f.params);
  w.Put<int32_t>(0);
  return w.out;
}

std::optional<int16_t> PeekFrameParams(const std::vector<uint8_t>& payload) {
  if (payload.size() < 6) return std::nullopt;
  int16_t params = 0;
  std::memcpy(&params, payload.data() + payload.size() - 6, 2);
  return params;
}

}  // namespace ftcal::natnet
