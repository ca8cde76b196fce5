// ftcal-ati-bridge: ATI Net F/T transducers (RDT over UDP) -> ft_batch_t on FT_<LEG>.
//
// The bridge is a Device (common/device.h): ServiceApp's loop waits on its sockets, runs its
// re-send deadlines, and sends the 1 Hz heartbeat, at once when the state changes (RUNNING <->
// DEGRADED). It subscribes to nothing, so the loop does not wait on LCM.
#include <spdlog/spdlog.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "ati_bridge.h"
#include "common/bridge_main.h"

namespace {

constexpr char kName[] = "ftcal-ati-bridge";

// What the boxes sent and what became of it, per leg, and the latency the bridge added.
void LogCounts(const ftcal::AtiBridge& bridge, ftcal::ServiceApp& app) {
  spdlog::logger& log = app.log();
  for (std::size_t i = 0; i < bridge.size(); ++i) {
    const auto& c = bridge.counters(i);
    // received = published + duplicates + late + stale + uncalibrated + publish_errors.
    log.info(
        "{}: received {} published {} lost {} duplicates {} late {} stale {} uncalibrated {} "
        "publish_errors {} wrong_length {} restarts {} reboots {}",
        bridge.leg(i), c.received, c.published, c.lost, c.duplicates, c.late, c.stale,
        c.uncalibrated, c.publish_errors, c.wrong_length, c.restarts, c.reboots);
  }
  log.info(
      "latency receipt->published: p50 {} us p99 {} us (kernel timestamp: p50 {} us p99 {} us)",
      bridge.user_latency().QuantileUs(0.5), bridge.user_latency().QuantileUs(0.99),
      bridge.kernel_latency().QuantileUs(0.5), bridge.kernel_latency().QuantileUs(0.99));
  std::uint64_t held = 0, published = 0;
  for (std::size_t i = 0; i < bridge.size(); ++i) {
    held += bridge.counters(i).held_in_stack;
    published += bridge.counters(i).published;
  }
  log.info(
      "held in the network stack: {} of {} records (kernel timestamp before the socket was "
      "last found empty), their latency p50 {} us p99 {} us",
      held, published, bridge.held_latency().QuantileUs(0.5),
      bridge.held_latency().QuantileUs(0.99));
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> legs;
  ftcal::AtiBridgeOptions options;
  ftcal::BridgeSpec<ftcal::AtiBridge> spec;
  spec.service = {
      kName,
      "Streams the legs' ATI Net F/T transducers over RDT (UDP; a start command from an "
      "ephemeral port of this host, stop on exit; real-time, or buffered with the config's "
      "records_per_datagram, which must match the box's comrdtbsiz) and publishes every valid "
      "datagram as one ft_batch_t on FT_<LEG>: per record counts, wrench [N; N*m] (counts per "
      "unit from the config or the sensor's /netftapi2.xml, the config's sign applied), "
      "sequence numbers, status, gap and flags. Lost, duplicated, reordered and malformed "
      "records are counted, never published. Heartbeat counters per leg; DEGRADED while a "
      "transducer is silent."};
  spec.add_flags = [&](CLI::App& cli) {
    cli.add_option("--legs", legs, "legs to serve, e.g. HL,ML (default: every leg of the config)")
        ->delimiter(',');
    cli.add_option("--silence-timeout", options.silence_timeout_s,
                   "seconds without a record before the start command is sent again")
        ->capture_default_str()
        ->check(CLI::PositiveNumber);
  };
  spec.configure = [&](ftcal::ServiceApp& app) {
    return std::make_unique<ftcal::AtiBridge>(
        app.config(), legs,
        [&app](const std::string& channel, const void* data, int size) {
          app.bus().PublishRaw(channel, data, size);
        },
        spdlog::get(kName), options);
  };
  // The calibration pages fetched and the sockets opened before the loop: a page that cannot be
  // read ends the bridge as a device failure, a box set up otherwise (below) as the config's.
  spec.open = [](ftcal::AtiBridge& bridge) -> ftcal::Device& {
    bridge.Start();
    return bridge;
  };
  // A box set up otherwise than the config says (its RDT buffer size).
  spec.refuses_config = ftcal::IsA<ftcal::AtiBoxMismatchError>;
  spec.stopped = LogCounts;
  return ftcal::RunBridge(argc, argv, spec);
}
