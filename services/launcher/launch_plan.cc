#include "launcher/launch_plan.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <map>
#include <set>
#include <sstream>

namespace ftcal::launch {
namespace {

std::string Number(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// supervisor expands %(name)s in command and environment: a literal '%' is written '%%'.
std::string SupervisorEscape(const std::string& s) {
  std::string out;
  for (char c : s) {
    out += c;
    if (c == '%') out += '%';
  }
  return out;
}

std::vector<std::string> CommandLine(const config::LaunchProcess& process,
                                     const Placeholders& values, const std::string& where) {
  std::vector<std::string> words{Expand(process.command(), values, where + ".command")};
  for (int i = 0; i < process.args_size(); ++i) {
    words.push_back(Expand(process.args(i), values, where + ".args[" + std::to_string(i) + "]"));
  }
  return words;
}

std::string Join(const std::vector<std::string>& words, bool quote) {
  std::string out;
  for (const auto& w : words) {
    if (!out.empty()) out += ' ';
    out += quote ? ShellQuote(w) : w;
  }
  return out;
}

const char* SupervisorAutorestart(config::RestartPolicy::AutoRestart a) {
  switch (a) {
    case config::RestartPolicy::NEVER:
      return "false";
    case config::RestartPolicy::UNEXPECTED:
      return "unexpected";
    default:
      return "true";
  }
}

const char* SystemdRestart(config::RestartPolicy::AutoRestart a) {
  switch (a) {
    case config::RestartPolicy::NEVER:
      return "no";
    case config::RestartPolicy::UNEXPECTED:
      return "on-failure";
    default:
      return "always";
  }
}

}  // namespace

const config::LaunchGroup& FindGroup(const config::Launch& launch, const std::string& name) {
  std::string known;
  for (const auto& g : launch.group()) {
    if (g.name() == name) return g;
    known += (known.empty() ? "" : ", ") + g.name();
  }
  throw LaunchError("no launch group '" + name +
                    "' in the config (launch.group: " + (known.empty() ? "none" : known) + ")");
}

const config::LaunchHost& FindHost(const config::Launch& launch, const std::string& name) {
  for (const auto& h : launch.host()) {
    if (h.name() == name) return h;
  }
  throw LaunchError("no launch host '" + name + "' in the config");
}

const config::LaunchProcess* FindProcess(const config::LaunchGroup& group,
                                         const std::string& name) {
  for (const auto& p : group.process()) {
    if (p.name() == name) return &p;
  }
  return nullptr;
}

std::vector<int> StartOrder(const config::LaunchGroup& group) {
  std::map<std::string, int> index;
  for (int i = 0; i < group.process_size(); ++i) index[group.process(i).name()] = i;
  std::vector<int> order;
  std::vector<bool> placed(group.process_size(), false);
  // Repeatedly take the first process whose dependencies are all placed: the config's order
  // among the free ones. The config was validated acyclic; a cycle here is a bug.
  while (static_cast<int>(order.size()) < group.process_size()) {
    bool progressed = false;
    for (int i = 0; i < group.process_size(); ++i) {
      if (placed[i]) continue;
      bool ready = true;
      for (const auto& dep : group.process(i).after()) {
        const auto it = index.find(dep);
        if (it == index.end()) {
          throw LaunchError("group '" + group.name() + "': process '" + group.process(i).name() +
                            "' waits for unknown process '" + dep + "'");
        }
        if (!placed[it->second]) ready = false;
      }
      if (!ready) continue;
      placed[i] = true;
      order.push_back(i);
      progressed = true;
      break;
    }
    if (!progressed) {
      throw LaunchError("group '" + group.name() + "': the dependencies (after) form a cycle");
    }
  }
  return order;
}

std::vector<std::vector<int>> StartWaves(const config::LaunchGroup& group) {
  std::map<std::string, int> level;
  std::vector<std::vector<int>> waves;
  for (int i : StartOrder(group)) {
    int l = 0;
    for (const auto& dep : group.process(i).after()) l = std::max(l, level.at(dep) + 1);
    level[group.process(i).name()] = l;
    if (static_cast<int>(waves.size()) <= l) waves.resize(l + 1);
    waves[l].push_back(i);
  }
  return waves;
}

std::vector<std::string> HostsOf(const config::LaunchGroup& group) {
  std::vector<std::string> hosts;
  for (const auto& p : group.process()) {
    bool seen = false;
    for (const auto& h : hosts) seen = seen || h == p.host();
    if (!seen) hosts.push_back(p.host());
  }
  return hosts;
}

std::string Expand(const std::string& arg, const Placeholders& values, const std::string& where) {
  std::string out;
  std::size_t at = 0;
  while (at < arg.size()) {
    const auto open = arg.find("${", at);
    if (open == std::string::npos) {
      out += arg.substr(at);
      break;
    }
    out += arg.substr(at, open - at);
    const auto close = arg.find('}', open);
    if (close == std::string::npos) {
      throw LaunchError(where + ": '" + arg + "': '${' without its '}'");
    }
    const std::string name = arg.substr(open + 2, close - open - 2);
    if (name == "config") {
      out += values.config;
    } else if (name == "run_dir") {
      out += values.run_dir;
    } else if (name == "lcm_url") {
      out += values.lcm_url;
    } else {
      throw LaunchError(where + ": '" + arg + "': unknown ${" + name +
                        "} (known: ${config}, ${run_dir}, ${lcm_url})");
    }
    at = close + 1;
  }
  return out;
}

std::string StatusName(const config::LaunchProcess& process) {
  if (process.status_name() == "-") return "";
  if (!process.status_name().empty()) return process.status_name();
  const auto slash = process.command().rfind('/');
  return slash == std::string::npos ? process.command() : process.command().substr(slash + 1);
}

std::string ShellQuote(const std::string& word) {
  if (!word.empty() &&
      word.find_first_not_of("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789"
                             "_-./:=,+@") == std::string::npos) {
    return word;
  }
  std::string out = "'";
  for (char c : word) {
    if (c == '\'') {
      out += "'\\''";
    } else {
      out += c;
    }
  }
  return out + "'";
}

std::string GateText(const config::HealthGate& gate) {
  std::ostringstream s;
  switch (gate.kind()) {
    case config::HealthGate::STATUS_RUNNING:
      s << "STATUS_RUNNING (its FTCAL_STATUS says RUNNING"
        << (gate.accept_degraded() ? " or DEGRADED" : "") << ")";
      break;
    case config::HealthGate::RATE:
      s << "RATE " << gate.channel()
        << " >= " << Number(std::round(gate.min_fraction() * 1000) / 10) << "% of "
        << Number(gate.rate_hz()) << " Hz";
      if (gate.min_channels() > 0) s << " (each of >= " << gate.min_channels() << " channels)";
      s << " over " << Number(gate.window_s()) << " s";
      break;
    case config::HealthGate::FRESH:
      s << "FRESH " << gate.channel() << " younger than " << Number(gate.max_age_s()) << " s";
      break;
    default:
      s << "unknown gate";
  }
  s << " within " << Number(gate.within_s()) << " s";
  return s.str();
}

std::string SupervisordConf(const std::string& host, const std::string& run_dir) {
  std::ostringstream s;
  s << "; Written by ftcal-launch for host '" << host
    << "': edits are overwritten by the next\n"
       "; `ftcal-launch up`. The control socket is a local unix socket (owner only); there is\n"
       "; no [inet_http_server]: a remote host is driven through ssh, never over HTTP.\n"
       "[unix_http_server]\n"
       "file="
    << run_dir
    << "/supervisor.sock\n"
       "chmod=0700\n\n"
       "[supervisord]\n"
       "logfile="
    << run_dir
    << "/supervisord.log\n"
       "pidfile="
    << run_dir
    << "/supervisord.pid\n"
       "childlogdir="
    << run_dir
    << "/logs\n"
       "identifier=ftcal-"
    << host
    << "\n"
       "nodaemon=false\n"
       "strip_ansi=true\n\n"
       "[rpcinterface:supervisor]\n"
       "supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface\n\n"
       "[supervisorctl]\n"
       "serverurl=unix://"
    << run_dir
    << "/supervisor.sock\n\n"
       "[include]\n"
       "files = "
    << run_dir << "/groups/*.conf\n";
  return s.str();
}

std::string GroupConf(const config::Config& config, const config::LaunchGroup& group,
                      const std::string& host, const Placeholders& values,
                      const std::vector<std::string>& listener_command) {
  std::ostringstream s;
  s << "; Group '" << group.name() << "' on host '" << host
    << "', written by ftcal-launch from the config's launch section.\n";
  std::vector<std::string> programs;
  for (int i = 0; i < group.process_size(); ++i) {
    const auto& p = group.process(i);
    if (p.host() != host) continue;
    const std::string where = "launch.group[" + group.name() + "].process[" + p.name() + "]";
    programs.push_back(p.name());
    const auto& r = p.restart();
    s << "\n[program:" << p.name() << "]\n"
      << "command=" << SupervisorEscape(Join(CommandLine(p, values, where), true)) << "\n"
      << "autostart=false\n"
      << "autorestart=" << SupervisorAutorestart(r.autorestart())
      << "\n"
      // supervisor takes whole seconds; a sub-second startsecs rounds up, so "started" never
      // means less than asked.
      << "startsecs=" << static_cast<int>(std::ceil(r.startsecs_s())) << "\n"
      << "startretries=" << r.startretries() << "\n"
      << "stopsignal=" << r.stopsignal() << "\n"
      << "stopwaitsecs=" << static_cast<int>(std::ceil(r.stopwaitsecs_s())) << "\n"
      << "stopasgroup=true\nkillasgroup=true\n"
      << "stdout_logfile=" << values.run_dir << "/logs/" << group.name() << "-" << p.name()
      << ".out\n"
      << "stderr_logfile=" << values.run_dir << "/logs/" << group.name() << "-" << p.name()
      << ".err\n"
      << "stdout_logfile_maxbytes=10MB\nstderr_logfile_maxbytes=10MB\n";
    if (p.env_size() > 0) {
      s << "environment=";
      for (int e = 0; e < p.env_size(); ++e) {
        const std::string& kv = p.env(e);
        const auto eq = kv.find('=');
        std::string value =
            Expand(kv.substr(eq + 1), values, where + ".env[" + std::to_string(e) + "]");
        std::string quoted;
        for (char c : value) {
          if (c == '"' || c == '\\') quoted += '\\';
          quoted += c;
        }
        s << (e ? "," : "") << kv.substr(0, eq) << "=\"" << SupervisorEscape(quoted) << "\"";
      }
      s << "\n";
    }
  }
  s << "\n[group:" << group.name() << "]\nprograms=";
  for (std::size_t i = 0; i < programs.size(); ++i) s << (i ? "," : "") << programs[i];
  s << "\n";
  if (!listener_command.empty()) {
    // One listener per group and host: it reports this group's processes only, so two groups on
    // one supervisord do not publish each other's events twice.
    std::vector<std::string> words = listener_command;
    words.insert(words.end(),
                 {"--group", group.name(), "--host-name", host, "--lcm-url", config.lcm_url(),
                  "--channel", config.launch().process_state_channel()});
    s << "\n[eventlistener:" << group.name() << "-events]\n"
      << "command=" << SupervisorEscape(Join(words, true)) << "\n"
      << "events=PROCESS_STATE\n"
      << "autostart=true\nautorestart=true\n"
      << "buffer_size=1000\n"
      << "stderr_logfile=" << values.run_dir << "/logs/" << group.name() << "-events.err\n";
    // supervisord starts a replacement for a dead process only when its loop next wakes: on
    // some child's output, else after its 1 s poll timeout (2 s when the first wake-up came
    // before the child could be reaped). A byte every 0.1 s from this program is that wake-up,
    // so a process killed with -9 is back well within a second. Its output is discarded.
    s << "\n[program:" << group.name() << "-pacer]\n"
      << "command=" << SupervisorEscape(Join({listener_command[0], "--pace", "0.1"}, true)) << "\n"
      << "autostart=true\nautorestart=true\nstartsecs=0\n"
      << "stdout_logfile=NONE\nstderr_logfile=NONE\n";
  }
  return s.str();
}

std::string SystemdUnitName(const config::LaunchGroup& group,
                            const config::LaunchProcess& process) {
  return "ftcal-" + group.name() + "-" + process.name() + ".service";
}

std::string SystemdUnit(const config::Config& /*config*/, const config::LaunchGroup& group,
                        const config::LaunchProcess& p, const Placeholders& values,
                        const std::string& user) {
  // useradd's default rule for names, and never root: a unit is one process's account.
  const bool name_ok =
      !user.empty() && user.size() <= 32 &&
      (std::islower(static_cast<unsigned char>(user[0])) || user[0] == '_') &&
      user.find_first_not_of("abcdefghijklmnopqrstuvwxyz0123456789_-") == std::string::npos;
  if (!name_ok || user == "root") {
    throw LaunchError("export-systemd --user '" + user +
                      "': the name of a dedicated account ([a-z_][a-z0-9_-]*), not root");
  }
  const std::string where = "launch.group[" + group.name() + "].process[" + p.name() + "]";
  const auto& r = p.restart();
  std::ostringstream s;
  s << "# Written by ftcal-launch export-systemd from the config's launch group '" << group.name()
    << "'.\n[Unit]\nDescription=ftcal " << group.name() << ": " << p.name() << "\n";
  for (const auto& dep : p.after()) {
    const auto* d = FindProcess(group, dep);
    if (d == nullptr || d->host() != p.host()) continue;  // a unit cannot order on another host
    s << "After=" << SystemdUnitName(group, *d) << "\nWants=" << SystemdUnitName(group, *d) << "\n";
  }
  // supervisor's startretries within a window: systemd's start limit, so a process that keeps
  // dying ends failed instead of restarting forever.
  s << "StartLimitIntervalSec="
    << static_cast<int>(std::ceil(60 + r.startsecs_s() * (r.startretries() + 1)))
    << "\nStartLimitBurst=" << r.startretries() + 1 << "\n\n[Service]\n";
  s << "Type=" << (p.sd_notify() ? "notify" : "simple") << "\n";
  if (p.sd_notify()) s << "NotifyAccess=main\n";
  s << "ExecStart=" << Join(CommandLine(p, values, where), true) << "\n";
  for (int e = 0; e < p.env_size(); ++e) {
    const std::string& kv = p.env(e);
    const auto eq = kv.find('=');
    s << "Environment=\"" << kv.substr(0, eq) << "="
      << Expand(kv.substr(eq + 1), values, where + ".env[" + std::to_string(e) + "]") << "\"\n";
  }
  // Not root, and the directories closed to others: the run dir holds the config the processes
  // read, the state dir what they accepted on signed channels.
  s << "User=" << user << "\nGroup=" << user << "\n";
  s << "RuntimeDirectory=ftcal\nRuntimeDirectoryMode=0700\nRuntimeDirectoryPreserve=yes\n";
  s << "StateDirectory=ftcal\nStateDirectoryMode=0700\n";
  s << "Restart=" << SystemdRestart(r.autorestart()) << "\nRestartSec=0.2\n";
  if (p.sd_notify() && r.watchdog_s() > 0) s << "WatchdogSec=" << Number(r.watchdog_s()) << "\n";
  if (r.memory_max_mb() > 0) s << "MemoryMax=" << r.memory_max_mb() << "M\n";
  s << "KillSignal=SIG" << r.stopsignal() << "\nTimeoutStopSec=" << Number(r.stopwaitsecs_s())
    << "\n\n[Install]\nWantedBy=multi-user.target\n";
  return s.str();
}

}  // namespace ftcal::launch
