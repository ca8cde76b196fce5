// Signed channels (services/common/envelope.h) on memq://: a good envelope delivers its inner
// message; unsigned, untrusted, forged, moved, replayed and stale ones are refused before the
// inner message is decoded, each counted under its kind and sender; sequences rise across a
// signer's restart; the seed file's permissions are enforced; ftcal-keygen's key verifies.
#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include <sys/wait.h>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "child_process.h"
#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/envelope.h"
#include "signed_commander.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/servo_command_t.hpp"

namespace ftcal {
namespace {

using testing::Encode;
using testing::NowUs;

using auth::Signer;
using auth::TrustedKey;
using auth::Verifier;

std::shared_ptr<spdlog::logger> QuietLogger() {
  static auto log =
      std::make_shared<spdlog::logger>("test", std::make_shared<spdlog::sinks::null_sink_mt>());
  return log;
}

Signer MakeSigner(uint8_t fill) {
  std::array<uint8_t, auth::kSeedBytes> seed{};
  seed.fill(fill);
  seed[0] = 0x42;
  return Signer::FromSeed(seed);
}

servo_command_t Command(double goal) {
  servo_command_t c{};
  c.num_servos = 2;
  c.id = {1, 2};
  c.goal_angle_rad = {goal, -goal};
  c.torque_enable = true;
  return c;
}

class SignedChannelTest : public ::testing::Test {
 protected:
  SignedChannelTest()
      : op_(MakeSigner(1)),
        op_next_(MakeSigner(2)),
        intruder_(MakeSigner(3)),
        verifier_({TrustedKey{"operator", op_.public_key(), {"SERVO_CMD", "EXPERIMENT"}},
                   TrustedKey{"operator-next", op_next_.public_key(), {"SERVO_CMD"}}}),
        stats_(QuietLogger()),
        bus_("memq://", stats_) {}

  void Listen(int64_t window_us, bool allow_unsigned = false) {
    bus_.SubscribeSigned<servo_command_t>(
        "SERVO_CMD", &verifier_, window_us, allow_unsigned,
        [this](const MessageInfo&, const servo_command_t& c) { got_.push_back(c); });
  }
  void Send(const std::string& channel, const std::vector<uint8_t>& bytes) {
    bus_.PublishRaw(channel, bytes.data(), static_cast<int>(bytes.size()));
    while (bus_.HandleOnce(0) > 0) {
    }
  }
  int64_t Kind(const std::string& kind) {
    const auto it = stats_.kinds().find(kind);
    return it == stats_.kinds().end() ? 0 : it->second;
  }

  Signer op_, op_next_, intruder_;
  Verifier verifier_;
  ServiceStats stats_;
  LcmBus bus_;
  std::vector<servo_command_t> got_;
};

TEST_F(SignedChannelTest, AGoodEnvelopeDeliversItsInnerMessage) {
  Listen(250'000);
  bus_.PublishSigned("SERVO_CMD", Command(0.5), op_);
  while (bus_.HandleOnce(0) > 0) {
  }
  ASSERT_EQ(got_.size(), 1u);
  EXPECT_EQ(got_[0].goal_angle_rad[1], -0.5);
  EXPECT_EQ(stats_.drops(), 0);
  // The second trusted key (rotation) works as well.
  Send("SERVO_CMD", Encode(op_next_.Seal("SERVO_CMD", Command(0.7), NowUs())));
  ASSERT_EQ(got_.size(), 2u);
  EXPECT_EQ(got_[1].goal_angle_rad[0], 0.7);
}

TEST_F(SignedChannelTest, UnsignedIsRefusedUnlessAllowed) {
  Listen(250'000);
  Send("SERVO_CMD", Encode(Command(0.5)));
  EXPECT_TRUE(got_.empty());
  EXPECT_EQ(Kind("unsigned on SERVO_CMD"), 1);
}

TEST_F(SignedChannelTest, UnsignedIsAcceptedAndCountedWhereTheConfigAllowsIt) {
  Listen(0, /*allow_unsigned=*/true);
  Send("SERVO_CMD", Encode(Command(0.5)));
  ASSERT_EQ(got_.size(), 1u);
  EXPECT_EQ(stats_.counters().at("unsigned_accepted"), 1);
}

TEST_F(SignedChannelTest, AnUntrustedSignerIsRefused) {
  Listen(250'000);
  Send("SERVO_CMD", Encode(intruder_.Seal("SERVO_CMD", Command(0.5), NowUs())));
  EXPECT_TRUE(got_.empty());
  ASSERT_EQ(stats_.drops(), 1);
  EXPECT_EQ(Kind("untrusted signer on SERVO_CMD"), 1);
  // Any number of fresh keys: still one kind (the counts and the log stay bounded).
  for (uint8_t fill = 10; fill < 20; ++fill) {
    Send("SERVO_CMD", Encode(MakeSigner(fill).Seal("SERVO_CMD", Command(0.5), NowUs())));
  }
  EXPECT_EQ(Kind("untrusted signer on SERVO_CMD"), 11);
  EXPECT_EQ(stats_.kinds().size(), 1u);
}

TEST_F(SignedChannelTest, AKeyIsTrustedOnlyOnItsChannels) {
  bus_.SubscribeSigned<experiment_marker_t>(
      "EXPERIMENT", &verifier_, 0, false,
      [](const MessageInfo&, const experiment_marker_t&) { FAIL() << "delivered"; });
  Send("EXPERIMENT", Encode(op_next_.Seal("EXPERIMENT", experiment_marker_t{}, NowUs())));
  EXPECT_EQ(Kind("not allowed on channel from operator-next on EXPERIMENT"), 1);
}

TEST_F(SignedChannelTest, AForgedOrAlteredEnvelopeIsRefused) {
  Listen(250'000);
  // The operator's key in the signer field, any signature: a forgery.
  signed_envelope_t forged = intruder_.Seal("SERVO_CMD", Command(0.5), NowUs());
  std::memcpy(forged.signer, op_.public_key().data(), 32);
  Send("SERVO_CMD", Encode(forged));
  // A genuine envelope with its goal changed on the way.
  signed_envelope_t altered = op_.Seal("SERVO_CMD", Command(0.5), NowUs());
  altered.payload[20] ^= 0x01;
  Send("SERVO_CMD", Encode(altered));
  // A genuine envelope signed for another channel (the signature covers the channel).
  Send("SERVO_CMD", Encode(op_.Seal("EXPERIMENT", Command(0.5), NowUs())));
  // A genuine envelope with its time moved (the signature covers the time).
  signed_envelope_t retimed = op_.Seal("SERVO_CMD", Command(0.5), NowUs() - 10'000'000);
  retimed.utime = NowUs();
  Send("SERVO_CMD", Encode(retimed));
  EXPECT_TRUE(got_.empty());
  EXPECT_EQ(Kind("bad signature from operator on SERVO_CMD"), 4);
  // None of them advanced the operator's sequence: a good one still passes.
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs())));
  EXPECT_EQ(got_.size(), 1u);
}

TEST_F(SignedChannelTest, AReplayedEnvelopeIsRefusedHoweverRecent) {
  Listen(250'000);
  const auto bytes = Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs()));
  Send("SERVO_CMD", bytes);
  Send("SERVO_CMD", bytes);
  EXPECT_EQ(got_.size(), 1u);
  EXPECT_EQ(Kind("replayed from operator on SERVO_CMD"), 1);
  // An older genuine envelope (lower sequence) sent after a newer one: refused as well.
  const auto older = Encode(op_.Seal("SERVO_CMD", Command(0.6), NowUs()));
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.7), NowUs())));
  Send("SERVO_CMD", older);
  EXPECT_EQ(got_.size(), 2u);
  EXPECT_EQ(Kind("replayed from operator on SERVO_CMD"), 2);
}

TEST_F(SignedChannelTest, AStaleOrFutureEnvelopeIsRefusedOutsideTheWindow) {
  Listen(250'000);
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs() - 400'000)));
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs() + 400'000)));
  EXPECT_TRUE(got_.empty());
  EXPECT_EQ(Kind("stale from operator on SERVO_CMD"), 2);
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs() + 10'000'000)));
  EXPECT_EQ(Kind("ahead of time from operator on SERVO_CMD"), 1);
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs() - 100'000)));
  // Inside the window, but signed after the future one by the same signer, which counts from
  // max(last + 1, now): its sequence is 10 s ahead too, and refused as well.
  EXPECT_EQ(Kind("ahead of time from operator on SERVO_CMD"), 2);
  EXPECT_TRUE(got_.empty());
  // The receiver adopted neither: the signer restarted with a right clock is heard at once.
  Signer restarted = MakeSigner(1);
  Send("SERVO_CMD", Encode(restarted.Seal("SERVO_CMD", Command(0.5), NowUs() - 100'000)));
  EXPECT_EQ(got_.size(), 1u);
}

// Issue 36, finding 8: on a channel without a window (EXPERIMENT's and CALIBRATION's were), one
// envelope numbered far in the future was adopted, and every honest envelope of its signer was
// then refused as a replay until the receiver restarted.
TEST_F(SignedChannelTest, AFarFutureSequenceIsRefusedNotAdopted) {
  Listen(/*window_us=*/0);
  signed_envelope_t ahead = op_.Seal("SERVO_CMD", Command(0.5), NowUs());
  Signer future = MakeSigner(1);  // the operator's key, its clock a day ahead
  Send("SERVO_CMD", Encode(future.Seal("SERVO_CMD", Command(0.9), NowUs() + 86'400'000'000)));
  EXPECT_EQ(Kind("ahead of time from operator on SERVO_CMD"), 1);
  // Signed now, numbered a day ahead (sequence is signed; only the key holder can do this).
  Signer counted = MakeSigner(1);
  counted.Seal("SERVO_CMD", Command(0.1), NowUs() + 86'400'000'000);  // its counter jumps
  Send("SERVO_CMD", Encode(counted.Seal("SERVO_CMD", Command(0.9), NowUs())));
  EXPECT_EQ(Kind("ahead of time from operator on SERVO_CMD"), 2);
  EXPECT_TRUE(got_.empty());
  // The honest envelope signed before both is still taken: nothing was adopted.
  Send("SERVO_CMD", Encode(ahead));
  ASSERT_EQ(got_.size(), 1u);
  EXPECT_EQ(got_[0].goal_angle_rad[0], 0.5);
  EXPECT_EQ(Kind("replayed from operator on SERVO_CMD"), 0);
}

// Times at the ends of int64 (a key holder may sign anything): refused, and judged without
// overflow (UBSan runs this suite).
TEST_F(SignedChannelTest, ExtremeTimesAreRefusedWithoutOverflow) {
  Listen(250'000);
  Send("SERVO_CMD", Encode(MakeSigner(1).Seal("SERVO_CMD", Command(0.5), INT64_MIN)));
  Send("SERVO_CMD", Encode(MakeSigner(1).Seal("SERVO_CMD", Command(0.5), INT64_MAX)));
  EXPECT_TRUE(got_.empty());
  EXPECT_EQ(Kind("ahead of time from operator on SERVO_CMD"), 1);
  // INT64_MIN signs a sequence of max(1, INT64_MIN) = 1: not above nothing seen, so the window
  // judges it.
  EXPECT_EQ(Kind("stale from operator on SERVO_CMD"), 1);
}

// Issue 36, findings 1 and 2: a receiver forgot on restart what it had accepted. With a store
// (what ServiceApp gives every live process), a new verifier on the same file refuses it.
TEST_F(SignedChannelTest, WhatWasAcceptedIsRefusedAfterARestart) {
  const std::string dir = testing::MakeTempDir();
  const std::string path = dir + "/ftcal-test.seen";
  const auto first = Encode(op_.Seal("EXPERIMENT", experiment_marker_t{}, NowUs()));
  const auto later = Encode(op_.Seal("EXPERIMENT", experiment_marker_t{}, NowUs()));
  auto open = [&](Verifier& v, const std::vector<uint8_t>& b) {
    return v.Open("EXPERIMENT", b.data(), static_cast<int>(b.size()),
                  static_cast<uint64_t>(experiment_marker_t::getHash()), NowUs(), 5'000'000);
  };
  {
    Verifier before({TrustedKey{"operator", op_.public_key(), {"EXPERIMENT"}}});
    auto store = std::make_shared<auth::SeenStore>(path);
    before.Persist(store);
    EXPECT_FALSE(open(before, first).second);
    EXPECT_EQ(store->Flush(), "");
  }
  // The file says what was taken: the signer's key and its sequence, nothing else.
  const auto marks = auth::SeenStore::Read(path);
  ASSERT_EQ(marks.size(), 1u);
  EXPECT_EQ(std::get<1>(marks.begin()->first), "EXPERIMENT");
  EXPECT_EQ(std::get<2>(marks.begin()->first),
            auth::ToHex(op_.public_key().data(), op_.public_key().size()));

  Verifier forgetful({TrustedKey{"operator", op_.public_key(), {"EXPERIMENT"}}});
  EXPECT_FALSE(open(forgetful, first).second) << "without the store a restart takes it again";

  Verifier after({TrustedKey{"operator", op_.public_key(), {"EXPERIMENT"}}});
  after.Persist(std::make_shared<auth::SeenStore>(path));
  const auto refused = open(after, first).second;
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "replayed from operator");
  EXPECT_NE(refused->detail.find(path), std::string::npos) << refused->detail;
  EXPECT_FALSE(open(after, later).second) << "a newer envelope is still taken";
  testing::RemoveTree(dir);
}

TEST(SeenStoreTest, AFileItCannotReadIsRefusedNamingTheLine) {
  const std::string dir = testing::MakeTempDir();
  std::ofstream(dir + "/x.seen")
      << "sequence EXPERIMENT abcd 12\nsequence EXPERIMENT abcd twelve\n";
  try {
    auth::SeenStore store(dir + "/x.seen");
    ADD_FAILURE() << "read";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("x.seen' line 2"), std::string::npos) << e.what();
  }
  testing::RemoveTree(dir);
}

// A recording played to a live process: refused as stale, with a reason that says so.
TEST_F(SignedChannelTest, ARecordingPlayedToALiveReceiverIsRefusedSayingWhy) {
  const auto old = Encode(op_.Seal("EXPERIMENT", experiment_marker_t{}, NowUs() - 3'600'000'000));
  const auto [opened, refused] =
      verifier_.Open("EXPERIMENT", old.data(), static_cast<int>(old.size()),
                     static_cast<uint64_t>(experiment_marker_t::getHash()), NowUs(), 5'000'000);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->kind, "stale from operator");
  EXPECT_NE(refused->detail.find("--log or --replay"), std::string::npos) << refused->detail;
  // Offline, the same envelope judged against the recording's receive time verifies.
  Verifier offline({TrustedKey{"operator", op_.public_key(), {"EXPERIMENT"}}});
  EXPECT_FALSE(offline
                   .Open("EXPERIMENT", old.data(), static_cast<int>(old.size()),
                         static_cast<uint64_t>(experiment_marker_t::getHash()),
                         NowUs() - 3'600'000'000 + 20'000, 5'000'000)
                   .second);
}

TEST_F(SignedChannelTest, SequencesRiseAcrossASignersRestart) {
  Listen(250'000);
  Send("SERVO_CMD", Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs())));
  Signer restarted = MakeSigner(1);  // the same seed, a new process
  ASSERT_EQ(restarted.public_key(), op_.public_key());
  std::this_thread::sleep_for(std::chrono::milliseconds(2));
  Send("SERVO_CMD", Encode(restarted.Seal("SERVO_CMD", Command(0.6), NowUs())));
  EXPECT_EQ(got_.size(), 2u);
}

TEST_F(SignedChannelTest, AMalformedEnvelopeIsRefusedByTheWireGuard) {
  Listen(250'000);
  auto bytes = Encode(op_.Seal("SERVO_CMD", Command(0.5), NowUs()));
  // `size` claims 2^30 payload bytes.
  const size_t at = 8 + 32 + 24;
  bytes[at] = 0x40;
  Send("SERVO_CMD", bytes);
  EXPECT_EQ(Kind("malformed envelope (length over cap) on SERVO_CMD"), 1);
}

// ---- the seed file ----

class SeedFileTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("ftcal_seed_" + std::to_string(::getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }
  std::string Write(const std::string& name, const std::string& text, mode_t mode) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    ::chmod(path.c_str(), mode);
    return path;
  }
  std::filesystem::path dir_;
};

constexpr char kSeedHex[] = "000102030405060708090a0b0c0d0e0f101112131415161718191a1b1c1d1e1f";

TEST_F(SeedFileTest, AKeyFileReadableByOthersIsRefused) {
  const std::string path = Write("op.key", std::string(kSeedHex) + "\n", 0644);
  try {
    Signer::FromSeedFile(path);
    FAIL() << "accepted a key file with mode 0644";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("mode 0644"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
  }
  ::chmod(path.c_str(), 0640);
  EXPECT_THROW(Signer::FromSeedFile(path), std::runtime_error);
  ::chmod(path.c_str(), 0600);
  const Signer s = Signer::FromSeedFile(path);
  std::array<uint8_t, 32> seed{};
  for (int i = 0; i < 32; ++i) seed[i] = static_cast<uint8_t>(i);
  EXPECT_EQ(s.public_key(), Signer::FromSeed(seed).public_key());
}

TEST_F(SeedFileTest, ANonSeedIsRefusedByName) {
  EXPECT_THROW(Signer::FromSeedFile(Write("short.key", "abcd\n", 0600)), std::runtime_error);
  EXPECT_THROW(Signer::FromSeedFile((dir_ / "missing.key").string()), std::runtime_error);
}

// RFC 8032 test vector 1: the seed's public key and the empty message's signature are the
// published ones, so the signatures are standard Ed25519, verifiable by any implementation.
TEST(Ed25519Test, Rfc8032VectorOne) {
  const std::string seed_hex = "9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60";
  std::array<uint8_t, 32> seed{};
  for (int i = 0; i < 32; ++i)
    seed[i] = static_cast<uint8_t>(std::stoi(seed_hex.substr(2 * i, 2), nullptr, 16));
  const Signer s = Signer::FromSeed(seed);
  EXPECT_EQ(auth::ToHex(s.public_key().data(), 32),
            "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a");
}

TEST(KeygenTest, WritesAnOwnerOnlySeedWhosePublicKeyItPrints) {
  const std::string dir =
      std::filesystem::temp_directory_path() / ("ftcal_keygen_" + std::to_string(::getpid()));
  std::filesystem::create_directories(dir);
  const std::string key = dir + "/op.key";
  testing::Child gen({FTCAL_KEYGEN, "--out", key}, dir + "/out", dir + "/err");
  const auto status = gen.Wait(30);
  ASSERT_TRUE(status.has_value());
  EXPECT_EQ(*status, 0) << testing::ReadFile(dir + "/err");
  struct stat st {};
  ASSERT_EQ(::stat(key.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  std::string printed = testing::ReadFile(dir + "/out");
  ASSERT_EQ(printed.size(), 65u) << printed;
  printed.pop_back();
  const Signer s = Signer::FromSeedFile(key);
  EXPECT_EQ(auth::ToHex(s.public_key().data(), 32), printed);
  // A second run never overwrites the key.
  testing::Child again({FTCAL_KEYGEN, "--out", key}, dir + "/out2", dir + "/err2");
  const auto status2 = again.Wait(30);
  ASSERT_TRUE(status2.has_value());
  EXPECT_NE(*status2, 0);
  EXPECT_EQ(auth::ToHex(Signer::FromSeedFile(key).public_key().data(), 32), printed);
  std::filesystem::remove_all(dir);
}

// ftcal-envelopes opens a log's envelopes: signer by name, verdict, the inner message's fields.
TEST(EnvelopesToolTest, PrintsEachEnvelopeOpenedAndFlagsABadSignature) {
  const std::string dir = testing::MakeTempDir();
  Signer op = MakeSigner(1);
  {
    lcm::LogFile log(dir + "/in.lcmlog", "w");
    ASSERT_TRUE(log.good());
    auto write = [&](const signed_envelope_t& e, int64_t t) {
      auto bytes = Encode(e);
      lcm::LogEvent ev{};
      ev.timestamp = t;
      ev.channel = "SERVO_CMD";
      ev.datalen = static_cast<int32_t>(bytes.size());
      ev.data = bytes.data();
      ASSERT_EQ(log.writeEvent(&ev), 0);
    };
    write(op.Seal("SERVO_CMD", Command(0.5), 1'000'000), 1'000'100);
    signed_envelope_t tampered = op.Seal("SERVO_CMD", Command(0.25), 2'000'000);
    tampered.payload[30] ^= 0x40;
    write(tampered, 2'000'100);
  }
  std::ofstream(dir + "/config.pbtxt")
      << testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt")
      << "\nauth { trusted_key { name: \"operator\" public_key_hex: \""
      << auth::ToHex(op.public_key().data(), 32) << "\" channel: \"SERVO_CMD\" } }\n";
  // sim.pbtxt has an auth section already: merge by replacing it.
  std::string text = testing::ReadFile(dir + "/config.pbtxt");
  const auto first = text.find("auth {\n  allow_unsigned: true\n}\n");
  ASSERT_NE(first, std::string::npos);
  text.erase(first, std::string("auth {\n  allow_unsigned: true\n}\n").size());
  std::ofstream(dir + "/config.pbtxt") << text;
  testing::Child tool({FTCAL_ENVELOPES, "--config", dir + "/config.pbtxt", dir + "/in.lcmlog"},
                      dir + "/out", dir + "/err");
  const auto status = tool.Wait(30);
  ASSERT_TRUE(status.has_value());
  const std::string out = testing::ReadFile(dir + "/out");
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 1) << testing::ReadFile(dir + "/err");
  std::istringstream lines(out);
  std::string good, bad;
  std::getline(lines, good);
  std::getline(lines, bad);
  EXPECT_NE(good.find("SERVO_CMD signer=operator"), std::string::npos) << out;
  EXPECT_NE(good.find("signature-ok trusted"), std::string::npos) << out;
  EXPECT_NE(good.find("ftcal.servo_command_t: utime=0 action=0 num_servos=2 id=[1,2] "
                      "goal_angle_rad=[0.5,-0.5] torque_enable=1"),
            std::string::npos)
      << out;
  EXPECT_NE(bad.find("BAD-SIGNATURE"), std::string::npos) << out;
  testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
