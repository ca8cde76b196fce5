// What every ftcal process shares: flags, config loading, logging, the bus (live LCM or a
// replayed log), SIGINT/SIGTERM, periodic work and the 1 Hz FTCAL_STATUS heartbeat.
//
//   int main(int argc, char** argv) {
//     ftcal::ServiceApp app({"ftcal-foo", "Reads FT_<LEG>; publishes FOO.", /*replayable=*/true});
//     if (auto rc = app.Init(argc, argv)) return *rc;
//     Foo foo(app.config(), app.bus());   // subscribes its handlers
//     return app.Run();
//   }
//
// Flags: --config FILE (default: config/sim.pbtxt as built into the binary), --lcm-url URL
// (overrides the config's lcm_url), --log-level LEVEL (else SPDLOG_LEVEL), and for a replayable
// stage
// --replay IN.lcmlog --out OUT.lcmlog. On replay the heartbeat is not logged; instead one final
// service_status_t (state STOPPING, the run's counters) is written to the output log on the
// status channel, stamped with the last input time.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/logger.h>

#include "common/bus.h"
#include "common/device.h"
#include "common/heartbeat.h"
#include "common/exit_codes.h"
#include "common/scheduling.h"
#include "common/service_stats.h"
#include "common/user_errors.h"
#include "proto/config.pb.h"

namespace ftcal {

class LogReplayBus;
class WrittenDigest;

// What a careful operator should hear about an LCM URL: a multicast ttl > 0 (traffic leaves
// the host), a recv_buf_size above the kernel's limit `rmem_max` (the socket silently gets
// less, and a recording loses bursts). Empty when there is nothing to say.
std::vector<std::string> LcmUrlWarnings(const std::string& url, long long rmem_max);

struct ServiceSpec {
  std::string name;         // e.g. "ftcal-status"; also the logger's and heartbeat's name
  std::string description;  // what the process reads and publishes, for --help
  bool replayable = false;  // a stage: offers --replay/--out
  // The replay's output is a calibrator input (the segmenter's poses log): its SHA-256 is taken
  // as it is written and handed to the digest cache, so the calibrator need not hash it.
  bool digest_replay_output = false;
};

class ServiceApp {
 public:
  explicit ServiceApp(ServiceSpec spec);
  ~ServiceApp();
  ServiceApp(const ServiceApp&) = delete;
  ServiceApp& operator=(const ServiceApp&) = delete;

  // Add process-specific flags here before Init().
  CLI::App& cli() { return cli_; }

  // Parses flags, sets up logging, loads the config, opens the bus and installs the signal
  // handlers. Returns an exit code (common/exit_codes.h) when the process should end now: 0
  // after --help, 1 for a bad flag, 3 for a bad config file (its ConfigError printed), 4 when
  // the bus or the replay log cannot be opened.
  std::optional<int> Init(int argc, char** argv);

  // Valid after a successful Init().
  const config::Config& config() const { return config_; }
  const std::string& config_path() const { return config_path_; }
  Bus& bus() { return *bus_; }
  // The bus as the replay it is on --replay (what only a replay does: its counts, skipping a
  // span of the input); null live.
  LogReplayBus* ReplayBus() { return replay_; }
  ServiceStats& stats() { return *stats_; }
  spdlog::logger& log() { return *log_; }
  bool replaying() const { return replay_ != nullptr; }
  // The --replay input's path (empty live).
  const std::string& replay_input() const { return replay_in_; }

  // The state the heartbeat reports (service_status_t::RUNNING, DEGRADED, ...). Run() moves
  // STARTING to RUNNING; a process sets DEGRADED/FAILED when an input or device is missing.
  // Live, a RUNNING process that dropped more than the config's health.max_drop_share of its
  // input over the last heartbeat period reports DEGRADED instead, the drops' commonest kind in
  // its last error (a flood of garbage must show), until a period below the share.
  void SetState(int8_t state) { state_ = state; }
  int8_t state() const { return state_; }

  // Runs `fn` every `period_s` of bus time (the log's clock on replay), never more often than
  // the loop's 100 ms tick.
  void AddPeriodic(double period_s, std::function<void()> fn);

  // Runs `fn` once the input has ended (a replay read to its end, or a live shutdown), before
  // the final status, while the bus still publishes: a stage publishes what it held back for
  // input that will not come. Not after an interrupted replay (its output is not written).
  void AtInputEnd(std::function<void()> fn) { at_input_end_.push_back(std::move(fn)); }

  // Runs until SIGINT/SIGTERM (or RequestShutdown()) live, or to the end of the input on
  // replay; then publishes a final STOPPING status and logs a summary. Returns the exit code:
  // 0, or 4 when a replay was interrupted or its output could not be written.
  int Run();

  // The heartbeat as it would be published now.
  service_status_t Status() const;

  // The loop of a process paced by its device instead of LCM (the bridges: sockets or a serial
  // line wake them; common/device.h): one wait over the device's descriptors and, when anything
  // is subscribed, the bus's, until SIGINT/SIGTERM. It applies the scheduling asked for
  // (OfferSchedulingFlags) once the device is open, sends systemd's READY=1 and STOPPING=1 (no-ops
  // when not under systemd), and publishes the heartbeat a second, and at once when the device
  // turns degraded or healthy: DEGRADED with Degraded()'s reason as the last error (one log line
  // per change), the device's counters, systemd's watchdog fed (the heartbeat stops when the loop
  // hangs, and so does the feed). On the way out: Close(), the counters, a STOPPING heartbeat.
  // Exceptions from the device pass to the caller, with the state left as it was.
  void RunDevice(Device& device);
  // The heartbeat on the status channel, and systemd's watchdog fed. A process whose device
  // failed before its loop sends its last (FAILED) heartbeat with this.
  void PublishHeartbeat();

  // A device-paced process's scheduling (common/scheduling.h), the same flags in every bridge:
  // --realtime, --realtime-priority and --slice-us. Offer them before Init(); RunDevice()
  // applies them, on the thread that runs the device loop once the device is open (the
  // calibration pages and port probes run as an ordinary process), and sets the counters
  // sched_fifo, memory_locked and sched_slice (1 when granted); refusals are logged.
  void OfferSchedulingFlags();

 private:
  struct Periodic {
    int64_t period_us;
    int64_t next_utime;
    std::function<void()> fn;
  };
  void Tick();
  void PublishStatus();
  void DeviceLoopStarted();
  void DeviceLoopStopped();
  void NotifyReady();
  void ApplySchedulingFlags();
  // Judges the inputs and drops since the last heartbeat (health.max_drop_share).
  void WatchDrops();
  // Stores the replay output's digest, taken as it was written, in the digest cache.
  void HandOverOutputDigest(const LogReplayBus& replay);
  bool watchdog_ = false;  // systemd asked for WATCHDOG=1 (WatchdogSec=)

  ServiceSpec spec_;
  CLI::App cli_;
  std::string config_path_;
  std::string lcm_url_;
  std::string log_level_;
  std::vector<std::function<void()>> at_input_end_;
  std::string replay_in_;
  std::string replay_out_;
  std::string state_dir_;
  SchedulingOptions scheduling_;
  bool scheduling_offered_ = false;

  ProcessIdentity identity_;
  std::chrono::steady_clock::time_point started_;
  std::shared_ptr<spdlog::logger> log_;
  std::unique_ptr<ServiceStats> stats_;
  config::Config config_;
  std::unique_ptr<Bus> bus_;
  LogReplayBus* replay_ = nullptr;                // bus_ when it is a replay (ReplayBus())
  std::unique_ptr<WrittenDigest> output_digest_;  // spec_.digest_replay_output, when replaying
  int8_t state_;
  std::vector<Periodic> periodic_;
  // WatchDrops: the counts at the last heartbeat, and why the input is judged flooded ("" when
  // it is not).
  int64_t watched_in_ = 0, watched_drops_ = 0;
  std::map<std::string, int64_t> watched_kinds_;
  std::string flood_;
};

}  // namespace ftcal
