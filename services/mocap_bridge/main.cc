// ftcal-mocap-bridge: Qualisys QTM (RT protocol, TCP) -> MOCAP_BODY.
#include <memory>

#include "common/bridge_main.h"
#include "mocap_bridge.h"

int main(int argc, char** argv) {
  ftcal::BridgeSpec<ftcal::MocapBridge> spec;
  spec.service = {
      "ftcal-mocap-bridge",
      "Connects to the Qualisys QTM real-time server named by the config's mocap section "
      "(TCP, little-endian port, protocol mocap.protocol_version), streams the chassis body "
      "(mocap.body_name, 6D with residual) and the labelled markers (3D), and publishes one "
      "mocap_body_t per frame on MOCAP_BODY: R^G_C and R^W_C (heading removed) as "
      "quaternions, the heading, position and markers in metres, untracked poses as NaN with "
      "tracked=false. Reconnects with back-off; DEGRADED while QTM is absent, silent or not "
      "capturing. Exits 3 (config) when QTM refuses the configured protocol version. Reads "
      "nothing from LCM."};
  spec.configure = [](ftcal::ServiceApp& app) {
    return std::make_unique<ftcal::MocapBridge>(
        ftcal::MocapBridgeOptionsFromConfig(app.config().mocap()), app.stats(),
        [&app](const ftcal::mocap_body_t& msg) {
          app.bus().Publish(app.config().channels().mocap_body(), msg);
        },
        [&app] { return app.bus().NowUtime(); });
  };
  // QTM refusing the configured protocol version, which the bridge learns only once connected.
  spec.refuses_config = ftcal::IsA<ftcal::MocapConfigError>;
  return ftcal::RunBridge(argc, argv, spec);
}
