// ftcal-dynamixel-bridge: the Dynamixel MX-106 bus (Protocol 2.0) to SERVO_STATE, SERVO_CMD to
// the bus. A thin main around DynamixelBridge: ServiceApp's device loop waits on the serial port
// (DynamixelDevice: a read-write cycle at dynamixel.rate_hz) and the process's one LCM socket
// (the ServiceApp's bus, whose SubscribeSigned verifies SERVO_CMD's envelope and names its
// signer); the CommandGate decides whether to act on a command.
#include <chrono>
#include <cmath>
#include <string>

#include "common/bus.h"
#include "common/exit_codes.h"
#include "common/service.h"
#include "dynamixel_bridge/command_gate.h"
#include "dynamixel_bridge/dynamixel_bridge.h"
#include "dynamixel_bridge/dynamixel_device.h"

namespace {

using Clock = std::chrono::steady_clock;

double SteadyS() { return std::chrono::duration<double>(Clock::now().time_since_epoch()).count(); }

}  // namespace

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-dynamixel-bridge",
       "Reads the Dynamixel MX-106 servos (Protocol 2.0) on the config's serial device: SYNC "
       "READ of the present block at dynamixel.rate_hz, Hardware Error Status now and then, and "
       "publishes SERVO_STATE (servo_state_t: shaft angles in rad, 0 = leg straight down, "
       "velocity, current, hardware error, unwrapped device tick, STALE/HW_ERROR/TORQUE_OFF "
       "flags; LOST for a servo silent for --lost-after cycles, which is then only PINGed "
       "every --reprobe-every s). Reads SERVO_CMD (servo_command_t in a signed envelope from a key "
       "the config's "
       "auth trusts for it) and, once armed by one commander, writes torque enable and goal "
       "positions clamped to the angle limits minus dynamixel.limit_margin_rad and rate-limited "
       "to dynamixel.max_velocity_rad_s; holds the measured position when the armed commander "
       "is silent for dynamixel.deadman_s. When it finds a servo it writes the servo's own "
       "limits (Velocity/Acceleration Limit and Profile from dynamixel.max_velocity_rad_s and "
       "max_acceleration_rad_s2, Min/Max Position Limit in Position mode, Bus Watchdog from "
       "dynamixel.bus_watchdog_s) and reads them back; ARM is refused while they differ, and a "
       "servo whose watchdog expired is cleared and held until a new ARM. DEGRADED while a "
       "servo is silent, faulty or not as configured, or the port is down (it is reopened with "
       "back-off).",
       /*replayable=*/false});
  ftcal::DynamixelBridgeOptions options;
  app.cli().add_option("--device", options.device,
                       "serial device; overrides the config's dynamixel.device");
  app.cli()
      .add_option("--hw-error-every", options.hardware_error_every,
                  "read Hardware Error Status every n-th cycle (and after any alert)")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.cli()
      .add_option("--lost-after", options.lost_after_misses,
                  "cycles in a row without a valid reply before a servo is LOST: left out of "
                  "the reads (so it costs the others no timeout) and PINGed now and then")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.cli()
      .add_option("--reprobe-every", options.reprobe_every_s,
                  "seconds between PINGs of a lost servo")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.OfferSchedulingFlags();
  if (auto rc = app.Init(argc, argv)) return *rc;

  const auto& config = app.config();
  const double rate_hz = config.dynamixel().rate_hz();
  if (!(rate_hz > 0 && rate_hz <= 1000)) {
    app.log().critical("config: dynamixel.rate_hz {} outside (0, 1000]", rate_hz);
    return ftcal::kExitConfig;
  }
  try {
    ftcal::CommandGate gate(config, app.stats(), SteadyS());
    ftcal::auth::Verifier verifier = ftcal::auth::Verifier::FromConfig(config);
    // Not kept on disk: config validation keeps auth.servo_cmd_window_s below
    // dynamixel.start_quiet_s, so a command taken before a restart is stale when the gate listens.
    verifier.set_persist(false);
    if (!verifier.Trusts(config.channels().servo_cmd())) {
      app.log().warn("no key in the config's auth is trusted on {}: every command is refused",
                     config.channels().servo_cmd());
    }
    ftcal::DynamixelBridge bridge(
        config, options, app.stats(),
        [&](const ftcal::servo_state_t& msg) {
          gate.OnState(msg);
          app.bus().Publish(config.channels().servo_state(), msg);
        },
        [&] { return app.bus().NowUtime(); });

    app.bus().SubscribeSigned<ftcal::servo_command_t>(
        config.channels().servo_cmd(), &verifier,
        static_cast<int64_t>(config.auth().servo_cmd_window_s() * 1e6),
        /*allow_unsigned=*/false,
        [&gate](const ftcal::MessageInfo& info, const ftcal::servo_command_t& cmd) {
          gate.OnCommand(*info.signer, cmd, SteadyS());
        });

    bridge.Connect();
    // The bus cycle paces this process, not LCM: ServiceApp's device loop waits on the port and
    // the bus's socket (SERVO_CMD) at once, with the heartbeat and systemd's notify protocol
    // (READY=1 once connected, the watchdog with the heartbeat, STOPPING=1).
    ftcal::DynamixelDevice device(bridge, gate, app.stats(), rate_hz,
                                  config.dynamixel().deadman_s(), SteadyS);
    app.RunDevice(device);
  } catch (const std::invalid_argument& e) {  // the bridge's config checks
    app.log().critical("{}", e.what());
    return ftcal::kExitConfig;
  } catch (const std::exception& e) {
    app.log().critical("{}", e.what());
    return ftcal::kExitDeviceIo;
  }
  app.stats().LogSummary();
  return 0;
}
