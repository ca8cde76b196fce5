// ftcal-mocap-bridge: Qualisys QTM (RT protocol, TCP) -> MOCAP_BODY.
#include "common/exit_codes.h"
#include "common/service.h"
#include "common/shutdown.h"
#include "mocap_bridge.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-mocap-bridge",
       "Connects to the Qualisys QTM real-time server named by the config's mocap section "
       "(TCP, little-endian port, protocol mocap.protocol_version), streams the chassis body "
       "(mocap.body_name, 6D with residual) and the labelled markers (3D), and publishes one "
       "mocap_body_t per frame on MOCAP_BODY: R^G_C and R^W_C (heading removed) as "
       "quaternions, the heading, position and markers in metres, untracked poses as NaN with "
       "tracked=false. Reconnects with back-off; DEGRADED while QTM is absent, silent or not "
       "capturing. Exits 2 when QTM refuses the configured protocol version. Reads nothing "
       "from LCM.",
       /*replayable=*/false});
  if (auto rc = app.Init(argc, argv)) return *rc;

  ftcal::Bus& bus = app.bus();
  const auto& channels = app.config().channels();
  int rc = 0;
  try {
    ftcal::MocapBridge bridge(
        ftcal::MocapBridgeOptionsFromConfig(app.config().mocap()), app.stats(),
        [&](const ftcal::mocap_body_t& msg) { bus.Publish(channels.mocap_body(), msg); },
        [&] { return bus.NowUtime(); });
    // The device socket paces this process, not LCM (it subscribes to nothing): ServiceApp's
    // device loop, with the heartbeat and systemd's notify protocol.
    app.RunDeviceLoop([&] { return bridge.health_reason(); },
                      [&](int max_wait_ms) { bridge.Step(max_wait_ms); });
  } catch (const ftcal::MocapConfigError& e) {
    app.stats().Error("configuration", e.what());  // logs it, and the last heartbeat carries it
    app.SetState(ftcal::service_status_t::FAILED);
    rc = ftcal::kExitConfig;
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
