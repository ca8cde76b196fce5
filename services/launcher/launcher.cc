#include "launcher/launcher.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <future>
#include <iostream>
#include <optional>
#include <sstream>

#include <spdlog/spdlog.h>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "ftcal/config.h"

namespace ftcal::launch {
namespace {

using Clock = std::chrono::steady_clock;

const char* kStateNames[] = {"STARTING", "RUNNING", "DEGRADED", "STOPPING", "FAILED"};

std::string Seconds(Clock::time_point since) {
  char buf[32];
  std::snprintf(buf, sizeof(buf), "%6.2f s",
                std::chrono::duration<double>(Clock::now() - since).count());
  return buf;
}

std::string OneLine(std::string s) {
  for (char& c : s) {
    if (c == '\n' || c == '\r') c = ' ';
  }
  return s;
}

// Written beside the target and renamed over it, as every ftcal output.
void WriteLocalAtomically(const std::string& path, const std::string& content) {
  const std::string tmp = path + ".tmp." + std::to_string(::getpid());
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out << content;
    out.flush();
    if (!out) {
      std::filesystem::remove(tmp);
      throw std::runtime_error("cannot write " + tmp);
    }
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    std::filesystem::remove(tmp);
    throw std::runtime_error("cannot rename " + tmp + " to " + path + ": " + ec.message());
  }
}

// Runs `work` (a supervisorctl call, hundreds of ms of Python) on a thread while the watcher
// keeps reading the bus: a backlog would reach the gates late and bunched, as a false rate.
template <class F>
auto WhilePumping(GateWatcher& watcher, F work) -> decltype(work()) {
  auto done = std::async(std::launch::async, std::move(work));
  while (done.wait_for(std::chrono::seconds(0)) != std::future_status::ready) watcher.Pump(0.02);
  return done.get();
}

// How every command reports a failure: one line on stderr and an exit code. A launch section
// a command cannot use (LaunchError) is a config error whichever command met it; a host or
// file it cannot reach is a device/I-O error.
template <class Body>
int RunCommand(Body body) {
  try {
    return body();
  } catch (const LaunchError& e) {
    std::cerr << "ftcal-launch: " << e.what() << "\n";
    return kExitConfig;
  } catch (const std::exception& e) {
    std::cerr << "ftcal-launch: " << e.what() << "\n";
    return kExitDeviceIo;
  }
}

}  // namespace

Launcher::Launcher(Options options) : o_(std::move(options)) {}

std::optional<int> Launcher::Init() {
  try {
    if (o_.config_path.empty()) {
      config_text_ = DefaultConfigText();
      config_ = LoadConfigText(config_text_, kDefaultConfigName);
    } else {
      std::ifstream in(o_.config_path, std::ios::binary);
      std::ostringstream text;
      text << in.rdbuf();
      if (!in) throw ConfigError("cannot read config file '" + o_.config_path + "'");
      config_text_ = text.str();
      config_ = LoadConfigText(config_text_, o_.config_path);
    }
  } catch (const std::exception& e) {
    std::cerr << "ftcal-launch: " << e.what() << "\n";
    return kExitConfig;
  }
  if (o_.lcm_url.empty()) o_.lcm_url = config_.lcm_url();
  if (!config_.has_launch() || config_.launch().group_size() == 0) {
    std::cerr << "ftcal-launch: " << (o_.config_path.empty() ? kDefaultConfigName : o_.config_path)
              << ": no launch groups (launch.group)\n";
    return kExitConfig;
  }
  if (!o_.group.empty()) {
    try {
      FindGroup(config_.launch(), o_.group);
    } catch (const LaunchError& e) {
      std::cerr << "ftcal-launch: " << e.what() << "\n";
      return kExitUsage;
    }
  }
  return std::nullopt;
}

HostSupervisor& Launcher::Host(const std::string& name) {
  auto& slot = hosts_[name];
  if (!slot) {
    const auto& h = FindHost(config_.launch(), name);
    std::vector<std::string> shell(h.shell().begin(), h.shell().end());
    slot = std::make_unique<HostSupervisor>(name, shell,
                                            h.run_dir().empty() ? o_.run_dir : h.run_dir());
  }
  return *slot;
}

Placeholders Launcher::ValuesFor(const std::string& host) {
  const auto& h = FindHost(config_.launch(), host);
  Placeholders v;
  v.run_dir = Host(host).run_dir();
  v.lcm_url = config_.lcm_url();
  v.config = h.config_path().empty() ? v.run_dir + "/config.pbtxt" : h.config_path();
  return v;
}

GateWatcher& Launcher::Watcher() {
  if (!watcher_)
    watcher_ =
        std::make_unique<GateWatcher>(o_.lcm_url, config_.channels().status(), RoutesOf(config_));
  return *watcher_;
}

void Launcher::Prepare(const config::LaunchGroup& group, const std::string& host) {
  HostSupervisor& hs = Host(host);
  const Placeholders values = ValuesFor(host);
  // Every host reads the config this launcher runs on (unless the host names its own copy).
  if (FindHost(config_.launch(), host).config_path().empty()) {
    hs.WriteFile("config.pbtxt", config_text_);
  }
  std::vector<std::string> listener;
  if (config_.launch().event_listener()) listener = {o_.events_command};
  hs.WriteFile("supervisord.conf", SupervisordConf(host, hs.run_dir()));
  hs.WriteFile("groups/" + group.name() + ".conf",
               GroupConf(config_, group, host, values, listener));
  hs.EnsureRunning();
  // reread + update: a changed program section is restarted, an unchanged one left alone.
  auto r = hs.Ctl({"reread"});
  if (r.output.find("ERROR") != std::string::npos) {
    throw std::runtime_error("host '" + host + "': supervisorctl reread: " + OneLine(r.output));
  }
  r = hs.Ctl({"update"});
  if (r.output.find("ERROR") != std::string::npos) {
    throw std::runtime_error("host '" + host + "': supervisorctl update: " + OneLine(r.output));
  }
}

std::optional<int> Launcher::StartAndGate(const config::LaunchGroup& group,
                                          const std::vector<const config::LaunchProcess*>& wave,
                                          bool restart) {
  GateWatcher& watcher = Watcher();
  const int64_t since = watcher.Now();
  auto key_of = [&](const config::LaunchProcess& p) { return group.name() + ":" + p.name(); };
  // Started together: they wait for nothing in each other, and supervisorctl's start blocks
  // for startsecs, which would add up one process after another.
  // One supervisorctl status per host, before and after: each call is a Python start-up.
  auto statuses = [&] {
    std::map<std::string, std::map<std::string, ProgramStatus>> by_host;
    for (const auto* p : wave) {
      if (!by_host.count(p->host())) {
        HostSupervisor& hs = Host(p->host());
        by_host[p->host()] = WhilePumping(watcher, [&] { return hs.Status(); });
      }
    }
    return by_host;
  };
  auto before_by_host = statuses();
  std::vector<std::future<CommandResult>> starts;
  std::vector<bool> fresh;
  for (const auto* p : wave) {
    HostSupervisor& hs = Host(p->host());
    auto& before = before_by_host[p->host()];
    const std::string key = key_of(*p);
    const bool was_running = before.count(key) && before[key].state == "RUNNING";
    fresh.push_back(restart || !was_running);
    if (fresh.back()) {
      starts.push_back(std::async(std::launch::async, [&hs, key, restart] {
        return hs.Ctl({restart ? "restart" : "start", key});
      }));
    }
  }
  for (auto& f : starts) {
    while (f.wait_for(std::chrono::seconds(0)) != std::future_status::ready) watcher.Pump(0.02);
    f.get();
  }
  // supervisorctl start gives up on the first failed attempt while supervisor goes on retrying
  // (BACKOFF): wait until each process has settled, RUNNING or FATAL, as long as its policy
  // allows (startsecs per attempt, back-off 1, 2, ... s between them).
  double settle_s = 5;
  for (const auto* p : wave) {
    const auto& r = p->restart();
    const double n = r.startretries();
    settle_s = std::max(settle_s, (n + 1) * (r.startsecs_s() + 1) + n * (n + 1) / 2 + 5);
  }
  const auto settle_until = Clock::now() + std::chrono::duration<double>(settle_s);
  auto after_by_host = statuses();
  auto unsettled = [&] {
    for (const auto* p : wave) {
      const auto& st = after_by_host[p->host()];
      const auto it = st.find(key_of(*p));
      if (it != st.end() && (it->second.state == "STARTING" || it->second.state == "BACKOFF")) {
        return true;
      }
    }
    return false;
  };
  while (unsettled() && Clock::now() < settle_until) {
    watcher.Pump(0.3);
    after_by_host = statuses();
  }
  for (std::size_t i = 0; i < wave.size(); ++i) {
    const config::LaunchProcess& p = *wave[i];
    HostSupervisor& hs = Host(p.host());
    const std::string key = key_of(p);
    const std::string who = "process '" + p.name() + "' on host '" + p.host() + "'";
    auto& now = after_by_host[p.host()];
    const auto it = now.find(key);
    if (it == now.end() || it->second.state != "RUNNING") {
      const std::string state =
          it == now.end() ? "unknown to supervisor" : it->second.state + " " + it->second.detail;
      std::cerr << "ftcal-launch: " << who << " did not start: supervisor says " << state
                << " (restart policy: startsecs " << p.restart().startsecs_s()
                << " s, startretries " << p.restart().startretries() << "); its stderr ends:\n"
                << hs.Tail("logs/" + group.name() + "-" + p.name() + ".err") << "\n";
      return kExitRefused;
    }
    const int64_t pid = it->second.pid;
    // A process already running keeps its history: its gates judge it from now on.
    const int64_t gate_since = fresh[i] ? since : watcher.Now();
    const std::string status_name = StatusName(p);
    for (const auto& gate : p.gate()) {
      auto alive = [&](std::string* why) {
        auto s = WhilePumping(watcher, [&] { return hs.Status(); });
        const auto at = s.find(key);
        if (at != s.end() && at->second.state == "RUNNING" && at->second.pid == pid) return true;
        *why = "supervisor says " +
               (at == s.end() ? std::string("gone") : at->second.state + " " + at->second.detail);
        return false;
      };
      const GateVerdict v = watcher.Await(gate, pid, status_name, gate_since, alive);
      if (!v.passed) {
        std::cerr << "ftcal-launch: " << who << ": gate " << GateText(gate)
                  << " failed: " << v.figure << "\n";
        return kExitRefused;
      }
      std::cout << "  " << p.name() << ": gate " << GateText(gate) << " passed: " << v.figure
                << "\n";
    }
  }
  return std::nullopt;
}

int Launcher::Up() {
  const auto t0 = Clock::now();
  return RunCommand([&]() -> int {
    const auto& group = FindGroup(config_.launch(), o_.group);
    const auto hosts = HostsOf(group);
    for (const auto& h : hosts) {
      Prepare(group, h);
      std::cout << "[" << Seconds(t0) << "] host " << h << ": supervisord up, run dir "
                << Host(h).run_dir() << "\n";
    }
    Watcher();  // listening from here on: the first process's gates may not miss its start
    for (const auto& wave : StartWaves(group)) {
      std::vector<const config::LaunchProcess*> procs;
      std::string names;
      for (int i : wave) {
        procs.push_back(&group.process(i));
        names +=
            (names.empty() ? "" : ", ") + group.process(i).host() + "/" + group.process(i).name();
      }
      if (auto rc = StartAndGate(group, procs, /*restart=*/false)) {
        std::cerr << "ftcal-launch: up " << group.name() << " stopped before the dependents of "
                  << names << "; what started keeps running (ftcal-launch down " << group.name()
                  << " stops it)\n";
        return *rc;
      }
      std::cout << "[" << Seconds(t0) << "] " << names << ": RUNNING\n";
    }
    std::cout << "group " << group.name() << " up: " << group.process_size() << " processes on "
              << hosts.size() << " host(s) in " << Seconds(t0) << "\n";
    return kExitDone;
  });
}

int Launcher::Down() {
  return RunCommand([&]() -> int {
    const auto& group = FindGroup(config_.launch(), o_.group);
    auto order = StartOrder(group);
    for (const auto& h : HostsOf(group)) {
      HostSupervisor& hs = Host(h);
      if (!hs.Alive()) {
        std::cout << "host " << h << ": no supervisord running\n";
        continue;
      }
      for (auto it = order.rbegin(); it != order.rend(); ++it) {
        const auto& p = group.process(*it);
        if (p.host() == h) hs.Ctl({"stop", group.name() + ":" + p.name()});
      }
      // The listener last, so the recording holds the processes' STOPPED events.
      hs.Ctl({"stop", group.name() + "-events", group.name() + "-pacer"});
      hs.Ctl({"remove", group.name()});
      hs.Ctl({"remove", group.name() + "-events"});
      hs.Ctl({"remove", group.name() + "-pacer"});
      hs.RemoveFile("groups/" + group.name() + ".conf");
      if (hs.Status().empty()) {
        hs.Ctl({"shutdown"});
        std::cout << "host " << h << ": group " << group.name()
                  << " stopped, supervisord shut down\n";
      } else {
        std::cout << "host " << h << ": group " << group.name() << " stopped\n";
      }
    }
    return kExitDone;
  });
}

int Launcher::Restart() {
  return RunCommand([&]() -> int {
    const config::LaunchGroup* found = nullptr;
    for (const auto& g : config_.launch().group()) {
      if (!o_.group.empty() && g.name() != o_.group) continue;
      if (FindProcess(g, o_.process) == nullptr) continue;
      if (found != nullptr) {
        std::cerr << "ftcal-launch: process '" << o_.process << "' is in groups '" << found->name()
                  << "' and '" << g.name() << "': say which with --group\n";
        return kExitUsage;
      }
      found = &g;
    }
    if (found == nullptr) {
      std::cerr << "ftcal-launch: no process '" << o_.process << "' in any launch group\n";
      return kExitUsage;
    }
    const auto t0 = Clock::now();
    const auto& p = *FindProcess(*found, o_.process);
    if (auto rc = StartAndGate(*found, {&p}, /*restart=*/true)) return *rc;
    std::cout << "[" << Seconds(t0) << "] " << p.host() << "/" << p.name() << ": restarted\n";
    return kExitDone;
  });
}

int Launcher::Status() {
  return RunCommand([&]() -> int {
    // The supervisors first: they say which processes run, under which pids, and so whose
    // heartbeats to wait for.
    struct Row {
      std::string host, name, heartbeat_name;
      std::optional<ProgramStatus> supervised;
      bool Expects() const { return !heartbeat_name.empty() && supervised && supervised->pid > 0; }
    };
    std::vector<Row> rows;
    for (const auto& group : config_.launch().group()) {
      if (!o_.group.empty() && group.name() != o_.group) continue;
      std::map<std::string, std::map<std::string, ProgramStatus>> by_host;
      for (const auto& h : HostsOf(group)) {
        HostSupervisor& hs = Host(h);
        by_host[h] = hs.Alive() ? hs.Status() : std::map<std::string, ProgramStatus>{};
      }
      for (const auto& p : group.process()) {
        Row r{p.host(), group.name() + ":" + p.name(), StatusName(p), std::nullopt};
        const auto& st = by_host[p.host()];
        if (const auto it = st.find(r.name); it != st.end()) r.supervised = it->second;
        rows.push_back(std::move(r));
      }
    }
    if (o_.listen_s > 0) {
      GateWatcher& watcher = Watcher();
      watcher.Pump(o_.listen_s, [&] {
        return std::all_of(rows.begin(), rows.end(), [&](const Row& r) {
          return !r.Expects() || watcher.Heartbeat(r.heartbeat_name, r.supervised->pid);
        });
      });
    }
    std::printf("%-12s %-28s %-9s %-26s %-9s %s\n", "HOST", "PROCESS", "SUPERVISOR", "DETAIL",
                "HEARTBEAT", "LAST ERROR");
    bool silent_or_down = false;
    for (const Row& r : rows) {
      const std::string state = r.supervised ? r.supervised->state : "ABSENT";
      const std::string detail = r.supervised ? r.supervised->detail : "";
      std::string beat = "-", error;
      if (watcher_ && r.Expects()) {
        if (auto hb = watcher_->Heartbeat(r.heartbeat_name, r.supervised->pid)) {
          beat = hb->state >= 0 && hb->state <= 4 ? kStateNames[hb->state] : "?";
          error = hb->last_error;
        } else {
          beat = "SILENT";
        }
      }
      if (state != "RUNNING" || beat == "SILENT") silent_or_down = true;
      std::printf("%-12s %-28s %-9s %-26s %-9s %s\n", r.host.c_str(), r.name.c_str(), state.c_str(),
                  detail.substr(0, 26).c_str(), beat.c_str(), error.c_str());
    }
    return silent_or_down ? kExitRefused : kExitDone;
  });
}

int Launcher::ExportSystemd() {
  return RunCommand([&]() -> int {
    const auto& group = FindGroup(config_.launch(), o_.group);
    const auto& host = FindHost(config_.launch(), o_.host);
    std::filesystem::create_directories(o_.out_dir);
    Placeholders values;
    values.lcm_url = config_.lcm_url();
    // systemd's own run dir (RuntimeDirectory=ftcal in each unit); the config where a lab keeps
    // system-wide files unless the host names its copy.
    values.run_dir = host.run_dir().empty() ? "%t/ftcal" : host.run_dir();
    values.config =
        host.config_path().empty() ? "/etc/ftcal/" + group.name() + ".pbtxt" : host.config_path();
    std::cout << "units read the config at " << values.config << " on host " << host.name() << "\n";
    int n = 0;
    for (const auto& p : group.process()) {
      if (p.host() != host.name()) continue;
      const std::string path = o_.out_dir + "/" + SystemdUnitName(group, p);
      WriteLocalAtomically(path, SystemdUnit(config_, group, p, values, o_.systemd_user));
      std::cout << path << "\n";
      ++n;
    }
    if (n == 0) {
      std::cerr << "ftcal-launch: group '" << group.name() << "' runs nothing on host '"
                << host.name() << "'\n";
      return kExitUsage;
    }
    return kExitDone;
  });
}

}  // namespace ftcal::launch
