// Dynamixel Protocol 2.0 codec against the worked examples of docs/device-protocols.md §2.3
// (e-Manual, ROBOTIS' SDKs) and hand-built byte streams.
#include "protocol2.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

namespace ftcal::dxl {
namespace {

using Bytes = std::vector<std::uint8_t>;

// The bitwise definition from §2.3, independent of the table the library uses.
std::uint16_t BitwiseCrc(const Bytes& data) {
  std::uint16_t r = 0;
  for (std::uint8_t b : data) {
    r ^= static_cast<std::uint16_t>(b << 8);
    for (int i = 0; i < 8; ++i)
      r = (r & 0x8000) ? static_cast<std::uint16_t>((r << 1) ^ 0x8005)
                       : static_cast<std::uint16_t>(r << 1);
  }
  return r;
}

TEST(DxlCrc, CatalogueCheckValue) {
  const char* check = "123456789";
  EXPECT_EQ(Crc16(reinterpret_cast<const std::uint8_t*>(check), 9), 0xFEE8);
  EXPECT_EQ(BitwiseCrc(Bytes(check, check + 9)), 0xFEE8);
}

TEST(DxlCrc, IncrementalEqualsWhole) {
  const Bytes data = {0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01};
  const std::uint16_t part = Crc16(data.data(), 3);
  EXPECT_EQ(Crc16(data.data() + 3, data.size() - 3, part), Crc16(data.data(), data.size()));
}

TEST(DxlPackets, PingId1) {
  EXPECT_EQ(BuildPing(1), (Bytes{0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x03, 0x00, 0x01, 0x19, 0x4E}));
}

TEST(DxlPackets, ReadPresentPositionId3) {
  EXPECT_EQ(BuildRead(3, 132, 4), (Bytes{0xFF, 0xFF, 0xFD, 0x00, 0x03, 0x07, 0x00, 0x02, 0x84, 0x00,
                                         0x04, 0x00, 0x11, 0x35}));
}

const Bytes kStatusPosition2048 = {0xFF, 0xFF, 0xFD, 0x00, 0x03, 0x08, 0x00, 0x55,
                                   0x00, 0x00, 0x08, 0x00, 0x00, 0xDF, 0xB4};

TEST(DxlPackets, StatusReplyPosition2048) {
  EXPECT_EQ(BuildStatus(3, 0, {0x00, 0x08, 0x00, 0x00}), kStatusPosition2048);
}

TEST(DxlPackets, SyncReadIds1To6) {
  EXPECT_EQ(BuildSyncRead(132, 4, {1, 2, 3, 4, 5, 6}),
            (Bytes{0xFF, 0xFF, 0xFD, 0x00, 0xFE, 0x0D, 0x00, 0x82, 0x84, 0x00,
                   0x04, 0x00, 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0xB2, 0x9B}));
}

const Bytes kSyncWriteGoal = {0xFF, 0xFF, 0xFD, 0x00, 0xFE, 0x11, 0x00, 0x83,
                              0x74, 0x00, 0x04, 0x00, 0x01, 0x00, 0x04, 0x00,
                              0x00, 0x02, 0x00, 0x0C, 0x00, 0x00, 0x13, 0x0C};

TEST(DxlPackets, SyncWriteGoalPosition) {
  EXPECT_EQ(BuildSyncWrite(116, 4, {{1, {0x00, 0x04, 0x00, 0x00}}, {2, {0x00, 0x0C, 0x00, 0x00}}}),
            kSyncWriteGoal);
  EXPECT_EQ(BuildSyncWriteGoalPosition({{1, 1024}, {2, 3072}}), kSyncWriteGoal);
}

TEST(DxlPackets, StuffedWrite) {
  EXPECT_EQ(BuildWrite(1, 224, {0xFF, 0xFF, 0xFD, 0x00}),
            (Bytes{0xFF, 0xFF, 0xFD, 0x00, 0x01, 0x0A, 0x00, 0x03, 0xE0, 0x00, 0xFF, 0xFF, 0xFD,
                   0xFD, 0x00, 0x62, 0xFA}));
}

// No vendor bytes for these two: check the layout by hand and the CRC with the bitwise form.
void ExpectLayout(const Bytes& packet, const Bytes& before_crc) {
  ASSERT_EQ(packet.size(), before_crc.size() + 2);
  EXPECT_EQ(Bytes(packet.begin(), packet.end() - 2), before_crc);
  const std::uint16_t crc = BitwiseCrc(before_crc);
  EXPECT_EQ(packet[packet.size() - 2], crc & 0xFF);
  EXPECT_EQ(packet[packet.size() - 1], crc >> 8);
}

TEST(DxlPackets, RebootAndTorqueEnable) {
  ExpectLayout(BuildReboot(5), {0xFF, 0xFF, 0xFD, 0x00, 0x05, 0x03, 0x00, 0x08});
  // WRITE address 64 (0x40) one byte.
  ExpectLayout(BuildTorqueEnable(2, true),
               {0xFF, 0xFF, 0xFD, 0x00, 0x02, 0x06, 0x00, 0x03, 0x40, 0x00, 0x01});
  ExpectLayout(BuildTorqueEnable(2, false),
               {0xFF, 0xFF, 0xFD, 0x00, 0x02, 0x06, 0x00, 0x03, 0x40, 0x00, 0x00});
}

TEST(DxlPackets, BadArgumentsRefused) {
  EXPECT_THROW(BuildPing(253), DxlError);
  EXPECT_THROW(BuildPing(255), DxlError);
  EXPECT_NO_THROW(BuildPing(kBroadcastId));
  EXPECT_THROW(BuildSyncRead(132, 4, {}), DxlError);
  EXPECT_THROW(BuildSyncRead(132, 4, {1, 2, 1}), DxlError);
  EXPECT_THROW(BuildSyncRead(132, 4, {1, kBroadcastId}), DxlError);
  EXPECT_THROW(BuildSyncWrite(116, 4, {{1, {1, 2, 3}}}), DxlError);
  EXPECT_THROW(BuildStatus(kBroadcastId, 0, {}), DxlError);
}

TEST(DxlStuffing, RoundTripAndStrictness) {
  const Bytes raw = {0xFF, 0xFF, 0xFD, 0xFF, 0xFF, 0xFD, 0xFD, 0x00, 0xFF, 0xFF, 0xFD};
  const Bytes stuffed = Stuff(raw);
  EXPECT_EQ(stuffed, (Bytes{0xFF, 0xFF, 0xFD, 0xFD, 0xFF, 0xFF, 0xFD, 0xFD, 0xFD, 0x00, 0xFF, 0xFF,
                            0xFD, 0xFD}));
  EXPECT_EQ(Unstuff(stuffed), raw);
  EXPECT_THROW(Unstuff({0x01, 0xFF, 0xFF, 0xFD, 0x00}), DxlError);
  EXPECT_THROW(Unstuff({0xFF, 0xFF, 0xFD}), DxlError);
}

void Feed(PacketParser* p, const Bytes& b) { p->Feed(b.data(), b.size()); }

TEST(DxlParser, StatusExampleDecodes) {
  PacketParser p;
  Feed(&p, kStatusPosition2048);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s.has_value());
  EXPECT_EQ(s->id, 3);
  EXPECT_EQ(s->error, 0);
  EXPECT_EQ(s->params, (Bytes{0x00, 0x08, 0x00, 0x00}));
  EXPECT_FALSE(p.NextStatus().has_value());
  EXPECT_EQ(p.buffered(), 0u);
  EXPECT_EQ(p.stats().packets, 1u);
}

TEST(DxlParser, NoiseBeforeAndBetween) {
  PacketParser p;
  // Noise includes a partial header FF FF FD followed by a non-00 byte.
  Bytes stream = {0x13, 0xFF, 0x00, 0xFF, 0xFF, 0xFD, 0x07, 0x42};
  stream.insert(stream.end(), kStatusPosition2048.begin(), kStatusPosition2048.end());
  stream.insert(stream.end(), {0xAA, 0xFF});
  const Bytes second = BuildStatus(4, 0x80, {0x01});
  stream.insert(stream.end(), second.begin(), second.end());
  Feed(&p, stream);
  auto a = p.NextStatus();
  ASSERT_TRUE(a);
  EXPECT_EQ(a->id, 3);
  auto b = p.NextStatus();
  ASSERT_TRUE(b);
  EXPECT_EQ(b->id, 4);
  EXPECT_TRUE(b->alert());
  EXPECT_EQ(b->params, Bytes{0x01});
  EXPECT_EQ(p.stats().noise_bytes, 10u);
  EXPECT_EQ(p.stats().crc_errors, 0u);
}

TEST(DxlParser, CorruptedCrcDroppedAndNextPacketKept) {
  PacketParser p;
  Bytes bad = kStatusPosition2048;
  bad[10] ^= 0x01;  // a data bit flipped on the wire
  Feed(&p, bad);
  const Bytes good = BuildStatus(5, 0, {0x10, 0x20});
  Feed(&p, good);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->id, 5);
  EXPECT_EQ(s->params, (Bytes{0x10, 0x20}));
  EXPECT_EQ(p.stats().crc_errors, 1u);
  EXPECT_EQ(p.stats().packets, 1u);
}

TEST(DxlParser, SplitPacketEveryByte) {
  PacketParser p;
  for (std::size_t i = 0; i + 1 < kStatusPosition2048.size(); ++i) {
    p.Feed(&kStatusPosition2048[i], 1);
    EXPECT_FALSE(p.NextStatus().has_value()) << "complete after " << i + 1 << " bytes";
  }
  p.Feed(&kStatusPosition2048.back(), 1);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->params, (Bytes{0x00, 0x08, 0x00, 0x00}));
  EXPECT_EQ(p.stats().noise_bytes, 0u);
}

TEST(DxlParser, TwoPacketsBackToBack) {
  PacketParser p;
  Bytes stream = kStatusPosition2048;
  const Bytes second = BuildStatus(1, 0, {0xAB});
  stream.insert(stream.end(), second.begin(), second.end());
  Feed(&p, stream);
  EXPECT_EQ(p.NextStatus()->id, 3);
  EXPECT_EQ(p.NextStatus()->id, 1);
  EXPECT_FALSE(p.NextStatus());
  EXPECT_EQ(p.stats().noise_bytes, 0u);
}

TEST(DxlParser, StuffedDataContainingHeader) {
  // Indirect data reading back FF FF FD 00: the servo stuffs it. Built by hand:
  // FF FF FD 00 | id 07 | length 09 00 | 55 | err 00 | FF FF FD FD 00 | CRC.
  Bytes packet = {0xFF, 0xFF, 0xFD, 0x00, 0x07, 0x09, 0x00,
                  0x55, 0x00, 0xFF, 0xFF, 0xFD, 0xFD, 0x00};
  const std::uint16_t crc = BitwiseCrc(packet);
  packet.push_back(crc & 0xFF);
  packet.push_back(crc >> 8);
  EXPECT_EQ(BuildStatus(7, 0, {0xFF, 0xFF, 0xFD, 0x00}), packet);
  PacketParser p;
  Feed(&p, packet);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->params, (Bytes{0xFF, 0xFF, 0xFD, 0x00}));
  EXPECT_EQ(p.stats().malformed, 0u);
}

TEST(DxlParser, UnstuffedDataWithValidCrcIsMalformed) {
  // A sender that forgot to stuff: CRC is right, but FF FF FD 00 sits inside the data.
  Bytes packet = {0xFF, 0xFF, 0xFD, 0x00, 0x07, 0x08, 0x00, 0x55, 0x00, 0xFF, 0xFF, 0xFD, 0x00};
  const std::uint16_t crc = BitwiseCrc(packet);
  packet.push_back(crc & 0xFF);
  packet.push_back(crc >> 8);
  PacketParser p;
  Feed(&p, packet);
  EXPECT_FALSE(p.NextStatus());
  EXPECT_GE(p.stats().malformed, 1u);
  EXPECT_EQ(p.stats().packets, 0u);
}

TEST(DxlParser, AbsurdLengthResyncs) {
  PacketParser p(64);
  Bytes stream = {0xFF, 0xFF, 0xFD, 0x00, 0x01, 0xFF, 0x7F};  // length 32767 > 64
  stream.insert(stream.end(), kStatusPosition2048.begin(), kStatusPosition2048.end());
  Feed(&p, stream);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->id, 3);
  EXPECT_EQ(p.stats().malformed, 1u);
}

TEST(DxlParser, TimeoutDiscardsPartialReply) {
  PacketParser p;
  p.Feed(kStatusPosition2048.data(), 9);
  EXPECT_FALSE(p.NextStatus());
  p.Timeout();
  EXPECT_EQ(p.stats().timeouts, 1u);
  EXPECT_EQ(p.buffered(), 0u);
  // The rest of the late reply is then noise, and the next reply parses.
  p.Feed(kStatusPosition2048.data() + 9, kStatusPosition2048.size() - 9);
  Feed(&p, kStatusPosition2048);
  EXPECT_TRUE(p.NextStatus());
  EXPECT_FALSE(p.NextStatus());
}

TEST(DxlParser, InstructionEchoSkippedByStatusReader) {
  PacketParser p;
  Bytes stream = BuildSyncRead(132, 4, {1, 2, 3});
  stream.insert(stream.end(), kStatusPosition2048.begin(), kStatusPosition2048.end());
  Feed(&p, stream);
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->id, 3);
  // And the simulator's side reads instructions.
  PacketParser q;
  Feed(&q, BuildSyncRead(132, 4, {1, 2, 3}));
  const auto i = q.NextInstruction();
  ASSERT_TRUE(i);
  EXPECT_EQ(i->id, kBroadcastId);
  EXPECT_EQ(i->instruction, kSyncRead);
  EXPECT_EQ(i->params, (Bytes{0x84, 0x00, 0x04, 0x00, 1, 2, 3}));
}

// Addresses 120-147 laid out by hand (offset = address - 120), all LE:
//  0 tick 0x7FFE | 2 moving 1 | 3 moving status 0x03 | 4 PWM -200 (0xFF38)
//  6 current -100 (0xFF9C) | 8 velocity -5 (0xFFFFFFFB) | 12 position 3072 (0x00000C00)
// 16 velocity trajectory 17 | 20 position trajectory 3000 (0x0BB8) | 24 voltage 120 (0x0078)
// 26 temperature 41 | 27 unused
const Bytes kPresentBlock = {0xFE, 0x7F, 0x01, 0x03, 0x38, 0xFF, 0x9C, 0xFF, 0xFB, 0xFF,
                             0xFF, 0xFF, 0x00, 0x0C, 0x00, 0x00, 0x11, 0x00, 0x00, 0x00,
                             0xB8, 0x0B, 0x00, 0x00, 0x78, 0x00, 0x29, 0x00};

TEST(DxlPresentBlock, DecodeHandBuilt) {
  ASSERT_EQ(kPresentBlock.size(), kPresentBlockBytes);
  const PresentState s = DecodePresentBlock(kPresentBlock.data(), kPresentBlock.size());
  EXPECT_EQ(s.realtime_tick_ms, 0x7FFE);
  EXPECT_EQ(s.moving, 1);
  EXPECT_EQ(s.moving_status, 3);
  EXPECT_EQ(s.present_pwm, -200);
  EXPECT_EQ(s.present_current, -100);
  EXPECT_EQ(s.present_velocity, -5);
  EXPECT_EQ(s.present_position, 3072);
  EXPECT_EQ(s.velocity_trajectory, 17);
  EXPECT_EQ(s.position_trajectory, 3000);
  EXPECT_EQ(s.present_input_voltage, 120);
  EXPECT_EQ(s.present_temperature, 41);
  EXPECT_EQ(EncodePresentBlock(s), kPresentBlock);
  EXPECT_THROW(DecodePresentBlock(kPresentBlock.data(), 27), DxlError);
}

TEST(DxlPresentBlock, ThroughSyncReadStatus) {
  PacketParser p;
  Feed(&p, BuildStatus(6, 0, kPresentBlock));
  const auto s = p.NextStatus();
  ASSERT_TRUE(s);
  EXPECT_EQ(s->id, 6);
  EXPECT_EQ(DecodePresentBlock(s->params.data(), s->params.size()).present_position, 3072);
}

TEST(DxlUnits, Conversions) {
  EXPECT_DOUBLE_EQ(PositionToRad(3072, 2048, 1), M_PI / 2);
  EXPECT_DOUBLE_EQ(PositionToRad(3072, 2048, -1), -M_PI / 2);
  EXPECT_DOUBLE_EQ(PositionToRad(0, 2048, 1), -M_PI);
  EXPECT_DOUBLE_EQ(PositionToRad(1000, 1000, 1), 0.0);
  EXPECT_EQ(RadToPosition(M_PI / 2, 2048, 1), 3072);
  EXPECT_EQ(RadToPosition(M_PI / 2, 1000, -1), 1000 - 1024);
  EXPECT_THROW(PositionToRad(0, 0, 0), DxlError);
  EXPECT_THROW(RadToPosition(std::nan(""), 2048, 1), DxlError);
  // 0.229 rpm = 0.229 * 2 pi / 60 rad/s = 0.0239808 rad/s per unit.
  EXPECT_NEAR(VelocityToRadPerS(1), 0.02398082, 1e-8);
  EXPECT_NEAR(VelocityToRadPerS(-100), -2.398082, 1e-6);
  EXPECT_NEAR(CurrentToA(-100), -0.336, 1e-12);
  EXPECT_NEAR(VoltageToV(120), 12.0, 1e-12);
}

TEST(DxlUnits, TickUnwrap) {
  TickUnwrapper u;
  EXPECT_EQ(u.Update(32760), 32760);
  EXPECT_EQ(u.Update(32767), 32767);
  EXPECT_EQ(u.Update(5), 32773);  // wrapped: 32767 -> 0 -> 5
  EXPECT_EQ(u.Update(10), 32778);
}

TEST(DxlErrors, Describe) {
  EXPECT_EQ(DescribeStatusError(0), "ok");
  EXPECT_EQ(DescribeStatusError(0x03), "CRC error");
  EXPECT_EQ(DescribeStatusError(0x80), "alert");
  EXPECT_EQ(DescribeStatusError(0x87), "alert, access error");
}

}  // namespace
}  // namespace ftcal::dxl
