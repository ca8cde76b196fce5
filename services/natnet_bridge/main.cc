// ftcal-natnet-bridge: OptiTrack Motive (NatNet over UDP) -> MOCAP_BODY.
#include <algorithm>
#include <chrono>

#include "common/service.h"
#include "common/shutdown.h"
#include "natnet_bridge.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-natnet-bridge",
       "Receives OptiTrack Motive's NatNet stream (3.x or 4.x; multicast, or unicast with "
       "keep-alive) from the server named by the config's mocap.natnet section, maps the rigid "
       "body mocap.body_name by name from Motive's data descriptions, and publishes one "
       "mocap_body_t per frame on MOCAP_BODY with the same meaning as ftcal-mocap-bridge: "
       "R^G_C and R^W_C (heading removed) as quaternions in ftcal's z-up global frame, the "
       "heading, position and the body's markers in metres, untracked poses as NaN with "
       "tracked=false, utime the mid-exposure time on the host clock. Reconnects with "
       "back-off when Motive is gone; waits while Motive is up but not streaming; DEGRADED "
       "meanwhile. Exits 2 when the config does not select OPTITRACK (mocap.system) or "
       "Motive streams NatNet older than 3.0. Reads nothing from LCM.",
       /*replayable=*/false});
  if (auto rc = app.Init(argc, argv)) return *rc;

  ftcal::Bus& bus = app.bus();
  const auto& channels = app.config().channels();
  int rc = 0;
  try {
    ftcal::NatNetBridge bridge(
        ftcal::NatNetBridgeOptionsFromConfig(app.config().mocap()), app.stats(),
        [&](const ftcal::mocap_body_t& msg) { bus.Publish(channels.mocap_body(), msg); },
        [&] { return bus.NowUtime(); });
    // The device sockets pace this process (as in ftcal-mocap-bridge); nothing is read from
    // LCM, so the heartbeat is published from this loop.
    using Clock = std::chrono::steady_clock;
    auto next_heartbeat = Clock::now();
    app.SetState(ftcal::service_status_t::RUNNING);
    std::string last_reason;
    while (!ftcal::ShutdownRequested()) {
      const auto now = Clock::now();
      if (now >= next_heartbeat) {
        const std::string reason = bridge.health_reason();
        app.SetState(reason.empty() ? ftcal::service_status_t::RUNNING
                                    : ftcal::service_status_t::DEGRADED);
        if (reason != last_reason) {
          if (reason.empty()) {
            app.log().info("streaming");
          } else {
            app.log().warn("degraded: {}", reason);
          }
          last_reason = reason;
        }
        bus.Publish(channels.status(), app.Status(), /*count=*/false);
        next_heartbeat += std::chrono::seconds(1);
        if (next_heartbeat <= now) next_heartbeat = now + std::chrono::seconds(1);
      }
      const auto until_heartbeat =
          std::chrono::duration_cast<std::chrono::milliseconds>(next_heartbeat - Clock::now());
      bridge.Step(static_cast<int>(std::clamp<int64_t>(until_heartbeat.count() + 1, 0, 100)));
    }
    app.SetState(ftcal::service_status_t::STOPPING);
  } catch (const ftcal::NatNetConfigError& e) {
    app.stats().Error("configuration", e.what());
    app.SetState(ftcal::service_status_t::FAILED);
    rc = 2;
  } catch (const std::exception& e) {
    // Anything else ends the bridge: said in its log and in its last heartbeat.
    app.stats().Error("run", ftcal::UserText(e, "reading the motion capture"));
    app.SetState(ftcal::service_status_t::FAILED);
    rc = ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
  bus.Publish(channels.status(), app.Status(), /*count=*/false);
  app.stats().LogSummary();
  return rc;
}
