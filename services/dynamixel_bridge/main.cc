// ftcal-dynamixel-bridge: the Dynamixel MX-106 bus (Protocol 2.0) to SERVO_STATE, SERVO_CMD to
// the bus. A thin main around DynamixelBridge: ServiceApp's device loop waits on the serial port
// (DynamixelDevice: a read-write cycle at dynamixel.rate_hz) and the process's one LCM socket
// (the ServiceApp's bus, whose SubscribeSigned verifies SERVO_CMD's envelope and names its
// signer); the CommandGate decides whether to act on a command.
#include <spdlog/fmt/fmt.h>

#include <chrono>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>

#include "common/bridge_main.h"
#include "common/bus.h"
#include "dynamixel_bridge/command_gate.h"
#include "dynamixel_bridge/dynamixel_bridge.h"
#include "dynamixel_bridge/dynamixel_device.h"

namespace {

using Clock = std::chrono::steady_clock;

double SteadyS() { return std::chrono::duration<double>(Clock::now().time_since_epoch()).count(); }

// The bus cycle's rate, which the bridge class does not see (DynamixelDevice paces it).
double RateHz(const ftcal::config::Config& config) {
  const double rate_hz = config.dynamixel().rate_hz();
  if (!(rate_hz > 0 && rate_hz <= 1000)) {
    throw std::invalid_argument(fmt::format("dynamixel.rate_hz {} outside (0, 1000]", rate_hz));
  }
  return rate_hz;
}

// The bridge with what it answers to: commands come through the verifier and the gate, the
// servos' state goes out through the gate (which follows it) to SERVO_STATE. The Device the loop
// runs is made once the port is open: the gate's first ARM block is what Connect() found.
struct DynamixelProcess {
  DynamixelProcess(ftcal::ServiceApp& app, const ftcal::DynamixelBridgeOptions& options)
      : stats(app.stats()),
        rate_hz(RateHz(app.config())),
        deadman_s(app.config().dynamixel().deadman_s()),
        gate(app.config(), app.stats(), SteadyS()),
        verifier(ftcal::auth::Verifier::FromConfig(app.config())),
        bridge(
            app.config(), options, app.stats(),
            [this, &app](const ftcal::servo_state_t& msg) {
              gate.OnState(msg);
              app.bus().Publish(app.config().channels().servo_state(), msg);
            },
            [&app] { return app.bus().NowUtime(); }) {
    const auto& config = app.config();
    // Not kept on disk: config validation keeps auth.servo_cmd_window_s below
    // dynamixel.start_quiet_s, so a command taken before a restart is stale when the gate
    // listens.
    verifier.set_persist(false);
    if (!verifier.Trusts(config.channels().servo_cmd())) {
      app.log().warn("no key in the config's auth is trusted on {}: every command is refused",
                     config.channels().servo_cmd());
    }
    app.bus().SubscribeSigned<ftcal::servo_command_t>(
        config.channels().servo_cmd(), &verifier,
        static_cast<int64_t>(config.auth().servo_cmd_window_s() * 1e6),
        /*allow_unsigned=*/false,
        [this](const ftcal::MessageInfo& info, const ftcal::servo_command_t& cmd) {
          gate.OnCommand(*info.signer, cmd, SteadyS());
        });
  }

  // Opens the port and pings the servos. A port that does not open is no failure: the bridge
  // runs DEGRADED and reopens it with back-off.
  ftcal::Device& Open() {
    bridge.Connect();
    return device.emplace(bridge, gate, stats, rate_hz, deadman_s, SteadyS);
  }

  ftcal::ServiceStats& stats;
  double rate_hz;
  double deadman_s;
  ftcal::CommandGate gate;
  ftcal::auth::Verifier verifier;
  ftcal::DynamixelBridge bridge;
  std::optional<ftcal::DynamixelDevice> device;
};

}  // namespace

int main(int argc, char** argv) {
  ftcal::DynamixelBridgeOptions options;
  ftcal::BridgeSpec<DynamixelProcess> spec;
  spec.service = {
      "ftcal-dynamixel-bridge",
      "Reads the Dynamixel MX-106 servos (Protocol 2.0) on the config's serial device: SYNC "
      "READ of the present block at dynamixel.rate_hz, Hardware Error Status now and then, and "
      "publishes SERVO_STATE (servo_state_t: shaft angles in rad, 0 = leg straight down, "
      "velocity, current, hardware error, unwrapped device tick, STALE/HW_ERROR/TORQUE_OFF "
      "flags; LOST for a servo silent for --lost-after cycles, which is then only PINGed "
      "every --reprobe-every s). Reads SERVO_CMD (servo_command_t in a signed envelope from a "
      "key the config's auth trusts for it) and, once armed by one commander, writes torque "
      "enable and goal positions clamped to the angle limits minus dynamixel.limit_margin_rad "
      "and rate-limited to dynamixel.max_velocity_rad_s; holds the measured position when the "
      "armed commander is silent for dynamixel.deadman_s. When it finds a servo it writes the "
      "servo's own limits (Velocity/Acceleration Limit and Profile from "
      "dynamixel.max_velocity_rad_s and max_acceleration_rad_s2, Min/Max Position Limit in "
      "Position mode, Bus Watchdog from dynamixel.bus_watchdog_s) and reads them back; ARM is "
      "refused while they differ, and a servo whose watchdog expired is cleared and held until "
      "a new ARM. DEGRADED while a servo is silent, faulty or not as configured, or the port is "
      "down (it is reopened with back-off)."};
  spec.add_flags = [&options](CLI::App& cli) {
    cli.add_option("--device", options.device,
                   "serial device; overrides the config's dynamixel.device");
    cli.add_option("--hw-error-every", options.hardware_error_every,
                   "read Hardware Error Status every n-th cycle (and after any alert)")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
    cli.add_option("--lost-after", options.lost_after_misses,
                   "cycles in a row without a valid reply before a servo is LOST: left out of "
                   "the reads (so it costs the others no timeout) and PINGed now and then")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
    cli.add_option("--reprobe-every", options.reprobe_every_s,
                   "seconds between PINGs of a lost servo")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
  };
  spec.configure = [&options](ftcal::ServiceApp& app) {
    return std::make_unique<DynamixelProcess>(app, options);
  };
  // The bus cycle paces this process, not LCM: the loop waits on the port and on the bus's
  // socket (SERVO_CMD) at once, with the heartbeat and systemd's notify protocol (READY=1 once
  // connected, the watchdog with the heartbeat, STOPPING=1).
  spec.open = [](DynamixelProcess& p) -> ftcal::Device& { return p.Open(); };
  return ftcal::RunBridge(argc, argv, spec);
}
