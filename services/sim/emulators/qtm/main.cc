// ftcal-emulate-qtm: the twin's QTM RT server for the bridge's tests and the simulator. Serves a
// BigAntTwin scenario in real time with the chosen faults and writes the frames it sent (the
// truth) to a CSV file when it ends.
#include <signal.h>

#include <CLI/CLI.hpp>

#include <cmath>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <sstream>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "qtm_emulator.h"
#include "sim/live.h"
#include "sim/twin.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

// "T:D" in seconds -> a tick window.
ftcal::sim::TickWindow ParseWindow(const std::string& text, double rate_hz, const char* flag) {
  const auto colon = text.find(':');
  char* end = nullptr;
  const double t = std::strtod(text.c_str(), &end);
  const double d = colon == std::string::npos ? NAN : std::strtod(text.c_str() + colon + 1, &end);
  if (colon == std::string::npos || *end != '\0' || !(t >= 0) || !(d > 0)) {
    throw CLI::ValidationError(flag, "'" + text + "' is not START_S:DURATION_S");
  }
  return {std::llround(t * rate_hz), std::max<int64_t>(1, std::llround(d * rate_hz))};
}

}  // namespace

int main(int argc, char** argv) try {
  CLI::App cli(
      "Qualisys QTM real-time server emulator (little-endian binary protocol) serving the "
      "BigAnt twin's chassis pose and markers in real time, with fault injection. Writes the "
      "frames it sent to --truth (CSV, atomically) when it ends.",
      "ftcal-emulate-qtm");
  std::string config_path;  // empty: the built-in config/sim.pbtxt
  std::string scenario = "walk";
  double duration_s = 10.0;
  double rate_hz = 100.0;
  int port = -1;
  std::string address;
  uint64_t seed = 1;
  std::string truth_path;
  int max_clients = 10;
  ftcal::sim::QtmFaults faults;
  std::vector<std::string> untracked, silent, no_more_data, disconnect;
  std::vector<double> settings_changed;
  cli.add_option("--config", config_path, "config (robot geometry, mocap address and port)")
      ->capture_default_str();
  cli.add_option("--scenario", scenario, "twin scenario: walk (TripodWalk) or standing")
      ->check(CLI::IsMember({"walk", "standing"}))
      ->capture_default_str();
  cli.add_option("--duration", duration_s, "seconds to serve (then exit)")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  cli.add_option("--rate-hz", rate_hz,
                 "frames per second (the twin's 100 Hz frames repeat "
                 "cyclically at other rates)")
      ->check(CLI::Range(1.0, 20000.0))
      ->capture_default_str();
  cli.add_option("--port", port, "TCP port (default: the config's mocap.port; 0: any)")
      ->check(CLI::Range(0, 65535));
  cli.add_option("--address", address, "IPv4 address to listen on (default: the config's)");
  cli.add_option("--seed", seed, "twin and fault seed")->capture_default_str();
  cli.add_option("--truth", truth_path, "CSV of every frame sent, written at exit");
  cli.add_option("--max-clients", max_clients)->check(CLI::Range(1, 100))->capture_default_str();
  cli.add_option("--gap-probability", faults.gap_probability, "per frame")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--max-gap", faults.max_gap_frames, "frames skipped per gap, at most")
      ->check(CLI::Range(1, 1000));
  cli.add_option("--marker-dropout-probability", faults.marker_dropout_probability,
                 "per frame and marker, on top of the twin's own dropouts")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--corrupt-probability", faults.corrupt_probability, "per frame")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--untracked", untracked, "START_S:DURATION_S body not tracked (repeatable)");
  cli.add_option("--silent", silent, "START_S:DURATION_S nothing sent (repeatable)");
  cli.add_option("--no-more-data", no_more_data,
                 "START_S:DURATION_S measurement stopped; frames restart at 1 after");
  cli.add_option("--disconnect", disconnect,
                 "START_S:DURATION_S QTM shuts down: clients closed, refused meanwhile");
  cli.add_option("--settings-changed", settings_changed, "T_S Camera Settings Changed event");
  bool reorder_bodies = false;
  cli.add_flag("--reorder-bodies", reorder_bodies,
               "swap the chassis and a decoy body in the 6D list at every settings change and "
               "restart, so a client must re-map bodies by name");
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;

  try {
    faults.seed = seed;
    for (const auto& w : untracked)
      faults.untracked.push_back(ParseWindow(w, rate_hz, "--untracked"));
    for (const auto& w : silent) faults.silent.push_back(ParseWindow(w, rate_hz, "--silent"));
    for (const auto& w : no_more_data) {
      faults.no_more_data.push_back(ParseWindow(w, rate_hz, "--no-more-data"));
    }
    for (const auto& w : disconnect) {
      faults.disconnected.push_back(ParseWindow(w, rate_hz, "--disconnect"));
    }
    for (double t : settings_changed) faults.settings_changed.push_back(std::llround(t * rate_hz));

    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);
    ftcal::TwinOptions twin_options;
    twin_options.seed = seed;
    const ftcal::BigAntTwin twin(config, twin_options);

    // The twin's frames up front (100 Hz, services/sim/live.h); served one per tick,
    // cyclically, whatever the rate.
    std::vector<ftcal::sim::QtmPose> poses;
    {
      const double twin_s = std::min(duration_s, 120.0);
      const ftcal::sim::TwinSeries series(twin, scenario == "walk" ? "walk" : "stand", twin_s);
      for (std::size_t i = 0; i < series.size(); ++i) {
        // The residual QtmPose always carried (its default), not the twin's marker noise.
        poses.push_back(
            ftcal::sim::QtmPoseFromFrame(series.Frame(i), ftcal::sim::QtmPose{}.residual_m));
      }
    }

    ftcal::sim::QtmEmulatorOptions options;
    options.address = address.empty() ? config.mocap().server_address() : address;
    options.port = static_cast<uint16_t>(port >= 0 ? port : int(config.mocap().port()));
    options.rate_hz = rate_hz;
    options.body_name = config.mocap().body_name();
    options.max_clients = max_clients;
    for (const auto& m : twin.MarkersB()) options.body_points_m.push_back(m);
    options.labels = ftcal::sim::DefaultQtmLabels(ftcal::kNumChassisMarkers);
    options.faults = faults;
    options.reorder_bodies_on_change = reorder_bodies;

    const int64_t total_ticks = std::llround(duration_s * rate_hz);
    ftcal::sim::QtmEmulator emulator(
        options, [&poses, total_ticks](int64_t tick) -> std::optional<ftcal::sim::QtmPose> {
          if (tick >= total_ticks) return std::nullopt;
          return poses[static_cast<size_t>(tick) % poses.size()];
        });

    std::vector<ftcal::sim::QtmSentFrame> truth;
    emulator.SetObserver([&truth](const ftcal::sim::QtmSentFrame& s) { truth.push_back(s); });

    struct sigaction sa {};
    sa.sa_handler = OnSignal;
    sigemptyset(&sa.sa_mask);
    ::sigaction(SIGINT, &sa, nullptr);
    ::sigaction(SIGTERM, &sa, nullptr);
    std::printf("ftcal-emulate-qtm listening on %s:%u, %g Hz, %lld frames\n",
                options.address.c_str(), emulator.port(), rate_hz,
                static_cast<long long>(total_ticks));
    std::fflush(stdout);

    emulator.Run(-1, [] { return g_stop == 0; });

    const auto& c = emulator.counters();
    std::printf(
        "ticks=%lld frames_sent=%lld corrupt=%lld untracked=%lld gaps=%lld skipped=%lld "
        "connections=%lld refused=%lld versions_refused=%lld parameters=%lld events=%lld "
        "disconnects=%lld no_more_data=%lld\n",
        (long long)c.ticks, (long long)c.frames_sent, (long long)c.frames_corrupt,
        (long long)c.frames_untracked, (long long)c.gaps, (long long)c.frames_skipped,
        (long long)c.connections, (long long)c.refused_clients, (long long)c.versions_refused,
        (long long)c.parameters_sent, (long long)c.events_sent, (long long)c.disconnects,
        (long long)c.no_more_data_sent);
    std::fflush(stdout);
    if (!truth_path.empty()) {
      ftcal::WriteFileAtomic(truth_path, ftcal::sim::QtmTruthCsv(options.labels, truth));
    }
  } catch (const std::exception& e) {
    std::cerr << "ftcal-emulate-qtm: " << e.what() << "\n";
    return 2;
  }
  return 0;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-emulate-qtm");
}
