// Issue 36, finding 9: under a flood of garbage on FT_HL the corrector kept RUNNING with an
// empty last_error. The real ftcal-corrector, started with a calibration (RUNNING), is flooded:
// its heartbeat must turn DEGRADED and name the drops, and turn RUNNING again after the flood.
#include <signal.h>

#include <chrono>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/service_status_t.hpp"
#include "sim/twin.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";

class FloodTest : public testing::NetnsDirTest {};

TEST_F(FloodTest, AFloodOfGarbageShowsInTheCorrectorsHeartbeat) {
  const config::Config config = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  WriteCalibrationFile(BigAntTwin(config, TwinOptions{}).TruthProto(), Path("truth.pbtxt"));
  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  Child corrector({FTCAL_CORRECTOR, "--lcm-url", kUrl, "--calibration", Path("truth.pbtxt")},
                  Path("corrector.out"), Path("corrector.err"));
  auto log = [&] {
    return testing::ReadFile(Path("corrector.out")) + testing::ReadFile(Path("corrector.err"));
  };
  auto await = [&](const std::function<bool(const service_status_t&)>& pred, double timeout_s,
                   const std::function<void()>& meanwhile) {
    struct Ear {
      pid_t pid;
      std::optional<service_status_t> latest;
      void On(const lcm::ReceiveBuffer* rbuf, const std::string&) {
        service_status_t s;
        if (s.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) ==
                static_cast<int>(rbuf->data_size) &&
            s.pid == pid) {
          latest = s;
        }
      }
    } ear{corrector.pid(), std::nullopt};
    auto* sub = lcm.subscribe("FTCAL_STATUS", &Ear::On, &ear);
    std::optional<service_status_t> found;
    const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (!found && Clock::now() < deadline) {
      if (meanwhile) meanwhile();
      lcm.handleTimeout(meanwhile ? 1 : 50);
      if (ear.latest && pred(*ear.latest)) found = ear.latest;
      ear.latest.reset();
    }
    lcm.unsubscribe(sub);
    return found;
  };
  ASSERT_TRUE(
      await([](const service_status_t& s) { return s.state == service_status_t::RUNNING; }, 30, {}))
      << log();

  std::mt19937 rng(36);
  std::vector<uint8_t> garbage(64);
  auto flood = [&] {
    for (int i = 0; i < 20; ++i) {
      for (auto& b : garbage) b = static_cast<uint8_t>(rng());
      lcm.publish("FT_HL", garbage.data(), static_cast<unsigned>(garbage.size()));
    }
  };
  const auto degraded = await(
      [](const service_status_t& s) { return s.state == service_status_t::DEGRADED; }, 30, flood);
  ASSERT_TRUE(degraded) << log();
  EXPECT_NE(degraded->last_error.find("above health.max_drop_share"), std::string::npos)
      << degraded->last_error;
  EXPECT_NE(degraded->last_error.find("on FT_HL"), std::string::npos) << degraded->last_error;
  EXPECT_GT(degraded->drops, 0);
  // The flood over, the corrector says so.
  const auto running =
      await([](const service_status_t& s) { return s.state == service_status_t::RUNNING; }, 30, {});
  ASSERT_TRUE(running) << log();
  EXPECT_EQ(running->last_error, "") << running->last_error;
  corrector.Signal(SIGTERM);
  EXPECT_TRUE(corrector.Wait(15));
}

}  // namespace
}  // namespace ftcal
