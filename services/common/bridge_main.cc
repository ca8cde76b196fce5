#include "common/bridge_main.h"

#include "common/user_errors.h"
#include "ftcal/service_status_t.hpp"

namespace ftcal {

int FailBridge(ServiceApp& app, BridgeStage stage, bool refused_config, const std::exception& e) {
  const bool config = stage == BridgeStage::kConfigure || refused_config;
  const char* doing = stage == BridgeStage::kConfigure ? "building the bridge from the config"
                      : stage == BridgeStage::kOpen    ? "opening the device"
                                                       : "running the device";
  const char* kind = config                        ? "configuration"
                     : stage == BridgeStage::kOpen ? "opening the device"
                                                   : "run";
  app.stats().Fatal(kind, UserText(e, doing));
  app.SetState(service_status_t::FAILED);
  try {
    app.PublishHeartbeat();
  } catch (const std::exception& not_sent) {
    app.log().warn("the FAILED heartbeat was not sent: {}",
                   UserText(not_sent, "sending the heartbeat"));
  }
  app.stats().LogSummary();
  return ExitCodeFor(e, config ? kExitConfig : kExitDeviceIo);
}

}  // namespace ftcal
