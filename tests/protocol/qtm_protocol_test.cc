// QTM RT codec against hand-built packets laid out from docs/device-protocols.md §3.2/§3.6
// (little-endian port) and a parameters reply in the documented ≥ 1.21 layout.
#include "qtm_protocol.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <fstream>
#include <sstream>

namespace ftcal::qtm {
namespace {

using Bytes = std::vector<std::uint8_t>;

// Data packet with one 3D component, every byte written out (offsets in the packet):
//   0 size 64 | 4 type 3 | 8 timestamp i64 = 2^32 + 2 us | 16 frame 7 | 20 component count 1
//  24 component size 40 | 28 component type 1 (3D) | 32 marker count 2 | 36 drop 5 | 38 out of sync
//  0 40 marker 1: 1.0f (00 00 80 3F), -2.5f (00 00 20 C0), 100.0f (00 00 C8 42) 52 marker 2: not
//  seen, every bit set (FF FF FF FF) x 3
const Bytes k3DPacket = {
    0x40, 0x00, 0x00, 0x00, 0x03, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00,
    0x07, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 0x28, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00,
    0x02, 0x00, 0x00, 0x00, 0x05, 0x00, 0x00, 0x00, 0x00, 0x00, 0x80, 0x3F, 0x00, 0x00, 0x20, 0xC0,
    0x00, 0x00, 0xC8, 0x42, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF};

Packet DeframeOne(const Bytes& bytes) {
  Deframer d;
  d.Feed(bytes.data(), bytes.size());
  auto p = d.Next();
  EXPECT_TRUE(p.has_value());
  EXPECT_EQ(d.buffered(), 0u);
  return p ? *p : Packet{};
}

TEST(QtmData, HandBuilt3DWithUntrackedMarker) {
  const Packet p = DeframeOne(k3DPacket);
  EXPECT_TRUE(p.is(PacketType::kData));
  const DataFrame f = DecodeData(p);
  EXPECT_EQ(f.timestamp_us, 4294967298LL);
  EXPECT_EQ(f.frame_number, 7);
  ASSERT_TRUE(f.has_markers);
  EXPECT_FALSE(f.markers_have_residuals);
  EXPECT_FALSE(f.has_bodies);
  EXPECT_EQ(f.markers_drop_rate_permille, 5);
  ASSERT_EQ(f.markers.size(), 2u);
  EXPECT_TRUE(f.markers[0].tracked());
  EXPECT_EQ(f.markers[0].p_GoM_G_mm, Eigen::Vector3d(1.0, -2.5, 100.0));
  EXPECT_TRUE(std::isnan(f.markers[0].residual_mm));
  EXPECT_FALSE(f.markers[1].tracked());
  EXPECT_TRUE(std::isnan(f.markers[1].p_GoM_G_mm.x()));
  // The encoder produces exactly these bytes.
  EXPECT_EQ(EncodeData(f).size(), k3DPacket.size());
  Bytes encoded = EncodeData(f);
  // NaN payload bits are not preserved through double; compare all but the untracked marker.
  EXPECT_EQ(Bytes(encoded.begin(), encoded.begin() + 52),
            Bytes(k3DPacket.begin(), k3DPacket.begin() + 52));
}

// Little-endian writers for the layouts below; each call is one field of the tables in §3.6.
struct Writer {
  Bytes b;
  void I32(std::int32_t v) {
    for (int i = 0; i < 4; ++i)
      b.push_back(static_cast<std::uint8_t>(static_cast<std::uint32_t>(v) >> (8 * i)));
  }
  void U16(std::uint16_t v) {
    b.push_back(v & 0xFF);
    b.push_back(v >> 8);
  }
  void I64(std::int64_t v) {
    I32(static_cast<std::int32_t>(v));
    I32(static_cast<std::int32_t>(static_cast<std::uint64_t>(v) >> 32));
  }
  void F32(float f) {
    std::uint32_t u;
    std::memcpy(&u, &f, 4);
    I32(static_cast<std::int32_t>(u));
  }
  void Nan() { I32(-1); }  // FF FF FF FF
  // Patch the i32 at `offset` (sizes known only at the end).
  void PatchI32(std::size_t offset, std::int32_t v) {
    for (int i = 0; i < 4; ++i)
      b[offset + i] = static_cast<std::uint8_t>(static_cast<std::uint32_t>(v) >> (8 * i));
  }
};

// Data packet: 6DRes with two bodies (the second untracked), then 3DRes with one marker:
//   header: size, 3, timestamp 1,000,000, frame 123, 2 components
//   6DRes: size 16 + 2*52, type 11, count 2, drop 0, oos 3,
//          body 1: x y z = 10, 20, 30 mm; rotation 90 deg about z, sent column-major
//                  r11 r21 r31 r12 r22 r32 r13 r23 r33 = 0 1 0 -1 0 0 0 0 1; residual 0.75
//          body 2: 12 x NaN, residual NaN
//   3DRes: size 16 + 16, type 9, count 1, drop 1, oos 2, marker (-1, -2, -3) residual 0.5
Bytes Build6DResAnd3DResPacket() {
  Writer w;
  w.I32(0);  // size, patched
  w.I32(3);
  w.I64(1000000);
  w.I32(123);
  w.I32(2);
  w.I32(16 + 2 * 52);
  w.I32(11);
  w.I32(2);
  w.U16(0);
  w.U16(3);
  for (float v : {10.f, 20.f, 30.f, 0.f, 1.f, 0.f, -1.f, 0.f, 0.f, 0.f, 0.f, 1.f, 0.75f}) w.F32(v);
  for (int i = 0; i < 13; ++i) w.Nan();
  w.I32(16 + 16);
  w.I32(9);
  w.I32(1);
  w.U16(1);
  w.U16(2);
  for (float v : {-1.f, -2.f, -3.f, 0.5f}) w.F32(v);
  w.PatchI32(0, static_cast<std::int32_t>(w.b.size()));
  return w.b;
}

TEST(QtmData, SixDResColumnMajorAndUntrackedBody) {
  const Bytes bytes = Build6DResAnd3DResPacket();
  ASSERT_EQ(bytes.size(), 8u + 16 + 120 + 32);
  const DataFrame f = DecodeData(DeframeOne(bytes));
  EXPECT_EQ(f.timestamp_us, 1000000);
  EXPECT_EQ(f.frame_number, 123);
  ASSERT_TRUE(f.has_bodies);
  EXPECT_TRUE(f.bodies_have_residuals);
  EXPECT_EQ(f.bodies_out_of_sync_permille, 3);
  ASSERT_EQ(f.bodies.size(), 2u);
  const Body& b = f.bodies[0];
  EXPECT_TRUE(b.tracked());
  EXPECT_EQ(b.p_GoBo_G_mm, Eigen::Vector3d(10, 20, 30));
  Eigen::Matrix3d rz90;
  rz90 << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  EXPECT_EQ(b.R_GB, rz90);
  // Body x axis points along global y.
  EXPECT_EQ(b.R_GB * Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY());
  EXPECT_DOUBLE_EQ(b.residual_mm, 0.75);
  EXPECT_FALSE(f.bodies[1].tracked());
  EXPECT_TRUE(std::isnan(f.bodies[1].R_GB(2, 2)));
  ASSERT_TRUE(f.has_markers);
  EXPECT_TRUE(f.markers_have_residuals);
  EXPECT_EQ(f.markers_drop_rate_permille, 1);
  ASSERT_EQ(f.markers.size(), 1u);
  EXPECT_EQ(f.markers[0].p_GoM_G_mm, Eigen::Vector3d(-1, -2, -3));
  EXPECT_DOUBLE_EQ(f.markers[0].residual_mm, 0.5);
}

TEST(QtmData, EncodeDecodeRoundTrip6D) {
  DataFrame f;
  f.timestamp_us = -5;
  f.frame_number = 99;
  f.has_bodies = true;
  Body b;
  b.p_GoBo_G_mm = {1.5, -2.25, 3.0};
  b.R_GB << 0, 0, 1, 1, 0, 0, 0, 1, 0;
  f.bodies = {b, Body{}};
  const DataFrame g = DecodeData(DeframeOne(EncodeData(f)));
  ASSERT_EQ(g.bodies.size(), 2u);
  EXPECT_FALSE(g.bodies_have_residuals);
  EXPECT_EQ(g.bodies[0].R_GB, b.R_GB);
  EXPECT_EQ(g.bodies[0].p_GoBo_G_mm, b.p_GoBo_G_mm);
  EXPECT_FALSE(g.bodies[1].tracked());
  EXPECT_FALSE(g.has_markers);
  EXPECT_EQ(g.timestamp_us, -5);
}

TEST(QtmData, UnknownComponentSkippedBySize) {
  Writer w;
  w.I32(0);
  w.I32(3);
  w.I64(0);
  w.I32(1);
  w.I32(2);
  w.I32(8 + 5);  // an Analog-like component (type 3) of 5 payload bytes
  w.I32(3);
  for (int i = 0; i < 5; ++i) w.b.push_back(0xAB);
  w.I32(16);  // an empty 3D component
  w.I32(1);
  w.I32(0);
  w.U16(0);
  w.U16(0);
  w.PatchI32(0, static_cast<std::int32_t>(w.b.size()));
  const DataFrame f = DecodeData(DeframeOne(w.b));
  EXPECT_EQ(f.skipped_component_types, std::vector<std::int32_t>{3});
  EXPECT_TRUE(f.has_markers);
  EXPECT_TRUE(f.markers.empty());
}

void ExpectDataRefused(const Bytes& bytes, const std::string& needle) {
  Packet p;
  p.type = 3;
  p.payload.assign(bytes.begin() + 8, bytes.end());
  try {
    DecodeData(p);
    ADD_FAILURE() << "accepted; expected an error mentioning '" << needle << "'";
  } catch (const QtmError& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

TEST(QtmData, MalformedComponentsRefused) {
  Bytes b = k3DPacket;
  b[24] = 0x29;  // component size 41: overruns the packet
  ExpectDataRefused(b, "size 41");
  b = k3DPacket;
  b[24] = 0x07;  // component size 7 < 8
  ExpectDataRefused(b, "size 7");
  b = k3DPacket;
  b[32] = 0x03;  // 3 markers claimed, room for 2
  ExpectDataRefused(b, "3 items");
  b = k3DPacket;
  b[32] = 0xFF;
  b[33] = 0xFF;
  b[34] = 0xFF;
  b[35] = 0x7F;  // absurd count: must not wrap into a plausible size
  ExpectDataRefused(b, "items");
  b = k3DPacket;
  b[20] = 0x02;  // two components claimed, one present
  ExpectDataRefused(b, "component 2/2");
  b = k3DPacket;
  b[20] = 0x00;  // zero components: the 3D bytes are left over
  ExpectDataRefused(b, "bytes after");
  b = Bytes(k3DPacket.begin(), k3DPacket.begin() + 20);  // header cut short
  ExpectDataRefused(b, "needs 16");
}

TEST(QtmDeframer, PacketSplitAcrossReads) {
  Bytes stream = EncodeText(PacketType::kCommand, "QTM RT Interface connected.");
  const Bytes data = Build6DResAnd3DResPacket();
  stream.insert(stream.end(), data.begin(), data.end());
  const Bytes event = EncodePacket(6, {3});
  stream.insert(stream.end(), event.begin(), event.end());
  // Feed in pieces of 5 bytes: every header and payload is split somewhere.
  Deframer d;
  std::vector<Packet> got;
  for (std::size_t i = 0; i < stream.size(); i += 5) {
    d.Feed(stream.data() + i, std::min<std::size_t>(5, stream.size() - i));
    while (auto p = d.Next()) got.push_back(*p);
  }
  ASSERT_EQ(got.size(), 3u);
  EXPECT_TRUE(IsWelcome(DecodeText(got[0])));
  EXPECT_EQ(DecodeData(got[1]).frame_number, 123);
  EXPECT_EQ(DecodeEvent(got[2]), 3);
  EXPECT_EQ(EventName(3), "Capture Started");
  EXPECT_EQ(d.buffered(), 0u);
}

TEST(QtmDeframer, SeveralPacketsInOneRead) {
  Bytes stream;
  for (int i = 0; i < 4; ++i) {
    const Bytes p = EncodePacket(4, {});  // No More Data
    stream.insert(stream.end(), p.begin(), p.end());
  }
  Deframer d;
  d.Feed(stream.data(), stream.size());
  int n = 0;
  while (auto p = d.Next()) {
    EXPECT_TRUE(p->is(PacketType::kNoMoreData));
    EXPECT_TRUE(p->payload.empty());
    ++n;
  }
  EXPECT_EQ(n, 4);
}

TEST(QtmDeframer, BadSizesAreFatal) {
  Deframer d;
  const Bytes small = {0x07, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00};
  d.Feed(small.data(), small.size());
  EXPECT_THROW(d.Next(), QtmError);
  EXPECT_THROW(d.Next(), QtmError);  // stays failed
  d.Reset();
  const Bytes ok = EncodeCommand("Version 1.25");
  d.Feed(ok.data(), ok.size());
  EXPECT_TRUE(d.Next());

  Deframer big(1 << 20);
  const Bytes huge = {0x00, 0x00, 0x00, 0x10, 0x03, 0x00, 0x00, 0x00};  // 256 MiB
  big.Feed(huge.data(), huge.size());
  try {
    big.Next();
    ADD_FAILURE() << "accepted a 256 MiB packet";
  } catch (const QtmError& e) {
    EXPECT_NE(std::string(e.what()).find("268435456"), std::string::npos) << e.what();
  }
  Deframer neg;
  const Bytes negative = {0xFF, 0xFF, 0xFF, 0xFF, 0x01, 0x00, 0x00, 0x00};
  neg.Feed(negative.data(), negative.size());
  EXPECT_THROW(neg.Next(), QtmError);
}

TEST(QtmCommands, CommandBytesAndText) {
  // size 8 + 12 + NUL = 21, type 1, "Version 1.25", 00.
  const Bytes expected = {0x15, 0x00, 0x00, 0x00, 0x01, 0x00, 0x00, 0x00, 'V', 'e', 'r',
                          's',  'i',  'o',  'n',  ' ',  '1',  '.',  '2',  '5', 0x00};
  EXPECT_EQ(EncodeCommand("Version 1.25"), expected);
  EXPECT_THROW(EncodeCommand(std::string("a\0b", 3)), QtmError);
  Packet reply;
  reply.type = 1;
  const std::string text = "Version set to 1.25";
  reply.payload.assign(text.begin(), text.end());  // without the NUL: still fine
  EXPECT_TRUE(IsVersionAccepted(DecodeText(reply), "1.25"));
  EXPECT_FALSE(IsVersionAccepted("Version NOT supported", "1.25"));
  Packet error;
  error.type = 0;
  const std::string parse = "Parse Error";
  error.payload.assign(parse.begin(), parse.end());
  error.payload.push_back(0);
  error.payload.push_back('x');  // bytes after the NUL are not text
  EXPECT_EQ(DecodeText(error), "Parse Error");
  Packet data;
  data.type = 3;
  EXPECT_THROW(DecodeText(data), QtmError);
}

TEST(QtmCommands, WelcomePrefix) {
  EXPECT_TRUE(IsWelcome("QTM RT Interface connected"));
  EXPECT_TRUE(IsWelcome("QTM RT Interface connected."));
  EXPECT_FALSE(IsWelcome("QTM RT Interface"));
  EXPECT_FALSE(IsWelcome("Connection refused. Max number of clients reached."));
}

TEST(QtmEvents, SizeChecked) {
  EXPECT_EQ(DecodeEvent(Packet{6, {11}}), kEventCameraSettingsChanged);
  EXPECT_THROW(DecodeEvent(Packet{6, {}}), QtmError);
  EXPECT_THROW(DecodeEvent(Packet{6, {1, 2}}), QtmError);
  EXPECT_THROW(DecodeEvent(Packet{1, {1}}), QtmError);
  EXPECT_EQ(EventName(200), "event 200");
}

std::string ReadFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream os;
  os << in.rdbuf();
  return os.str();
}

TEST(QtmParameters, BodiesAndLabelsInOrder) {
  const std::string xml = ReadFile(std::string(FTCAL_PROTOCOL_TEST_DATA) + "/qtm_parameters.xml");
  ASSERT_FALSE(xml.empty());
  const Parameters p = ParseParameters(xml);
  ASSERT_TRUE(p.frequency_hz.has_value());
  EXPECT_EQ(*p.frequency_hz, 100.0);
  EXPECT_TRUE(p.has_6d);
  EXPECT_EQ(p.body_names, (std::vector<std::string>{"wand", "chassis"}));
  EXPECT_TRUE(p.has_3d);
  EXPECT_EQ(p.labels_3d,
            (std::vector<std::string>{"chassis_fl", "chassis_fr", "chassis_hl", "chassis_hr"}));
}

void ExpectXmlRefused(const std::string& xml, const std::string& needle) {
  try {
    ParseParameters(xml);
    ADD_FAILURE() << "accepted; expected an error mentioning '" << needle << "'";
  } catch (const QtmError& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

TEST(QtmParameters, BadDocumentsRefused) {
  ExpectXmlRefused("<QTM_Parameters_Ver_1.25><The_6D>", "malformed XML");
  ExpectXmlRefused("<Parameters/>", "root element <Parameters>");
  // Protocol 1.20 layout.
  ExpectXmlRefused(
      "<QTM_Parameters_Ver_1.20><The_6D><Bodies>1</Bodies><Body><Name>a</Name></Body>"
      "</The_6D></QTM_Parameters_Ver_1.20>",
      "1.21");
  ExpectXmlRefused(
      "<QTM_Parameters_Ver_1.25><The_6D><Body><Name>a</Name></Body><Body><Name>a</Name></Body>"
      "</The_6D></QTM_Parameters_Ver_1.25>",
      "duplicate name 'a'");
  ExpectXmlRefused(
      "<QTM_Parameters_Ver_1.25><The_6D><Body><Enabled>true</Enabled></Body></The_6D>"
      "</QTM_Parameters_Ver_1.25>",
      "6D body 1 has no <Name>");
  ExpectXmlRefused(
      "<QTM_Parameters_Ver_1.25><The_3D><Labels>2</Labels><Label><Name>m</Name></Label>"
      "</The_3D></QTM_Parameters_Ver_1.25>",
      "Labels");
  ExpectXmlRefused(
      "<QTM_Parameters_Ver_1.25><General><Frequency>fast</Frequency></General>"
      "</QTM_Parameters_Ver_1.25>",
      "Frequency");
}

TEST(QtmParameters, SectionsAbsent) {
  const Parameters p = ParseParameters("<QTM_Parameters_Ver_1.25/>");
  EXPECT_FALSE(p.has_6d);
  EXPECT_FALSE(p.has_3d);
  EXPECT_FALSE(p.frequency_hz);
}

}  // namespace
}  // namespace ftcal::qtm
