// ftcal-record as a process over real LCM multicast (inside scripts/netns-exec): a burst
// published as fast as one process can is recorded whole, in order, byte for byte, and an
// existing recording is never overwritten. Debian's lcm-logger recorded 612 of the same 5000
// here (LCM's default 30-message queue, which it cannot change): the reason ftcal-record exists.
#include <signal.h>
#include <sys/wait.h>

#include <cstdlib>
#include <filesystem>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/config.h"
#include "ftcal/digest_cache.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=4194304";

using testing::SleepS;

std::unique_ptr<Child> StartRecorder(const std::string& dir, const std::vector<std::string>& args,
                                     const std::string& tag) {
  std::vector<std::string> argv = {FTCAL_RECORD, "--config",
                                   std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt", "--lcm-url",
                                   kUrl};
  argv.insert(argv.end(), args.begin(), args.end());
  return std::make_unique<Child>(argv, dir + "/" + tag + ".out", dir + "/" + tag + ".err");
}

int Stop(Child& c) {
  c.Signal(SIGINT);
  const auto status = c.Wait(10);
  if (!status || !WIFEXITED(*status)) return -1;
  return WEXITSTATUS(*status);
}

TEST(Recorder, ABurstIsRecordedWholeInOrderAndNothingIsOverwritten) {
  ASSERT_TRUE(testing::InNetns());
  const std::string dir = testing::MakeTempDir();
  const std::string out = dir + "/session.lcmlog";
  // The recording's digest, taken as it is written, goes to this cache (the programs inherit it).
  const std::string cache = dir + "/cache";
  const testing::ScopedEnv cache_env("FTCAL_CACHE_DIR", cache);
  auto recorder = StartRecorder(dir, {out}, "first");
  SleepS(1.0);  // subscribed
  // 2000 x 100 bytes: within the namespace's 4 MB socket buffer, so the kernel keeps them all
  // and only the recorder's own queue could lose one.
  constexpr int kBurst = 2000;
  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  for (int i = 0; i < kBurst; ++i) {
    std::string payload(100, ' ');
    std::snprintf(payload.data(), payload.size(), "%08d", i);
    ASSERT_EQ(lcm.publish("BURST", payload.data(), static_cast<unsigned>(payload.size())), 0);
  }
  SleepS(1.5);
  EXPECT_EQ(Stop(*recorder), 0) << testing::ReadFile(dir + "/first.err");

  lcm::LogFile log(out, "r");
  ASSERT_TRUE(log.good());
  int n = 0;
  int64_t last_eventnum = -1;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    EXPECT_GT(e->eventnum, last_eventnum);
    last_eventnum = e->eventnum;
    if (e->channel != "BURST") continue;
    ASSERT_EQ(e->datalen, 100);
    char want[16];
    std::snprintf(want, sizeof(want), "%08d", n);
    EXPECT_EQ(std::string(static_cast<const char*>(e->data), 8), want) << "event " << n;
    ++n;
  }
  EXPECT_EQ(n, kBurst) << "records lost or doubled";

  // The digest handed to the cache is the file's: what the first calibration will take as its
  // provenance instead of hashing the recording.
  const std::string sha = Sha256File(out);
  EXPECT_NE(
      testing::ReadFile(dir + "/first.err").find("SHA-256 " + sha + " handed to the digest cache"),
      std::string::npos)
      << testing::ReadFile(dir + "/first.err");
  EXPECT_EQ(DigestCache(cache).Lookup(out), std::optional<std::string>(sha));

  // The same OUT again: refused, exit 2, the recording untouched; --increment: OUT.00, OUT.01.
  const auto size = std::filesystem::file_size(out);
  auto again = StartRecorder(dir, {out}, "again");
  const auto status = again->Wait(10);
  ASSERT_TRUE(status && WIFEXITED(*status));
  EXPECT_EQ(WEXITSTATUS(*status), 2) << testing::ReadFile(dir + "/again.err");
  EXPECT_EQ(std::filesystem::file_size(out), size);
  for (const char* suffix : {".00", ".01"}) {
    auto inc = StartRecorder(dir, {"--increment", out}, std::string("inc") + suffix);
    SleepS(0.5);
    EXPECT_EQ(Stop(*inc), 0);
    EXPECT_TRUE(std::filesystem::exists(out + suffix)) << suffix;
  }
  if (!::testing::Test::HasFailure()) testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
