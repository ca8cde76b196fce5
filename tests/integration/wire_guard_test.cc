// The wire guard: every crafted message that made LCM 1.3.1's generated decoder allocate
// gigabytes, throw into the handler or read past the buffer is refused before the decoder runs,
// with its kind counted, in bounded time and memory; every well-formed message still passes;
// the generated schemas agree with lcm-gen's fingerprints.
#include <sys/resource.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <vector>

#include <gtest/gtest.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/wire_guard.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/process_state_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "ftcal/sequencer_control_t.hpp"
#include "ftcal/drift_t.hpp"
#include "ftcal/servo_command_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/signed_envelope_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "ftcal_test/crafted_t.hpp"

namespace ftcal::wire {
const std::vector<const Schema*>& CraftedSchemas();
}

namespace ftcal {
namespace {

std::shared_ptr<spdlog::logger> QuietLogger() {
  static auto log =
      std::make_shared<spdlog::logger>("test", std::make_shared<spdlog::sinks::null_sink_mt>());
  return log;
}

struct RegisterCrafted {
  RegisterCrafted() { wire::Register(wire::CraftedSchemas()); }
} register_crafted;

template <class Msg>
std::vector<uint8_t> Encode(const Msg& msg) {
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  EXPECT_EQ(msg.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  return bytes;
}

void PutBe32(std::vector<uint8_t>& bytes, size_t at, int32_t value) {
  const auto v = static_cast<uint32_t>(value);
  for (int i = 0; i < 4; ++i) bytes[at + i] = static_cast<uint8_t>(v >> (24 - 8 * i));
}

template <class Msg>
std::optional<wire::Refusal> Guard(const std::vector<uint8_t>& bytes) {
  Msg msg;
  return wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &msg);
}

long MaxRssKb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss;
}

// ---- the schemas are lcm-gen's ----

template <class Msg>
void ExpectSchemaMatches() {
  const wire::Schema* schema = wire::FindSchema(static_cast<uint64_t>(Msg::getHash()));
  ASSERT_NE(schema, nullptr) << Msg::getTypeName();
  EXPECT_EQ(std::string(schema->name).substr(std::string(schema->name).find('.') + 1),
            Msg::getTypeName());
}

TEST(WireSchemaTest, EveryMessageTypeHasASchemaWithLcmGensFingerprint) {
  ExpectSchemaMatches<calibration_t>();
  ExpectSchemaMatches<contact_wrench_t>();
  ExpectSchemaMatches<experiment_marker_t>();
  ExpectSchemaMatches<ft_batch_t>();
  ExpectSchemaMatches<mocap_body_t>();
  ExpectSchemaMatches<service_status_t>();
  ExpectSchemaMatches<servo_command_t>();
  ExpectSchemaMatches<servo_state_t>();
  ExpectSchemaMatches<steady_pose_t>();
  ExpectSchemaMatches<sync_sample_t>();
  ExpectSchemaMatches<signed_envelope_t>();
  ExpectSchemaMatches<contact_wrench_sum_t>();
  ExpectSchemaMatches<sequencer_control_t>();
  ExpectSchemaMatches<process_state_t>();
  ExpectSchemaMatches<drift_t>();
  ExpectSchemaMatches<ftcal_test::crafted_t>();
  // One schema per .lcm file, none left over: a type the guard does not know is refused.
  EXPECT_EQ(wire::FtcalSchemas().size(), 15u);
}

// ---- well-formed messages pass, and decode to what was sent ----

// DRIFT is all fixed-size arrays: its bound is its exact size. One byte short or over is refused
// before the decoder runs.
TEST(WireGuardTest, DriftHasExactlyItsFixedSize) {
  drift_t d{};
  d.utime = 1'700'000'000'000'000;
  d.status = drift_t::WARN;
  d.offset_change[4][5] = 0.05;
  d.warn_mask[4] = 63;
  d.balance_force_rms_n[0] = std::numeric_limits<double>::quiet_NaN();
  auto bytes = Encode(d);
  drift_t got;
  ASSERT_FALSE(wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &got));
  EXPECT_EQ(got.offset_change[4][5], 0.05);
  EXPECT_EQ(got.warn_mask[4], 63);
  EXPECT_TRUE(std::isnan(got.balance_force_rms_n[0]));
  const auto short_by_one = wire::Decode(bytes.data(), static_cast<int>(bytes.size()) - 1, &got);
  ASSERT_TRUE(short_by_one);
  EXPECT_EQ(short_by_one->kind, "array past the end");
  bytes.push_back(0);
  const auto over_by_one = wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &got);
  ASSERT_TRUE(over_by_one);
  EXPECT_EQ(over_by_one->kind, "trailing bytes");
}

mocap_body_t Mocap(int markers) {
  mocap_body_t m{};
  m.utime = 1'700'000'000'000'000;
  m.frame_number = 42;
  m.body = "chassis";
  m.tracked = true;
  for (int i = 0; i < 4; ++i) m.q_wc[i] = m.q_gc[i] = i == 0 ? 1.0 : 0.0;
  m.residual_m = std::numeric_limits<double>::quiet_NaN();  // NaN is a legitimate value here
  m.num_markers = markers;
  for (int k = 0; k < markers; ++k) {
    m.marker_m.push_back({0.1 * k, 0.2, 0.3});
    m.marker_tracked.push_back(k % 2);
  }
  return m;
}

TEST(WireGuardTest, WellFormedMessagesPassAndDecodeAsSent) {
  const mocap_body_t mocap = Mocap(5);
  mocap_body_t got;
  const auto bytes = Encode(mocap);
  ASSERT_FALSE(wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &got));
  EXPECT_EQ(got.marker_m[4][0], 0.4);
  EXPECT_EQ(got.body, "chassis");
  EXPECT_TRUE(std::isnan(got.residual_m));

  // A batch of the most samples a message may carry (MAX_N) passes; one more is refused
  // before any decoding, naming the type's own cap, though the bytes are all there.
  contact_wrench_t cw{};
  cw.leg = 1;
  for (int n = contact_wrench_t::MAX_N; n <= contact_wrench_t::MAX_N + 1; ++n) {
    cw.n = static_cast<int16_t>(n);
    cw.utime.assign(static_cast<size_t>(n), 5);
    cw.wrench_w.assign(static_cast<size_t>(n), std::vector<double>{1, 2, 3, 4, 5, 6});
    cw.servo_age_s.assign(static_cast<size_t>(n), 0.001f);
    cw.mocap_age_s.assign(static_cast<size_t>(n), -1.0f);
    cw.flags.assign(static_cast<size_t>(n), 0);
    const auto refused = Guard<contact_wrench_t>(Encode(cw));
    if (n == contact_wrench_t::MAX_N) {
      EXPECT_FALSE(refused);
    } else {
      ASSERT_TRUE(refused);
      EXPECT_EQ(refused->kind, "length over cap");
      EXPECT_NE(refused->detail.find("(cap 40)"), std::string::npos) << refused->detail;
    }
  }
  ft_batch_t ft{};
  ft.leg = "HL";
  ft.n = ft_batch_t::MAX_N + 1;
  const auto n = static_cast<size_t>(ft.n);
  ft.sample_utime.assign(n, 1);
  ft.rdt_sequence.assign(n, 1);
  ft.ft_sequence.assign(n, 1);
  ft.status.assign(n, 0);
  ft.counts.assign(n, std::vector<int32_t>(6, 0));
  ft.wrench.assign(n, std::vector<double>(6, 0.0));
  ft.gap.assign(n, 0);
  ft.flags.assign(n, 0);
  const auto ft_refused = Guard<ft_batch_t>(Encode(ft));
  ASSERT_TRUE(ft_refused);
  EXPECT_EQ(ft_refused->kind, "length over cap");

  service_status_t st{};
  st.name = "ftcal-x";
  st.num_counters = 2;
  st.counter_name = {"a", "bb"};
  st.counter_value = {1, 2};
  EXPECT_FALSE(Guard<service_status_t>(Encode(st)));

  ftcal_test::crafted_t c{};
  c.rows = 2;
  c.cols = 3;
  c.v = {{1, 2, 3}, {4, 5, 6}};
  c.count = 1;
  c.w = {7};
  c.n8 = 2;
  c.n16 = {-1, 300};
  c.flag = 1;
  ftcal_test::crafted_t back;
  const auto cb = Encode(c);
  ASSERT_FALSE(wire::Decode(cb.data(), static_cast<int>(cb.size()), &back));
  EXPECT_EQ(back.v[1][2], 6);
  EXPECT_EQ(back.n16[0], -1);
  // Empty arrays and empty inner dimensions of a small message are fine.
  ftcal_test::crafted_t empty{};
  empty.rows = 3;
  empty.cols = 0;
  empty.v = {{}, {}, {}};
  EXPECT_FALSE(Guard<ftcal_test::crafted_t>(Encode(empty)));
}

// ---- the crafted messages of issue 12 ----

// 153 bytes claiming 4e8 markers (161 since sample_utime follows the markers): the decoder
// resized marker_m to 4e8 vectors (8.8 GB, a minute) before finding the bytes missing.
std::vector<uint8_t> MocapClaiming4e8Markers() {
  auto bytes = Encode(Mocap(0));
  PutBe32(bytes, bytes.size() - 12, 400'000'000);  // num_markers, before sample_utime
  return bytes;
}

TEST(WireGuardTest, A161ByteMocapClaiming400MillionMarkersIsRefusedInBoundedTimeAndMemory) {
  const auto bytes = MocapClaiming4e8Markers();
  ASSERT_EQ(bytes.size(), 161u);
  ServiceStats stats(QuietLogger());
  LcmBus bus("memq://", stats);
  int delivered = 0;
  bus.Subscribe<mocap_body_t>("MOCAP_BODY",
                              [&](const MessageInfo&, const mocap_body_t&) { ++delivered; });
  const long rss_before_kb = MaxRssKb();
  const auto t0 = std::chrono::steady_clock::now();
  constexpr int kMessages = 100;
  for (int i = 0; i < kMessages; ++i) {
    bus.PublishRaw("MOCAP_BODY", bytes.data(), static_cast<int>(bytes.size()));
    while (bus.HandleOnce(0) > 0) {
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  bus.Publish("MOCAP_BODY", Mocap(3));  // and the next good one still gets through
  while (bus.HandleOnce(0) > 0) {
  }
  EXPECT_EQ(delivered, 1);
  EXPECT_EQ(stats.drops(), kMessages);
  EXPECT_EQ(stats.kinds().at("undecodable mocap_body_t on MOCAP_BODY: length over cap"), kMessages);
  // Bounds, not speed figures: unguarded, one such message took a minute and 8.8 GB.
  EXPECT_LT(MaxRssKb() - rss_before_kb, 16 * 1024);
  EXPECT_LT(seconds, 2.0);
}

TEST(WireGuardTest, A20ByteMessageWithLengthMinusOneIsRefusedNotThrown) {
  // The message was a SERVO_STATE whose num_servos said -1. servo_state_t now carries
  // exactly six servos and no length: the same 20 bytes are six leg names short.
  servo_state_t state{};
  auto bytes = Encode(state);
  bytes.resize(20);  // fingerprint, utime, the first string's length
  PutBe32(bytes, 16, -1);
  auto refused = Guard<servo_state_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "array past the end");
  EXPECT_NE(refused->detail.find("servo_state_t.leg"), std::string::npos) << refused->detail;
  // A length of -1 where a type still has one: servo_command_t's num_servos (21 bytes).
  servo_command_t cmd{};
  bytes = Encode(cmd);
  bytes.resize(21);  // fingerprint, utime, action, num_servos
  PutBe32(bytes, 17, -1);
  refused = Guard<servo_command_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "negative length");
  EXPECT_NE(refused->detail.find("servo_command_t.id"), std::string::npos) << refused->detail;
}

TEST(WireGuardTest, AStringOfLengthZeroIsRefusedNotThrown) {
  experiment_marker_t m{};
  auto bytes = Encode(m);
  PutBe32(bytes, 16, 0);  // session_id's length
  auto refused = Guard<experiment_marker_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "bad string length");
  EXPECT_NE(refused->detail.find("session_id"), std::string::npos) << refused->detail;
  bytes.resize(20);  // the 20-byte message of the issue
  refused = Guard<experiment_marker_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "bad string length");
}

TEST(WireGuardTest, ADoubleArrayWhoseByteCountOverflowsIntIsRefused) {
  // LCM's check `n * 8 > maxlen` overflows int for n = 3e8 and passes: the decoder then reads
  // 2.4 GB from a 40-byte buffer. Here the cap refuses it, and under the cap the bytes do.
  ftcal_test::crafted_t c{};
  auto bytes = Encode(c);
  PutBe32(bytes, 16, 300'000'000);  // count, after rows and cols
  auto refused = Guard<ftcal_test::crafted_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "length over cap");
  EXPECT_NE(refused->detail.find("crafted_t.w"), std::string::npos) << refused->detail;
  PutBe32(bytes, 16, 10'000'000);
  refused = Guard<ftcal_test::crafted_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "array past the end");
}

TEST(WireGuardTest, A32ByteTwoDimensionalArrayWithAnEmptyInnerDimensionIsRefused) {
  ftcal_test::crafted_t c{};
  auto bytes = Encode(c);
  bytes.pop_back();  // no n8, no flag: 32 bytes as in the issue
  bytes.pop_back();
  ASSERT_EQ(bytes.size(), 32u);
  // 4.6e7 rows of zero columns decoded "successfully" into 1.1 GB of empty vectors.
  PutBe32(bytes, 8, 46'000'000);
  PutBe32(bytes, 12, 0);
  auto refused = Guard<ftcal_test::crafted_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "length over cap");
  // Under the cap, the decoded size is still bounded by the message's.
  PutBe32(bytes, 8, 1'000'000);
  refused = Guard<ftcal_test::crafted_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "decoded size over bound");
}

TEST(WireGuardTest, MultiDimensionalArraysAreMultipliedOut) {
  ftcal_test::crafted_t c{};
  c.rows = 2;
  c.cols = 2;
  c.v = {{1, 2}, {3, 4}};
  auto bytes = Encode(c);
  PutBe32(bytes, 12, 3);  // 2 x 3 doubles claimed, 2 x 2 there (and 4 bytes of other fields)
  const auto refused = Guard<ftcal_test::crafted_t>(bytes);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "array past the end") << refused->detail;
}

TEST(WireGuardTest, WrongFingerprintTrailingBytesBadBooleansAndMissingNulAreRefused) {
  EXPECT_EQ(Guard<servo_command_t>(Encode(Mocap(0)))->kind, "wrong fingerprint");

  auto bytes = Encode(Mocap(1));
  bytes.push_back(0);
  EXPECT_EQ(Guard<mocap_body_t>(bytes)->kind, "trailing bytes");

  bytes = Encode(Mocap(1));
  bytes[bytes.size() - 9] = 7;  // marker_tracked[0], before sample_utime
  EXPECT_EQ(Guard<mocap_body_t>(bytes)->kind, "bad boolean");

  experiment_marker_t m{};
  m.session_id = "abc";
  bytes = Encode(m);
  bytes[16 + 4 + 3] = 'x';  // the NUL after "abc"
  EXPECT_EQ(Guard<experiment_marker_t>(bytes)->kind, "string without NUL");

  bytes = Encode(m);
  bytes[16 + 4 + 1] = 0;  // "a\0c": the decoder would keep 3 bytes, an encoder send 1
  EXPECT_EQ(Guard<experiment_marker_t>(bytes)->kind, "string with a NUL inside");

  bytes = Encode(m);
  PutBe32(bytes, 16, 1 << 30);
  EXPECT_EQ(Guard<experiment_marker_t>(bytes)->kind, "string past the end");

  EXPECT_EQ(Guard<experiment_marker_t>(std::vector<uint8_t>(5, 0))->kind, "truncated");
}

// Every prefix and every single-byte change of a good message either passes and decodes to
// exactly its size, or is refused: the decoder never sees what the guard did not check.
TEST(WireGuardTest, EveryTruncationAndByteFlipOfAGoodMessageIsSafe) {
  const auto good = Encode(Mocap(2));
  for (size_t n = 0; n < good.size(); ++n) {
    std::vector<uint8_t> prefix(good.begin(), good.begin() + static_cast<long>(n));
    EXPECT_TRUE(Guard<mocap_body_t>(prefix)) << n;
  }
  for (size_t at = 0; at < good.size(); ++at) {
    for (int v : {0x00, 0x01, 0x7f, 0x80, 0xff}) {
      auto bytes = good;
      bytes[at] = static_cast<uint8_t>(v);
      mocap_body_t msg;
      const auto refused = wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &msg);
      if (refused) {
        EXPECT_NE(refused->kind, "decoder threw") << at;
        EXPECT_NE(refused->kind, "decoder disagrees") << at;
      }
    }
  }
}

}  // namespace
}  // namespace ftcal
