// ftcal-drift on live LCM (issue #40): the same stage as over a log, fed by lcm-logplayer at ten
// times real speed from a walk ftcal-sim wrote with MR's offsets stepping 2 N / 0.05 N*m at 10 s.
// The test waits for events only: the tracker's heartbeat before playing, then DRIFT messages
// until one covers the log's end. That one must carry MR's change within the bounds of
// the truth the twin wrote beside the log, WARN on MR's six components alone, and the heartbeat
// DEGRADED naming them.
#include <sys/wait.h>

#include <chrono>
#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/drift_t.hpp"
#include "ftcal/legs.h"
#include "ftcal/service_status_t.hpp"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::ReadFile;

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";

class DriftLiveTest : public testing::NetnsDirTest {};

struct Heard {
  std::vector<drift_t> drift;
  std::vector<service_status_t> status;
  void OnDrift(const lcm::ReceiveBuffer*, const std::string&, const drift_t* m) {
    drift.push_back(*m);
  }
  void OnStatus(const lcm::ReceiveBuffer*, const std::string&, const service_status_t* m) {
    if (m->name == "ftcal-drift") status.push_back(*m);
  }
};

TEST_F(DriftLiveTest, TracksAStepFromLiveMessagesAndWarns) {
  const std::string log = Path("walk.lcmlog");
  {
    Child sim({FTCAL_SIM, "log", "--config", kConfig, "--out", log, "--seed", "4", "--scenarios",
               "walk", "--walk-s", "60", "--drift-step", "MR:10:2,-2,2,0.05,-0.05,0.05"},
              Path("sim.out"), Path("sim.err"));
    const auto rc = sim.Wait(60);
    ASSERT_TRUE(rc && WIFEXITED(*rc) && WEXITSTATUS(*rc) == 0) << ReadFile(Path("sim.err"));
  }
  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  Heard heard;
  lcm.subscribe("DRIFT", &Heard::OnDrift, &heard);
  lcm.subscribe("FTCAL_STATUS", &Heard::OnStatus, &heard);

  Child drift({FTCAL_DRIFT, "--config", kConfig, "--lcm-url", kUrl, "--calibration",
               Path("walk.truth.pbtxt")},
              Path("drift.out"), Path("drift.err"));
  // Subscribed and in its loop once it is heard.
  ASSERT_EQ(testing::AwaitHeartbeats(lcm, {drift.pid()}, 30).size(), 1u)
      << ReadFile(Path("drift.err"));

  Child player({FTCAL_LCM_LOGPLAYER, "-s", "10", "-l", kUrl, log}, Path("player.out"),
               Path("player.err"));
  // The log's last sample time, to know when a DRIFT has seen everything.
  int64_t last_utime = 0;
  {
    lcm::LogFile in(log, "r");
    ASSERT_TRUE(in.good());
    while (const lcm::LogEvent* e = in.readNextEvent()) {
      last_utime = e->timestamp;
    }
  }
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  auto covers_end = [&] {
    return !heard.drift.empty() && heard.drift.back().utime >= last_utime - 100'000;
  };
  while (!covers_end() && std::chrono::steady_clock::now() < until) lcm.handleTimeout(100);
  ASSERT_TRUE(covers_end()) << heard.drift.size() << " DRIFT heard\n"
                            << ReadFile(Path("drift.err"));
  const auto played = player.Wait(30);
  ASSERT_TRUE(played && WIFEXITED(*played) && WEXITSTATUS(*played) == 0)
      << ReadFile(Path("player.err"));
  // One heartbeat after the end: its state and last error.
  const size_t beats = heard.status.size();
  const auto beat_until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (heard.status.size() == beats && std::chrono::steady_clock::now() < beat_until)
    lcm.handleTimeout(100);
  testing::Terminate(drift, "ftcal-drift", Path("drift.err"));

  const drift_t& m = heard.drift.back();
  const double step[6] = {2, -2, 2, 0.05, -0.05, 0.05};
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      const double truth = k == 4 ? step[i] : 0.0;
      EXPECT_NEAR(m.offset_change[k][i], truth, i < 3 ? 0.1 : 0.005)
          << kLegNames[k] << " component " << i;
    }
    EXPECT_EQ(m.warn_mask[k], k == 4 ? 63 : 0) << kLegNames[k];
  }
  EXPECT_EQ(m.status, int{drift_t::WARN});
  ASSERT_GT(heard.status.size(), beats);
  EXPECT_EQ(heard.status.back().state, int{service_status_t::DEGRADED});
  EXPECT_NE(heard.status.back().last_error.find("MR fx"), std::string::npos)
      << heard.status.back().last_error;
  // Live, at 10x, UDP may lose a datagram; most seconds of the log were published.
  EXPECT_GE(heard.drift.size(), 4u);
}

}  // namespace
}  // namespace ftcal
