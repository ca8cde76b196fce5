// The message boundary (services/common/messages.h): every FromLcm / ToLcm pair round-trips a
// value with a distinct number in every field, the refusals name what was wrong, and the
// device-input subscriptions hand a stage the converted inputs of a real replayed log.
#include "common/messages.h"

#include <unistd.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>

#include "ftcal/config.h"
#include "common/log_replay_bus.h"
#include "common/wire_guard.h"
#include "ftcal/geometry.h"

namespace ftcal {
namespace {

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";

// A distinct number for every field: i-th call gives base + i/8 (exact in binary).
struct Distinct {
  double next = 1.0;
  double operator()() { return next += 0.125; }
};

Vec6 DistinctVec6(Distinct& d) {
  Vec6 v;
  for (int i = 0; i < 6; ++i) v[i] = d();
  return v;
}

Mat3 SomeRotation() { return RotationFromRollPitchYaw(0.1, -0.2, 0.3); }

void ExpectRotationNear(const Mat3& a, const Mat3& b) {
  EXPECT_LT((a - b).cwiseAbs().maxCoeff(), 1e-14) << a << "\nvs\n" << b;
}

template <class Fn>
std::string BadInputReason(Fn fn) {
  try {
    fn();
  } catch (const BadInput& e) {
    return e.kind() + ": " + e.what();
  }
  return "";
}

FtBatch SomeBatch(int leg, int n) {
  Distinct d;
  FtBatch b;
  b.leg = leg;
  b.receipt_utime = 1'700'000'000'123'999;
  b.n = n;
  for (int i = 0; i < n; ++i) {
    FtRecord& r = b.records[static_cast<size_t>(i)];
    r.in.utime = 1'700'000'000'123'456 + 143 * i;
    r.in.leg = leg;
    r.in.wrench = DistinctVec6(d);
    r.in.flags = i % 2 ? ft_batch_t::FLAG_SATURATED | ft_batch_t::FLAG_GAP : 0;
    r.rdt_sequence = 4'294'967'290 + i;
    r.ft_sequence = 7 * i - 3;
    r.status = i == 1 ? 0x20000 : 0;
    r.gap = i;
  }
  return b;
}

void ExpectSame(const FtRecord& a, const FtRecord& b);

TEST(Messages, FtBatchRoundTrip) {
  for (const int n : {1, 7, kMaxFtRecords}) {
    const FtBatch in = SomeBatch(4, n);
    const ft_batch_t msg = ToLcm(in);
    EXPECT_EQ(msg.leg, "MR");
    EXPECT_EQ(msg.n, n);
    FtBatch back;
    FromLcm(msg, 4, &back);
    EXPECT_EQ(back.leg, 4);
    EXPECT_EQ(back.receipt_utime, in.receipt_utime);
    ASSERT_EQ(back.n, n);
    for (int i = 0; i < n; ++i) {
      ExpectSame(back.records[static_cast<size_t>(i)], in.records[static_cast<size_t>(i)]);
    }
    // On another leg's channel the message is refused, naming both.
    const std::string why = BadInputReason([&] { FromLcm(msg, 1, &back); });
    EXPECT_NE(why.find("'MR'"), std::string::npos) << why;
    EXPECT_NE(why.find("ML"), std::string::npos) << why;
  }
  // A batch of none, or of more than a datagram can hold, is refused, naming the count.
  ft_batch_t empty = ToLcm(SomeBatch(0, 1));
  empty.n = 0;
  FtBatch out;
  EXPECT_NE(BadInputReason([&] { FromLcm(empty, 0, &out); }).find("holds 0 records"),
            std::string::npos);
  const FtInput one{5, 2, Vec6::Constant(1.5), 0};
  const FtBatch single = BatchOf(one, 9);
  EXPECT_EQ(single.n, 1);
  EXPECT_EQ(single.leg, 2);
  EXPECT_EQ(single.receipt_utime, 9);
  EXPECT_EQ(single.records[0].in.wrench, one.wrench);
}

// The in-place read agrees with the generated encoder for any count and sign of the numbers,
// and refuses what is not an ft_batch_t of the channel's leg or is cut short.
TEST(Messages, PeekRdtSequencesReadsWhatTheEncoderWrote) {
  for (const int n : {1, 7, kMaxFtRecords}) {
    for (int64_t seq : {int64_t{1}, int64_t{4'294'967'295}, int64_t{-7}, int64_t{1} << 40}) {
      FtBatch b = SomeBatch(0, n);
      for (int i = 0; i < n; ++i) b.records[static_cast<size_t>(i)].rdt_sequence = seq + 3 * i;
      std::vector<uint8_t> bytes(static_cast<size_t>(ToLcm(b).getEncodedSize()));
      ASSERT_EQ(ToLcm(b).encode(bytes.data(), 0, static_cast<int>(bytes.size())),
                static_cast<int>(bytes.size()));
      const auto size = static_cast<int>(bytes.size());
      std::array<int64_t, kMaxFtRecords> got{};
      ASSERT_EQ(PeekRdtSequences(bytes.data(), size, 0, &got), n);
      for (int i = 0; i < n; ++i) EXPECT_EQ(got[static_cast<size_t>(i)], seq + 3 * i);
      // Another leg's channel, cut short, another fingerprint: refused, not read past the end.
      EXPECT_EQ(PeekRdtSequences(bytes.data(), size, 1, &got), std::nullopt);
      EXPECT_EQ(PeekRdtSequences(bytes.data(), size - 1, 0, &got), std::nullopt);
      EXPECT_EQ(PeekRdtSequences(bytes.data(), 19, 0, &got), std::nullopt);
      bytes[3] ^= 0x01;
      EXPECT_EQ(PeekRdtSequences(bytes.data(), size, 0, &got), std::nullopt);
    }
  }
}

// ---- the in-place reads (Peek*) against the generated decoder ----

template <class Msg>
std::vector<uint8_t> Encoded(const Msg& msg) {
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  EXPECT_EQ(msg.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  return bytes;
}

bool SameBits(double a, double b) { return std::memcmp(&a, &b, sizeof a) == 0; }

// What wire::Decode then FromLcm give for these bytes; nullopt when either refuses.
std::optional<FtBatch> DecodedFt(const std::vector<uint8_t>& b, int leg) {
  ft_batch_t msg;
  if (wire::Decode(b.data(), static_cast<int>(b.size()), &msg)) return std::nullopt;
  try {
    FtBatch out;
    FromLcm(msg, leg, &out);
    return out;
  } catch (const BadInput&) {
    return std::nullopt;
  }
}
std::optional<ServoInput> DecodedServo(const std::vector<uint8_t>& b) {
  servo_state_t msg;
  if (wire::Decode(b.data(), static_cast<int>(b.size()), &msg)) return std::nullopt;
  try {
    return FromLcm(msg);
  } catch (const BadInput&) {
    return std::nullopt;
  }
}
// Also nullopt for another body than "chassis" (DeviceInputs::FromMocap) and more than 16
// markers (not read in place); a BadInput (a tracked q_wc not a unit quaternion) is passed on.
std::optional<MocapInput> DecodedMocap(const std::vector<uint8_t>& b, int chassis_markers) {
  mocap_body_t msg;
  if (wire::Decode(b.data(), static_cast<int>(b.size()), &msg)) return std::nullopt;
  if (msg.body != "chassis" || msg.num_markers > 16) return std::nullopt;
  return FromLcm(msg, chassis_markers);
}

void ExpectSame(const FtInput& a, const FtInput& b) {
  EXPECT_EQ(a.utime, b.utime);
  EXPECT_EQ(a.leg, b.leg);
  for (int i = 0; i < 6; ++i) EXPECT_TRUE(SameBits(a.wrench[i], b.wrench[i])) << i;
  EXPECT_EQ(a.flags, b.flags);
}
void ExpectSame(const FtRecord& a, const FtRecord& b) {
  ExpectSame(a.in, b.in);
  EXPECT_EQ(a.rdt_sequence, b.rdt_sequence);
  EXPECT_EQ(a.ft_sequence, b.ft_sequence);
  EXPECT_EQ(a.status, b.status);
  EXPECT_EQ(a.gap, b.gap);
}
void ExpectSame(const FtBatch& a, const FtBatch& b) {
  EXPECT_EQ(a.leg, b.leg);
  EXPECT_EQ(a.receipt_utime, b.receipt_utime);
  ASSERT_EQ(a.n, b.n);
  for (int i = 0; i < a.n; ++i) {
    ExpectSame(a.records[static_cast<size_t>(i)], b.records[static_cast<size_t>(i)]);
  }
}
void ExpectSame(const ServoInput& a, const ServoInput& b) {
  EXPECT_EQ(a.utime, b.utime);
  for (int k = 0; k < kNumLegs; ++k) EXPECT_TRUE(SameBits(a.angle_rad[k], b.angle_rad[k])) << k;
}
void ExpectSame(const MocapInput& a, const MocapInput& b) {
  EXPECT_EQ(a.utime, b.utime);
  EXPECT_EQ(a.tracked, b.tracked);
  EXPECT_EQ(a.markers_ok, b.markers_ok);
  if (a.tracked && b.tracked) {
    for (int i = 0; i < 9; ++i) EXPECT_TRUE(SameBits(a.R_WC(i), b.R_WC(i))) << i;
  }
}

// Every field distinct, a NaN, a negative counter and flags with the sign bit: read as the
// encoder wrote them.
ft_batch_t SomeFtBatch(int leg, int n = 7) {
  ft_batch_t msg = ToLcm(SomeBatch(leg, n));
  for (int i = 0; i < n; ++i) {
    for (size_t j = 0; j < 6; ++j) msg.counts[static_cast<size_t>(i)][j] = -1000 * (i + 1);
  }
  msg.wrench[static_cast<size_t>(n - 1)][4] = std::numeric_limits<double>::quiet_NaN();
  msg.flags[0] = -2;
  return msg;
}

servo_state_t SomeServoState() {
  Distinct d;
  servo_state_t msg{};
  msg.utime = 42;
  msg.sample_utime = 37;  // the read's instant, before its completion
  for (int i = 0; i < kNumLegs; ++i) {
    msg.leg[i] = std::string(kLegNames[static_cast<size_t>(kNumLegs - 1 - i)]);  // bus order
    msg.id[i] = i + 1;
    msg.angle_rad[i] = -d();
    msg.velocity_rad_s[i] = d();
    msg.current_a[i] = d();
    msg.device_tick_ms[i] = 1000 + i;
  }
  return msg;
}

mocap_body_t SomeMocapBody(const std::string& body, int markers, bool all_tracked) {
  mocap_body_t msg = ToLcm(MocapInput{77, true, SomeRotation(), true}, body, markers);
  msg.utime = 81;  // received after the frame's instant (77)
  msg.frame_number = 9;
  msg.device_utime = 1234;
  if (!all_tracked && markers > 0) msg.marker_tracked[static_cast<size_t>(markers - 1)] = false;
  return msg;
}

TEST(Messages, PeekFtBatchGivesWhatTheDecoderGives) {
  for (int leg = 0; leg < kNumLegs; ++leg) {
    for (const int n : {1, 7, kMaxFtRecords}) {
      const std::vector<uint8_t> b = Encoded(SomeFtBatch(leg, n));
      const auto size = static_cast<int>(b.size());
      FtBatch peek;
      ASSERT_TRUE(PeekFtBatch(b.data(), size, leg, &peek)) << kLegNames[static_cast<size_t>(leg)];
      ExpectSame(peek, *DecodedFt(b, leg));
      EXPECT_EQ(peek.records[0].rdt_sequence, 4'294'967'290);
      EXPECT_EQ(peek.records[0].ft_sequence, -3);
      EXPECT_EQ(peek.records[0].in.flags, -2);
      // On another leg's channel, cut short, one byte too many, another fingerprint: not read
      // here (the decoder then says what is wrong).
      EXPECT_FALSE(PeekFtBatch(b.data(), size, (leg + 1) % kNumLegs, &peek));
      EXPECT_FALSE(PeekFtBatch(b.data(), size - 1, leg, &peek));
      std::vector<uint8_t> longer = b;
      longer.push_back(0);
      EXPECT_FALSE(PeekFtBatch(longer.data(), size + 1, leg, &peek));
      std::vector<uint8_t> other = b;
      other[3] ^= 0x01;
      EXPECT_FALSE(PeekFtBatch(other.data(), size, leg, &peek));
    }
  }
}

TEST(Messages, PeekServoStateGivesWhatTheDecoderGives) {
  const std::vector<uint8_t> b = Encoded(SomeServoState());
  const auto size = static_cast<int>(b.size());
  const std::optional<ServoInput> peek = PeekServoState(b.data(), size);
  ASSERT_TRUE(peek.has_value());
  ExpectSame(*peek, *DecodedServo(b));
  EXPECT_EQ(peek->utime, 37);  // aligned by the read's instant, not its completion
  EXPECT_EQ(peek->angle_rad[kNumLegs - 1], SomeServoState().angle_rad[0]);  // by name
  EXPECT_FALSE(PeekServoState(b.data(), size - 1));
  servo_state_t dup = SomeServoState();
  dup.leg[5] = dup.leg[0];
  const std::vector<uint8_t> dup_bytes = Encoded(dup);
  EXPECT_FALSE(PeekServoState(dup_bytes.data(), static_cast<int>(dup_bytes.size())));
  servo_state_t unknown = SomeServoState();
  unknown.leg[2] = "XX";
  const std::vector<uint8_t> unknown_bytes = Encoded(unknown);
  EXPECT_FALSE(PeekServoState(unknown_bytes.data(), static_cast<int>(unknown_bytes.size())));
}

TEST(Messages, PeekMocapBodyGivesWhatTheDecoderGives) {
  for (const int markers : {0, 4, 16}) {
    for (const bool all_tracked : {true, false}) {
      const std::vector<uint8_t> b = Encoded(SomeMocapBody("chassis", markers, all_tracked));
      const auto size = static_cast<int>(b.size());
      const std::optional<MocapInput> peek = PeekMocapBody(b.data(), size, "chassis", 4);
      ASSERT_TRUE(peek.has_value()) << markers;
      ExpectSame(*peek, *DecodedMocap(b, 4));
      EXPECT_EQ(peek->utime, 77);  // aligned by the frame's instant, not its receipt
      EXPECT_EQ(peek->markers_ok, markers >= 4 && all_tracked);
      EXPECT_FALSE(PeekMocapBody(b.data(), size, "other", 4));
      EXPECT_FALSE(PeekMocapBody(b.data(), size - 1, "chassis", 4));
    }
  }
  mocap_body_t lost = ToLcm(MocapInput{78, false, Mat3::Identity(), false}, "chassis", 4);
  const std::vector<uint8_t> lost_bytes = Encoded(lost);
  const auto peek_lost =
      PeekMocapBody(lost_bytes.data(), static_cast<int>(lost_bytes.size()), "chassis", 4);
  ASSERT_TRUE(peek_lost.has_value());
  EXPECT_FALSE(peek_lost->tracked);
  EXPECT_FALSE(peek_lost->markers_ok);
  // More markers than are read in place: left to the decoder.
  const std::vector<uint8_t> many = Encoded(SomeMocapBody("chassis", 17, true));
  EXPECT_FALSE(PeekMocapBody(many.data(), static_cast<int>(many.size()), "chassis", 4));
  // A tracked q_wc that is not a unit quaternion is the same BadInput either way.
  mocap_body_t bad = SomeMocapBody("chassis", 4, true);
  bad.q_wc[0] = 2.0;
  const std::vector<uint8_t> bad_bytes = Encoded(bad);
  EXPECT_NE(BadInputReason([&] {
              PeekMocapBody(bad_bytes.data(), static_cast<int>(bad_bytes.size()), "chassis", 4);
            }).find("unit quaternion"),
            std::string::npos);
}

// Damaged bytes: whatever an in-place read accepts, the wire guard, the decoder and FromLcm
// accept too and give the same; and whatever they accept in the form read in place (the
// channel's leg, the chassis body, up to 16 markers), it reads. Random changes of one to three
// bytes, a byte cut or added, over each message.
TEST(Messages, PeeksAcceptExactlyWhatTheDecoderAccepts) {
  std::mt19937 rng(20261206);
  auto damaged = [&rng](std::vector<uint8_t> b) {
    std::uniform_int_distribution<int> how(0, 9), byte(0, 255);
    const int kind = how(rng);
    if (kind == 0) {
      b.pop_back();
    } else if (kind == 1) {
      b.push_back(static_cast<uint8_t>(byte(rng)));
    } else {
      std::uniform_int_distribution<size_t> at(0, b.size() - 1);
      for (int i = 0; i < 1 + kind % 3; ++i) {
        // Small values half the time: lengths, booleans and counts near their valid ones.
        b[at(rng)] = static_cast<uint8_t>(kind % 2 ? byte(rng) % 4 : byte(rng));
      }
    }
    return b;
  };
  constexpr int kTries = 3000;
  int ft_read = 0, servo_read = 0, mocap_read = 0;
  for (int t = 0; t < kTries; ++t) {
    const int leg = t % kNumLegs;
    const std::vector<uint8_t> ft = damaged(Encoded(SomeFtBatch(leg, 1 + t % 8)));
    FtBatch ft_peek;
    const bool ft_peeked = PeekFtBatch(ft.data(), static_cast<int>(ft.size()), leg, &ft_peek);
    const std::optional<FtBatch> ft_decoded = DecodedFt(ft, leg);
    ASSERT_EQ(ft_peeked, ft_decoded.has_value()) << "try " << t;
    if (ft_peeked) {
      ExpectSame(ft_peek, *ft_decoded);
      ++ft_read;
    }

    const std::vector<uint8_t> servo = damaged(Encoded(SomeServoState()));
    const auto servo_peek = PeekServoState(servo.data(), static_cast<int>(servo.size()));
    const std::optional<ServoInput> servo_decoded = DecodedServo(servo);
    ASSERT_EQ(servo_peek.has_value(), servo_decoded.has_value()) << "try " << t;
    if (servo_peek) {
      ExpectSame(*servo_peek, *servo_decoded);
      ++servo_read;
    }

    const std::vector<uint8_t> mocap = damaged(Encoded(SomeMocapBody("chassis", 4, t % 2 == 0)));
    std::optional<MocapInput> mocap_peek, mocap_decoded;
    std::string peek_refused, decode_refused;
    try {
      mocap_peek = PeekMocapBody(mocap.data(), static_cast<int>(mocap.size()), "chassis", 4);
    } catch (const BadInput& e) {
      peek_refused = e.kind();
    }
    try {
      mocap_decoded = DecodedMocap(mocap, 4);
    } catch (const BadInput& e) {
      decode_refused = e.kind();
    }
    ASSERT_EQ(peek_refused, decode_refused) << "try " << t;
    ASSERT_EQ(mocap_peek.has_value(), mocap_decoded.has_value()) << "try " << t;
    if (mocap_peek) {
      ExpectSame(*mocap_peek, *mocap_decoded);
      ++mocap_read;
    }
  }
  // Not vacuous: most changes land in numbers, which both read the same.
  EXPECT_GT(ft_read, kTries / 4);
  EXPECT_GT(servo_read, kTries / 4);
  EXPECT_GT(mocap_read, kTries / 4);
  EXPECT_LT(ft_read, kTries);
  EXPECT_LT(servo_read, kTries);
  EXPECT_LT(mocap_read, kTries);
}

TEST(Messages, ServoStateRoundTripAndLegsByName) {
  Distinct d;
  ServoInput in;
  in.utime = 42;
  for (double& a : in.angle_rad) a = d();
  const ServoInput back = FromLcm(ToLcm(in));
  EXPECT_EQ(back.utime, in.utime);
  EXPECT_EQ(back.angle_rad, in.angle_rad);

  // The bus order is the servo ids', not the legs': the angles follow the names.
  servo_state_t msg = ToLcm(in);
  std::reverse(std::begin(msg.leg), std::end(msg.leg));
  std::reverse(std::begin(msg.angle_rad), std::end(msg.angle_rad));
  EXPECT_EQ(FromLcm(msg).angle_rad, in.angle_rad);

  servo_state_t dup = ToLcm(in);
  dup.leg[5] = "HL";
  EXPECT_NE(BadInputReason([&] { FromLcm(dup); }).find("HL twice"), std::string::npos);
  servo_state_t unknown = ToLcm(in);
  unknown.leg[2] = "XX";
  EXPECT_NE(BadInputReason([&] { FromLcm(unknown); }).find("'XX'"), std::string::npos);
  // (Fewer than six servos cannot be sent: the arrays are fixed at six on the wire.)
}

TEST(Messages, MocapBodyRoundTrip) {
  for (const bool markers_ok : {true, false}) {
    MocapInput in;
    in.utime = 77;
    in.tracked = true;
    in.R_WC = SomeRotation();
    in.markers_ok = markers_ok;
    const mocap_body_t msg = ToLcm(in, "chassis", 4);
    EXPECT_EQ(msg.body, "chassis");
    const MocapInput back = FromLcm(msg, 4);
    EXPECT_EQ(back.utime, in.utime);
    EXPECT_TRUE(back.tracked);
    ExpectRotationNear(back.R_WC, in.R_WC);
    EXPECT_EQ(back.markers_ok, markers_ok);
    // Fewer markers than the chassis has: not all tracked.
    EXPECT_FALSE(FromLcm(msg, 5).markers_ok);
  }
  MocapInput lost;
  lost.utime = 78;
  lost.tracked = false;
  const MocapInput back = FromLcm(ToLcm(lost, "chassis", 4), 4);
  EXPECT_FALSE(back.tracked);
  EXPECT_FALSE(back.markers_ok);

  mocap_body_t bad = ToLcm(MocapInput{79, true, SomeRotation(), true}, "chassis", 4);
  bad.q_wc[0] = 2.0;
  EXPECT_NE(BadInputReason([&] { FromLcm(bad, 4); }).find("unit quaternion"), std::string::npos);
  bad.q_wc[0] = NAN;  // passed on, non-finite, for the aligner to count
  EXPECT_FALSE(FromLcm(bad, 4).R_WC.allFinite());
}

// The bridges' side: roll 0.1, pitch -0.2, heading 0.3 at (1, -2, 0.5) m. q_wc is the same
// attitude without its heading, read back through the consumers' FromLcm; untracked is NaN.
TEST(Messages, BodyPoseFromTheBridgesSide) {
  const Pose3 X_GC(RotationFromRollPitchYaw(0.1, -0.2, 0.3), Vec3(1.0, -2.0, 0.5));
  mocap_body_t msg{};
  msg.tracked = true;
  SetBodyPose(&X_GC, 0.002, &msg);
  EXPECT_NEAR(msg.yaw_rad, 0.3, 1e-12);
  EXPECT_EQ(msg.position_m[0], 1.0);
  EXPECT_EQ(msg.position_m[1], -2.0);
  EXPECT_EQ(msg.position_m[2], 0.5);
  EXPECT_EQ(msg.residual_m, 0.002);
  ExpectRotationNear(
      QuaternionToRotation(Eigen::Vector4d(msg.q_gc[0], msg.q_gc[1], msg.q_gc[2], msg.q_gc[3])),
      X_GC.R);
  msg.num_markers = 0;
  ExpectRotationNear(FromLcm(msg, 0).R_WC, RotationFromRollPitchYaw(0.1, -0.2, 0.0));

  SetBodyPose(nullptr, 0.002, &msg);
  for (double q : msg.q_gc) EXPECT_TRUE(std::isnan(q));
  for (double q : msg.q_wc) EXPECT_TRUE(std::isnan(q));
  for (double p : msg.position_m) EXPECT_TRUE(std::isnan(p));
  EXPECT_TRUE(std::isnan(msg.yaw_rad));
  EXPECT_TRUE(std::isnan(msg.residual_m));
}

TEST(Messages, SyncSampleRoundTrip) {
  Distinct d;
  AlignedSample a;
  a.sample.utime = 1234;
  for (int k = 0; k < kNumLegs; ++k) {
    a.sample.wrench[k] = DistinctVec6(d);
    a.sample.angle_rad[k] = d();
  }
  a.sample.R_WC = SomeRotation();
  a.sample.attitude_ok = true;
  a.sample.markers_ok = false;
  a.flags = 5;
  const AlignedSample back = FromLcm(ToLcm(a));
  EXPECT_EQ(back.sample.utime, a.sample.utime);
  EXPECT_EQ(back.sample.wrench, a.sample.wrench);
  EXPECT_EQ(back.sample.angle_rad, a.sample.angle_rad);
  ExpectRotationNear(back.sample.R_WC, a.sample.R_WC);
  EXPECT_TRUE(back.sample.attitude_ok);
  EXPECT_FALSE(back.sample.markers_ok);
  EXPECT_EQ(back.flags, 5);
  // The reused-message form gives the same bytes as the fresh one.
  sync_sample_t reused{};
  ToLcm(a, &reused);
  ToLcm(a, &reused);
  const sync_sample_t fresh = ToLcm(a);
  ASSERT_EQ(reused.getEncodedSize(), fresh.getEncodedSize());
  std::vector<uint8_t> x(fresh.getEncodedSize()), y(fresh.getEncodedSize());
  reused.encode(x.data(), 0, static_cast<int>(x.size()));
  fresh.encode(y.data(), 0, static_cast<int>(y.size()));
  EXPECT_EQ(x, y);
}

TEST(Messages, SteadyPoseRoundTripAndLegsByName) {
  Distinct d;
  SteadyPoseOut p;
  for (int k = 0; k < kNumLegs; ++k) {
    p.pose.wrench[k] = DistinctVec6(d);
    p.pose.wrench_sem[k] = DistinctVec6(d);
    p.pose.angle_rad[k] = d();
  }
  p.pose.R_WC = SomeRotation();
  p.pose.attitude_sem_rad = Vec3(d(), d(), d());
  p.pose.samples = 201;
  p.start_utime = 1'000'000;
  p.end_utime = 3'000'000;
  p.pose.t_s = 2.0;  // the centre of the span: what the message implies
  p.num_samples = 201;
  p.markers_ok = false;
  const SteadyPoseHeader header{99, "session-7", 12};
  steady_pose_t msg = ToLcm(p, header);
  SteadyPoseHeader h;
  const SteadyPoseOut back = FromLcm(msg, &h);
  EXPECT_EQ(h.utime, 99);
  EXPECT_EQ(h.session_id, "session-7");
  EXPECT_EQ(h.pose_index, 12);
  EXPECT_EQ(back.pose.wrench, p.pose.wrench);
  EXPECT_EQ(back.pose.angle_rad, p.pose.angle_rad);
  ExpectRotationNear(back.pose.R_WC, p.pose.R_WC);
  EXPECT_EQ(back.pose.t_s, 2.0);
  EXPECT_EQ(back.start_utime, p.start_utime);
  EXPECT_EQ(back.end_utime, p.end_utime);
  EXPECT_EQ(back.num_samples, 201);
  EXPECT_FALSE(back.markers_ok);
  EXPECT_EQ(back.pose.samples, 201);
  EXPECT_EQ(back.pose.wrench_sem, p.pose.wrench_sem);
  EXPECT_EQ(back.pose.attitude_sem_rad, p.pose.attitude_sem_rad);

  // A scatter over other samples than the medians' does not travel, and one NaN is no scatter.
  SteadyPoseOut other = p;
  other.pose.samples = 150;
  EXPECT_EQ(FromLcm(ToLcm(other, header)).pose.samples, 0);
  EXPECT_TRUE(std::isnan(ToLcm(other, header).wrench_sem[5][5]));
  steady_pose_t holed = ToLcm(p, header);
  holed.attitude_sem_rad[1] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(FromLcm(holed).pose.samples, 0);

  std::swap(msg.leg[0], msg.leg[3]);
  std::swap(msg.wrench[0], msg.wrench[3]);
  std::swap(msg.wrench_sem[0], msg.wrench_sem[3]);
  std::swap(msg.angle_rad[0], msg.angle_rad[3]);
  EXPECT_EQ(FromLcm(msg).pose.wrench, p.pose.wrench);
  EXPECT_EQ(FromLcm(msg).pose.wrench_sem, p.pose.wrench_sem);
  msg.leg[1] = "HR";  // twice now
  EXPECT_NE(BadInputReason([&] { FromLcm(msg); }).find("HR twice"), std::string::npos);
}

TEST(Messages, CalibrationRoundTripAndRefusals) {
  calibration::Calibration proto;
  proto.set_version(3);
  proto.set_robot_name("bigant-messages-test");
  proto.set_total_mass_kg(8.18);
  const calibration_t msg = ToLcm(proto, 17, 555);
  const CalibrationMessage back = FromLcm(msg);
  EXPECT_EQ(back.proto.SerializeAsString(), proto.SerializeAsString());
  EXPECT_EQ(back.version, 17);
  EXPECT_EQ(back.utime, 555);
  EXPECT_EQ(back.sha256, Sha256Hex(proto.SerializeAsString()));
  EXPECT_EQ(msg.content_sha256, back.sha256);

  auto reason = [](const calibration_t& m) -> std::string {
    try {
      FromLcm(m);
    } catch (const std::runtime_error& e) {
      return e.what();
    }
    return "";
  };
  calibration_t bad_hash = msg;
  bad_hash.content_sha256[0] = bad_hash.content_sha256[0] == '0' ? '1' : '0';
  EXPECT_NE(reason(bad_hash).find("does not match"), std::string::npos);
  calibration_t bad_size = msg;
  bad_size.size += 1;
  EXPECT_NE(reason(bad_size).find("size field"), std::string::npos);
  calibration_t not_proto = msg;
  not_proto.data.assign({0xff, 0xff, 0xff});
  not_proto.size = 3;
  not_proto.content_sha256 = Sha256Hex(std::string(3, '\xff'));
  EXPECT_NE(reason(not_proto).find("not a binary"), std::string::npos);
}

TEST(Messages, ContactWrenchRoundTrip) {
  Distinct d;  // multiples of 1/8: the float ages carry them exactly
  std::vector<LegWrench> in;
  for (int i = 0; i < 7; ++i) {
    LegWrench w;
    w.utime = 31337 + 143 * i;
    w.leg = 2;
    w.wrench_W = DistinctVec6(d);
    w.servo_age_s = d();
    w.mocap_age_s = d();
    w.flags = i % 2 ? kFlagStaleMocap | kFlagSaturated : 0;
    in.push_back(w);
  }
  contact_wrench_t msg;
  // A message reused for a longer batch first: the shorter one must not carry its tail.
  ClearLcm(2, 1, &msg);
  for (int i = 0; i < 9; ++i) AppendLcm(in[0], &msg);
  ClearLcm(2, 31337 + 1000, &msg);
  for (const LegWrench& w : in) AppendLcm(w, &msg);
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  ASSERT_EQ(msg.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  contact_wrench_t decoded;
  ASSERT_FALSE(wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &decoded));
  EXPECT_EQ(decoded.receipt_utime, 31337 + 1000);
  const std::vector<LegWrench> back = FromLcm(decoded);
  ASSERT_EQ(back.size(), in.size());
  for (size_t i = 0; i < in.size(); ++i) {
    EXPECT_EQ(back[i].utime, in[i].utime);
    EXPECT_EQ(back[i].leg, in[i].leg);
    EXPECT_EQ(back[i].wrench_W, in[i].wrench_W);
    EXPECT_EQ(back[i].servo_age_s, in[i].servo_age_s);
    EXPECT_EQ(back[i].mocap_age_s, in[i].mocap_age_s);
    EXPECT_EQ(back[i].flags, in[i].flags);
  }
  // The size the architecture map quotes: fingerprint, receipt, leg and count, then 65 bytes
  // a leg-sample.
  EXPECT_EQ(bytes.size(), 8u + 8 + 1 + 2 + 65 * in.size());
  contact_wrench_t bad = decoded;
  bad.leg = 6;
  EXPECT_NE(BadInputReason([&] { FromLcm(bad); }).find("leg 6"), std::string::npos);
  bad = decoded;
  bad.n = 0;
  EXPECT_NE(BadInputReason([&] { FromLcm(bad); }).find("0 entries"), std::string::npos);
}

TEST(Messages, ContactWrenchSumRoundTrip) {
  Distinct d;
  std::vector<WrenchSum> in;
  for (int i = 0; i < 3; ++i) {
    WrenchSum s;
    s.utime = 31338 + i;
    s.total_W = DistinctVec6(d);
    s.residual_W = DistinctVec6(d);
    s.calibration_version = 8;
    s.oldest_ft_age_s = d();
    s.flags = i == 1 ? kFlagStaleFt | kFlagStaleServo : 0;
    in.push_back(s);
  }
  contact_wrench_sum_t msg;
  ClearLcm(8, &msg);
  for (const WrenchSum& s : in) AppendLcm(s, &msg);
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  ASSERT_EQ(msg.encode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  contact_wrench_sum_t decoded;
  ASSERT_FALSE(wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &decoded));
  const std::vector<WrenchSum> back = FromLcm(decoded);
  ASSERT_EQ(back.size(), in.size());
  for (size_t i = 0; i < in.size(); ++i) {
    EXPECT_EQ(back[i].utime, in[i].utime);
    EXPECT_EQ(back[i].total_W, in[i].total_W);
    EXPECT_EQ(back[i].residual_W, in[i].residual_W);
    EXPECT_EQ(back[i].calibration_version, 8);
    EXPECT_EQ(back[i].oldest_ft_age_s, in[i].oldest_ft_age_s);
    EXPECT_EQ(back[i].flags, in[i].flags);
  }
  EXPECT_EQ(bytes.size(), 8u + 8 + 2 + 109 * in.size());
}

// The flags travel as int8_t; a mask with bit 7 set arrives as a negative number and must be
// read as the bits it carries (0x80 = 128), not sign-extended to -128 (0xffffff80), which
// would set every higher bit of the int32_t mask.
TEST(Messages, FlagsWithBit7AreReadAsTheirBitsNotSignExtended) {
  contact_wrench_t leg_msg;
  ClearLcm(1, 5, &leg_msg);
  LegWrench w;
  w.utime = 7;
  w.leg = 1;
  AppendLcm(w, &leg_msg);
  leg_msg.flags[0] = static_cast<int8_t>(0x80 | kFlagSaturated);
  EXPECT_EQ(FromLcm(leg_msg).at(0).flags, 0x88);

  contact_wrench_sum_t sum_msg;
  ClearLcm(3, &sum_msg);
  AppendLcm(WrenchSum{}, &sum_msg);
  sum_msg.flags[0] = static_cast<int8_t>(0x80);
  EXPECT_EQ(FromLcm(sum_msg).at(0).flags, 128);
}

// LCM 1.3's coretypes move doubles and floats through int64_t* and int32_t*
// (lcm_coretypes.h), which C++'s aliasing rule does not allow: with strict aliasing, GCC served
// a value-initialised message's zeros instead of the doubles its inlined decode had just
// written (CheckSums in tests/integration/twin_log.h read every total_w as 0), and may as well
// encode a double before the store that set it. Every target that includes the generated types
// builds with -fno-strict-aliasing (cmake/LcmTypes.cmake). This is the pattern that broke,
// against bytes written here by hand: big-endian IEEE 754, LCM's wire format.
void PutBigEndian(uint64_t bits, int bytes, std::vector<uint8_t>* out) {
  for (int i = bytes - 1; i >= 0; --i) out->push_back(static_cast<uint8_t>(bits >> (8 * i)));
}
uint64_t BitsOf(double v) {
  uint64_t b;
  std::memcpy(&b, &v, 8);
  return b;
}
uint32_t BitsOf(float v) {
  uint32_t b;
  std::memcpy(&b, &v, 4);
  return b;
}

// Small on purpose: the inlined decode and the read of the value-initialised message in one
// function is what let the compiler forward the zeros.
contact_wrench_sum_t DecodedSum(const std::vector<uint8_t>& wire) {
  contact_wrench_sum_t m{};
  if (m.decode(wire.data(), 0, static_cast<int>(wire.size())) != static_cast<int>(wire.size())) {
    m.calibration_version = -1;
  }
  return m;
}
double DecodedTotal(const std::vector<uint8_t>& wire, int i) {
  contact_wrench_sum_t m{};
  if (m.decode(wire.data(), 0, static_cast<int>(wire.size())) != static_cast<int>(wire.size())) {
    return -1.0;
  }
  return m.total_w[0][static_cast<size_t>(i)];
}

TEST(LcmCoretypes, ValueInitialisedMessagesDecodeAndEncodeEveryDouble) {
  const double total[6] = {1.5, -2.0, 0.25, 3.75, -0.5, 9.0};
  const double residual[6] = {-1.5, 2.0, -80.0, 3.5, 0.125, -9.0};
  std::vector<uint8_t> wire;
  PutBigEndian(static_cast<uint64_t>(contact_wrench_sum_t::getHash()), 8, &wire);
  PutBigEndian(42, 8, &wire);       // calibration_version
  PutBigEndian(1, 2, &wire);        // n
  PutBigEndian(1234567, 8, &wire);  // utime[0]
  for (double v : total) PutBigEndian(BitsOf(v), 8, &wire);
  for (double v : residual) PutBigEndian(BitsOf(v), 8, &wire);
  PutBigEndian(BitsOf(0.75f), 4, &wire);
  PutBigEndian(3, 1, &wire);  // flags[0]

  for (int i = 0; i < 6; ++i) EXPECT_EQ(DecodedTotal(wire, i), total[i]) << i;
  const contact_wrench_sum_t in = DecodedSum(wire);
  EXPECT_EQ(in.calibration_version, 42);
  ASSERT_EQ(in.n, 1);
  EXPECT_EQ(in.utime[0], 1234567);
  for (size_t i = 0; i < 6; ++i) {
    EXPECT_EQ(in.total_w[0][i], total[i]) << i;
    EXPECT_EQ(in.residual_w[0][i], residual[i]) << i;
  }
  EXPECT_EQ(in.oldest_ft_age_s[0], 0.75f);
  EXPECT_EQ(in.flags[0], 3);

  contact_wrench_sum_t out{};
  out.calibration_version = 42;
  out.n = 1;
  out.utime = {1234567};
  out.total_w = {std::vector<double>(total, total + 6)};
  out.residual_w = {std::vector<double>(residual, residual + 6)};
  out.oldest_ft_age_s = {0.75f};
  out.flags = {3};
  std::vector<uint8_t> encoded(wire.size());
  ASSERT_EQ(out.encode(encoded.data(), 0, static_cast<int>(encoded.size())),
            static_cast<int>(wire.size()));
  EXPECT_EQ(encoded, wire);
}

TEST(Messages, Phases) {
  for (const HangSeries s :
       {HangSeries::kXPos, HangSeries::kXNeg, HangSeries::kZPos, HangSeries::kZNeg}) {
    EXPECT_EQ(HangSeriesOfPhase(PhaseOfHangSeries(s)), s);
  }
  EXPECT_EQ(PhaseOfHangSeries(HangSeries::kZNeg), int{experiment_marker_t::HANG_Z_NEG});
  EXPECT_EQ(PhaseName(experiment_marker_t::HANG_X_NEG), "HANG_X_NEG");
  EXPECT_EQ(PhaseName(experiment_marker_t::TRIPOD), "TRIPOD");
  EXPECT_EQ(PhaseName(42), "phase 42");
  EXPECT_FALSE(HangSeriesOfPhase(experiment_marker_t::STANDING));
  EXPECT_FALSE(HangSeriesOfPhase(experiment_marker_t::IDLE));
}

// The subscriptions over a real replayed log: each handler gets its input converted, the
// other rigid body's frames are not handed on, and a message on the wrong leg's channel is a
// counted drop, not a crash.
TEST(Messages, DeviceInputsOverAReplayedLog) {
  const config::Config config = LoadConfigFile(kConfig);
  const std::string dir = ::testing::TempDir();
  const std::string in_path = dir + "/messages_test_" + std::to_string(::getpid()) + ".lcmlog";
  Distinct d;
  FtInput ft;
  ft.utime = 10;
  ft.leg = 3;
  ft.wrench = DistinctVec6(d);
  ServoInput servo;
  servo.utime = 11;
  for (double& a : servo.angle_rad) a = d();
  const MocapInput mocap{12, true, SomeRotation(), true};
  const int markers = static_cast<int>(config.robot().chassis_marker_count());
  {
    lcm::LogFile log(in_path, "w");
    int64_t n = 0;
    auto write = [&](const std::string& channel, const auto& msg) {
      std::vector<uint8_t> buf(static_cast<size_t>(msg.getEncodedSize()));
      msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
      lcm::LogEvent ev;
      ev.eventnum = n;
      ev.timestamp = 100 + n++;
      ev.channel = channel;
      ev.datalen = static_cast<int32_t>(buf.size());
      ev.data = buf.data();
      log.writeEvent(&ev);
    };
    const auto& ch = config.channels();
    write(ch.ft_prefix() + "HR", ToLcm(BatchOf(ft, 10)));
    write(ch.ft_prefix() + "HL", ToLcm(BatchOf(ft, 10)));  // HR's sample on HL's channel
    write(ch.servo_state(), ToLcm(servo));
    write(ch.mocap_body(), ToLcm(mocap, "another body", markers));
    write(ch.mocap_body(), ToLcm(mocap, config.mocap().body_name(), markers));
  }
  ServiceStats stats(std::make_shared<spdlog::logger>(
      "messages_test", std::make_shared<spdlog::sinks::null_sink_mt>()));
  LogReplayBus bus(in_path, in_path + ".out", stats);
  const DeviceInputs inputs(config);
  EXPECT_EQ(inputs.FtChannel(3), config.channels().ft_prefix() + "HR");
  std::vector<FtRecord> fts;
  std::vector<ServoInput> servos;
  std::vector<MocapInput> frames;
  inputs.Subscribe(bus, {[&](const FtBatch& b) { fts.insert(fts.end(), b.begin(), b.end()); },
                         [&](const ServoInput& in) { servos.push_back(in); },
                         [&](const MocapInput& in) { frames.push_back(in); }});
  bus.Run([] {}, 1'000'000);
  ::unlink(in_path.c_str());
  ASSERT_EQ(fts.size(), 1u);
  EXPECT_EQ(fts[0].in.leg, 3);
  EXPECT_EQ(fts[0].in.wrench, ft.wrench);
  ASSERT_EQ(servos.size(), 1u);
  EXPECT_EQ(servos[0].angle_rad, servo.angle_rad);
  ASSERT_EQ(frames.size(), 1u);
  ExpectRotationNear(frames[0].R_WC, mocap.R_WC);
  EXPECT_TRUE(frames[0].markers_ok);
  EXPECT_EQ(stats.drops(), 1);
}

}  // namespace
}  // namespace ftcal
