// ftcal-ati-bridge: ATI Net F/T transducers (RDT over UDP) -> ft_sample_t on FT_<LEG>.
//
// The loop is the bridge's own poll() over its device sockets rather than the bus's: the
// bridge subscribes to nothing, and LCM's udpm provider opens no receive socket until something
// subscribes, so there is no LCM fd to wait on. It wakes at least every 100 ms for the shutdown
// flag, the re-send deadlines and the 1 Hz heartbeat, which is also sent at once when the
// state changes (RUNNING <-> DEGRADED).
#include <spdlog/spdlog.h>

#include <chrono>
#include <string>
#include <vector>

#include "ati_bridge.h"
#include "common/exit_codes.h"
#include "common/service.h"
#include "common/shutdown.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-ati-bridge",
       "Streams the legs' ATI Net F/T transducers over RDT (UDP; a start command from an "
       "ephemeral port of this host, stop on exit) and publishes every valid record as "
       "ft_sample_t on FT_<LEG>: counts, wrench [N; N*m] (counts per unit from the config or "
       "the sensor's /netftapi2.xml, the config's sign applied), sequence numbers, status, gap "
       "and flags. Lost, duplicated, reordered and malformed records are counted, never "
       "published. Heartbeat counters per leg; DEGRADED while a transducer is silent.",
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
    if (ftcal::IsInternalError(e)) failure = ftcal::kExitInternal;
    try {
      bus.Publish(app.config().channels().status(), app.Status(), /*count=*/false);
    } catch (const std::exception&) {
    }
    return failure;
  }

  std::int64_t reported_in = 0;
  auto sync_stats = [&] {
    std::int64_t received = 0;
    for (std::size_t i = 0; i < bridge->size(); ++i) {
      received += static_cast<std::int64_t>(bridge->counters(i).received);
    }
    // msgs_in counts device records: catch the stats up (CountIn has no bulk form).
    for (; reported_in < received; ++reported_in) app.stats().CountIn();
    for (const auto& [name, value] : bridge->CounterTable()) app.stats().Counter(name) = value;
  };
  auto publish_status = [&] {
    sync_stats();
    app.PublishHeartbeat();
  };

  // The boxes' sockets pace this loop, not LCM: ServiceApp's device-loop calls give it the
  // heartbeat and systemd's notify protocol (READY=1, the watchdog, STOPPING=1).
  using Clock = std::chrono::steady_clock;
  app.SetState(ftcal::service_status_t::RUNNING);
  sync_stats();
  app.DeviceLoopStarted();
  auto next_heartbeat = Clock::now() + std::chrono::seconds(1);
  while (!ftcal::ShutdownRequested()) {
    try {
      bridge->Poll(100);
    } catch (const std::exception& e) {
      app.stats().Error("poll", ftcal::UserText(e, "reading the transducers"));
    }
    const int8_t state =
        bridge->AllUp() ? ftcal::service_status_t::RUNNING : ftcal::service_status_t::DEGRADED;
    const bool changed = state != app.state();
    app.SetState(state);
    // The status carries what is wrong now, and nothing once it is healthy again.
    if (state == ftcal::service_status_t::DEGRADED) {
      app.stats().SetLastError(bridge->Problems());
    } else if (changed) {
      app.stats().ClearLastError();
    }
    const auto now = Clock::now();
    if (changed || now >= next_heartbeat) {
      try {
        publish_status();
      } catch (const std::exception& e) {
        app.stats().Error("heartbeat", e.what());
      }
      if (now >= next_heartbeat) next_heartbeat = now + std::chrono::seconds(1);
    }
  }
  bridge->Stop();
  sync_stats();
  app.DeviceLoopStopped();
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
