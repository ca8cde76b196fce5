// ftcal-launch: the config's launch groups onto each host's supervisord, in dependency order,
// behind health gates. The work is in launcher.{h,cc}; this is flags and exit codes.
#include <iostream>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "launcher/launcher.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "Launches the config's launch groups (launch.group) on their hosts: writes each host's "
      "supervisord.conf and the group's [program:x] sections under the host's run dir, starts "
      "one unprivileged supervisord per host (control socket: a local unix socket; a remote "
      "host through its launch.host.shell, e.g. ssh, never over HTTP), then starts the "
      "processes in dependency order (after), holding each dependent until the health gates "
      "of what it waits for pass (FTCAL_STATUS heartbeats, message rates, freshness, heard on "
      "the config's LCM URL). A failed gate stops the start and names the process, the gate "
      "and the figure (exit 2).",
      "ftcal-launch");
  ftcal::launch::Options o;
  cli.add_option("--config", o.config_path,
                 "configuration file with the launch section; default: the " +
                     std::string(ftcal::kDefaultConfigName) + " built in");
  cli.add_option("--lcm-url", o.lcm_url, "LCM URL to watch the gates on; default: the config's");
  cli.add_option("--run-dir", o.run_dir,
                 "run dir of a host whose launch.host.run_dir is empty (expanded by that host's "
                 "shell)")
      ->capture_default_str();
  cli.add_option("--events-command", o.events_command,
                 "the supervisor event listener to run on every host (found on its PATH)")
      ->capture_default_str();
  std::string log_level;
  ftcal::AddLogLevelOption(cli, &log_level);
  cli.require_subcommand(1);

  auto* up = cli.add_subcommand("up",
                                "write the hosts' supervisor files, start GROUP in order "
                                "behind its health gates");
  up->add_option("group", o.group, "launch group name")->required();
  auto* down = cli.add_subcommand("down",
                                  "stop GROUP (reverse order) and remove it; a host's "
                                  "supervisord with nothing left is shut down");
  down->add_option("group", o.group, "launch group name")->required();
  auto* restart = cli.add_subcommand("restart", "restart one process and wait for its gates");
  restart->add_option("name", o.process, "process name")->required();
  restart->add_option("--group", o.group, "its group, when the name is in several");
  auto* status = cli.add_subcommand("status",
                                    "every host's supervisor state of the group's "
                                    "processes, with their heartbeats");
  status->add_option("group", o.group, "launch group name (default: every group)");
  status
      ->add_option("--listen", o.listen_s,
                   "at most this many seconds to listen for heartbeats (less once every "
                   "running process has been heard)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  auto* systemd =
      cli.add_subcommand("export-systemd",
                         "write one systemd unit per process of GROUP on HOST (Type=notify, "
                         "Restart=, WatchdogSec=, MemoryMax=) into --out");
  systemd->add_option("group", o.group, "launch group name")->required();
  systemd->add_option("--host", o.host, "the host whose processes to export")->required();
  systemd->add_option("--out", o.out_dir, "directory to write the units into")->required();
  systemd
      ->add_option("--user", o.systemd_user,
                   "the dedicated account the units run as (User=, Group=; never root): make it "
                   "with `useradd --system ftcal` and give it the devices' groups (dialout)")
      ->capture_default_str();
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;
  if (!log_level.empty()) o.log_level = log_level;

  ftcal::launch::Launcher launcher(o);
  if (auto rc = launcher.Init()) return *rc;
  if (*up) return launcher.Up();
  if (*down) return launcher.Down();
  if (*restart) return launcher.Restart();
  if (*status) return launcher.Status();
  if (*systemd) return launcher.ExportSystemd();
  return ftcal::kExitUsage;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-launch");
}
