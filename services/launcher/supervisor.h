// One host's supervisord, driven through supervisorctl on that host's own unix socket: locally
// through `sh -c`, remotely through the host's shell prefix (ssh). ftcal-launch never talks to
// supervisor over HTTP and never manages processes itself.
#pragma once

#include <sys/types.h>

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace ftcal::launch {

struct CommandResult {
  int exit_code = -1;  // -1: killed by a signal or timed out
  std::string output;  // stdout and stderr together
};

// Runs the shell command line `line` on a host: `shell` + [line], or `sh -c line` when `shell`
// is empty; `input` is written to its stdin. Throws std::runtime_error when it cannot start or
// runs longer than `timeout_s` (it is then killed).
CommandResult RunShell(const std::vector<std::string>& shell, const std::string& line,
                       const std::string& input = "", double timeout_s = 60);

struct ProgramStatus {
  std::string state;  // STOPPED STARTING RUNNING BACKOFF STOPPING EXITED FATAL UNKNOWN
  int64_t pid = 0;    // when RUNNING
  std::string
      detail;  // the rest of supervisorctl's line: "pid 12, uptime 0:00:05", "Exited too quickly"
};

// Parses `supervisorctl status` output: "group:name   STATE   detail" per line, keyed by
// "group:name" (or "name" for a program outside a group).
std::map<std::string, ProgramStatus> ParseStatus(const std::string& output);

class HostSupervisor {
 public:
  // `run_dir_spec` may hold shell variables ($HOME): the host's shell expands it.
  HostSupervisor(std::string host, std::vector<std::string> shell, std::string run_dir_spec);

  const std::string& host() const { return host_; }
  // The run dir as an absolute path on the host (created with mode 0700 on first use).
  const std::string& run_dir();
  std::string conf_path() { return run_dir() + "/supervisord.conf"; }

  // Writes `content` to run_dir/`relative` on the host atomically (temporary file, rename).
  void WriteFile(const std::string& relative, const std::string& content);
  void RemoveFile(const std::string& relative);
  // Reads run_dir/`relative`'s last `max_bytes` ("" when absent), for error messages.
  std::string Tail(const std::string& relative, int max_bytes = 600);

  // True when this host's supervisord answers on its socket.
  bool Alive();
  // Starts supervisord (it daemonizes) unless alive; waits up to `timeout_s` for its socket.
  void EnsureRunning(double timeout_s = 10);
  // supervisorctl -c CONF ARGS... on the host.
  CommandResult Ctl(const std::vector<std::string>& args, double timeout_s = 120);
  std::map<std::string, ProgramStatus> Status();
  // The pid supervisord wrote (0 when none): for tests and a hard stop.
  pid_t SupervisordPid();

 private:
  std::string host_;
  std::vector<std::string> shell_;
  std::string run_dir_spec_;
  std::string run_dir_;
};

}  // namespace ftcal::launch
