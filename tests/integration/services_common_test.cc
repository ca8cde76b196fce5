// services/common without a network: the bus on LCM's in-process memq:// transport, the
// shutdown loop, the heartbeat message, ftcal-status's board, and a real stage process run over
// a log (--replay/--out) whose output is checked event by event against hand-computed values.
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "child_process.h"
#include "test_helpers.h"
#include "common/atomic_log.h"
#include "common/bridge_main.h"
#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/device.h"
#include "common/exit_codes.h"
#include "common/heartbeat.h"
#include "common/service.h"
#include "common/shutdown.h"
#include "common/user_errors.h"
#include "common/written_digest.h"
#include "ftcal/config.h"
#include "ftcal/digest_cache.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "status/status_board.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;

std::shared_ptr<spdlog::logger> QuietLogger() {
  static auto log =
      std::make_shared<spdlog::logger>("test", std::make_shared<spdlog::sinks::null_sink_mt>());
  return log;
}

// An FT message of `n` records received at `utime`, the last one sampled then and each earlier
// one 1 ms before the next; every record's numbers differ from the others'.
ft_batch_t Sample(const std::string& leg, int64_t utime, double scale, int n = 1) {
  ft_batch_t s{};
  s.receipt_utime = utime;
  s.leg = leg;
  s.n = static_cast<int16_t>(n);
  for (int j = 0; j < n; ++j) {
    const int64_t back = n - 1 - j;
    s.sample_utime.push_back(utime - 1000 * back);
    s.rdt_sequence.push_back(utime / 1000 - back);
    s.ft_sequence.push_back(7 * s.rdt_sequence.back());
    s.status.push_back(0);
    std::vector<int32_t> counts(6);
    std::vector<double> wrench(6);
    for (int i = 0; i < 6; ++i) {
      counts[i] = static_cast<int32_t>(1000 * (i + 1) * scale) + j;
      wrench[i] = (i + 1) * scale - 3.5 + 0.25 * j;
    }
    s.counts.push_back(counts);
    s.wrench.push_back(wrench);
    s.gap.push_back(0);
    s.flags.push_back(0);
  }
  return s;
}

template <class Msg>
std::vector<uint8_t> Encode(const Msg& msg) {
  std::vector<uint8_t> bytes(static_cast<size_t>(msg.getEncodedSize()));
  msg.encode(bytes.data(), 0, static_cast<int>(bytes.size()));
  return bytes;
}

// ---- ServiceStats ----

// A box refusing after a reboot flooded the log with 3025 identical lines: a repeated kind is
// logged once, then at most once per period with how many came since; last_error is current.
TEST(ServiceStatsTest, RepeatsAreLoggedOncePerPeriodWithTheirCount) {
  std::ostringstream out;
  auto log = std::make_shared<spdlog::logger>(
      "stats", std::make_shared<spdlog::sinks::ostream_sink_st>(out));
  log->set_pattern("%v");
  ServiceStats stats(log, std::chrono::milliseconds(200));
  for (int i = 0; i < 1000; ++i)
    stats.Error("box refused", "connection refused #" + std::to_string(i));
  for (int i = 0; i < 10; ++i) stats.Drop("bad record", "short");
  auto lines = [&] {
    std::vector<std::string> v;
    std::istringstream in(out.str());
    for (std::string l; std::getline(in, l);) v.push_back(l);
    return v;
  };
  ASSERT_EQ(lines().size(), 2u) << out.str();
  EXPECT_EQ(stats.last_error(), "box refused: connection refused #999");
  std::this_thread::sleep_for(std::chrono::milliseconds(250));
  stats.Error("box refused", "connection refused #1000");
  ASSERT_EQ(lines().size(), 3u) << out.str();
  EXPECT_EQ(
      lines()[2],
      "box refused: 1000 more since the last line (1001 in all); latest: connection refused #1000");
  EXPECT_EQ(stats.kinds().at("box refused"), 1001);
  EXPECT_EQ(stats.errors(), 1001);
  stats.ClearLastError();
  EXPECT_EQ(stats.last_error(), "");
}

// A failure that ends the process is said at once, whatever was logged of its kind before, and
// counted and carried in the status like any error.
TEST(ServiceStatsTest, AFatalErrorIsLoggedEvenAfterRepeatsOfItsKind) {
  std::ostringstream out;
  auto log = std::make_shared<spdlog::logger>(
      "stats", std::make_shared<spdlog::sinks::ostream_sink_st>(out));
  log->set_pattern("%l %v");
  ServiceStats stats(log);
  stats.Error("run", "first");
  stats.Error("run", "second, held back as a repeat");
  stats.Fatal("run", "the device is gone");
  EXPECT_NE(out.str().find("critical run: the device is gone\n"), std::string::npos) << out.str();
  EXPECT_EQ(stats.errors(), 3);
  EXPECT_EQ(stats.kinds().at("run"), 3);
  EXPECT_EQ(stats.last_error(), "run: the device is gone");
}

// ---- RunBridge: where a bridge fails gives its exit code (docs/exit-codes.md) ----

// What a device throws when it refuses the configuration (as QTM refusing the protocol version).
class RefusedByTheDevice : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A device whose first deadline runs `on_deadline`.
class ScriptedDevice : public Device {
 public:
  explicit ScriptedDevice(std::function<void()> on_deadline)
      : on_deadline_(std::move(on_deadline)) {}
  void AddPollFds(std::vector<pollfd>*) override {}
  void OnPolled(const pollfd*, std::size_t) override {}
  Clock::time_point NextDeadline() const override { return Clock::time_point{}; }  // now
  void OnDeadline(Clock::time_point) override { on_deadline_(); }
  bool Degraded(std::string*) override { return false; }

 private:
  std::function<void()> on_deadline_;
};

struct BridgeFailure {
  const char* name;
  BridgeStage stage;
  std::function<void()> fail;  // throws
  int exit_code;
};

class RunBridgeTest : public ::testing::TestWithParam<BridgeFailure> {};

TEST_P(RunBridgeTest, EndsWithTheExitCodeOfWhereItFailed) {
  const BridgeFailure& f = GetParam();
  ClearShutdownRequest();  // the loop that does not fail ends on a request (below)
  const std::string dir = testing::MakeTempDir();
  BridgeSpec<ScriptedDevice> spec;
  spec.service = {"ftcal-scripted-bridge", "a bridge that fails where the test says"};
  spec.configure = [&f](ServiceApp&) {
    if (f.stage == BridgeStage::kConfigure) f.fail();
    return std::make_unique<ScriptedDevice>([&f] {
      if (f.stage == BridgeStage::kRun) f.fail();
      RequestShutdown();
    });
  };
  spec.open = [&f](ScriptedDevice& device) -> Device& {
    if (f.stage == BridgeStage::kOpen) f.fail();
    return device;
  };
  spec.refuses_config = IsA<RefusedByTheDevice>;
  std::vector<std::string> args = {
      "ftcal-scripted-bridge", "--lcm-url", "memq://", "--log-level", "off", "--state-dir", dir};
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  EXPECT_EQ(RunBridge(static_cast<int>(argv.size()), argv.data(), spec), f.exit_code);
  ClearShutdownRequest();
  testing::RemoveTree(dir);
}

INSTANTIATE_TEST_SUITE_P(
    Stages, RunBridgeTest,
    ::testing::Values(
        BridgeFailure{"ConfigChecks", BridgeStage::kConfigure,
                      [] { throw std::invalid_argument("config: foo.rate_hz 0"); }, kExitConfig},
        BridgeFailure{"Opening", BridgeStage::kOpen,
                      [] { throw std::runtime_error("foo: connection refused"); }, kExitDeviceIo},
        BridgeFailure{"OpeningRefusedByTheDevice", BridgeStage::kOpen,
                      [] { throw RefusedByTheDevice("foo refuses version 2"); }, kExitConfig},
        BridgeFailure{"Running", BridgeStage::kRun,
                      [] { throw std::runtime_error("foo: hung up"); }, kExitDeviceIo},
        BridgeFailure{"RunningRefusedByTheDevice", BridgeStage::kRun,
                      [] { throw RefusedByTheDevice("foo refuses version 2"); }, kExitConfig},
        BridgeFailure{"ABugWhileConfiguring", BridgeStage::kConfigure,
                      [] { throw std::out_of_range("vector::_M_range_check"); }, kExitInternal},
        BridgeFailure{"NoFailure", BridgeStage::kRun, [] {}, kExitDone}),
    [](const ::testing::TestParamInfo<BridgeFailure>& info) { return info.param.name; });

// ---- the LCM URL ----

TEST(LcmUrlTest, TtlAboveZeroAndARecvBufferAboveTheKernelLimitAreNamed) {
  EXPECT_TRUE(LcmUrlWarnings("udpm://239.255.76.67:7667?ttl=0", 212992).empty());
  EXPECT_TRUE(
      LcmUrlWarnings("udpm://239.255.76.67:7667?ttl=0&recv_buf_size=212992", 212992).empty());
  EXPECT_TRUE(LcmUrlWarnings("memq://", 0).empty());
  const auto ttl = LcmUrlWarnings("udpm://239.255.76.67:7667?ttl=1", 212992);
  ASSERT_EQ(ttl.size(), 1u);
  EXPECT_NE(ttl[0].find("ttl=1 sends every message"), std::string::npos) << ttl[0];
  const auto buf = LcmUrlWarnings("udpm://239.255.76.67:7667?ttl=0&recv_buf_size=8388608", 212992);
  ASSERT_EQ(buf.size(), 1u);
  EXPECT_NE(buf[0].find("recv_buf_size=8388608 but the kernel allows 212992 bytes"),
            std::string::npos)
      << buf[0];
  EXPECT_NE(buf[0].find("sysctl -w net.core.rmem_max=8388608"), std::string::npos) << buf[0];
  // LCM's multi-port provider takes the same two options.
  EXPECT_TRUE(LcmUrlWarnings("mpudpm://239.255.76.67:7667?ttl=0&nports=64", 212992).empty());
  EXPECT_EQ(
      LcmUrlWarnings("mpudpm://239.255.76.67:7667?ttl=1&nports=64&recv_buf_size=8388608", 212992)
          .size(),
      2u);
}

// ---- AtomicLogFile's temporary file ----

// A pid that was alive a moment ago and is not any more.
pid_t DeadPid() {
  const pid_t pid = ::fork();
  if (pid == 0) ::_exit(0);
  ::waitpid(pid, nullptr, 0);
  return pid;
}

bool Exists(const std::string& path) {
  struct stat st {};
  return ::lstat(path.c_str(), &st) == 0;
}

// kill -9 of each stage left 1.3 GB of *.tmp.<pid> files: the temporary file is beside the
// target under a name no one can predict, gone after an uncommitted run, and a new run of the
// same output removes what dead runs left (and only that).
TEST(AtomicLogFileTest, TemporaryFileBesideTheTargetAndLeftoversOfDeadRunsRemoved) {
  const std::string dir = testing::MakeTempDir();
  const std::string out = dir + "/out.lcmlog";
  const std::string dead = dir + "/.out.lcmlog.tmp." + std::to_string(DeadPid()) + ".Ab12Cd";
  const std::string alive = dir + "/.out.lcmlog.tmp." + std::to_string(::getppid()) + ".Ef34Gh";
  const std::string other = dir + "/.other.lcmlog.tmp." + std::to_string(DeadPid()) + ".Ij56Kl";
  for (const auto& p : {dead, alive, other}) std::ofstream(p) << "leftover";
  {
    AtomicLogFile log(out, "test output");
    EXPECT_FALSE(Exists(dead)) << "a dead run's leftover of this output stays";
    EXPECT_TRUE(Exists(alive)) << "a running writer's file was removed";
    EXPECT_TRUE(Exists(other)) << "another output's file was removed";
    const std::string prefix = dir + "/.out.lcmlog.tmp." + std::to_string(::getpid()) + ".";
    EXPECT_EQ(log.temp_path().compare(0, prefix.size(), prefix), 0) << log.temp_path();
    EXPECT_EQ(log.temp_path().size(), prefix.size() + 6);
    EXPECT_TRUE(Exists(log.temp_path()));
    log.Write(1, "CH", "abc", 3);
  }
  EXPECT_FALSE(Exists(out)) << "an uncommitted log appeared under the final name";
  std::vector<std::string> names;
  for (const auto& e : std::filesystem::directory_iterator(dir))
    names.push_back(e.path().filename());
  EXPECT_EQ(names.size(), 2u) << "the uncommitted temporary file stayed";
  {
    AtomicLogFile log(out, "test output");
    log.Write(1, "CH", "abc", 3);
    log.Commit();
    EXPECT_FALSE(Exists(log.temp_path()));
    struct stat st {};
    ASSERT_EQ(::stat(out.c_str(), &st), 0);
    EXPECT_EQ(st.st_mode & 0777, 0644u);
  }
  // An output that cannot be written is known before any work: the constructor refuses.
  try {
    AtomicLogFile log(dir + "/no/such/dir/out.lcmlog", "test output");
    ADD_FAILURE() << "a log in a missing directory was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("cannot create a file in '" + dir + "/no/such/dir'"),
              std::string::npos)
        << e.what();
  }
  try {
    AtomicLogFile log(dir, "test output");
    ADD_FAILURE() << "a directory as the output was accepted";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("is a directory"), std::string::npos) << e.what();
  }
  testing::RemoveTree(dir);
}

// A writer's digest: the tap sees every byte of the committed file, in order (its SHA-256 is
// the file's), the status after Commit() is the file's under its final name, and the digest
// handed to the cache is what a reader then finds there. A tap set late, or one that fails,
// hands nothing over.
TEST(AtomicLogFileTest, ATapSeesEveryByteAndTheDigestIsHandedToTheCache) {
  const std::string dir = testing::MakeTempDir();
  const std::string out = dir + "/out.lcmlog";
  const DigestCache cache(dir + "/cache");
  const testing::ScopedEnv cache_env("FTCAL_CACHE_DIR", dir + "/cache");
  std::string payload(3000, '\0');
  for (size_t i = 0; i < payload.size(); ++i) payload[i] = static_cast<char>(i * 7);
  {
    AtomicLogFile log(out, "test output");
    WrittenDigest digest;
    log.SetTap(digest.Tap());
    // Over 1 MiB, so that the writer thread hands over several buffers.
    for (int i = 0; i < 1000; ++i)
      log.Write(i, i % 2 ? "FT_LF" : "SERVO_STATE", payload.data(), 1 + (i * 37) % 3000);
    EXPECT_THROW(log.SetTap([](const char*, size_t) {}), std::logic_error);
    EXPECT_EQ(log.committed_stat().st_ino, 0u) << "a status before Commit()";
    log.Commit();
    struct stat st {};
    ASSERT_EQ(::stat(out.c_str(), &st), 0);
    EXPECT_EQ(log.committed_stat().st_ino, st.st_ino);
    EXPECT_EQ(log.committed_stat().st_size, st.st_size);
    EXPECT_GT(st.st_size, 1 << 20);
    const std::string hex = digest.HandOver(out, log.committed_stat());
    EXPECT_EQ(hex, Sha256File(out));
    EXPECT_EQ(cache.Lookup(out), std::optional<std::string>(Sha256File(out)));
  }
  // A tap that throws has not seen every byte: no status, nothing handed over; the log is
  // still written.
  const std::string out2 = dir + "/out2.lcmlog";
  {
    AtomicLogFile log(out2, "test output");
    log.SetTap([](const char*, size_t) { throw std::runtime_error("digest failed"); });
    log.Write(1, "CH", "abc", 3);
    log.Commit();
    EXPECT_EQ(log.committed_stat().st_ino, 0u);
    WrittenDigest digest;
    EXPECT_EQ(digest.HandOver(out2, log.committed_stat()), "");
    EXPECT_FALSE(cache.Lookup(out2));
    EXPECT_TRUE(Exists(out2));
  }
  testing::RemoveTree(dir);
}

// ---- the bus on memq:// ----

TEST(LcmBusTest, TypedHandlersGetDecodedMessagesAndBadOnesAreCountedNotThrown) {
  ServiceStats stats(QuietLogger());
  LcmBus bus("memq://", stats);
  std::vector<ft_batch_t> got;
  bus.Subscribe<ft_batch_t>("FT_.*", [&](const MessageInfo& info, const ft_batch_t& s) {
    EXPECT_EQ(info.channel, "FT_" + s.leg);
    EXPECT_GT(info.recv_utime, 0);
    if (s.leg == "XX") throw BadInput("unknown leg", "leg XX");
    if (std::count(s.status.begin(), s.status.end(), 666) > 0) throw std::runtime_error("boom");
    got.push_back(s);
  });
  const uint8_t garbage[7] = {1, 2, 3, 4, 5, 6, 7};
  bus.PublishRaw("FT_HL", garbage, sizeof(garbage));  // drop: undecodable
  bus.Publish("FT_ML", experiment_marker_t{});        // drop: wrong type
  bus.Publish("FT_FL", Sample("FL", 10, 1.0));        // ok
  bus.Publish("FT_XX", Sample("XX", 11, 1.0));        // drop: BadInput
  ft_batch_t failing = Sample("HR", 12, 1.0, 3);
  failing.status[1] = 666;
  bus.Publish("FT_HR", failing);                   // error: exception
  bus.Publish("FT_MR", Sample("MR", 13, 2.0, 3));  // ok
  bus.Publish("OTHER", Sample("FR", 14, 1.0));     // not subscribed
  while (bus.HandleOnce(0) > 0) {
  }
  ASSERT_EQ(got.size(), 2u);
  EXPECT_EQ(got[0].leg, "FL");
  EXPECT_EQ(got[1].leg, "MR");
  ASSERT_EQ(got[1].n, 3);
  ASSERT_EQ(got[1].wrench.size(), 3u);
  EXPECT_EQ(got[1].wrench[0][5], 6 * 2.0 - 3.5);
  EXPECT_EQ(got[1].wrench[2][5], 6 * 2.0 - 3.5 + 0.5);
  EXPECT_EQ(got[1].sample_utime, (std::vector<int64_t>{13 - 2000, 13 - 1000, 13}));
  EXPECT_EQ(stats.msgs_out(), 7);
  EXPECT_EQ(stats.msgs_in(), 6);
  EXPECT_EQ(stats.drops(), 3);
  EXPECT_EQ(stats.errors(), 1);
  EXPECT_EQ(stats.last_error(), "handler for FT_.*: boom");
  EXPECT_EQ(stats.kinds().at("unknown leg"), 1);
  EXPECT_EQ(stats.kinds().at("undecodable ft_batch_t on FT_HL: truncated"), 1);
  EXPECT_EQ(stats.kinds().at("undecodable ft_batch_t on FT_ML: wrong fingerprint"), 1);
}

// A consumer that cannot keep up sheds what waited too long instead of serving it late. memq
// stamps each message when it is published, so 200 published at once and handled at 2 ms each
// have waited 2 ms more with every message handled.
TEST(LcmBusTest, ShedLateDropsWhatWaitedTooLongAndServesTheRestFresh) {
  ServiceStats stats(QuietLogger());
  LcmBus bus("memq://", stats);
  constexpr int kSent = 200;
  constexpr int64_t kMaxQueueUs = 20'000;
  std::vector<int64_t> waited_us;
  int other = 0;
  bus.Subscribe<ft_batch_t>("FT_HL", [&](const MessageInfo& info, const ft_batch_t&) {
    waited_us.push_back(bus.NowUtime() - info.recv_utime);
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  });
  bus.Subscribe<ft_batch_t>("FT_ML", [&](const MessageInfo&, const ft_batch_t&) { ++other; });
  bus.ShedLate("FT_HL", kMaxQueueUs);
  for (int i = 0; i < kSent; ++i) bus.Publish("FT_HL", Sample("HL", i, 1.0));
  for (int i = 0; i < 50; ++i) bus.Publish("FT_ML", Sample("ML", i, 1.0));
  while (bus.HandleOnce(0) > 0) {
  }
  const int handled = static_cast<int>(waited_us.size());
  const int64_t shed = stats.kinds().count("late FT_HL") ? stats.kinds().at("late FT_HL") : 0;
  // 20 ms of queue at >= 2 ms per message: at most 11 handled (fewer on a slow machine).
  EXPECT_GE(handled, 1);
  EXPECT_LE(handled, 11);
  EXPECT_EQ(handled + shed, kSent);
  EXPECT_EQ(stats.drops(), shed);
  for (int64_t w : waited_us) EXPECT_LE(w, kMaxQueueUs);
  // The other channel waited as long and was not shed: only the named subscription sheds.
  EXPECT_EQ(other, 50);
  EXPECT_EQ(stats.msgs_in(), kSent + 50);
}

// The standard library's texts for its own failures never reach a user; ftcal's texts do.
// Each library exception is a real one, thrown by the call that throws it in a program.
TEST(UserErrorsTest, LibraryTextsAreNamedAsWhatTheyAreAndFtcalTextsPassThrough) {
  auto caught = [](auto&& fn) -> std::exception_ptr {
    try {
      fn();
    } catch (...) {
      return std::current_exception();
    }
    return nullptr;
  };
  auto text = [](std::exception_ptr p, const char* doing) {
    try {
      std::rethrow_exception(p);
    } catch (const std::exception& e) {
      return std::pair{UserText(e, doing), ExitCodeFor(e, kExitRefused)};
    }
    return std::pair{std::string(), -1};
  };
  struct Case {
    std::exception_ptr thrown;
    const char* library_text;  // what the library says, which must not be shown
  };
  std::string empty;
  std::vector<int> six(6);
  const Case internal[] = {
      {caught([&] { empty.replace(5, 1, "x"); }), "basic_string"},
      {caught([&] { (void)six.at(7); }), "_M_range_check"},
      {caught([] { (void)std::stoi("abc"); }), "stoi"},
      {caught([] { (void)std::stoi("99999999999999999999"); }), "stoi"},
      {caught([&] { empty.reserve(empty.max_size() + 1); }), "basic_string"},
      {caught([] { throw std::bad_alloc(); }), "bad_alloc"},
      {caught([] {
         std::function<void()> f;
         f();
       }),
       "bad_function_call"},
  };
  for (const Case& c : internal) {
    ASSERT_TRUE(c.thrown) << c.library_text;
    const auto [shown, rc] = text(c.thrown, "reading the logs");
    EXPECT_EQ(shown.find(c.library_text), std::string::npos) << shown;
    EXPECT_NE(shown.find("while reading the logs"), std::string::npos) << shown;
    EXPECT_EQ(rc, kExitInternal) << shown;
  }
  EXPECT_EQ(text(caught([] { throw std::bad_alloc(); }), "reading the logs").first,
            "out of memory while reading the logs");
  const char* ours[] = {"robot.leg[2].servo.id: 300 is above 252",
                        "channel pattern '[' is not a valid regular expression",
                        "replay input '/x.lcmlog': No such file or directory"};
  const std::exception_ptr ftcal_thrown[] = {caught([&] { throw ConfigError(ours[0]); }),
                                             caught([&] { throw std::invalid_argument(ours[1]); }),
                                             caught([&] { throw std::runtime_error(ours[2]); })};
  for (int i = 0; i < 3; ++i) {
    const auto [shown, rc] = text(ftcal_thrown[i], "reading the logs");
    EXPECT_EQ(shown, ours[i]);
    EXPECT_EQ(rc, kExitRefused);
  }
}

// A handler's bug reaches the status (what ftcal-status shows) as a bug, not as the library's
// text.
TEST(UserErrorsTest, AHandlersIndexOutOfRangeIsCountedAsAnInternalErrorInTheStatus) {
  ServiceStats stats(QuietLogger());
  LcmBus bus("memq://", stats);
  bus.Subscribe<ft_batch_t>("FT_.*", [&](const MessageInfo&, const ft_batch_t& s) {
    std::vector<double> three(3);
    (void)three.at(static_cast<std::size_t>(s.status.at(0)));
  });
  ft_batch_t bad = Sample("HL", 10, 1.0);
  bad.status[0] = 7;
  bus.Publish("FT_HL", bad);
  while (bus.HandleOnce(0) > 0) {
  }
  EXPECT_EQ(stats.errors(), 1);
  EXPECT_EQ(stats.last_error().find("_M_range_check"), std::string::npos) << stats.last_error();
  EXPECT_NE(stats.last_error().find("an internal error while handling a message on FT_HL"),
            std::string::npos)
      << stats.last_error();
}

TEST(LcmBusTest, BadUrlIsAClearError) {
  ServiceStats stats(QuietLogger());
  try {
    LcmBus bus("nosuchprovider://x", stats);
    FAIL() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("nosuchprovider://x"), std::string::npos) << e.what();
  }
}

TEST(ShutdownLoopTest, SigtermEndsAQuietLoopPromptly) {
  ServiceStats stats(QuietLogger());
  LcmBus bus("memq://", stats);
  ClearShutdownRequest();
  InstallShutdownHandlers();
  int ticks = 0;
  std::chrono::steady_clock::time_point sent;
  std::thread killer([&sent] {
    std::this_thread::sleep_for(std::chrono::milliseconds(350));
    sent = std::chrono::steady_clock::now();
    ::kill(::getpid(), SIGTERM);  // to the process, as `kill` would: any thread may take it
  });
  bus.Run([&ticks] { ++ticks; }, 50'000);
  const auto ended = std::chrono::steady_clock::now();
  killer.join();
  EXPECT_TRUE(ShutdownRequested());
  ClearShutdownRequest();
  // The loop wakes at least every 100 ms; 200 ms allows for a loaded machine.
  EXPECT_LT(std::chrono::duration<double>(ended - sent).count(), 0.2);
  // Periodic work ran while the bus was quiet (every 50 ms for 350 ms).
  EXPECT_GE(ticks, 3);
}

// ---- the heartbeat message ----

TEST(HeartbeatTest, StatusCarriesIdentityStateAndEveryCounter) {
  ServiceStats stats(QuietLogger());
  stats.CountIn();
  stats.CountIn();
  stats.CountOut();
  stats.Drop("k1", "r1");
  stats.Drop("k1", "r2");
  stats.Error("k2", "went wrong");
  stats.Counter("zeta") = 5;
  stats.Counter("alpha") = -2;
  const ProcessIdentity id{"ftcal-x", "hostA", 4242};
  const service_status_t s =
      MakeServiceStatus(id, int8_t{service_status_t::DEGRADED}, 12.5, stats, 1'000'000);
  EXPECT_EQ(s.name, "ftcal-x");
  EXPECT_EQ(s.host, "hostA");
  EXPECT_EQ(s.pid, 4242);
  EXPECT_EQ(s.state, int8_t{service_status_t::DEGRADED});
  EXPECT_EQ(s.uptime_s, 12.5);
  EXPECT_EQ(s.utime, 1'000'000);
  EXPECT_EQ(s.msgs_in, 2);
  EXPECT_EQ(s.msgs_out, 1);
  EXPECT_EQ(s.drops, 2);
  EXPECT_EQ(s.errors, 1);
  EXPECT_EQ(s.last_error, "k2: went wrong");
  ASSERT_EQ(s.num_counters, 2);
  EXPECT_EQ(s.counter_name, (std::vector<std::string>{"alpha", "zeta"}));
  EXPECT_EQ(s.counter_value, (std::vector<int64_t>{-2, 5}));
  // It survives LCM's encoding: the counters' lengths match num_counters.
  const auto bytes = Encode(s);
  service_status_t back;
  ASSERT_EQ(back.decode(bytes.data(), 0, static_cast<int>(bytes.size())),
            static_cast<int>(bytes.size()));
  EXPECT_EQ(back.counter_value, s.counter_value);
  EXPECT_EQ(ThisProcess("p").pid, static_cast<int64_t>(::getpid()));
}

// ---- ftcal-status's board ----

service_status_t Beat(const std::string& name, int64_t pid, int8_t state) {
  service_status_t s{};
  s.name = name;
  s.host = "h";
  s.pid = pid;
  s.state = state;
  s.uptime_s = 75;
  s.msgs_in = 11;
  s.msgs_out = 22;
  s.num_counters = 1;
  s.counter_name = {"frames"};
  s.counter_value = {9};
  return s;
}

TEST(StatusBoardTest, SilentProcessesAreLostOrStoppedAfterTheThreshold) {
  StatusBoard board(3.0);
  const int64_t t0 = 1'000'000'000;
  board.Update(Beat("b-proc", 2, service_status_t::RUNNING), t0);
  board.Update(Beat("a-proc", 1, service_status_t::RUNNING), t0);
  board.Update(Beat("c-proc", 3, service_status_t::STOPPING), t0);
  board.Update(Beat("a-proc", 1, service_status_t::DEGRADED), t0 + 2'000'000);  // newer beat

  auto rows = board.Rows(t0 + 3'000'000);  // exactly 3 s: not yet silent *longer* than 3 s
  ASSERT_EQ(rows.size(), 3u);
  EXPECT_EQ(rows[0].status.name, "a-proc");
  EXPECT_EQ(rows[0].shown_state, "DEGRADED");
  EXPECT_DOUBLE_EQ(rows[0].age_s, 1.0);
  EXPECT_EQ(rows[1].shown_state, "RUNNING");
  EXPECT_EQ(rows[2].shown_state, "STOPPING");

  rows = board.Rows(t0 + 3'000'001);
  EXPECT_EQ(rows[0].shown_state, "DEGRADED");
  EXPECT_EQ(rows[1].shown_state, "LOST");
  EXPECT_EQ(rows[2].shown_state, "STOPPED");
}

TEST(StatusBoardTest, RenderShowsEveryColumnAndNeutralisesControlCharacters) {
  StatusBoard board;
  service_status_t s = Beat("ftcal-x", 77, service_status_t::RUNNING);
  s.last_error = "bad\x1b[2Jthing\nnext";
  board.Update(s, 5'000'000);
  const std::string table = board.Render(5'500'000);
  EXPECT_EQ(table,
            "NAME     HOST  PID  STATE    UPTIME  IN  OUT  DROPS  ERRORS  AGE   LAST ERROR         "
            "COUNTERS\n"
            "ftcal-x  h     77   RUNNING  1m15s   11  22   0      0       0.5s  bad?[2Jthing?next  "
            "frames=9\n");
  EXPECT_EQ(StatusBoard().Render(0).find("(no heartbeats yet)") != std::string::npos, true);
}

// ---- a stage over a log ----

class ReplayStageTest : public ::testing::Test {
 protected:
  void SetUp() override { dir_ = testing::MakeTempDir(); }
  void TearDown() override {
    if (!HasFailure()) testing::RemoveTree(dir_);
  }
  std::string Path(const std::string& name) const { return dir_ + "/" + name; }
  static void Write(lcm::LogFile& log, const std::string& channel, int64_t t,
                    const std::vector<uint8_t>& bytes) {
    lcm::LogEvent e{};
    e.timestamp = t;
    e.channel = channel;
    e.datalen = static_cast<int32_t>(bytes.size());
    e.data = const_cast<uint8_t*>(bytes.data());
    ASSERT_EQ(log.writeEvent(&e), 0);
  }
  std::string dir_;
};

using Event = testing::LoggedEvent;
using testing::ReadLogEvents;

template <class Msg>
Msg Decode(const Event& e) {
  Msg m;
  EXPECT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
            static_cast<int>(e.data.size()))
      << e.channel;
  return m;
}

TEST_F(ReplayStageTest, OutputsCarryTheInputTimesAndBadEventsAreCounted) {
  const int64_t t0 = 1'700'000'000'000'000;
  const int64_t ms = 1000;
  const std::string legs[] = {"HL", "ML", "FL", "HR", "MR", "FR"};
  const std::string in_path = Path("in.lcmlog");
  const std::vector<uint8_t> sacrificed = Encode(Sample("FR", t0, 9.0));
  const size_t damaged_bytes = 4 + 8 + 8 + 4 + 4 + 5 + sacrificed.size() + 13;
  {
    lcm::LogFile in(in_path, "w");
    ASSERT_TRUE(in.good());
    // Valid samples every 250 ms from t0 to t0 + 2.5 s, with bad events between them.
    for (int k = 0; k <= 10; ++k) {
      const int64_t t = t0 + k * 250 * ms;
      Write(in, "ECHO_IN", t, Encode(Sample(legs[k % 6], t - 5 * ms, k + 1.0, 1 + k % 3)));
      if (k == 0) Write(in, "OTHER", t + 10 * ms, Encode(Sample("HL", t, 1.0)));  // ignored
      if (k == 1) {
        Write(in, "ECHO_IN", t0 + 300 * ms, {0xde, 0xad, 0xbe, 0xef, 1, 2, 3});  // corrupt
        Write(in, "ECHO_IN", t0 + 400 * ms, Encode(experiment_marker_t{}));      // wrong type
        // Damage in the file itself: 13 bytes that are no event at all. LCM's reader refuses
        // the event before them too (it must be followed by a sync word), so that one is on a
        // channel the stage ignores, and the damage spans it and the junk.
        Write(in, "OTHER", t0 + 450 * ms, sacrificed);
        const char junk[] = "not an event";
        ASSERT_EQ(std::fwrite(junk, 1, 13, in.getFilePtr()), 13u);
      }
      if (k == 2) {
        Write(in, "ECHO_IN", t0 + 600 * ms, Encode(Sample("XX", t0, 1.0)));  // unknown leg
        ft_batch_t failing = Sample("HL", t0, 1.0, 2);
        failing.status[1] = 666;  // the stage's handler throws
        Write(in, "ECHO_IN", t0 + 700 * ms, Encode(failing));
      }
    }
  }
  const std::string out_path = Path("out.lcmlog");
  Child stage({FTCAL_ECHO_STAGE, "--replay", in_path, "--out", out_path}, Path("stage.out"),
              Path("stage.err"));
  const auto rc = stage.Wait(30);
  ASSERT_TRUE(rc.has_value()) << "replay did not finish";
  ASSERT_EQ(DescribeWaitStatus(*rc), "exit 0") << ReadFile(Path("stage.err"));

  // Hand-computed expectation: each valid sample echoed at its own time with the wrench
  // doubled; a tick at t0 + 1 s and t0 + 2 s (before the sample at that time) counting the
  // samples echoed so far; the final status at the last event's time.
  const auto out = ReadLogEvents(out_path);
  ASSERT_EQ(out.size(), 11u + 2u + 1u);
  size_t i = 0;
  for (int k = 0; k <= 10; ++k) {
    const int64_t t = t0 + k * 250 * ms;
    if (k == 4 || k == 8) {
      ASSERT_EQ(out[i].channel, "ECHO_TICK");
      EXPECT_EQ(out[i].timestamp, t);
      const auto tick = Decode<experiment_marker_t>(out[i]);
      EXPECT_EQ(tick.utime, t);
      EXPECT_EQ(tick.note, std::to_string(k));
      ++i;
    }
    ASSERT_EQ(out[i].channel, "ECHO_OUT") << "event " << i;
    EXPECT_EQ(out[i].timestamp, t);
    const ft_batch_t expected_in = Sample(legs[k % 6], t - 5 * ms, k + 1.0, 1 + k % 3);
    const auto echoed = Decode<ft_batch_t>(out[i]);
    EXPECT_EQ(echoed.receipt_utime, t);
    EXPECT_EQ(echoed.leg, expected_in.leg);
    ASSERT_EQ(echoed.n, expected_in.n) << "event " << i;
    EXPECT_EQ(echoed.sample_utime, expected_in.sample_utime);
    EXPECT_EQ(echoed.rdt_sequence, expected_in.rdt_sequence);
    EXPECT_EQ(echoed.counts, expected_in.counts);
    ASSERT_EQ(echoed.wrench.size(), expected_in.wrench.size());
    for (size_t r = 0; r < echoed.wrench.size(); ++r) {
      ASSERT_EQ(echoed.wrench[r].size(), 6u);
      for (int a = 0; a < 6; ++a) EXPECT_EQ(echoed.wrench[r][a], 2 * expected_in.wrench[r][a]);
    }
    ++i;
  }
  ASSERT_EQ(out[i].channel, "FTCAL_STATUS");
  EXPECT_EQ(out[i].timestamp, t0 + 2500 * ms);
  const auto status = Decode<service_status_t>(out[i]);
  EXPECT_EQ(status.name, "ftcal-echo-stage");
  EXPECT_EQ(status.state, int8_t{service_status_t::STOPPING});
  EXPECT_EQ(status.msgs_in, 11 + 4);   // every ECHO_IN event, bad ones included
  EXPECT_EQ(status.msgs_out, 11 + 2);  // echoes and ticks; the status does not count itself
  EXPECT_EQ(status.drops, 3);          // corrupt, wrong type, unknown leg
  EXPECT_EQ(status.errors, 2);         // the damaged bytes, the handler's exception
  EXPECT_EQ(status.last_error, "handler for ECHO_IN: handler failure requested by status 666");
  ASSERT_EQ(status.num_counters, 1);
  EXPECT_EQ(status.counter_name[0], "echoed");
  EXPECT_EQ(status.counter_value[0], 11);
  // The damage was reported with where it is.
  EXPECT_NE(ReadFile(Path("stage.err"))
                .find("skipped " + std::to_string(damaged_bytes) + " unreadable bytes"),
            std::string::npos)
      << ReadFile(Path("stage.err"));
  // Written atomically: nothing but the input and the output in the directory.
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir_)) {
    const auto name = entry.path().filename().string();
    if (name.find(".lcmlog") != std::string::npos) {
      EXPECT_TRUE(name == "in.lcmlog" || name == "out.lcmlog") << name;
      ++files;
    }
  }
  EXPECT_EQ(files, 2);
}

TEST_F(ReplayStageTest, ATruncatedLastEventIsCountedAndTheRestReplayed) {
  const std::string in_path = Path("in.lcmlog");
  {
    lcm::LogFile in(in_path, "w");
    Write(in, "ECHO_IN", 1'000'000, Encode(Sample("HL", 1, 1.0)));
    Write(in, "ECHO_IN", 2'000'000, Encode(Sample("ML", 2, 1.0)));
  }
  const auto size = std::filesystem::file_size(in_path);
  std::filesystem::resize_file(in_path, size - 5);
  const std::string out_path = Path("out.lcmlog");
  Child stage({FTCAL_ECHO_STAGE, "--replay", in_path, "--out", out_path}, Path("stage.out"),
              Path("stage.err"));
  const auto rc = stage.Wait(30);
  ASSERT_TRUE(rc.has_value());
  ASSERT_EQ(DescribeWaitStatus(*rc), "exit 0") << ReadFile(Path("stage.err"));
  const auto out = ReadLogEvents(out_path);
  ASSERT_EQ(out.size(), 2u);  // one echo, the final status
  EXPECT_EQ(out[0].channel, "ECHO_OUT");
  EXPECT_EQ(out[0].timestamp, 1'000'000);
  const auto status = Decode<service_status_t>(out[1]);
  EXPECT_EQ(status.msgs_in, 1);
  EXPECT_EQ(status.errors, 1);
  EXPECT_NE(status.last_error.find("unreadable bytes at offset"), std::string::npos)
      << status.last_error;
}

TEST_F(ReplayStageTest, AMissingInputIsRefusedAndNoOutputIsLeft) {
  const std::string out_path = Path("out.lcmlog");
  Child stage({FTCAL_ECHO_STAGE, "--replay", Path("absent.lcmlog"), "--out", out_path},
              Path("stage.out"), Path("stage.err"));
  const auto rc = stage.Wait(30);
  ASSERT_TRUE(rc.has_value());
  EXPECT_EQ(DescribeWaitStatus(*rc), "exit 4");  // docs/exit-codes.md: I/O
  const std::string err = ReadFile(Path("stage.err"));
  EXPECT_NE(err.find(Path("absent.lcmlog")), std::string::npos) << err;
  EXPECT_NE(err.find("No such file"), std::string::npos) << err;
  EXPECT_FALSE(std::filesystem::exists(out_path));
}

TEST_F(ReplayStageTest, ABadConfigFileExitsThreeNamingTheFile) {
  const std::string config = Path("bad.pbtxt");
  std::ofstream(config) << "lcm_url: \"memq://\"\nno_such_field: 3\n";
  Child stage({FTCAL_ECHO_STAGE, "--config", config}, Path("stage.out"), Path("stage.err"));
  const auto rc = stage.Wait(30);
  ASSERT_TRUE(rc.has_value());
  EXPECT_EQ(DescribeWaitStatus(*rc), "exit 3");  // docs/exit-codes.md: config
  const std::string err = ReadFile(Path("stage.err"));
  EXPECT_NE(err.find(config + ":2:"), std::string::npos) << err;
  EXPECT_NE(err.find("no_such_field"), std::string::npos) << err;
}

TEST_F(ReplayStageTest, ReplayFlagsMustComeTogether) {
  Child stage({FTCAL_ECHO_STAGE, "--replay", Path("x.lcmlog")}, Path("stage.out"),
              Path("stage.err"));
  const auto rc = stage.Wait(30);
  ASSERT_TRUE(rc.has_value());
  EXPECT_NE(DescribeWaitStatus(*rc), "exit 0");
  EXPECT_NE(ReadFile(Path("stage.err")).find("--out"), std::string::npos)
      << ReadFile(Path("stage.err"));
}

// docs/exit-codes.md: a bad flag is usage (1) in every program, whatever CLI11 calls it; an
// invalid --log-level is one (it once silenced all logging, and a refusal then exited with no
// message); --help shows the table.
TEST_F(ReplayStageTest, BadFlagsExitOneAndHelpListsTheExitCodes) {
  for (const std::vector<std::string>& args :
       {std::vector<std::string>{"--log-level", "verbose"},
        std::vector<std::string>{"--replay", Path("x.lcmlog")},
        std::vector<std::string>{"--no-such-flag"}}) {
    std::vector<std::string> argv = {FTCAL_ECHO_STAGE};
    argv.insert(argv.end(), args.begin(), args.end());
    Child stage(argv, Path("stage.out"), Path("stage.err"));
    const auto rc = stage.Wait(30);
    ASSERT_TRUE(rc.has_value());
    EXPECT_EQ(DescribeWaitStatus(*rc), "exit 1") << args[0];
  }
  EXPECT_NE(ReadFile(Path("stage.err")).find("--no-such-flag"), std::string::npos);
  {
    Child stage({FTCAL_ECHO_STAGE, "--log-level", "verbose"}, Path("stage.out"), Path("stage.err"));
    ASSERT_TRUE(stage.Wait(30).has_value());
    const std::string err = ReadFile(Path("stage.err"));
    EXPECT_NE(err.find("--log-level"), std::string::npos) << err;
    EXPECT_NE(err.find("verbose"), std::string::npos) << err;
  }
  Child help({FTCAL_ECHO_STAGE, "--help"}, Path("help.out"), Path("help.err"));
  const auto rc = help.Wait(30);
  ASSERT_TRUE(rc.has_value());
  EXPECT_EQ(DescribeWaitStatus(*rc), "exit 0");
  EXPECT_NE(ReadFile(Path("help.out")).find("Exit codes: 0 done; 1 usage"), std::string::npos)
      << ReadFile(Path("help.out"));
}

}  // namespace
}  // namespace ftcal
