// Real processes over real LCM multicast, inside a private network namespace
// (scripts/netns-exec runs this whole binary; see CMakeLists.txt): a heartbeat publisher built
// on services/common, ftcal-status and lcm-logger.
#include <signal.h>

#include <chrono>
#include <cstdlib>
#include <map>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/service_status_t.hpp"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";

void SleepS(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

double SecondsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

// The row of ftcal-status's table for `pid`, split into the fixed columns NAME HOST PID STATE
// UPTIME IN OUT DROPS ERRORS AGE, then the counters ("k=v" words).
std::vector<std::string> RowForPid(const std::string& table, pid_t pid) {
  std::istringstream lines(table);
  for (std::string line; std::getline(lines, line);) {
    std::istringstream words(line);
    std::vector<std::string> row;
    for (std::string w; words >> w;) row.push_back(w);
    if (row.size() >= 10 && row[2] == std::to_string(pid)) return row;
  }
  return {};
}

int64_t CounterIn(const std::vector<std::string>& row, const std::string& name) {
  for (size_t i = 10; i < row.size(); ++i) {
    if (row[i].rfind(name + "=", 0) == 0) return std::stoll(row[i].substr(name.size() + 1));
  }
  return -1;
}

class HeartbeatNetnsTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const char* netns = std::getenv("FTCAL_NETNS");
    ASSERT_TRUE(netns != nullptr && std::string(netns) == "1")
        << "this test sends UDP multicast: run it through scripts/netns-exec (ctest does)";
    dir_ = testing::MakeTempDir();
  }
  void TearDown() override {
    if (!dir_.empty() && !HasFailure()) testing::RemoveTree(dir_);
  }
  std::string Path(const std::string& name) const { return dir_ + "/" + name; }
  std::unique_ptr<Child> Start(const std::string& tag, std::vector<std::string> argv) {
    return std::make_unique<Child>(argv, Path(tag + ".out"), Path(tag + ".err"));
  }
  std::unique_ptr<Child> StartDemo(const std::string& tag) {
    return Start(tag, {FTCAL_HEARTBEAT_DEMO, "--lcm-url", kUrl});
  }

  std::string dir_;
};

TEST_F(HeartbeatNetnsTest, StatusShowsPublisherSigtermEndsItAndTheLogHoldsItsHeartbeats) {
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) was not found at configure time";
  const std::string log_path = Path("bus.lcmlog");
  auto logger = Start("logger", {FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", log_path});
  SleepS(0.3);  // the logger subscribes before anything is published

  const auto demo_started = std::chrono::steady_clock::now();
  auto demo = StartDemo("demo");
  auto status = Start("status", {FTCAL_STATUS_EXE, "--lcm-url", kUrl, "--once-after", "3"});
  const auto status_rc = status->Wait(15);
  ASSERT_TRUE(status_rc.has_value()) << "ftcal-status --once-after 3 did not exit";
  EXPECT_EQ(DescribeWaitStatus(*status_rc), "exit 0") << ReadFile(Path("status.err"));

  const std::string table = ReadFile(Path("status.out"));
  const auto row = RowForPid(table, demo->pid());
  ASSERT_FALSE(row.empty()) << "no row for the demo's pid " << demo->pid() << " in:\n" << table;
  EXPECT_EQ(row[0], "ftcal-heartbeat-demo") << table;
  EXPECT_EQ(row[3], "RUNNING") << table;
  const int64_t in = std::stoll(row[5]), out = std::stoll(row[6]);
  // The demo publishes a tick every 100 ms; its last heartbeat before the table is >= 1 s in.
  EXPECT_GE(out, 5) << table;
  // Both columns and the counters come from one heartbeat: each tick is one publication, each
  // tick heard back is one input.
  EXPECT_EQ(CounterIn(row, "ticks"), out) << table;
  EXPECT_EQ(CounterIn(row, "heard"), in) << table;
  EXPECT_GE(in, 1) << table;
  EXPECT_EQ(row[7], "0") << table;  // drops
  EXPECT_EQ(row[8], "0") << table;  // errors
  // ftcal-status shows itself too.
  EXPECT_FALSE(RowForPid(table, status->pid()).empty()) << table;

  // SIGTERM: a clean exit within 1 s.
  demo->Signal(SIGTERM);
  const auto term_sent = std::chrono::steady_clock::now();
  const auto demo_rc = demo->Wait(1.0);
  const double demo_run_s = std::chrono::duration<double>(term_sent - demo_started).count();
  ASSERT_TRUE(demo_rc.has_value()) << "demo still running 1 s after SIGTERM";
  EXPECT_EQ(DescribeWaitStatus(*demo_rc), "exit 0") << ReadFile(Path("demo.err"));
  EXPECT_LT(SecondsSince(term_sent), 1.0);

  SleepS(0.3);  // let the logger receive the final heartbeat
  logger->Signal(SIGINT);
  const auto logger_rc = logger->Wait(5);
  ASSERT_TRUE(logger_rc.has_value()) << "lcm-logger did not stop on SIGINT";

  // The recorded heartbeats of the demo, decoded from the log.
  lcm::LogFile log(log_path, "r");
  ASSERT_TRUE(log.good()) << log_path;
  std::vector<service_status_t> beats;
  for (const lcm::LogEvent* e = log.readNextEvent(); e != nullptr; e = log.readNextEvent()) {
    if (e->channel != "FTCAL_STATUS") continue;
    service_status_t s;
    ASSERT_EQ(s.decode(e->data, 0, e->datalen), e->datalen);
    if (s.name == "ftcal-heartbeat-demo") beats.push_back(s);
  }
  ASSERT_FALSE(beats.empty());
  // One at start, one a second, one at exit: about the seconds it ran, +2.
  EXPECT_GE(static_cast<double>(beats.size()), demo_run_s - 1) << demo_run_s << " s run";
  EXPECT_LE(static_cast<double>(beats.size()), demo_run_s + 2.5) << demo_run_s << " s run";
  for (size_t i = 0; i < beats.size(); ++i) {
    EXPECT_EQ(beats[i].pid, demo->pid());
    EXPECT_EQ(beats[i].num_counters, 2);
    if (i > 0) {
      EXPECT_GT(beats[i].uptime_s, beats[i - 1].uptime_s) << "beat " << i;
      EXPECT_GE(beats[i].msgs_out, beats[i - 1].msgs_out) << "beat " << i;
      EXPECT_GT(beats[i].utime, beats[i - 1].utime) << "beat " << i;
    }
    const int8_t expected_state = i + 1 == beats.size() ? int8_t{service_status_t::STOPPING}
                                                        : int8_t{service_status_t::RUNNING};
    EXPECT_EQ(beats[i].state, expected_state) << "beat " << i << " of " << beats.size();
  }
  EXPECT_LT(beats.front().uptime_s, 0.5);
  EXPECT_NEAR(beats.back().uptime_s, demo_run_s, 0.6);
}

TEST_F(HeartbeatNetnsTest, StatusMarksAKilledPublisherLost) {
  auto status = Start("status", {FTCAL_STATUS_EXE, "--lcm-url", kUrl, "--once-after", "6.5"});
  SleepS(0.5);  // ftcal-status is listening
  auto alive = StartDemo("alive");
  auto doomed = StartDemo("doomed");
  SleepS(2.2);  // heartbeats at start and about every second: two or three heard
  doomed->Signal(SIGKILL);
  ASSERT_TRUE(doomed->Wait(2).has_value());

  const auto status_rc = status->Wait(15);
  ASSERT_TRUE(status_rc.has_value()) << "ftcal-status --once-after 6.5 did not exit";
  EXPECT_EQ(DescribeWaitStatus(*status_rc), "exit 0") << ReadFile(Path("status.err"));
  const std::string table = ReadFile(Path("status.out"));
  const auto dead_row = RowForPid(table, doomed->pid());
  const auto live_row = RowForPid(table, alive->pid());
  ASSERT_FALSE(dead_row.empty()) << table;
  ASSERT_FALSE(live_row.empty()) << table;
  // Silent for >= ~4 s (killed at ~2.7 s, table at ~6.6 s) with no goodbye: LOST.
  EXPECT_EQ(dead_row[3], "LOST") << table;
  EXPECT_EQ(live_row[3], "RUNNING") << table;
}

}  // namespace
}  // namespace ftcal
