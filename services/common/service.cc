#include "common/service.h"

#include <unistd.h>

#include <climits>
#include <iostream>

#include <spdlog/cfg/env.h>
#include <spdlog/sinks/stdout_color_sinks.h>
#include <spdlog/spdlog.h>

#include "common/shutdown.h"
#include "ftcal/config.h"

#ifndef FTCAL_SOURCE_DIR
#error "FTCAL_SOURCE_DIR must be defined by the build (services/common/CMakeLists.txt)"
#endif

namespace ftcal {
namespace {

constexpr int64_t kLoopTickUs = 100'000;
constexpr double kHeartbeatPeriodS = 1.0;

const std::vector<std::string> kLogLevels = {"trace", "debug",    "info", "warn",
                                             "error", "critical", "off"};

bool FileExists(const std::string& path) { return ::access(path.c_str(), R_OK) == 0; }

std::string ExecutableDir() {
  char buf[PATH_MAX + 1] = {};
  const ssize_t n = ::readlink("/proc/self/exe", buf, PATH_MAX);
  if (n <= 0) return "";
  std::string path(buf, static_cast<size_t>(n));
  const auto slash = path.rfind('/');
  return slash == std::string::npos ? "" : path.substr(0, slash);
}

std::shared_ptr<spdlog::logger> MakeLogger(const std::string& name) {
  if (auto existing = spdlog::get(name)) return existing;  // a second app in one test process
  auto log = spdlog::stderr_color_mt(name);
  log->set_pattern("[%Y-%m-%d %H:%M:%S.%e] [%n] [%^%l%$] %v");
  return log;
}

}  // namespace

ServiceApp::ServiceApp(ServiceSpec spec)
    : spec_(std::move(spec)),
      cli_(spec_.description, spec_.name),
      identity_(ThisProcess(spec_.name)),
      started_(std::chrono::steady_clock::now()),
      state_(service_status_t::STARTING) {
  cli_.add_option("--config", config_path_,
                  "configuration file (protobuf text format, libcal/proto/config.proto); "
                  "default: the embedded " + DefaultConfigPath());
  cli_.add_option("--lcm-url", lcm_url_, "LCM URL; overrides the config's lcm_url");
  cli_.add_option("--log-level", log_level_, "log level; default from SPDLOG_LEVEL, else info")
      ->check(CLI::IsMember(kLogLevels));
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
                      : ""));
}

ServiceApp::~ServiceApp() = default;

std::string ServiceApp::DefaultConfigPath() {
  const std::string installed = ExecutableDir() + "/../share/ftcal/config/sim.pbtxt";
  if (FileExists(installed)) return installed;
  return std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
}

std::optional<int> ServiceApp::Init(int argc, char** argv) {
  try {
    cli_.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return cli_.exit(e);
  }

  log_ = MakeLogger(spec_.name);
  spdlog::cfg::load_env_levels();
  if (!log_level_.empty()) log_->set_level(spdlog::level::from_str(log_level_));
  stats_ = std::make_unique<ServiceStats>(log_);

  if (config_path_.empty()) config_path_ = DefaultConfigPath();
  try {
    config_ = LoadConfigFile(config_path_);
  } catch (const ConfigError& e) {
    std::cerr << spec_.name << ": " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << spec_.name << ": " << config_path_ << ": " << e.what() << "\n";
    return 2;
  }
  if (lcm_url_.empty()) lcm_url_ = config_.lcm_url();

  try {
    if (!replay_in_.empty()) {
      bus_ = std::make_unique<LogReplayBus>(replay_in_, replay_out_, *stats_);
    } else {
      bus_ = std::make_unique<LcmBus>(lcm_url_, *stats_);
    }
    InstallShutdownHandlers();
  } catch (const std::exception& e) {
    log_->critical("{}", e.what());
    return 1;
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
  return MakeServiceStatus(identity_, state_, uptime_s, *stats_, bus_->NowUtime());
}

void ServiceApp::PublishStatus() {
  bus_->Publish(config_.channels().status(), Status(), /*count=*/false);
}

// Each task is guarded on its own so that one failing task does not starve the others.
void ServiceApp::Tick() {
  const int64_t now = bus_->NowUtime();
  for (auto& task : periodic_) {
    if (task.next_utime == 0) task.next_utime = now + task.period_us;
    if (now < task.next_utime) continue;
    task.next_utime += task.period_us;
    if (task.next_utime <= now) task.next_utime = now + task.period_us;  // late: skip
    try {
      task.fn();
    } catch (const std::exception& e) {
      stats_->Error("periodic work", e.what());
    }
  }
}

int ServiceApp::Run() {
  if (state_ == service_status_t::STARTING) state_ = service_status_t::RUNNING;
  if (!replaying()) {
    PublishStatus();
    AddPeriodic(kHeartbeatPeriodS, [this] { PublishStatus(); });
  }
  bus_->Run([this] { Tick(); }, kLoopTickUs);
  state_ = service_status_t::STOPPING;

  int rc = 0;
  if (auto* replay = dynamic_cast<LogReplayBus*>(bus_.get())) {
    if (!replay->finished()) {
      rc = 1;
    } else {
      try {
        PublishStatus();
        replay->Commit();
        log_->info("replayed {} events from {} into {}", replay->events_read(), replay_in_,
                   replay_out_);
      } catch (const std::exception& e) {
        log_->critical("{}", e.what());
        rc = 1;
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

}  // namespace ftcal
