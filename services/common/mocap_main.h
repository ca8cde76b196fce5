// The run of a motion-capture bridge's main, the same for every capture system: the bridge
// publishes MOCAP_BODY and is paced by its device sockets, and a bridge that stops on an error
// says why in its log and in a last FAILED heartbeat.
#pragma once

#include <exception>

#include "common/exit_codes.h"
#include "common/service.h"
#include "common/user_errors.h"
#include "ftcal/mocap_body_t.hpp"
#include "proto/config.pb.h"

namespace ftcal {

// `Bridge` is a Device (common/device.h) constructed from (options, stats, publish, now);
// `ConfigError` is what it throws for a configuration it cannot serve (its own
// checks of the mocap section, or a server that refuses the configured protocol), which ends the
// process with kExitConfig, as docs/exit-codes.md has it for every bridge.
template <class Bridge, class ConfigError, class Options>
int RunMocapBridge(ServiceApp& app, Options (*options_from_config)(const config::Mocap&)) {
  Bus& bus = app.bus();
  const auto& channels = app.config().channels();
  int rc = 0;
  try {
    Bridge bridge(
        options_from_config(app.config().mocap()), app.stats(),
        [&](const mocap_body_t& msg) { bus.Publish(channels.mocap_body(), msg); },
        [&] { return bus.NowUtime(); });
    // The device socket paces this process, not LCM (it subscribes to nothing): ServiceApp's
    // device loop, with the heartbeat and systemd's notify protocol.
    app.RunDevice(bridge);
  } catch (const ConfigError& e) {
    app.stats().Error("configuration", e.what());  // logs it, and the last heartbeat carries it
    app.SetState(service_status_t::FAILED);
    rc = kExitConfig;
  } catch (const std::exception& e) {
    // Anything else ends the bridge: said in its log and in its last heartbeat.
    app.stats().Error("run", UserText(e, "reading the motion capture"));
    app.SetState(service_status_t::FAILED);
    rc = ExitCodeFor(e, kExitDeviceIo);
  }
  if (rc != 0) app.PublishHeartbeat();  // the last one, FAILED with the error
  app.stats().LogSummary();
  return rc;
}

}  // namespace ftcal
