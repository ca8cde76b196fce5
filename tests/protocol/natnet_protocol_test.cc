// NatNet codec against packets written field by field from docs/natnet-protocol.md (§2.2,
// §2.3, §3, §4): the byte layouts below come from the tables there, not from the encoder, so
// an encoder and decoder that agreed on a wrong layout would fail here.
#include "natnet_protocol.h"

#include <gtest/gtest.h>

#include <cstring>
#include <functional>

namespace ftcal::natnet {
namespace {

using Bytes = std::vector<uint8_t>;

// Little-endian field writer; each call is one row of a table in docs/natnet-protocol.md.
struct Fields {
  Bytes b;
  void U8(uint8_t v) { b.push_back(v); }
  void U16(uint16_t v) {
    U8(v & 0xFF);
    U8(v >> 8);
  }
  void I16(int16_t v) { U16(static_cast<uint16_t>(v)); }
  void I32(int32_t v) {
    for (int i = 0; i < 4; ++i) U8(static_cast<uint8_t>(static_cast<uint32_t>(v) >> (8 * i)));
  }
  void U64(uint64_t v) {
    for (int i = 0; i < 8; ++i) U8(static_cast<uint8_t>(v >> (8 * i)));
  }
  void F32(float f) {
    uint32_t u;
    std::memcpy(&u, &f, 4);
    I32(static_cast<int32_t>(u));
  }
  void F64(double d) {
    uint64_t u;
    std::memcpy(&u, &d, 8);
    U64(u);
  }
  void Str(const std::string& s) {
    b.insert(b.end(), s.begin(), s.end());
    U8(0);
  }
  size_t size() const { return b.size(); }
  // The i32 at `offset`, written once the bytes after it are known (4.1 byte counts).
  void PatchI32(size_t offset, int32_t v) {
    for (int i = 0; i < 4; ++i)
      b[offset + i] = static_cast<uint8_t>(static_cast<uint32_t>(v) >> (8 * i));
  }
};

constexpr Version k31{3, 1};
constexpr Version k41{4, 1};

// A frame with one rigid body (id 7, tracked) and two labeled markers, laid out per §4.1/§4.2/
// §4.4. With `v41` every section count is followed by its byte count and the suffix carries the
// two precision-timestamp words.
Bytes HandBuiltFrame(bool v41) {
  Fields f;
  auto section = [&](int32_t count, const std::function<void()>& records) {
    f.I32(count);
    size_t at = 0;
    if (v41) {
      at = f.size();
      f.I32(0);
    }
    const size_t start = f.size();
    records();
    if (v41) f.PatchI32(at, static_cast<int32_t>(f.size() - start));
  };
  f.I32(1234);        // frame number
  section(0, [] {});  // marker sets
  section(0, [] {});  // legacy unlabeled markers
  section(1, [&] {    // rigid bodies
    f.I32(7);
    f.F32(0.5f);
    f.F32(1.25f);
    f.F32(-2.0f);  // x y z, m
    f.F32(0.0f);
    f.F32(0.0f);
    f.F32(0.6f);
    f.F32(0.8f);     // qx qy qz qw
    f.F32(0.0004f);  // mean error
    f.I16(0x0001);   // params: tracked
  });
  section(0, [] {});           // skeletons
  if (v41) section(0, [] {});  // assets
  section(2, [&] {             // labeled markers
    f.I32((7 << 16) | 1);
    f.F32(0.1f);
    f.F32(0.2f);
    f.F32(0.3f);
    f.F32(0.014f);
    f.I16(0);
    f.F32(0.0002f);
    f.I32((7 << 16) | 2);
    f.F32(0.4f);
    f.F32(0.5f);
    f.F32(0.6f);
    f.F32(0.014f);
    f.I16(0x0001);
    f.F32(0.0f);
  });
  section(0, [] {});  // force plates
  section(0, [] {});  // devices
  f.I32(0x01020304);  // timecode
  f.I32(5);           // subframe
  f.F64(12.5);        // timestamp, s
  f.U64(1000);        // mid-exposure ticks
  f.U64(1500);        // data received
  f.U64(2500);        // transmit
  if (v41) {
    f.I32(0);
    f.I32(0);
  }
  f.I16(0x0002);  // params: model list changed
  f.I32(0);       // end-of-data tag
  return f.b;
}

void ExpectHandBuiltFrame(const FrameOfData& d) {
  EXPECT_EQ(d.frame_number, 1234);
  ASSERT_EQ(d.rigid_bodies.size(), 1u);
  const RigidBodyData& b = d.rigid_bodies[0];
  EXPECT_EQ(b.id, 7);
  EXPECT_EQ(b.position, (Vec3f{0.5f, 1.25f, -2.0f}));
  EXPECT_EQ(b.orientation, (Quatf{0.0f, 0.0f, 0.6f, 0.8f}));
  EXPECT_FLOAT_EQ(b.mean_error, 0.0004f);
  EXPECT_TRUE(b.tracked());
  ASSERT_EQ(d.labeled_markers.size(), 2u);
  EXPECT_EQ(d.labeled_markers[0].id, (7 << 16) | 1);
  EXPECT_FALSE(d.labeled_markers[0].occluded());
  EXPECT_EQ(d.labeled_markers[1].position, (Vec3f{0.4f, 0.5f, 0.6f}));
  EXPECT_TRUE(d.labeled_markers[1].occluded());
  EXPECT_EQ(d.timecode, 0x01020304u);
  EXPECT_EQ(d.timecode_subframe, 5u);
  EXPECT_EQ(d.timestamp_s, 12.5);
  EXPECT_EQ(d.mid_exposure_ticks, 1000u);
  EXPECT_EQ(d.data_received_ticks, 1500u);
  EXPECT_EQ(d.transmit_ticks, 2500u);
  EXPECT_TRUE(d.model_list_changed());
  EXPECT_FALSE(d.edit_mode());
}

TEST(NatNetFrame, HandBuilt31) {
  const Bytes p = HandBuiltFrame(false);
  ExpectHandBuiltFrame(DecodeFrame(p, k31));
  EXPECT_EQ(EncodeFrame(DecodeFrame(p, k31), k31), p);
}

TEST(NatNetFrame, HandBuilt41WithByteCounts) {
  const Bytes p = HandBuiltFrame(true);
  ExpectHandBuiltFrame(DecodeFrame(p, k41));
  EXPECT_EQ(EncodeFrame(DecodeFrame(p, k41), k41), p);
  // 4.0 has no byte counts: same bytes as 3.1 for this content.
  EXPECT_EQ(EncodeFrame(DecodeFrame(p, k41), Version{4, 0}), HandBuiltFrame(false));
}

TEST(NatNetFrame, ParamsPeekedFromTheSuffix) {
  EXPECT_EQ(PeekFrameParams(HandBuiltFrame(true)), std::optional<int16_t>(0x0002));
  EXPECT_EQ(PeekFrameParams(Bytes{1, 2, 3}), std::nullopt);
}

TEST(NatNetFrame, WrongVersionIsRefusedNotMisread) {
  // A 4.1 stream parsed as 3.1 and the reverse: never a frame (§6 "version mismatch").
  EXPECT_THROW(DecodeFrame(HandBuiltFrame(true), k31), NatNetError);
  EXPECT_THROW(DecodeFrame(HandBuiltFrame(false), k41), NatNetError);
}

TEST(NatNetFrame, SectionByteCountMustMatchItsRecords) {
  Bytes p = HandBuiltFrame(true);
  // Offsets: frame 0..3, marker sets 4..11, unlabeled 12..19, rigid-body count 20, bytes 24.
  int32_t bytes = 0;
  std::memcpy(&bytes, p.data() + 24, 4);
  ASSERT_EQ(bytes, 4 + 12 + 16 + 4 + 2);  // one rigid-body record, §4.2
  const int32_t wrong = bytes + 2;
  std::memcpy(p.data() + 24, &wrong, 4);
  try {
    DecodeFrame(p, k41);
    FAIL() << "a section whose records differ from its byte count was accepted";
  } catch (const NatNetError& e) {
    EXPECT_NE(std::string(e.what()).find("rigid body"), std::string::npos) << e.what();
  }
}

TEST(NatNetFrame, TruncatedOrPaddedOrBadTagRefused) {
  Bytes p = HandBuiltFrame(false);
  EXPECT_THROW(DecodeFrame(Bytes(p.begin(), p.end() - 1), k31), NatNetError);
  Bytes padded = p;
  padded.push_back(0);
  EXPECT_THROW(DecodeFrame(padded, k31), NatNetError);
  Bytes tag = p;
  tag.back() = 1;
  EXPECT_THROW(DecodeFrame(tag, k31), NatNetError);
  // A count far beyond the payload is refused before anything is allocated for it.
  Bytes huge = p;
  const int32_t n = 1 << 30;
  std::memcpy(huge.data() + 4, &n, 4);
  EXPECT_THROW(DecodeFrame(huge, k31), NatNetError);
}

TEST(NatNetFrame, OldVersionsRefused) {
  EXPECT_THROW(DecodeFrame(HandBuiltFrame(false), Version{2, 10}), NatNetError);
  EXPECT_TRUE(Supported(Version{3, 0}));
  EXPECT_TRUE(Supported(Version{4, 2}));
  EXPECT_FALSE(Supported(Version{2, 9}));
  EXPECT_FALSE(Supported(Version{5, 0}));
}

// NAT_MODELDEF: a marker set, a rigid body with two markers, and (4.1) an asset description
// the decoder must skip by its byte count (§3); with `rigid_body_first` the rigid body leads.
Bytes HandBuiltDescriptions(Version v, bool with_asset, bool rigid_body_first = false) {
  Fields f;
  f.I32(with_asset ? 3 : 2);
  auto description = [&](int32_t type, const std::function<void()>& body) {
    f.I32(type);
    size_t at = 0;
    const bool counted = v.AtLeast(4, 1);
    if (counted) {
      at = f.size();
      f.I32(0);
    }
    const size_t start = f.size();
    body();
    if (counted) f.PatchI32(at, static_cast<int32_t>(f.size() - start));
  };
  const auto marker_set = [&] {
    description(0, [&] {
      f.Str("chassis");
      f.I32(2);
      f.Str("Marker1");
      f.Str("Marker2");
    });
  };
  const auto asset = [&] {
    if (with_asset) {
      description(6, [&] {
        f.Str("trained");
        f.I32(1);
        f.I32(99);
        f.I32(0);
        f.I32(0);
      });
    }
  };
  const auto rigid_body = [&] {
    description(1, [&] {
      f.Str("chassis");
      f.I32(3);   // streaming id
      f.I32(-1);  // parent
      f.F32(0);
      f.F32(0);
      f.F32(0);  // offset
      if (v.AtLeast(4, 2)) {
        f.F32(0);
        f.F32(0);
        f.F32(0);
        f.F32(1);
      }
      f.I32(2);  // markers
      f.F32(0.1f);
      f.F32(0.0f);
      f.F32(0.0f);
      f.F32(0.0f);
      f.F32(0.2f);
      f.F32(0.0f);
      f.I32(0);
      f.I32(0);  // required active labels
      if (v.AtLeast(4, 0)) {
        f.Str("chassis_m01");
        f.Str("chassis_m02");
      }
    });
  };
  if (rigid_body_first) rigid_body();
  marker_set();
  asset();
  if (!rigid_body_first) rigid_body();
  return f.b;
}

TEST(NatNetDescriptions, HandBuilt41SkipsAnAssetByItsByteCount) {
  const Descriptions d = DecodeDescriptions(HandBuiltDescriptions(k41, true), k41);
  ASSERT_EQ(d.rigid_bodies.size(), 1u);
  EXPECT_EQ(d.rigid_bodies[0].name, "chassis");
  EXPECT_EQ(d.rigid_bodies[0].id, 3);
  EXPECT_EQ(d.rigid_bodies[0].parent_id, -1);
  ASSERT_EQ(d.rigid_bodies[0].marker_positions.size(), 2u);
  EXPECT_EQ(d.rigid_bodies[0].marker_positions[1], (Vec3f{0.0f, 0.2f, 0.0f}));
  EXPECT_EQ(d.rigid_bodies[0].marker_names,
            (std::vector<std::string>{"chassis_m01", "chassis_m02"}));
  ASSERT_EQ(d.marker_sets.size(), 1u);
  EXPECT_EQ(d.marker_sets[0].marker_names.size(), 2u);
  EXPECT_EQ(d.other, 1);
}

TEST(NatNetDescriptions, HandBuiltOtherVersionsRoundTrip) {
  for (Version v : {Version{3, 0}, Version{3, 1}, Version{4, 0}, Version{4, 1}, Version{4, 2}}) {
    const Bytes p = HandBuiltDescriptions(v, false);
    const Descriptions d = DecodeDescriptions(p, v);
    ASSERT_EQ(d.rigid_bodies.size(), 1u) << v.ToString();
    EXPECT_EQ(d.rigid_bodies[0].marker_names.size(), v.AtLeast(4, 0) ? 2u : 0u);
    EXPECT_EQ(EncodeDescriptions(d, v), p) << v.ToString();
  }
}

// Motive need not send the kinds in the order the encoder groups them (a rigid body before the
// marker sets, as one fuzz input had it): both are kept, and the encoding groups them.
TEST(NatNetDescriptions, RigidBodyBeforeMarkerSetDecodes) {
  for (Version v : {Version{3, 0}, Version{3, 1}, Version{4, 0}, Version{4, 1}, Version{4, 2}}) {
    const Descriptions d = DecodeDescriptions(HandBuiltDescriptions(v, false, true), v);
    ASSERT_EQ(d.rigid_bodies.size(), 1u) << v.ToString();
    EXPECT_EQ(d.rigid_bodies[0].name, "chassis") << v.ToString();
    EXPECT_EQ(d.rigid_bodies[0].id, 3) << v.ToString();
    ASSERT_EQ(d.marker_sets.size(), 1u) << v.ToString();
    EXPECT_EQ(d.marker_sets[0].marker_names.size(), 2u) << v.ToString();
    EXPECT_EQ(EncodeDescriptions(d, v), HandBuiltDescriptions(v, false)) << v.ToString();
  }
}

TEST(NatNetDescriptions, UnknownTypeWithoutByteCountStops) {
  Fields f;
  f.I32(1);
  f.I32(6);  // an asset in a 3.1 stream: no byte count to skip it by
  f.Str("x");
  EXPECT_THROW(DecodeDescriptions(f.b, k31), NatNetError);
}

TEST(NatNetDescriptions, ByteCountMismatchRefused) {
  Bytes p = HandBuiltDescriptions(k41, false);
  // Description 0 (marker set) byte count at offset 8: claim 2 bytes fewer.
  int32_t n = 0;
  std::memcpy(&n, p.data() + 8, 4);
  ASSERT_EQ(n, 8 + 4 + 8 + 8);  // "chassis\0", count, two names
  n -= 2;
  std::memcpy(p.data() + 8, &n, 4);
  EXPECT_THROW(DecodeDescriptions(p, k41), NatNetError);
}

TEST(NatNetPacket, HeaderLengthMustEqualDatagram) {
  const Bytes ok = {7, 0, 2, 0, 0xAA, 0xBB};
  const Packet p = DecodePacket(ok.data(), ok.size());
  EXPECT_EQ(p.id, kFrameOfData);
  EXPECT_EQ(p.payload, (Bytes{0xAA, 0xBB}));
  EXPECT_EQ(EncodePacket(kFrameOfData, p.payload), ok);
  const Bytes cut = {7, 0, 3, 0, 0xAA, 0xBB};
  EXPECT_THROW(DecodePacket(cut.data(), cut.size()), NatNetError);
  EXPECT_THROW(DecodePacket(ok.data(), 3), NatNetError);
  EXPECT_THROW(EncodePacket(kFrameOfData, Bytes(kMaxPayloadBytes + 1)), NatNetError);
}

TEST(NatNetServerInfo, HandBuilt279Bytes) {
  Fields f;
  f.b.resize(256, 0);
  std::memcpy(f.b.data(), "Motive", 6);
  f.U8(3);
  f.U8(1);
  f.U8(0);
  f.U8(0);  // app 3.1.0.0
  f.U8(4);
  f.U8(1);
  f.U8(0);
  f.U8(0);            // NatNet 4.1.0.0
  f.U64(10'000'000);  // 10 MHz
  f.U16(1511);
  f.U8(1);  // multicast
  f.U8(239);
  f.U8(255);
  f.U8(42);
  f.U8(99);
  ASSERT_EQ(f.size(), kServerInfoBytes);
  const ServerInfo s = DecodeServerInfo(f.b);
  EXPECT_EQ(s.app_name, "Motive");
  EXPECT_EQ(s.version(), k41);
  EXPECT_EQ(s.clock_frequency_hz, 10'000'000u);
  EXPECT_EQ(s.data_port, 1511);
  EXPECT_TRUE(s.multicast);
  EXPECT_EQ(s.multicast_group, (std::array<uint8_t, 4>{239, 255, 42, 99}));
  EXPECT_EQ(EncodeServerInfo(s), f.b);
  // A pre-3.0 server's 264 bytes are refused, not read as zeros.
  EXPECT_THROW(DecodeServerInfo(Bytes(f.b.begin(), f.b.begin() + 264)), NatNetError);
}

TEST(NatNetConnect, EveryVariantOfSection23) {
  EXPECT_EQ(DecodeConnectRequest({}), std::nullopt);
  EXPECT_EQ(DecodeConnectRequest({'P', 'i', 'n', 'g', 0}), std::nullopt);
  EXPECT_EQ(DecodeConnectRequest(Bytes(264, 0)), std::nullopt);
  Bytes lib44(269, 0);  // libNatNet 4.4 asking for 4.1 at 265..268
  lib44[265] = 4;
  lib44[266] = 1;
  EXPECT_EQ(DecodeConnectRequest(lib44), std::optional<Version>(k41));
  const Bytes ours = EncodeConnect("ftcal-natnet-bridge", Version{3, 1});
  EXPECT_EQ(ours.size(), 273u);
  EXPECT_EQ(DecodeConnectRequest(ours), std::optional<Version>(k31));
  EXPECT_EQ(DecodeConnectRequest(EncodeConnect("x", std::nullopt)), std::nullopt);
}

TEST(NatNetVersion, Parse) {
  EXPECT_EQ(ParseVersion("3.1"), std::optional<Version>(k31));
  EXPECT_EQ(ParseVersion("4.1.0.0"), std::optional<Version>(k41));
  EXPECT_EQ(ParseVersion("4"), std::nullopt);
  EXPECT_EQ(ParseVersion("x.1"), std::nullopt);
  EXPECT_EQ(ParseVersion("4.1a"), std::nullopt);
}

}  // namespace
}  // namespace ftcal::natnet
