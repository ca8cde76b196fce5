#include "common/service.h"
#include "common/user_errors.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <climits>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <optional>

#include <spdlog/cfg/env.h>
#include <systemd/sd-daemon.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "common/lcm_bus.h"
#include "common/log_replay_bus.h"
#include "common/shutdown.h"
#include "common/written_digest.h"
#include "ftcal/config.h"

namespace ftcal {
namespace {

constexpr int64_t kLoopTickUs = 100'000;
constexpr double kHeartbeatPeriodS = 1.0;

// The URL's integer option `key` ("ttl", "recv_buf_size"), if given.
std::optional<long long> UrlOption(const std::string& url, const std::string& key) {
  const auto q = url.find('?');
  if (q == std::string::npos) return std::nullopt;
  std::size_t at = q + 1;
  while (at < url.size()) {
    const auto end = std::min(url.find('&', at), url.size());
    const std::string item = url.substr(at, end - at);
    if (item.compare(0, key.size() + 1, key + "=") == 0) {
      try {
        return std::stoll(item.substr(key.size() + 1));
      } catch (const std::exception&) {
        return std::nullopt;
      }
    }
    at = end + 1;
  }
  return std::nullopt;
}

long long ReadRmemMax() {
  std::ifstream in("/proc/sys/net/core/rmem_max");
  long long v = -1;
  in >> v;
  return in ? v : -1;
}

std::shared_ptr<spdlog::logger> MakeLogger(const std::string& name) {
  if (auto existing = spdlog::get(name)) return existing;  // a second app in one test process
  auto log = spdlog::stderr_color_mt(name);
  log->set_pattern("[%Y-%m-%d %H:%M:%S.%e] [%n] [%^%l%$] %v");
  return log;
}

}  // namespace

std::vector<std::string> LcmUrlWarnings(const std::string& url, long long rmem_max) {
  std::vector<std::string> out;
  // LCM's two multicast providers, one group and port (udpm) or one port per channel hash
  // (mpudpm), take the same ttl and recv_buf_size.
  if (url.rfind("udpm://", 0) != 0 && url.rfind("mpudpm://", 0) != 0) return out;
  const auto ttl = UrlOption(url, "ttl");
  if (ttl && *ttl > 0) {
    out.push_back("LCM URL " + url + ": ttl=" + std::to_string(*ttl) +
                  " sends every message (device data, commands) beyond this host; use ttl=0 "
                  "unless the processes run on several hosts of a closed lab network");
  }
  const auto asked = UrlOption(url, "recv_buf_size");
  if (asked && rmem_max >= 0 && *asked > rmem_max) {
    out.push_back("LCM URL " + url + ": recv_buf_size=" + std::to_string(*asked) +
                  " but the kernel allows " + std::to_string(rmem_max) +
                  " bytes (net.core.rmem_max): bursts can be lost; raise it with sysctl -w "
                  "net.core.rmem_max=" +
                  std::to_string(*asked));
  }
  return out;
}

ServiceApp::ServiceApp(ServiceSpec spec)
    : spec_(std::move(spec)),
      cli_(spec_.description, spec_.name),
      identity_(ThisProcess(spec_.name)),
      started_(std::chrono::steady_clock::now()),
      state_(service_status_t::STARTING) {
  cli_.add_option("--config", config_path_,
                  "configuration file (protobuf text format, libcal/proto/config.proto); "
                  "default: the " +
                      std::string(kDefaultConfigName) + " built in");
  cli_.add_option("--lcm-url", lcm_url_, "LCM URL; overrides the config's lcm_url");
  AddLogLevelOption(cli_, &log_level_);
  cli_.add_option("--state-dir", state_dir_,
                  "where a live process keeps what it accepted on signed channels, so that a "
                  "restart refuses it again (default: $FTCAL_STATE_DIR, $STATE_DIRECTORY, "
                  "$XDG_STATE_HOME/ftcal, ~/.local/state/ftcal)");
  if (spec_.replayable) {
    auto* in = cli_.add_option("--replay", replay_in_,
                               "run over this LCM log at full speed instead of live LCM");
    auto* out = cli_.add_option("--out", replay_out_,
                                "with --replay: write the publications to this LCM log, each "
                                "stamped with the time of the input event that caused it");
    in->needs(out);
    out->needs(in);
  }
  cli_.footer(
      "Every ftcal process publishes a service_status_t heartbeat once a second on the "
      "config's status channel (FTCAL_STATUS), ends cleanly on SIGINT/SIGTERM, and counts "
      "rather than crashes on bad input." +
      std::string(spec_.replayable
                      ? " On --replay it writes one final service_status_t with its counters "
                        "to the output log instead of the heartbeat."
                      : "") +
      "\n\n" + ExitCodeTable());
}

ServiceApp::~ServiceApp() = default;

std::optional<int> ServiceApp::Init(int argc, char** argv) {
  if (auto rc = ParseCommandLine(cli_, argc, argv)) return rc;

  log_ = MakeLogger(spec_.name);
  spdlog::cfg::load_env_levels();
  if (!log_level_.empty()) log_->set_level(spdlog::level::from_str(log_level_));
  // Library code that logs through spdlog's default logger (common/user_errors.cc) speaks
  // as this process, at its level.
  spdlog::set_default_logger(log_);
  stats_ = std::make_unique<ServiceStats>(log_);

  try {
    config_ = LoadConfigOrDefault(config_path_);
    if (config_path_.empty()) config_path_ = kDefaultConfigName;
  } catch (const ConfigError& e) {
    std::cerr << spec_.name << ": " << e.what() << "\n";
    return kExitConfig;
  } catch (const std::exception& e) {
    std::cerr << spec_.name << ": " << config_path_ << ": " << UserText(e, "reading the config")
              << "\n";
    return ExitCodeFor(e, kExitConfig);
  }
  if (lcm_url_.empty()) lcm_url_ = config_.lcm_url();
  if (!replay_in_.empty()) {
    // Replays read and write files: the URL is not used.
  } else {
    for (const std::string& warning : LcmUrlWarnings(lcm_url_, ReadRmemMax())) {
      log_->warn("{}", warning);
    }
  }

  try {
    if (!replay_in_.empty()) {
      auto replay = std::make_unique<LogReplayBus>(replay_in_, replay_out_, *stats_);
      if (spec_.digest_replay_output) {
        output_digest_ = std::make_unique<WrittenDigest>();
        replay->TapOutput(output_digest_->Tap());
      }
      replay_ = replay.get();
      bus_ = std::move(replay);
    } else {
      bus_ = std::make_unique<LcmBus>(lcm_url_, *stats_, RoutesOf(config_));
    }
    InstallShutdownHandlers();
  } catch (const std::exception& e) {
    log_->critical("{}", UserText(e, replay_in_.empty() ? "opening LCM" : "opening the replay"));
    return ExitCodeFor(e, kExitDeviceIo);
  }
  if (!replaying()) {
    if (state_dir_.empty()) state_dir_ = auth::SeenStore::DefaultDir();
    if (state_dir_.empty()) {
      log_->warn(
          "no state directory (--state-dir, FTCAL_STATE_DIR, HOME unset): what this process "
          "accepts on signed channels is forgotten when it restarts");
    } else {
      try {
        bus_->SetSeenStore(
            std::make_shared<auth::SeenStore>(state_dir_ + "/" + spec_.name + ".seen"));
      } catch (const std::exception& e) {
        log_->critical("{}", UserText(e, "reading the state file"));
        return ExitCodeFor(e, kExitDeviceIo);
      }
    }
  }
  log_->info("pid {} config {} {}", identity_.pid, config_path_,
             replaying() ? "replay " + replay_in_ + " -> " + replay_out_ : "lcm " + lcm_url_);
  return std::nullopt;
}

void ServiceApp::AddPeriodic(double period_s, std::function<void()> fn) {
  if (!(period_s > 0)) throw std::invalid_argument("periodic work needs a period > 0 s");
  periodic_.push_back({static_cast<int64_t>(period_s * 1e6), 0, std::move(fn)});
}

service_status_t ServiceApp::Status() const {
  const double uptime_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started_).count();
  service_status_t st = MakeServiceStatus(identity_, state_, uptime_s, *stats_, bus_->NowUtime());
  if (!flood_.empty() && state_ == service_status_t::RUNNING) {
    st.state = service_status_t::DEGRADED;
    st.last_error = flood_;
  }
  return st;
}

void ServiceApp::WatchDrops() {
  const int64_t in = stats_->msgs_in() - watched_in_;
  const int64_t dropped = stats_->drops() - watched_drops_;
  const config::Health& health = config_.health();
  std::string top_kind;
  int64_t top = 0;
  for (const auto& [kind, n] : stats_->kinds()) {
    const auto before = watched_kinds_.find(kind);
    const int64_t since = n - (before == watched_kinds_.end() ? 0 : before->second);
    if (since > top) {
      top = since;
      top_kind = kind;
    }
  }
  watched_in_ = stats_->msgs_in();
  watched_drops_ = stats_->drops();
  watched_kinds_ = stats_->kinds();
  if (in < static_cast<int64_t>(health.min_inputs())) {
    if (!flood_.empty()) log_->info("input back within health.max_drop_share (a quiet period)");
    flood_.clear();
    return;
  }
  const double share = static_cast<double>(dropped) / static_cast<double>(in);
  if (share <= health.max_drop_share()) {
    if (!flood_.empty()) {
      log_->info("input back within health.max_drop_share: {} of {} dropped", dropped, in);
    }
    flood_.clear();
    return;
  }
  char text[128];
  std::snprintf(text, sizeof text,
                "dropping %lld of %lld inputs (%.0f%%, above health.max_drop_share %g)",
                static_cast<long long>(dropped), static_cast<long long>(in), 100.0 * share,
                health.max_drop_share());
  std::string reason = text;
  if (!top_kind.empty()) reason += "; most: " + top_kind + " (" + std::to_string(top) + ")";
  if (flood_.empty()) log_->warn("{}", reason);
  flood_ = std::move(reason);
}

void ServiceApp::PublishStatus() {
  bus_->Publish(config_.channels().status(), Status(), /*count=*/false);
}

// Each task is guarded on its own so that one failing task does not starve the others.
void ServiceApp::Tick() {
  const int64_t now = bus_->NowUtime();
  if (const auto& store = bus_->seen_store()) {
    const std::string error = store->TakeError();
    if (!error.empty()) stats_->Error("state not saved", error);
  }
  for (auto& task : periodic_) {
    if (task.next_utime == 0) task.next_utime = now + task.period_us;
    if (now < task.next_utime) continue;
    task.next_utime += task.period_us;
    if (task.next_utime <= now) task.next_utime = now + task.period_us;  // late: skip
    try {
      task.fn();
    } catch (const std::exception& e) {
      stats_->Error("periodic work", UserText(e, "doing periodic work"));
    }
  }
}

// systemd's notify protocol (a no-op without NOTIFY_SOCKET, i.e. not under systemd), so a host
// can run this process as a Type=notify unit with WatchdogSec=: ready once the bus is open and
// the handlers are subscribed (or the device loop starts), and the watchdog fed by the
// heartbeat, which stops when the loop hangs.
void ServiceApp::NotifyReady() {
  sd_notifyf(0, "READY=1\nMAINPID=%lu\nSTATUS=%s", static_cast<unsigned long>(::getpid()),
             spec_.name.c_str());
  uint64_t watchdog_us = 0;
  watchdog_ = sd_watchdog_enabled(0, &watchdog_us) > 0;
}

void ServiceApp::PublishHeartbeat() {
  WatchDrops();
  PublishStatus();
  if (watchdog_) sd_notify(0, "WATCHDOG=1");
}

void ServiceApp::DeviceLoopStarted() {
  if (scheduling_offered_) ApplySchedulingFlags();
  if (state_ == service_status_t::STARTING) state_ = service_status_t::RUNNING;
  PublishStatus();
  NotifyReady();
}

void ServiceApp::DeviceLoopStopped() {
  state_ = service_status_t::STOPPING;
  sd_notify(0, "STOPPING=1");
  try {
    PublishStatus();
  } catch (const std::exception& e) {
    log_->warn("final heartbeat not sent: {}", UserText(e, "sending the final heartbeat"));
  }
}

void ServiceApp::RunDevice(Device& device) {
  using Clock = Device::Clock;
  const auto period =
      std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(kHeartbeatPeriodS));
  const auto max_wait = std::chrono::milliseconds(100);  // the shutdown flag's latency
  device.ReportCounters(*stats_);  // every counter is in the first heartbeat, at zero
  DeviceLoopStarted();
  auto next_heartbeat = Clock::now() + period;
  std::vector<pollfd> fds;
  while (!ShutdownRequested()) {
    auto now = Clock::now();
    const int8_t state =
        device.Degraded(nullptr) ? service_status_t::DEGRADED : service_status_t::RUNNING;
    const bool changed = state != state_;
    if (changed || now >= next_heartbeat) {
      if (state == service_status_t::DEGRADED) {
        std::string why;
        device.Degraded(&why);
        if (changed) log_->warn("degraded: {}", why);
        stats_->SetLastError(why);  // the status carries what is wrong now
      } else if (changed) {
        log_->info("healthy again");
        stats_->ClearLastError();  // and nothing once it is healthy again
      }
      state_ = state;
      device.ReportCounters(*stats_);
      try {
        PublishHeartbeat();
      } catch (const std::exception& e) {
        stats_->Error("heartbeat", UserText(e, "sending the heartbeat"));
      }
      if (now >= next_heartbeat) {
        next_heartbeat += period;
        if (next_heartbeat <= now) next_heartbeat = now + period;
      }
    }
    // The bus's sockets: only those of the routes subscribed to (Bus::Filenos).
    fds.clear();
    for (int fd : bus_->Filenos()) fds.push_back({fd, POLLIN, 0});
    const std::size_t first = fds.size();
    device.AddPollFds(&fds);
    const auto wake = std::min({device.NextDeadline(), next_heartbeat, now + max_wait});
    WaitFds(fds, wake);
    if (std::any_of(fds.begin(), fds.begin() + static_cast<std::ptrdiff_t>(first),
                    [](const pollfd& p) { return (p.revents & POLLIN) != 0; })) {
      bus_->HandleOnce(0);
    }
    device.OnPolled(fds.data() + first, fds.size() - first);
    now = Clock::now();
    if (now >= device.NextDeadline()) device.OnDeadline(now);
  }
  device.Close();
  device.ReportCounters(*stats_);
  DeviceLoopStopped();
}

int ServiceApp::Run() {
  if (state_ == service_status_t::STARTING) state_ = service_status_t::RUNNING;
  if (!replaying()) {
    PublishStatus();
    NotifyReady();
    AddPeriodic(kHeartbeatPeriodS, [this] { PublishHeartbeat(); });
  }
  bus_->Run([this] { Tick(); }, kLoopTickUs);
  if (replay_ == nullptr || replay_->finished()) {
    for (const auto& fn : at_input_end_) fn();
  }
  state_ = service_status_t::STOPPING;
  if (!replaying()) sd_notify(0, "STOPPING=1");
  if (const auto& store = bus_->seen_store()) {
    const std::string error = store->Flush();
    if (!error.empty()) log_->error("state not saved: {}", error);
  }

  int rc = 0;
  if (replay_ != nullptr) {
    if (!replay_->finished()) {
      rc = kExitDeviceIo;  // interrupted: the output log is not written
    } else {
      try {
        PublishStatus();
        replay_->Commit();
        log_->info("replayed {} events from {} into {}", replay_->events_read(), replay_in_,
                   replay_out_);
        HandOverOutputDigest(*replay_);
      } catch (const std::exception& e) {
        log_->critical("{}", UserText(e, "writing the replay's output"));
        rc = ExitCodeFor(e, kExitDeviceIo);
      }
    }
  } else {
    try {
      PublishStatus();
    } catch (const std::exception& e) {
      log_->warn("final heartbeat not sent: {}", e.what());
    }
  }
  stats_->LogSummary();
  return rc;
}

void ServiceApp::HandOverOutputDigest(const LogReplayBus& replay) {
  if (!output_digest_) return;
  const std::string hex = output_digest_->HandOver(replay_out_, replay.output_stat());
  if (!hex.empty()) log_->info("{}: SHA-256 {} handed to the digest cache", replay_out_, hex);
}

void ServiceApp::OfferSchedulingFlags() {
  scheduling_offered_ = true;
  cli_.add_flag("--realtime", scheduling_.realtime,
                "run SCHED_FIFO with memory locked (a robot computer; needs root or "
                "CAP_SYS_NICE/CAP_IPC_LOCK, else a warning and an ordinary process)");
  cli_.add_option("--realtime-priority", scheduling_.realtime_priority,
                  "SCHED_FIFO priority with --realtime")
      ->capture_default_str()
      ->check(CLI::Range(1, 99));
  cli_.add_option("--slice-us", scheduling_.slice_us,
                  "without SCHED_FIFO, the scheduler slice to ask for (Linux >= 6.12 lets a "
                  "waking task with a shorter slice preempt); 0: the kernel's default")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 100000.0));
}

void ServiceApp::ApplySchedulingFlags() {
  const SchedulingGranted granted = ApplyScheduling(scheduling_, *log_);
  stats_->Counter("sched_fifo") = granted.fifo ? 1 : 0;
  stats_->Counter("memory_locked") = granted.locked ? 1 : 0;
  stats_->Counter("sched_slice") = granted.slice ? 1 : 0;
}

}  // namespace ftcal
