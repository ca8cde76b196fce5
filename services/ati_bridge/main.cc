// ftcal-ati-bridge: ATI Net F/T transducers (RDT over UDP) -> ft_batch_t on FT_<LEG>.
//
// The bridge is a Device (common/device.h): ServiceApp's loop waits on its sockets, runs its
// re-send deadlines, and sends the 1 Hz heartbeat, at once when the state changes (RUNNING <->
// DEGRADED). It subscribes to nothing, so the loop does not wait on LCM.
#include <spdlog/spdlog.h>

#include <string>
#include <vector>

#include "ati_bridge.h"
#include "common/exit_codes.h"
#include "common/service.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-ati-bridge",
       "Streams the legs' ATI Net F/T transducers over RDT (UDP; a start command from an "
       "ephemeral port of this host, stop on exit; real-time, or buffered with the config's "
       "records_per_datagram, which must match the box's comrdtbsiz) and publishes every valid "
       "datagram as one ft_batch_t on FT_<LEG>: per record counts, wrench [N; N*m] (counts per "
       "unit from the "
       "config or the sensor's /netftapi2.xml, the config's sign applied), sequence numbers, "
       "status, gap and flags. Lost, duplicated, reordered and malformed records are counted, "
       "never published. Heartbeat counters per leg; DEGRADED while a transducer is silent.",
       /*replayable=*/false});
  std::vector<std::string> legs;
  ftcal::AtiBridgeOptions options;
  app.cli()
      .add_option("--legs", legs, "legs to serve, e.g. HL,ML (default: every leg of the config)")
      ->delimiter(',');
  app.cli()
      .add_option("--silence-timeout", options.silence_timeout_s,
                  "seconds without a record before the start command is sent again")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.OfferSchedulingFlags();
  if (auto rc = app.Init(argc, argv)) return *rc;

  auto log = spdlog::get("ftcal-ati-bridge");
  ftcal::Bus& bus = app.bus();
  std::unique_ptr<ftcal::AtiBridge> bridge;
  int failure = ftcal::kExitConfig;  // until the bridge is built: its checks of the config
  try {
    bridge = std::make_unique<ftcal::AtiBridge>(
        app.config(), legs,
        [&bus](const std::string& channel, const void* data, int size) {
          bus.PublishRaw(channel, data, size);
        },
        log, options);
    failure = ftcal::kExitDeviceIo;  // the calibration pages, the sockets
    bridge->Start();
  } catch (const std::exception& e) {
    const std::string text = ftcal::UserText(e, "starting the bridge");
    log->critical("{}", text);
    app.SetState(ftcal::service_status_t::FAILED);
    app.stats().Error("start", text);
    // A box set up otherwise than the config says (its RDT buffer size): a config error.
    if (dynamic_cast<const ftcal::AtiBoxMismatchError*>(&e) != nullptr) {
      failure = ftcal::kExitConfig;
    }
    if (ftcal::IsInternalError(e)) failure = ftcal::kExitInternal;
    try {
      bus.Publish(app.config().channels().status(), app.Status(), /*count=*/false);
    } catch (const std::exception&) {
    }
    return failure;
  }

  // The boxes' sockets pace this process, not LCM: ServiceApp's device loop, with the heartbeat
  // (sent at once when a transducer goes silent or comes back) and systemd's notify protocol.
  try {
    app.RunDevice(*bridge);
  } catch (const std::exception& e) {
    // Nothing the bridge does is expected to throw here (a bad datagram is counted, a page that
    // cannot be read is retried): if something does, the process says so and ends.
    const std::string text = ftcal::UserText(e, "reading the transducers");
    log->critical("{}", text);
    app.SetState(ftcal::service_status_t::FAILED);
    app.stats().Error("run", text);
    try {
      app.PublishHeartbeat();
    } catch (const std::exception&) {
    }
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
  for (std::size_t i = 0; i < bridge->size(); ++i) {
    const auto& c = bridge->counters(i);
    // received = published + duplicates + late + stale + uncalibrated + publish_errors.
    log->info(
        "{}: received {} published {} lost {} duplicates {} late {} stale {} uncalibrated {} "
        "publish_errors {} wrong_length {} restarts {} reboots {}",
        bridge->leg(i), c.received, c.published, c.lost, c.duplicates, c.late, c.stale,
        c.uncalibrated, c.publish_errors, c.wrong_length, c.restarts, c.reboots);
  }
  log->info(
      "latency receipt->published: p50 {} us p99 {} us (kernel timestamp: p50 {} us p99 {} us)",
      bridge->user_latency().QuantileUs(0.5), bridge->user_latency().QuantileUs(0.99),
      bridge->kernel_latency().QuantileUs(0.5), bridge->kernel_latency().QuantileUs(0.99));
  std::uint64_t held = 0, published = 0;
  for (std::size_t i = 0; i < bridge->size(); ++i) {
    held += bridge->counters(i).held_in_stack;
    published += bridge->counters(i).published;
  }
  log->info(
      "held in the network stack: {} of {} records (kernel timestamp before the socket was "
      "last found empty), their latency p50 {} us p99 {} us",
      held, published, bridge->held_latency().QuantileUs(0.5),
      bridge->held_latency().QuantileUs(0.99));
  app.stats().LogSummary();
  return 0;
}
