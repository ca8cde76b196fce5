// ftcal-log-upgrade: an LCM log of older message versions rewritten into the current ones.
//
//   ftcal-log-upgrade OLD NEW
//
// Every event whose type is an older version of one of ftcal's (lcmtypes/legacy/README.md) is
// converted into the current type; every other event is copied byte for byte, with its channel
// and timestamp, in its place. NEW is written atomically. Exit codes (docs/exit-codes.md): 0
// done (also for a log already current: NEW is then a copy), 1 usage, 2 an older event refused
// (its bytes fail its version's checks, or it has no current form), 4 OLD cannot be read or NEW
// written, 5 a bug.
#include <cstdio>
#include <iostream>
#include <string>

#include <CLI/CLI.hpp>

#include "common/exit_codes.h"
#include "common/user_errors.h"
#include "log_upgrade/upgrade.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "Rewrites an LCM log recorded with older versions of ftcal's message types (the "
      "fixed-array change d2866c5, the scatter of bb8ed83, the nonce of 27d4812, ft_batch_t of "
      "1faf3aa) into the current ones; every other event is copied as it is. Prints what it "
      "converted per channel.",
      "ftcal-log-upgrade");
  cli.footer(ftcal::ExitCodeTable());
  std::string old_path;
  std::string new_path;
  cli.add_option("OLD", old_path, "the older log")->required();
  cli.add_option("NEW", new_path, "the upgraded log to write (replaced if it exists)")->required();
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;
  try {
    const auto summary = ftcal::log_upgrade::UpgradeLog(old_path, new_path);
    std::fputs(ftcal::log_upgrade::Render(summary, old_path, new_path).c_str(), stdout);
    return ftcal::kExitDone;
  } catch (const ftcal::log_upgrade::RefusedEvent& e) {
    std::cerr << "ftcal-log-upgrade: " << e.what() << "\n";
    return ftcal::kExitRefused;
  } catch (const std::invalid_argument& e) {
    if (ftcal::IsInternalError(e)) {
      std::cerr << "ftcal-log-upgrade: " << ftcal::UserText(e, "upgrading the log") << "\n";
      return ftcal::kExitInternal;
    }
    std::cerr << "ftcal-log-upgrade: " << e.what() << "\n";
    return ftcal::kExitUsage;
  } catch (const std::exception& e) {
    std::cerr << "ftcal-log-upgrade: " << ftcal::UserText(e, "upgrading the log") << "\n";
    return ftcal::ExitCodeFor(e, ftcal::kExitDeviceIo);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-log-upgrade");
}
