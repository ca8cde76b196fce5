// ftcal-mocap-bridge: Qualisys QTM (RT protocol, TCP) -> MOCAP_BODY.
#include <algorithm>
#include <chrono>

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
    // The loop is the bridge's own: ServiceApp::Run() waits on LCM only, while the device
    // socket is what paces this process. The bridge subscribes to nothing, so there is no LCM
    // input to poll; the heartbeat is published from here.
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
            app.stats().ClearLastError();  // the status says what is wrong now, not once
          } else {
            app.log().warn("degraded: {}", reason);
          }
          last_reason = reason;
        }
        if (!reason.empty()) app.stats().SetLastError(reason);
        bus.Publish(channels.status(), app.Status(), /*count=*/false);
        next_heartbeat += std::chrono::seconds(1);
        if (next_heartbeat <= now) next_heartbeat = now + std::chrono::seconds(1);
      }
      const auto until_heartbeat =
          std::chrono::duration_cast<std::chrono::milliseconds>(next_heartbeat - Clock::now());
      bridge.Step(static_cast<int>(std::clamp<int64_t>(until_heartbeat.count() + 1, 0, 100)));
    }
    app.SetState(ftcal::service_status_t::STOPPING);
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
  bus.Publish(channels.status(), app.Status(), /*count=*/false);
  app.stats().LogSummary();
  return rc;
}
