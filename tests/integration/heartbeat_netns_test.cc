// Real processes over real LCM multicast, inside a private network namespace
// (scripts/netns-exec runs this whole binary; see CMakeLists.txt): a heartbeat publisher built
// on services/common, ftcal-status and lcm-logger.
#include <signal.h>

#include <chrono>
#include <cstdlib>
#include <map>
#include <optional>
#include <sstream>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/service_status_t.hpp"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";

using testing::SleepS;

double SecondsSince(std::chrono::steady_clock::time_point t) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t).count();
}

// The row of ftcal-status's table for `pid`, split into the fixed columns NAME HOST PID STATE
// UPTIME IN OUT DROPS ERRORS AGE, then the last error's words and the counters ("k=v" words).
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

std::optional<service_status_t> AwaitHeartbeat(lcm::LCM& lcm, pid_t pid, double timeout_s) {
  const auto heard = testing::AwaitHeartbeats(lcm, {pid}, timeout_s);
  if (heard.empty()) return std::nullopt;
  return heard.begin()->second;
}

int64_t CounterIn(const std::vector<std::string>& row, const std::string& name) {
  for (size_t i = 10; i < row.size(); ++i) {
    if (row[i].rfind(name + "=", 0) == 0) return std::stoll(row[i].substr(name.size() + 1));
  }
  return -1;
}

class HeartbeatNetnsTest : public testing::NetnsDirTest {
 protected:
  std::unique_ptr<Child> Start(const std::string& tag, std::vector<std::string> argv) {
    return std::make_unique<Child>(argv, Path(tag + ".out"), Path(tag + ".err"));
  }
  std::unique_ptr<Child> StartDemo(const std::string& tag) {
    return Start(tag, {FTCAL_HEARTBEAT_DEMO, "--lcm-url", kUrl});
  }
};

TEST_F(HeartbeatNetnsTest, StatusShowsPublisherSigtermEndsItAndTheLogHoldsItsHeartbeats) {
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) was not found at configure time";
  const std::string log_path = Path("bus.lcmlog");
  auto logger = Start("logger", {FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", log_path});
  SleepS(0.3);  // the logger subscribes before anything is published

  lcm::LCM listener(kUrl);
  ASSERT_TRUE(listener.good());
  auto demo = StartDemo("demo");
  const auto first = AwaitHeartbeat(listener, demo->pid(), 30);
  ASSERT_TRUE(first.has_value()) << "no heartbeat from the demo in 30 s";
  // The demo's clock: it had been up first->uptime_s when its first heartbeat was heard.
  const auto demo_started = std::chrono::steady_clock::now() -
                            std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                std::chrono::duration<double>(first->uptime_s));
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
  EXPECT_LT(beats.front().uptime_s, 1.0);
  // Uptime counts from the process's start, a little after the spawn measured here.
  EXPECT_LE(beats.back().uptime_s, demo_run_s + 0.3);
  EXPECT_GE(beats.back().uptime_s, demo_run_s - 1.0);
}

TEST_F(HeartbeatNetnsTest, StatusMarksAKilledPublisherLost) {
  lcm::LCM listener(kUrl);
  ASSERT_TRUE(listener.good());
  auto alive = StartDemo("alive");
  auto doomed = StartDemo("doomed");
  ASSERT_TRUE(AwaitHeartbeat(listener, alive->pid(), 30).has_value());
  ASSERT_TRUE(AwaitHeartbeat(listener, doomed->pid(), 30).has_value());
  auto status = Start("status", {FTCAL_STATUS_EXE, "--lcm-url", kUrl, "--once-after", "6.5"});
  // Its own first heartbeat: it is listening, and its 6.5 s count from about now.
  ASSERT_TRUE(AwaitHeartbeat(listener, status->pid(), 30).has_value());
  SleepS(2.2);  // heartbeats about every second: two or three of the doomed one heard
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
  // Silent for >= ~4 s (killed at ~2.2 s, table at 6.5 s) with no goodbye: LOST.
  EXPECT_EQ(dead_row[3], "LOST") << table;
  EXPECT_EQ(live_row[3], "RUNNING") << table;
}

using Event = testing::LoggedEvent;
using testing::ReadLogEvents;

ft_batch_t DecodeSample(const Event& e) {
  ft_batch_t s;
  EXPECT_EQ(s.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
            static_cast<int>(e.data.size()));
  return s;
}

// The architecture's promise: the same handler code live and over the recording of that run
// gives the same outputs, except the time stamps, which replay takes from the recording.
TEST_F(HeartbeatNetnsTest, AStageLiveAndOverItsRecordingPublishesTheSame) {
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) was not found at configure time";
  const std::string log_path = Path("live.lcmlog");
  auto logger = Start("logger", {FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", log_path});
  auto stage = Start("stage", {FTCAL_ECHO_STAGE, "--lcm-url", kUrl});
  SleepS(0.7);  // both subscribed

  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  const std::string legs[] = {"HL", "ML", "FL", "HR", "MR", "FR"};
  constexpr int kSamples = 20;
  for (int k = 0; k < kSamples; ++k) {
    // 1..3 records a message, each record's numbers its own.
    ft_batch_t s{};
    s.receipt_utime = 1000 + k;
    s.leg = k == 7 ? "XX" : legs[k % 6];  // one refused
    s.n = static_cast<int16_t>(1 + k % 3);
    for (int j = 0; j < s.n; ++j) {
      s.sample_utime.push_back(s.receipt_utime - (s.n - 1 - j));
      s.rdt_sequence.push_back(10 * k + j + 1);
      s.ft_sequence.push_back(70 * k + 7 * j);
      s.status.push_back(0);
      s.counts.push_back(std::vector<int32_t>(6, 0));
      std::vector<double> wrench(6);
      for (int a = 0; a < 6; ++a) wrench[a] = 0.5 * k - a + 0.125 * j;
      s.wrench.push_back(wrench);
      s.gap.push_back(0);
      s.flags.push_back(0);
    }
    ASSERT_EQ(lcm.publish("ECHO_IN", &s), 0);
    if (k == 12) {
      const uint8_t junk[5] = {9, 9, 9, 9, 9};
      ASSERT_EQ(lcm.publish("ECHO_IN", junk, sizeof(junk)), 0);  // undecodable
    }
    SleepS(0.02);
  }
  SleepS(0.5);
  stage->Signal(SIGTERM);
  const auto stage_rc = stage->Wait(2);
  ASSERT_TRUE(stage_rc.has_value());
  EXPECT_EQ(DescribeWaitStatus(*stage_rc), "exit 0") << ReadFile(Path("stage.err"));
  SleepS(0.3);
  logger->Signal(SIGINT);
  ASSERT_TRUE(logger->Wait(5).has_value());

  const std::string out_path = Path("replayed.lcmlog");
  Child replay({FTCAL_ECHO_STAGE, "--replay", log_path, "--out", out_path}, Path("replay.out"),
               Path("replay.err"));
  const auto replay_rc = replay.Wait(30);
  ASSERT_TRUE(replay_rc.has_value());
  ASSERT_EQ(DescribeWaitStatus(*replay_rc), "exit 0") << ReadFile(Path("replay.err"));

  const auto recorded = ReadLogEvents(log_path);
  std::vector<Event> inputs, live, replayed;
  for (const auto& e : recorded) {
    if (e.channel == "ECHO_IN" && e.data.size() > 5) inputs.push_back(e);
    if (e.channel == "ECHO_OUT") live.push_back(e);
  }
  service_status_t final_status{};
  for (const auto& e : ReadLogEvents(out_path)) {
    if (e.channel == "ECHO_OUT") replayed.push_back(e);
    if (e.channel == "FTCAL_STATUS") {
      ASSERT_EQ(final_status.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                static_cast<int>(e.data.size()));
    }
  }
  ASSERT_EQ(inputs.size(), static_cast<size_t>(kSamples));
  ASSERT_EQ(live.size(), static_cast<size_t>(kSamples - 1));
  ASSERT_EQ(replayed.size(), live.size());
  size_t j = 0;
  for (const auto& in_event : inputs) {
    const ft_batch_t in = DecodeSample(in_event);
    if (in.leg == "XX") continue;
    const ft_batch_t a = DecodeSample(live[j]), b = DecodeSample(replayed[j]);
    EXPECT_EQ(a.leg, in.leg);
    EXPECT_EQ(b.leg, in.leg);
    ASSERT_EQ(a.n, in.n) << "echo " << j;
    ASSERT_EQ(b.n, in.n) << "echo " << j;
    EXPECT_EQ(a.rdt_sequence, in.rdt_sequence);
    EXPECT_EQ(b.rdt_sequence, a.rdt_sequence);
    EXPECT_EQ(a.sample_utime, in.sample_utime);
    EXPECT_EQ(b.sample_utime, a.sample_utime);
    for (size_t r = 0; r < in.wrench.size(); ++r) {
      for (int k = 0; k < 6; ++k) {
        EXPECT_EQ(a.wrench[r][k], 2 * in.wrench[r][k]);
        EXPECT_EQ(b.wrench[r][k], a.wrench[r][k]);
      }
    }
    // Replay stamps with the recorded input's time; live with the time it handled it.
    EXPECT_EQ(replayed[j].timestamp, in_event.timestamp);
    EXPECT_EQ(b.receipt_utime, in_event.timestamp);
    EXPECT_GE(a.receipt_utime, in_event.timestamp - 100'000);
    ++j;
  }
  EXPECT_EQ(final_status.msgs_in, kSamples + 1);
  EXPECT_EQ(final_status.drops, 2);  // the refused leg and the undecodable bytes
  EXPECT_EQ(final_status.errors, 0);
}

}  // namespace
}  // namespace ftcal
