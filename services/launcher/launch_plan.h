// What ftcal-launch derives from the config's launch groups without touching a host: the start
// order, each host's supervisord.conf and group section, the systemd units, the gates as text.
// Pure functions, so a test checks them without a network or a supervisord.
#pragma once

#include <stdexcept>
#include <string>
#include <vector>

#include "proto/config.pb.h"

namespace ftcal::launch {

// A launch request the config cannot satisfy (an unknown group, host or process, a ${name}
// nobody defines): the message names what and where.
class LaunchError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The values ${config}, ${run_dir} and ${lcm_url} take in a process's args on its host.
struct Placeholders {
  std::string config;
  std::string run_dir;
  std::string lcm_url;
};

const config::LaunchGroup& FindGroup(const config::Launch& launch, const std::string& name);
const config::LaunchHost& FindHost(const config::Launch& launch, const std::string& name);
// The group's process `name`, or nullptr.
const config::LaunchProcess* FindProcess(const config::LaunchGroup& group, const std::string& name);

// Indices into group.process() such that every process comes after those it waits for; among
// processes free to go, the config's order (so the order is the one a reader of the file expects).
std::vector<int> StartOrder(const config::LaunchGroup& group);

// StartOrder cut into waves: each wave waits only for processes of earlier waves, so its
// processes may start together.
std::vector<std::vector<int>> StartWaves(const config::LaunchGroup& group);

// The hosts the group runs on, in the order of their first process.
std::vector<std::string> HostsOf(const config::LaunchGroup& group);

// Replaces ${config}, ${run_dir}, ${lcm_url} in `arg`; LaunchError for any other ${...}.
std::string Expand(const std::string& arg, const Placeholders& values, const std::string& where);

// The process's heartbeat name (status_name, else the command's file name); "" when it sends
// none ("-").
std::string StatusName(const config::LaunchProcess& process);

// POSIX shell quoting: the word as one argument to sh (and to supervisor's shlex).
std::string ShellQuote(const std::string& word);

// A gate as one line: "RATE FT_* >= 95% of 500 Hz (each of >= 6 channels) within 5 s".
std::string GateText(const config::HealthGate& gate);

// supervisord's own file for a host: unix socket (mode 0700, no HTTP server), logs and pid
// file under `run_dir`, and every group file under run_dir/groups/ included.
std::string SupervisordConf(const std::string& host, const std::string& run_dir);

// One group's sections for one host: a [program:x] per process of the group on that host
// (autostart=false: ftcal-launch starts them in order behind the gates), [group:G], and the
// event listener when `listener_command` is not empty.
std::string GroupConf(const config::Config& config, const config::LaunchGroup& group,
                      const std::string& host, const Placeholders& values,
                      const std::vector<std::string>& listener_command);

// A systemd unit for one process (export-systemd), run as `user` (and its group): a dedicated
// account, never root, with its runtime and state directories (RuntimeDirectory=ftcal,
// StateDirectory=ftcal, both 0700) made by systemd and owned by it. The state directory keeps
// what the process accepted on signed channels ($STATE_DIRECTORY, common/seen_store.h).
std::string SystemdUnit(const config::Config& config, const config::LaunchGroup& group,
                        const config::LaunchProcess& process, const Placeholders& values,
                        const std::string& user = "ftcal");
// The unit's file name: "ftcal-<group>-<process>.service".
std::string SystemdUnitName(const config::LaunchGroup& group, const config::LaunchProcess& process);

}  // namespace ftcal::launch
