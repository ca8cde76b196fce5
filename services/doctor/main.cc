// ftcal-doctor: a recording's health before it is calibrated.
//
//   ftcal-doctor [--config FILE] session.lcmlog [session.lcmlog.00 ...]
//
// One screen: per device stream its rate, what it lost and where (by the device's counters),
// where the host heard nothing for a while (stalls), its clock against the host's and the
// queuing its samples met; the experiment's phases with their lengths and pose counts; the sigma
// each parameter class would get from the data present (sigma_forecast.h: step 2 only when the
// recording, or a further file such as the segmenter's --replay output, holds STEADY_POSE); and a
// verdict, also the exit code: 0 calibratable, 6 calibratable with warnings, 2 not calibratable
// (docs/exit-codes.md). The files of one recording are read in the order given.
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include "common/log_replay_bus.h"
#include "common/default_config.h"
#include "common/envelope.h"
#include "common/exit_codes.h"
#include "common/service_stats.h"
#include "common/user_errors.h"
#include "doctor/log_health.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "A recording's health before calibrating it: rates, gaps, stalls, clocks, phases, a "
      "forecast of each parameter class's sigma from the data present, and a verdict (exit 0 "
      "calibratable, 6 with warnings, 2 not calibratable).",
      "ftcal-doctor");
  cli.footer(ftcal::ExitCodeTable());
  std::vector<std::string> logs;
  std::string config_path;
  cli.add_option("logs", logs, "the recording's LCM log files, in order")->required();
  cli.add_option("--config", config_path,
                 "the robot's config (channels, auth, calibrator limits); default: the embedded "
                 "config/sim.pbtxt");
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;
  auto log = spdlog::stderr_logger_st("ftcal-doctor");
  log->set_level(spdlog::level::err);
  try {
    ftcal::auth::InitSodium();
    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);
    ftcal::doctor::LogExaminer examiner(config);
    const char* tmp = std::getenv("TMPDIR");
    const std::string scratch = std::string(tmp && *tmp ? tmp : "/tmp") + "/ftcal-doctor-" +
                                std::to_string(::getpid()) + ".lcmlog";
    for (const std::string& path : logs) {
      ftcal::ServiceStats stats(log);
      // Nothing is published: the replay output stays uncommitted and is removed.
      ftcal::LogReplayBus bus(path, scratch, stats);
      examiner.Attach(bus);
      bus.Run([] {}, 3'600'000'000);
      if (!bus.finished()) throw std::runtime_error("reading '" + path + "' stopped early");
      struct stat st {};
      ::stat(path.c_str(), &st);
      examiner.FileDone(path, st.st_size, bus.events_read(), stats);
    }
    const ftcal::doctor::HealthReport report = examiner.Finish();
    std::fputs(ftcal::doctor::Render(report).c_str(), stdout);
    return ftcal::doctor::ExitCodeOf(report);
  } catch (const std::exception& e) {
    std::cerr << "ftcal-doctor: " << ftcal::UserText(e, "examining the recording") << "\n";
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-doctor");
}
