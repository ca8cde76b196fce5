// ftcal-relay: republishes channels of a routed bus (config lcm_route) onto one LCM URL, for a
// tool that listens on one URL only (lcm-spy: scripts/spy starts it).
//
//   ftcal-relay --config FILE [--channels REGEX] --to URL
//
// It subscribes to the channels picked (default: all) on every port they travel, as any reader
// does, and publishes each message as it came, raw, on URL: a port no ftcal process uses, so
// nothing of the group receives the copies but the tool that asked.
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/default_config.h"
#include "common/exit_codes.h"
#include "common/shutdown.h"
#include "common/user_errors.h"

int main(int argc, char** argv) try {
  CLI::App cli("Republishes channels of a routed LCM bus (config lcm_route) onto one URL.",
               "ftcal-relay");
  cli.footer(ftcal::ExitCodeTable());
  std::string config_path, channels = ".*", to;
  cli.add_option("--config", config_path, "the config whose lcm_url and lcm_route to read");
  cli.add_option("--channels", channels, "a regular expression over whole channel names")
      ->capture_default_str();
  cli.add_option("--to", to, "the URL to republish on, e.g. udpm://239.255.76.67:7670?ttl=0")
      ->required();
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;
  auto log = spdlog::stderr_color_st("ftcal-relay");
  try {
    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);
    ftcal::ServiceStats stats(log);
    const std::vector<ftcal::LcmBus::Route> routes = ftcal::RoutesOf(config);
    bool ours = config.lcm_url() == to;
    for (const auto& r : routes) ours = ours || r.url == to;
    if (ours) {
      throw std::invalid_argument("--to " + to + " is a URL of the group itself: the copies " +
                                  "would reach every reader twice");
    }
    ftcal::LcmBus bus(config.lcm_url(), stats, routes);
    lcm::LCM out(to);
    if (!out.good()) throw std::runtime_error("cannot open LCM at '" + to + "'");
    int64_t relayed = 0;
    bus.SubscribeRaw(channels, [&](const ftcal::MessageInfo& info, const void* data, int size) {
      if (out.publish(info.channel, data, static_cast<unsigned>(size)) == 0) ++relayed;
    });
    ftcal::InstallShutdownHandlers();
    log->info("relaying '{}' from {} (and its routes) to {}", channels, config.lcm_url(), to);
    bus.Run([] {}, 1'000'000);
    log->info("{} messages relayed", relayed);
    return ftcal::kExitDone;
  } catch (const std::exception& e) {
    log->critical("{}", ftcal::UserText(e, "relaying"));
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-relay");
}
