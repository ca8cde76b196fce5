// The run of every bridge's main (docs/writing-a-bridge.md): the flags every process and every
// bridge has and the bridge's own, the config, the bridge built from it, its device opened,
// ServiceApp's device loop. Once the bus is open, a failure ends the same way in every bridge:
// one critical line saying why, a last FAILED heartbeat carrying it, and the exit code of
// docs/exit-codes.md for where it happened:
//
//   building the bridge from the config and flags (its checks of its section)   3 config
//   the device refusing the configuration, opening or running (an ATI box set
//     up otherwise than the config says, QTM refusing the protocol version)      3 config
//   opening the device (a calibration page, a socket), or the loop failing      4 device or I/O
//   an internal error (a bug, out of memory), anywhere                           5
//
// Before the bus is open (a bad flag, a config file that cannot be read, LCM that cannot be
// opened) there is nowhere to send a heartbeat: ServiceApp::Init's line and exit code are all.
//
//   int main(int argc, char** argv) {
//     ftcal::BridgeSpec<ftcal::FooBridge> spec;
//     spec.service = {"ftcal-foo-bridge", "Reads the Foo box; publishes FOO."};
//     spec.configure = [](ftcal::ServiceApp& app) {
//       return std::make_unique<ftcal::FooBridge>(app.config().foo(), app.stats(), ...);
//     };
//     return ftcal::RunBridge(argc, argv, spec);
//   }
#pragma once

#include <exception>
#include <functional>
#include <memory>
#include <type_traits>

#include <CLI/CLI.hpp>

#include "common/device.h"
#include "common/exit_codes.h"
#include "common/service.h"

namespace ftcal {

// What a bridge's main gives RunBridge. `Bridge` is what `configure` builds: the Device the loop
// runs, or, with `open`, what owns it.
template <class Bridge>
struct BridgeSpec {
  ServiceSpec service;  // the program's name and --help text; a bridge is not replayable
  // The bridge's own flags, beside the common ones and the scheduling flags every bridge offers
  // (ServiceApp::OfferSchedulingFlags), bound to variables `configure` reads.
  std::function<void(CLI::App&)> add_flags;
  // Builds the bridge from app.config() and the flags. What it throws is the bridge refusing
  // its configuration.
  std::function<std::unique_ptr<Bridge>(ServiceApp&)> configure;
  // Opens the device and returns the Device the loop runs. What it throws is a device that
  // cannot be opened, unless refuses_config says otherwise. Unset, the bridge is the Device and
  // opens its device in the loop, with back-off.
  std::function<Device&(Bridge&)> open;
  // True for an error by which the device refuses the configuration, when opening or running
  // (IsA<SomeError> below). Unset: none does.
  std::function<bool(const std::exception&)> refuses_config;
  // After a clean stop: what the bridge has to log beyond ServiceStats' summary.
  std::function<void(Bridge&, ServiceApp&)> stopped;
};

// True when `e` is an E: for BridgeSpec::refuses_config.
template <class E>
bool IsA(const std::exception& e) {
  return dynamic_cast<const E*>(&e) != nullptr;
}

enum class BridgeStage { kConfigure, kOpen, kRun };

// Ends a bridge that failed at `stage` (`refused_config`: by an error the spec's refuses_config
// names): the error logged and counted (ServiceStats::Fatal), the state FAILED, the last
// heartbeat sent with it if the bus still takes it, the summary logged. Returns the exit code
// of the table above.
int FailBridge(ServiceApp& app, BridgeStage stage, bool refused_config, const std::exception& e);

namespace bridge_main_detail {

template <class Bridge>
Device& Open(const BridgeSpec<Bridge>& spec, Bridge& bridge) {
  if constexpr (std::is_base_of_v<Device, Bridge>) {
    if (!spec.open) return bridge;
  }
  return spec.open(bridge);  // unset for a Bridge that is no Device: std::bad_function_call, a bug
}

}  // namespace bridge_main_detail

template <class Bridge>
int RunBridge(int argc, char** argv, const BridgeSpec<Bridge>& spec) {
  ServiceApp app(spec.service);
  if (spec.add_flags) spec.add_flags(app.cli());
  app.OfferSchedulingFlags();
  if (auto rc = app.Init(argc, argv)) return *rc;

  const auto refused = [&spec](const std::exception& e) {
    return spec.refuses_config && spec.refuses_config(e);
  };
  std::unique_ptr<Bridge> bridge;  // declared after `app`: gone before the bus it publishes on
  try {
    bridge = spec.configure(app);
  } catch (const std::exception& e) {
    return FailBridge(app, BridgeStage::kConfigure, refused(e), e);
  }
  Device* device = nullptr;
  try {
    device = &bridge_main_detail::Open(spec, *bridge);
  } catch (const std::exception& e) {
    return FailBridge(app, BridgeStage::kOpen, refused(e), e);
  }
  try {
    app.RunDevice(*device);
  } catch (const std::exception& e) {
    return FailBridge(app, BridgeStage::kRun, refused(e), e);
  }
  if (spec.stopped) spec.stopped(*bridge, app);
  app.stats().LogSummary();
  return kExitDone;
}

}  // namespace ftcal
