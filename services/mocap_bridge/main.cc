// ftcal-mocap-bridge: Qualisys QTM (RT protocol, TCP) -> MOCAP_BODY.
#include "common/mocap_main.h"
#include "common/service.h"
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
       "capturing. Exits 3 (config) when QTM refuses the configured protocol version. Reads "
       "nothing from LCM.",
       /*replayable=*/false});
  app.OfferSchedulingFlags();
  if (auto rc = app.Init(argc, argv)) return *rc;

  return ftcal::RunMocapBridge<ftcal::MocapBridge, ftcal::MocapConfigError>(
      app, ftcal::MocapBridgeOptionsFromConfig);
}
