// ftcal-natnet-bridge: OptiTrack Motive (NatNet over UDP) -> MOCAP_BODY.
#include <memory>

#include "common/bridge_main.h"
#include "natnet_bridge.h"

int main(int argc, char** argv) {
  ftcal::BridgeSpec<ftcal::NatNetBridge> spec;
  spec.service = {
      "ftcal-natnet-bridge",
      "Receives OptiTrack Motive's NatNet stream (3.x or 4.x; multicast, or unicast with "
      "keep-alive) from the server named by the config's mocap.natnet section, maps the rigid "
      "body mocap.body_name by name from Motive's data descriptions, and publishes one "
      "mocap_body_t per frame on MOCAP_BODY with the same meaning as ftcal-mocap-bridge: "
      "R^G_C and R^W_C (heading removed) as quaternions in ftcal's z-up global frame, the "
      "heading, position and the body's markers in metres, untracked poses as NaN with "
      "tracked=false, utime the mid-exposure time on the host clock. Reconnects with "
      "back-off when Motive is gone; waits while Motive is up but not streaming; DEGRADED "
      "meanwhile. Exits 3 (config) when the config does not select OPTITRACK "
      "(mocap.system) or Motive streams NatNet older than 3.0; 4 when a socket cannot be opened, "
      "bound or joined to the multicast group. Reads nothing from LCM."};
  spec.configure = [](ftcal::ServiceApp& app) {
    return std::make_unique<ftcal::NatNetBridge>(
        ftcal::NatNetBridgeOptionsFromConfig(app.config().mocap()), app.stats(),
        [&app](const ftcal::mocap_body_t& msg) {
          app.bus().Publish(app.config().channels().mocap_body(), msg);
        },
        [&app] { return app.bus().NowUtime(); });
  };
  spec.open = [](ftcal::NatNetBridge& bridge) -> ftcal::Device& {
    bridge.Open();  // a socket the host refuses: exit 4, not the config's fault
    return bridge;
  };
  // Motive streaming a NatNet older than 3.0, which the bridge learns from its SERVERINFO.
  spec.refuses_config = ftcal::IsA<ftcal::NatNetConfigError>;
  return ftcal::RunBridge(argc, argv, spec);
}
