// ftcal-natnet-bridge: OptiTrack Motive (NatNet over UDP) -> MOCAP_BODY.
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
    // The device socket paces this process, not LCM (it subscribes to nothing): ServiceApp's
    // device loop, with the heartbeat and systemd's notify protocol.
    app.RunDeviceLoop([&] { return bridge.health_reason(); },
                      [&](int max_wait_ms) { bridge.Step(max_wait_ms); });
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
  if (rc == 0) {
    app.DeviceLoopStopped();
  } else {
    app.PublishHeartbeat();  // the last one, FAILED with the error
  }
  app.stats().LogSummary();
  return rc;
}
