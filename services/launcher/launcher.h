// ftcal-launch's commands over the config's launch groups (launch_plan.h), the hosts'
// supervisords (supervisor.h) and the gates (gates.h). Each command returns an exit code
// (common/exit_codes.h) and prints what failed, naming the process, the host and the figure.
#pragma once

#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "launcher/gates.h"
#include "launcher/launch_plan.h"
#include "launcher/supervisor.h"
#include "proto/config.pb.h"

namespace ftcal::launch {

struct Options {
  std::string config_path;
  std::string lcm_url;
  std::string run_dir = "${XDG_RUNTIME_DIR:-/tmp}/ftcal-launch-$(id -u)";
  std::string events_command = "ftcal-supervisor-events";
  std::string log_level;
  std::string group;
  std::string process;
  std::string host;
  std::string out_dir;
  std::string systemd_user = "ftcal";  // export-systemd: the account the units run as
  // status: listens until every running process has been heard, at most this long (two and a
  // half heartbeat periods: one lost datagram does not make a process SILENT).
  double listen_s = 2.5;
};

class Launcher {
 public:
  explicit Launcher(Options options);
  // Loads the config; an exit code when it cannot.
  std::optional<int> Init();
  int Up();
  int Down();
  int Restart();
  int Status();
  int ExportSystemd();

 private:
  HostSupervisor& Host(const std::string& name);
  Placeholders ValuesFor(const std::string& host);
  // Writes the host's supervisord.conf and the group's file, starts supervisord if needed and
  // has it load the group. Throws std::runtime_error.
  void Prepare(const config::LaunchGroup& group, const std::string& host);
  // Starts the processes of one wave together (those not running, or all on restart), then
  // awaits each one's gates; an exit code on the first failure.
  std::optional<int> StartAndGate(const config::LaunchGroup& group,
                                  const std::vector<const config::LaunchProcess*>& wave,
                                  bool restart);
  GateWatcher& Watcher();

  Options o_;
  config::Config config_;
  std::string config_text_;
  std::map<std::string, std::unique_ptr<HostSupervisor>> hosts_;
  std::unique_ptr<GateWatcher> watcher_;
};

}  // namespace ftcal::launch
