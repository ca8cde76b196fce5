// ATI RDT codec against the byte examples of docs/device-protocols.md §1 and hand-built
// records whose fields are known.
#include "rdt_codec.h"

#include <gtest/gtest.h>

#include <fstream>
#include <sstream>
#include <vector>

namespace ftcal::rdt {
namespace {

using Bytes = std::vector<std::uint8_t>;

template <std::size_t N>
Bytes ToVec(const std::array<std::uint8_t, N>& a) {
  return Bytes(a.begin(), a.end());
}

TEST(RdtRequest, DocumentedExampleDatagramsByteExact) {
  EXPECT_EQ(ToVec(EncodeRequest(Command::kRealtime)), (Bytes{0x12, 0x34, 0x00, 0x02, 0, 0, 0, 0}));
  EXPECT_EQ(ToVec(EncodeRequest(Command::kBuffered)), (Bytes{0x12, 0x34, 0x00, 0x03, 0, 0, 0, 0}));
  EXPECT_EQ(ToVec(EncodeRequest(Command::kStop)), (Bytes{0x12, 0x34, 0x00, 0x00, 0, 0, 0, 0}));
  EXPECT_EQ(ToVec(EncodeRequest(Command::kBias)), (Bytes{0x12, 0x34, 0x00, 0x42, 0, 0, 0, 0}));
}

TEST(RdtRequest, OtherCommandsAndCountAreBigEndian) {
  EXPECT_EQ(ToVec(EncodeRequest(Command::kBuffered, 0x01020304)),
            (Bytes{0x12, 0x34, 0x00, 0x03, 0x01, 0x02, 0x03, 0x04}));
  EXPECT_EQ(ToVec(EncodeRequest(Command::kMultiUnit, 10)),
            (Bytes{0x12, 0x34, 0x00, 0x04, 0, 0, 0, 10}));
  EXPECT_EQ(ToVec(EncodeRequest(Command::kResetThreshold)),
            (Bytes{0x12, 0x34, 0x00, 0x41, 0, 0, 0, 0}));
}

TEST(RdtRequest, DecodeRoundTripAndRejects) {
  const auto bytes = EncodeRequest(Command::kBuffered, 5000);
  const Request r = DecodeRequest(bytes.data(), bytes.size());
  EXPECT_EQ(r.command, Command::kBuffered);
  EXPECT_EQ(r.sample_count, 5000u);
  const Bytes bad_header{0x12, 0x35, 0, 2, 0, 0, 0, 0};
  EXPECT_THROW(DecodeRequest(bad_header.data(), bad_header.size()), RdtError);
  const Bytes loop_driven{0x12, 0x34, 0, 1, 0, 0, 0, 0};  // 0x0001: not in the manual's table
  EXPECT_THROW(DecodeRequest(loop_driven.data(), loop_driven.size()), RdtError);
  EXPECT_THROW(DecodeRequest(bytes.data(), 7), RdtError);
}

// A record laid out by hand (offsets from §1.3):
//   0 rdt_sequence 0xFFFFFFFF | 4 ft_sequence 0x00010203 | 8 status 0x80020000 (saturation)
//  12 Fx = 1 | 16 Fy = -1 | 20 Fz = -2,000,000 (0xFFE17B80) | 24 Tx = 0x7FFFFFFF
//  28 Ty = INT32_MIN | 32 Tz = 250,000 (0x0003D090)
const Bytes kRecordA = {0xFF, 0xFF, 0xFF, 0xFF, 0x00, 0x01, 0x02, 0x03, 0x80, 0x02, 0x00, 0x00,
                        0x00, 0x00, 0x00, 0x01, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xE1, 0x7B, 0x80,
                        0x7F, 0xFF, 0xFF, 0xFF, 0x80, 0x00, 0x00, 0x00, 0x00, 0x03, 0xD0, 0x90};
// The next record of the stream: sequence wrapped to 0, status healthy, counts all zero.
const Bytes kRecordB = {0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x02, 0x49, 0, 0, 0, 0,
                        0,    0,    0,    0,    0,    0,    0,    0,    0, 0, 0, 0,
                        0,    0,    0,    0,    0,    0,    0,    0,    0, 0, 0, 0};

TEST(RdtRecord, HandBuiltRecordDecodes) {
  const auto records = DecodeDatagram(kRecordA.data(), kRecordA.size());
  ASSERT_EQ(records.size(), 1u);
  const Record& r = records[0];
  EXPECT_EQ(r.rdt_sequence, 0xFFFFFFFFu);
  EXPECT_EQ(r.ft_sequence, 0x00010203u);
  EXPECT_EQ(r.status, 0x80020000u);
  EXPECT_EQ(r.counts[0], 1);
  EXPECT_EQ(r.counts[1], -1);
  EXPECT_EQ(r.counts[2], -2000000);
  EXPECT_EQ(r.counts[3], 2147483647);
  EXPECT_EQ(r.counts[4], -2147483647 - 1);
  EXPECT_EQ(r.counts[5], 250000);
  EXPECT_TRUE(StatusSaturated(r.status));
}

TEST(RdtRecord, BufferedDatagramWithWrappedSequence) {
  Bytes datagram = kRecordA;
  datagram.insert(datagram.end(), kRecordB.begin(), kRecordB.end());
  const auto records = DecodeDatagram(datagram.data(), datagram.size());
  ASSERT_EQ(records.size(), 2u);
  EXPECT_EQ(records[1].rdt_sequence, 0u);
  EXPECT_EQ(records[1].ft_sequence, 0x00010249u);
  EXPECT_EQ(records[1].status, 0u);
}

TEST(RdtRecord, EncodeMatchesHandBuiltBytes) {
  Record r;
  r.rdt_sequence = 0xFFFFFFFF;
  r.ft_sequence = 0x00010203;
  r.status = 0x80020000;
  r.counts = {1, -1, -2000000, 2147483647, -2147483647 - 1, 250000};
  EXPECT_EQ(EncodeDatagram({r}), kRecordA);
}

TEST(RdtRecord, SingleRecordPathMatchesHandBuiltBytes) {
  const Record r = DecodeRecord(kRecordA.data());
  EXPECT_EQ(r.rdt_sequence, 0xFFFFFFFFu);
  EXPECT_EQ(r.ft_sequence, 0x00010203u);
  EXPECT_EQ(r.status, 0x80020000u);
  EXPECT_EQ(r.counts,
            (std::array<std::int32_t, 6>{1, -1, -2000000, 2147483647, -2147483647 - 1, 250000}));
  Bytes out(kRecordBytes, 0xAA);
  EncodeRecord(r, out.data());
  EXPECT_EQ(out, kRecordA);
}

TEST(RdtRecord, WrongLengthsRejectedWithReason) {
  Bytes datagram = kRecordA;
  for (std::size_t n : {0u, 1u, 35u, 37u, 71u}) {
    datagram.resize(n, 0);
    try {
      DecodeDatagram(datagram.data(), datagram.size());
      ADD_FAILURE() << "length " << n << " accepted";
    } catch (const RdtError& e) {
      EXPECT_NE(std::string(e.what()).find(std::to_string(n)), std::string::npos) << e.what();
    }
  }
}

using V = SequenceTracker::Verdict;

// The box's ft_sequence for a record of the first stream these tests follow: RDT at the full
// 7000 Hz, one internal sample per record, modular like the real counter.
std::uint32_t Ft(std::uint32_t rdt_sequence) { return rdt_sequence + 1000u; }

TEST(RdtSequence, InOrderStream) {
  SequenceTracker t;
  EXPECT_EQ(t.Update(1, Ft(1)).verdict, V::kStart);
  for (std::uint32_t s = 2; s <= 10; ++s) EXPECT_EQ(t.Update(s, Ft(s)).verdict, V::kNext);
  EXPECT_EQ(t.accepted(), 10u);
  EXPECT_EQ(t.lost(), 0u);
}

TEST(RdtSequence, LossOfThree) {
  SequenceTracker t;
  t.Update(1, Ft(1));
  t.Update(2, Ft(2));
  const auto r = t.Update(6, Ft(6));  // 3, 4, 5 lost
  EXPECT_EQ(r.verdict, V::kGap);
  EXPECT_EQ(r.lost, 3u);
  EXPECT_TRUE(r.accept());
  EXPECT_EQ(t.lost(), 3u);
  EXPECT_EQ(t.Update(7, Ft(7)).verdict, V::kNext);
}

TEST(RdtSequence, DuplicateDropped) {
  SequenceTracker t;
  t.Update(1, Ft(1));
  t.Update(2, Ft(2));
  const auto r = t.Update(2, Ft(2));
  EXPECT_EQ(r.verdict, V::kDuplicate);
  EXPECT_FALSE(r.accept());
  EXPECT_EQ(t.duplicates(), 1u);
  EXPECT_EQ(t.Update(3, Ft(3)).verdict, V::kNext);
}

TEST(RdtSequence, ReorderedDroppedAndLossNotUndone) {
  SequenceTracker t;
  t.Update(1, Ft(1));
  EXPECT_EQ(t.Update(3, Ft(3)).lost, 1u);  // 2 looks lost
  const auto r = t.Update(2, Ft(2));       // ... then arrives late
  EXPECT_EQ(r.verdict, V::kLate);
  EXPECT_FALSE(r.accept());
  EXPECT_EQ(t.late(), 1u);
  EXPECT_EQ(t.Update(4, Ft(4)).verdict, V::kNext);
  EXPECT_EQ(t.last_sequence(), 4u);
}

TEST(RdtSequence, WrapAround) {
  SequenceTracker t;
  // Reach the top of the range legitimately: a start then one large forward jump is
  // impossible (> 2^31), so walk in three jumps of < 2^31.
  t.Update(1, Ft(1));
  t.Update(0x70000000u, Ft(0x70000000u));
  t.Update(0xE0000000u, Ft(0xE0000000u));
  ASSERT_EQ(t.Update(0xFFFFFFFEu, Ft(0xFFFFFFFEu)).verdict, V::kGap);
  EXPECT_EQ(t.Update(0xFFFFFFFFu, Ft(0xFFFFFFFFu)).verdict, V::kNext);
  EXPECT_EQ(t.Update(0u, Ft(0u)).verdict, V::kNext);
  const auto r = t.Update(3u, Ft(3u));  // 1 and 2 lost across the wrap
  EXPECT_EQ(r.verdict, V::kGap);
  EXPECT_EQ(r.lost, 2u);
  // Taken 4 records ago, across the wrap: a duplicate. 1 was never taken: late.
  EXPECT_EQ(t.Update(0xFFFFFFFFu, Ft(0xFFFFFFFFu)).verdict, V::kDuplicate);
  EXPECT_EQ(t.Update(1u, Ft(1u)).verdict, V::kLate);
}

TEST(RdtSequence, ResetOnStartIgnoresPreviousStreamLeftovers) {
  SequenceTracker t;
  t.Update(1, Ft(1));
  t.Update(5000, Ft(5000));
  t.Reset();                                               // a start command was sent
  EXPECT_EQ(t.Update(5001, Ft(5001)).verdict, V::kStale);  // in flight from the old stream
  const auto r = t.Update(3, Ft(5010));                    // the new stream, records 1 and 2 lost
  EXPECT_EQ(r.verdict, V::kStart);
  EXPECT_EQ(r.lost, 2u);
  EXPECT_EQ(t.Update(4, Ft(5011)).verdict, V::kNext);
  EXPECT_EQ(t.stale(), 1u);
}

// The emulator's reorder fault on a stream's first record: 2 arrives before 1. Record 1 is
// late, not a new stream (its ft_sequence is older than 2's): never accepted after 2, and 3
// follows 2 without a gap or a restart.
TEST(RdtSequence, FirstTwoRecordsSwappedAreAStartAndALateRecord) {
  SequenceTracker t;
  const auto first = t.Update(2, Ft(2));
  EXPECT_EQ(first.verdict, V::kStart);
  EXPECT_EQ(first.lost, 1u);                        // 1 looks lost ...
  EXPECT_EQ(t.Update(1, Ft(1)).verdict, V::kLate);  // ... then arrives late
  EXPECT_EQ(t.Update(3, Ft(3)).verdict, V::kNext);
  EXPECT_EQ(t.Update(5, Ft(5)).verdict, V::kGap);
  EXPECT_EQ(t.Update(4, Ft(4)).verdict, V::kLate);  // and the same later in the stream
  EXPECT_EQ(t.Update(6, Ft(6)).verdict, V::kNext);
  EXPECT_EQ(t.accepted(), 4u);
  EXPECT_EQ(t.late(), 2u);
  EXPECT_EQ(t.lost(), 2u);
  EXPECT_EQ(t.restarts(), 0u);

  // The same after a Reset (the bridge re-sent its start): the new stream's 1 and 2 swapped.
  t.Reset();
  EXPECT_EQ(t.Update(2, Ft(9002)).verdict, V::kStart);
  EXPECT_EQ(t.Update(1, Ft(9001)).verdict, V::kLate);
  EXPECT_EQ(t.Update(3, Ft(9003)).verdict, V::kNext);
  EXPECT_EQ(t.restarts(), 0u);
}

// Two start commands in flight: the tracker locked onto the stream of the first, then the box
// serves the second from 1 with later samples. That is a restart, accepted at once, and the
// first stream's records still in flight are never accepted after it.
TEST(RdtSequence, NewStreamWithoutResetIsARestart) {
  SequenceTracker t;
  for (std::uint32_t s = 1; s <= 50; ++s) t.Update(s, Ft(s));
  const std::uint32_t ft0 = Ft(50) + 100;  // the box's counter went on between the streams
  const auto r = t.Update(1, ft0);
  EXPECT_EQ(r.verdict, V::kRestart);
  EXPECT_TRUE(r.accept());
  EXPECT_EQ(r.lost, 0u);
  EXPECT_EQ(t.Update(2, ft0 + 1).verdict, V::kNext);
  EXPECT_EQ(t.Update(51, Ft(51)).verdict, V::kLate);  // a straggler of the first stream
  EXPECT_EQ(t.Update(3, ft0 + 2).verdict, V::kNext);
  // The new stream's first record lost: it begins at 2.
  const std::uint32_t ft1 = ft0 + 1000;
  const auto r2 = t.Update(2, ft1);
  EXPECT_EQ(r2.verdict, V::kRestart);
  EXPECT_EQ(r2.lost, 1u);
  EXPECT_EQ(t.Update(1, ft1 - 1).verdict, V::kLate);  // ... and swapped with 2
  EXPECT_EQ(t.Update(3, ft1 + 1).verdict, V::kNext);
  EXPECT_EQ(t.restarts(), 2u);
  // Behind by sequence but beyond the start window: late whatever its ft_sequence.
  for (std::uint32_t s = 4; s <= 2000; ++s) t.Update(s, ft1 + s);
  EXPECT_EQ(t.Update(SequenceTracker::kStartWindow + 1, ft1 + 5000).verdict, V::kLate);
  EXPECT_EQ(t.restarts(), 2u);
}

// A duplicated record and a duplicate of a late one, across the 2^32 wrap of rdt_sequence
// (ft_sequence wrapping too).
TEST(RdtSequence, DuplicatesAndReorderingAcrossTheWrap) {
  SequenceTracker t;
  t.Update(1, 5);
  t.Update(0x70000000u, 0x70000004u);
  t.Update(0xE0000000u, 0xE0000004u);
  ASSERT_EQ(t.Update(0xFFFFFFFEu, 0x00000002u).verdict, V::kGap);
  EXPECT_EQ(t.Update(0xFFFFFFFEu, 0x00000002u).verdict, V::kDuplicate);
  EXPECT_EQ(t.Update(0u, 0x00000004u).verdict, V::kGap);            // 0xFFFFFFFF overtaken
  EXPECT_EQ(t.Update(0xFFFFFFFFu, 0x00000003u).verdict, V::kLate);  // ... arrives late
  EXPECT_EQ(t.Update(0xFFFFFFFFu, 0x00000003u).verdict, V::kLate);  // ... twice
  EXPECT_EQ(t.Update(0u, 0x00000004u).verdict, V::kDuplicate);
  // 1 and 2 just after the wrap are in the start window but sampled after 0: the stream goes on.
  EXPECT_EQ(t.Update(1u, 0x00000005u).verdict, V::kNext);
  EXPECT_EQ(t.Update(2u, 0x00000006u).verdict, V::kNext);
  EXPECT_EQ(t.duplicates(), 2u);
  EXPECT_EQ(t.late(), 2u);
  EXPECT_EQ(t.restarts(), 0u);
  EXPECT_EQ(t.last_sequence(), 2u);
}

// Buffered mode: whole datagrams of k records duplicated or overtaken. A duplicated datagram's
// records are duplicates (each was accepted), not late, though all but its last arrive behind the
// newest; an overtaken datagram's records are first lost, then late.
TEST(RdtSequence, BufferedDatagramsDuplicatedAndReordered) {
  constexpr std::uint32_t k = 7;
  SequenceTracker t;
  auto datagram = [&](std::uint32_t first) {
    std::vector<V> out;
    for (std::uint32_t s = first; s < first + k; ++s) out.push_back(t.Update(s, Ft(s)).verdict);
    return out;
  };
  const std::vector<V> next(k, V::kNext), dup(k, V::kDuplicate), late(k, V::kLate);
  std::vector<V> start = next;
  start[0] = V::kStart;
  EXPECT_EQ(datagram(1), start);
  EXPECT_EQ(datagram(1 + k), next);
  EXPECT_EQ(datagram(1 + k), dup);  // sent twice
  EXPECT_EQ(t.duplicates(), k);
  EXPECT_EQ(t.late(), 0u);
  // 1 + 2k overtaken by 1 + 3k: a gap of k records, then k late ones.
  std::vector<V> gap = next;
  gap[0] = V::kGap;
  EXPECT_EQ(datagram(1 + 3 * k), gap);
  EXPECT_EQ(t.lost(), k);
  EXPECT_EQ(datagram(1 + 2 * k), late);
  EXPECT_EQ(t.late(), k);
  // A dropped datagram: the next one's first record says k records are missing before it.
  const auto r = t.Update(1 + 5 * k, Ft(1 + 5 * k));
  EXPECT_EQ(r.verdict, V::kGap);
  EXPECT_EQ(r.lost, k);
  EXPECT_EQ(t.lost(), 2 * k);
  // A duplicate of a datagram older than the window is no longer known: late.
  for (std::uint32_t s = 2 + 5 * k; s < 1000; ++s) t.Update(s, Ft(s));
  EXPECT_EQ(t.Update(1 + k, Ft(1 + k)).verdict, V::kLate);
}

TEST(RdtSequence, AStartForgetsThePreviousStreamsSequences) {
  SequenceTracker t;
  for (std::uint32_t s = 1; s <= 20; ++s) t.Update(s, Ft(s));
  t.Reset();
  EXPECT_EQ(t.Update(5, Ft(100)).verdict, V::kStart);  // 1..4 lost
  // 3 was accepted in the old stream, not in this one: late, not a duplicate.
  EXPECT_EQ(t.Update(3, Ft(98)).verdict, V::kLate);
  EXPECT_EQ(t.duplicates(), 0u);
}

TEST(RdtBuffered, DefaultRecordsPerDatagramIsAboutOnePerMillisecond) {
  EXPECT_EQ(DefaultRecordsPerDatagram(7000), 7);
  EXPECT_EQ(DefaultRecordsPerDatagram(1000), 1);
  EXPECT_EQ(DefaultRecordsPerDatagram(1499), 1);
  EXPECT_EQ(DefaultRecordsPerDatagram(1500), 2);
  EXPECT_EQ(DefaultRecordsPerDatagram(500), 1);  // 0.5 rounds up; at least 1 anyway
  EXPECT_EQ(DefaultRecordsPerDatagram(100), 1);
  EXPECT_EQ(DefaultRecordsPerDatagram(1), 1);
  EXPECT_EQ(DefaultRecordsPerDatagram(100000), kMaxRecordsPerDatagram);
}

TEST(RdtConversion, CountsToNewtonsAndSign) {
  const std::array<std::int32_t, 6> counts = {1500000, -250000, 0, 1000, -3, 7};
  const Vector6d w = CountsToWrench(counts, 1e6, 1e3);
  EXPECT_DOUBLE_EQ(w(0), 1.5);
  EXPECT_DOUBLE_EQ(w(1), -0.25);
  EXPECT_DOUBLE_EQ(w(2), 0.0);
  EXPECT_DOUBLE_EQ(w(3), 1.0);
  EXPECT_DOUBLE_EQ(w(4), -0.003);
  EXPECT_DOUBLE_EQ(w(5), 0.007);
  const Vector6d flipped = CountsToWrench(counts, 1e6, 1e3, -1);
  EXPECT_TRUE(flipped.isApprox(-w));
  // The most negative count with a flipped sign (an int overflow before the fix).
  const std::array<std::int32_t, 6> extreme = {-2147483647 - 1, 0, 0, 0, 0, -2147483647 - 1};
  const Vector6d e = CountsToWrench(extreme, 1e6, 1e6, -1);
  EXPECT_DOUBLE_EQ(e(0), 2147.483648);
  EXPECT_DOUBLE_EQ(e(5), 2147.483648);
  EXPECT_THROW(CountsToWrench(counts, 0, 1e3), RdtError);
  EXPECT_THROW(CountsToWrench(counts, 1e6, -1), RdtError);
  EXPECT_THROW(CountsToWrench(counts, 1e6, 1e3, 2), RdtError);
}

TEST(RdtStatus, DecodeBits) {
  EXPECT_EQ(ClassifyStatus(0), StatusSeverity::kOk);
  EXPECT_EQ(ClassifyStatus(0x80010000u), StatusSeverity::kWarning);
  EXPECT_EQ(ClassifyStatus(0x80020000u), StatusSeverity::kError);
  EXPECT_FALSE(StatusSaturated(0x80010000u));
  EXPECT_TRUE(StatusSaturated(0x00020000u));
  EXPECT_TRUE(DescribeStatus(0).empty());
  const auto d = DescribeStatus(0x80020000u);
  ASSERT_EQ(d.size(), 2u);
  EXPECT_EQ(d[0], "summary: error or condition present");
  EXPECT_EQ(d[1], "transducer saturation or A/D error");
  const auto u = DescribeStatus(0x00008001u);  // bits 15 and 0 are not in the table
  ASSERT_EQ(u.size(), 2u);
  EXPECT_NE(u[0].find("bit 15"), std::string::npos);
  EXPECT_NE(u[1].find("bit 0"), std::string::npos);
}

TEST(RdtStatus, RatedRange) {
  const std::array<double, 6> range = {130, 130, 400, 10, 10, 10};
  Vector6d w;
  w << 129.9, -129.9, 399, 9.99, -9.99, 0;
  EXPECT_FALSE(ExceedsRatedRange(w, range));
  w(2) = -400;
  EXPECT_TRUE(ExceedsRatedRange(w, range));
  w(2) = 0;
  w(4) = std::nan("");
  EXPECT_TRUE(ExceedsRatedRange(w, range));
}

std::string ReadFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::ostringstream os;
  os << in.rdbuf();
  return os.str();
}

const std::string kDataDir = FTCAL_PROTOCOL_TEST_DATA;

TEST(RdtCalibrationPage, SampleParses) {
  const std::string xml = ReadFile(kDataDir + "/netftapi2.xml");
  ASSERT_FALSE(xml.empty());
  const NetFtConfig c = ParseNetFtXml(xml, "netftapi2.xml");
  EXPECT_EQ(c.counts_per_force, 1e6);
  EXPECT_EQ(c.counts_per_torque, 1e6);
  EXPECT_EQ(c.force_unit, "N");
  EXPECT_EQ(c.torque_unit, "Nm");
  EXPECT_EQ(c.rated_range, (std::array<double, 6>{130, 130, 400, 10, 10, 10}));
  EXPECT_EQ(c.rdt_rate_hz, 100);
  EXPECT_EQ(c.active_config, 0);
  EXPECT_EQ(c.calibration_index, 0);
  EXPECT_EQ(c.rdt_buffer_size, 1);
  EXPECT_EQ(c.run_status, 0u);
  EXPECT_EQ(c.config_name, "BigAnt HL N-Nm");
}

std::string Replace(std::string s, const std::string& from, const std::string& to) {
  const auto pos = s.find(from);
  EXPECT_NE(pos, std::string::npos) << from;
  if (pos != std::string::npos) s.replace(pos, from.size(), to);
  return s;
}

void ExpectRefused(const std::string& xml, const std::string& needle) {
  try {
    ParseNetFtXml(xml, "sensor-hl");
    ADD_FAILURE() << "accepted, expected an error mentioning '" << needle << "'";
  } catch (const RdtError& e) {
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("sensor-hl"), std::string::npos) << e.what();
  }
}

TEST(RdtCalibrationPage, BadPagesRefused) {
  const std::string xml = ReadFile(kDataDir + "/netftapi2.xml");
  ExpectRefused(Replace(xml, "<scfgfu>N</scfgfu>", "<scfgfu>lbf</scfgfu>"), "lbf");
  ExpectRefused(Replace(xml, "<scfgtu>Nm</scfgtu>", "<scfgtu>lbf-in</scfgtu>"), "scfgtu");
  ExpectRefused(Replace(xml, "<cfgcpf>1000000</cfgcpf>", ""), "cfgcpf");
  ExpectRefused(Replace(xml, "<cfgcpt>1000000</cfgcpt>", "<cfgcpt>1e6x</cfgcpt>"), "cfgcpt");
  ExpectRefused(Replace(xml, "<cfgcpt>1000000</cfgcpt>", "<cfgcpt>0</cfgcpt>"), "cfgcpt");
  ExpectRefused(Replace(xml, "130;130;400;10;10;10", "130;130;400;10;10"), "cfgmr");
  ExpectRefused(Replace(xml, "130;130;400;10;10;10", "130;130;400;10;10;10;1"), "cfgmr");
  ExpectRefused(Replace(xml, "130;130;400;10;10;10", "130;;400;10;10;10"), "cfgmr");
  ExpectRefused(Replace(xml, "<comrdtrate>100</comrdtrate>", ""), "comrdtrate");
  ExpectRefused(Replace(xml, "<setcfgsel>0</setcfgsel>", "<setcfgsel>-1</setcfgsel>"), "setcfgsel");
  ExpectRefused(Replace(xml, "</netft>", ""), "malformed XML");
  ExpectRefused("<html><body>404</body></html>", "<netft>");
  ExpectRefused("", "malformed XML");
}

// Counts per unit of 1e300 turned every force into 0: refused, naming the value and the range
// the rated ranges allow (130 N and 400 N must each span 2^10 .. 2^31 counts:
// 1024/130 = 7.87692 .. 2^31/400 = 5368709.12 counts/N).
TEST(RdtCalibrationPage, ImplausibleCountsPerUnitRefusedWithValueAndRange) {
  const std::string xml = ReadFile(kDataDir + "/netftapi2.xml");
  ExpectRefused(Replace(xml, "<cfgcpf>1000000</cfgcpf>", "<cfgcpf>1e300</cfgcpf>"), "1e+300");
  ExpectRefused(Replace(xml, "<cfgcpf>1000000</cfgcpf>", "<cfgcpf>1e300</cfgcpf>"),
                "[7.87692, 5.36871e+06]");
  ExpectRefused(Replace(xml, "<cfgcpf>1000000</cfgcpf>", "<cfgcpf>7.8</cfgcpf>"), "(cfgcpf) 7.8 ");
  ExpectRefused(Replace(xml, "<cfgcpt>1000000</cfgcpt>", "<cfgcpt>1e9</cfgcpt>"),
                "[102.4, 2.14748e+08]");
  // The edges are plausible: exactly 2^10 and 2^31 - 1 counts over the largest rated range.
  EXPECT_NO_THROW(CheckCountsPerUnit(1024.0 / 130, 102.4, {130, 130, 400, 10, 10, 10}, "x"));
  EXPECT_NO_THROW(
      CheckCountsPerUnit(2147483647.0 / 400, 2147483647.0 / 10, {130, 130, 400, 10, 10, 10}, "x"));
  // A rated range of 1e-300 N would need 1e303 counts/N to span 2^10 counts: refused.
  EXPECT_THROW(CheckCountsPerUnit(1e6, 1e6, {130, 130, 1e-300, 10, 10, 10}, "x"), RdtError);
}

}  // namespace
}  // namespace ftcal::rdt
