// Channel routes (config lcm_route; LcmBus): a routed channel is published on its route's port
// and only a process subscribed to it joins that port, so the kernel hands its datagrams to
// nobody else. Checked against plain LCM instances on each port, which hear what the kernel
// delivers there; in the binary's own network namespace.
#include <signal.h>

#include <chrono>
#include <fstream>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "child_process.h"
#include "common/bus.h"
#include "common/lcm_bus.h"
#include "ftcal/config.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

constexpr char kMain[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr char kFt[] = "udpm://239.255.76.67:7668?ttl=0";
constexpr int kEach = 50;

// What a plain LCM instance on one URL hears, per channel.
struct Ear {
  explicit Ear(const char* url) : lcm(url) {
    lcm.subscribe(".*", &Ear::On, this)->setQueueCapacity(1000);  // LCM keeps 30 by default
  }
  void On(const lcm::ReceiveBuffer*, const std::string& channel) { ++heard[channel]; }
  lcm::LCM lcm;
  std::map<std::string, int> heard;
};

std::shared_ptr<spdlog::logger> Quiet() {
  return std::make_shared<spdlog::logger>("route-test",
                                          std::make_shared<spdlog::sinks::null_sink_mt>());
}

TEST(LcmRoute, ARoutedChannelReachesItsReadersAndNoSocketOnTheMainPort) {
  ASSERT_TRUE(testing::InNetns());
  const std::vector<LcmBus::Route> routes = {{"FT_.*", kFt}};
  ServiceStats p_stats(Quiet()), r_stats(Quiet()), x_stats(Quiet());
  LcmBus publisher(kMain, p_stats, routes);
  LcmBus reader(kMain, r_stats, routes);   // one channel of each kind, by name
  LcmBus pattern(kMain, x_stats, routes);  // a regular expression
  EXPECT_EQ(publisher.UrlOf("FT_HL"), kFt);
  EXPECT_EQ(publisher.UrlOf("FTCAL_STATUS"), kMain);
  std::map<std::string, int> by_name, by_pattern;
  reader.SubscribeRaw("FT_HL",
                      [&](const MessageInfo& i, const void*, int) { ++by_name[i.channel]; });
  reader.SubscribeRaw("FTCAL_STATUS",
                      [&](const MessageInfo& i, const void*, int) { ++by_name[i.channel]; });
  pattern.SubscribeRaw("FT_.*",
                       [&](const MessageInfo& i, const void*, int) { ++by_pattern[i.channel]; });
  EXPECT_EQ(reader.Filenos().size(), 2u);  // both ports
  Ear main_port(kMain), ft_port(kFt);

  const uint8_t payload[16] = {};
  for (int i = 0; i < kEach; ++i) {
    publisher.PublishRaw("FT_HL", payload, sizeof payload);
    publisher.PublishRaw("FTCAL_STATUS", payload, sizeof payload);
  }
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  auto done = [&] {
    return by_name["FT_HL"] == kEach && by_name["FTCAL_STATUS"] == kEach &&
           by_pattern["FT_HL"] == kEach && main_port.heard["FTCAL_STATUS"] == kEach &&
           ft_port.heard["FT_HL"] == kEach;
  };
  while (!done() && std::chrono::steady_clock::now() < deadline) {
    reader.HandleOnce(10);
    pattern.HandleOnce(0);
    main_port.lcm.handleTimeout(0);
    ft_port.lcm.handleTimeout(0);
  }
  EXPECT_EQ(by_name["FT_HL"], kEach);
  EXPECT_EQ(by_name["FTCAL_STATUS"], kEach);
  EXPECT_EQ(by_pattern["FT_HL"], kEach);
  // The main port heard every status and, interleaved with them, none of the transducer's.
  EXPECT_EQ(main_port.heard["FTCAL_STATUS"], kEach);
  EXPECT_EQ(main_port.heard["FT_HL"], 0);
  EXPECT_EQ(ft_port.heard["FT_HL"], kEach);
  EXPECT_EQ(ft_port.heard["FTCAL_STATUS"], 0);
}

// scripts/spy's relay: a routed group's channels, main and routed, onto one URL lcm-spy reads.
TEST(LcmRoute, TheRelayCopiesEveryPickedChannelOntoOneUrl) {
  ASSERT_TRUE(testing::InNetns());
  const std::string dir = testing::MakeTempDir();
  const std::string config = dir + "/config.pbtxt";
  std::ofstream(config) << testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt")
                        << "\nlcm_route { channels: \"FT_.*\" url: \"" << kFt << "\" }\n";
  constexpr char kSpy[] = "udpm://239.255.76.67:7699?ttl=0";
  Ear spy(kSpy);
  testing::Child relay(
      {FTCAL_RELAY, "--config", config, "--channels", "FT_HL|FTCAL_STATUS", "--to", kSpy},
      dir + "/relay.out", dir + "/relay.err");
  ServiceStats stats(Quiet());
  LcmBus publisher(kMain, stats, {{"FT_.*", kFt}});
  const uint8_t payload[8] = {};
  // Until the relay has joined both ports: each copy it makes is heard here.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while ((spy.heard["FT_HL"] == 0 || spy.heard["FTCAL_STATUS"] == 0) &&
         std::chrono::steady_clock::now() < deadline) {
    publisher.PublishRaw("FT_HL", payload, sizeof payload);
    publisher.PublishRaw("FTCAL_STATUS", payload, sizeof payload);
    publisher.PublishRaw("FT_ML", payload, sizeof payload);  // not picked
    spy.lcm.handleTimeout(20);
  }
  EXPECT_GT(spy.heard["FT_HL"], 0) << testing::ReadFile(dir + "/relay.err");
  EXPECT_GT(spy.heard["FTCAL_STATUS"], 0) << testing::ReadFile(dir + "/relay.err");
  EXPECT_EQ(spy.heard["FT_ML"], 0);
  relay.Signal(SIGTERM);
  const auto status = relay.Wait(10);
  ASSERT_TRUE(status.has_value());
  EXPECT_EQ(testing::DescribeWaitStatus(*status), "exit 0")
      << testing::ReadFile(dir + "/relay.err");
  testing::RemoveTree(dir);
}

TEST(LcmRoute, ConfigRefusesARouteOnAPortAlreadyInUse) {
  const std::string base = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  try {
    LoadConfigText(
        base + "\nlcm_route { channels: \"FT_.*\" url: \"udpm://239.255.76.68:7667?ttl=0\" }\n",
        "test");
    FAIL() << "a route on lcm_url's port was taken";
  } catch (const std::exception& e) {
    EXPECT_NE(std::string(e.what()).find("lcm_route[0].url"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("uses port 7667"), std::string::npos) << e.what();
  }
  EXPECT_NO_THROW(LoadConfigText(
      base + "\nlcm_route { channels: \"FT_.*\" url: \"udpm://239.255.76.67:7668?ttl=0\" }\n",
      "test"));
}

}  // namespace
}  // namespace ftcal
