// One table of exit codes for every ftcal binary (docs/exit-codes.md): the same condition ends
// every program with the same code, and each program's --help prints the table.
#pragma once

#include <cstdio>
#include <exception>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

namespace ftcal {

enum ExitCode : int {
  kExitDone = 0,      // finished (or --help)
  kExitUsage = 1,     // a bad flag or argument on the command line
  kExitRefused = 2,   // input refused: a log, a message or a result that fails its checks
  kExitConfig = 3,    // the config file cannot be read or fails its checks
  kExitDeviceIo = 4,  // a device, the bus or a file cannot be opened, read or written
  kExitInternal = 5,  // an unexpected failure inside the program (a bug: please report it)
  kExitWarnings = 6,  // done, with warnings the caller should read (ftcal-doctor's verdict)
};

inline const char* ExitCodeTable() {
  return "Exit codes: 0 done; 1 usage (a bad flag or argument); 2 input refused (a log, "
         "message or result that fails its checks); 3 config (unreadable or fails its "
         "checks); 4 device or I/O (a device, the bus or a file cannot be opened, read or "
         "written); 5 internal error (a bug: please report it); 6 done with warnings "
         "(ftcal-doctor: calibratable, but read them first).";
}

// The levels spdlog knows: anything else would silently turn logging off.
inline const std::vector<std::string>& LogLevels() {
  static const std::vector<std::string> levels = {"trace", "debug",    "info", "warn",
                                                  "error", "critical", "off"};
  return levels;
}

inline CLI::Option* AddLogLevelOption(CLI::App& cli, std::string* level) {
  return cli
      .add_option("--log-level", *level,
                  "log level: trace, debug, info, warn, error, "
                  "critical or off; default from SPDLOG_LEVEL, "
                  "else info")
      ->check(CLI::IsMember(LogLevels()));
}

// Parses the command line. Returns the exit code when the program should end now: 0 after
// --help (printed), kExitUsage for a bad flag (CLI11's message printed).
inline std::optional<int> ParseCommandLine(CLI::App& cli, int argc, char** argv) {
  try {
    cli.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int rc = cli.exit(e);
    return rc == 0 ? kExitDone : kExitUsage;
  }
  return std::nullopt;
}

// The handler of main's function-try-block, `int main(...) try {...} catch (...) { return
// ftcal::ExitOnEscapedException("ftcal-x"); }`: an exception nothing else caught (a bug) ends the
// program with its message and kExitInternal, not with std::terminate's abort.
inline int ExitOnEscapedException(const char* program) noexcept {
  try {
    throw;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s: internal error (please report it): %s\n", program, e.what());
  } catch (...) {
    std::fprintf(stderr, "%s: internal error (please report it): an unknown exception\n", program);
  }
  return kExitInternal;
}

}  // namespace ftcal
