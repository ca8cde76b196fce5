// ftcal-status: a live table of every ftcal process, from their FTCAL_STATUS heartbeats.
#include <unistd.h>

#include <cstdio>
#include <memory>

#include "common/service.h"
#include "common/shutdown.h"
#include "status/group_board.h"
#include "status/status_board.h"

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-status",
       "Reads the service_status_t heartbeats on the status channel (FTCAL_STATUS) and prints "
       "a table of every process: name, host, pid, state, uptime, messages in/out, drops, "
       "errors, counters, last error and the age of its last heartbeat; a process silent for "
       "longer than --lost-after is shown LOST (STOPPED if it said goodbye). Refreshes in place "
       "on a terminal, prints plain tables otherwise. When the config has launch groups, a second "
       "table shows every launched process: host, supervisor state and restarts (from the "
       "hosts' event listeners on launch.process_state_channel), heartbeat state, output rate "
       "and last error, and SILENT! for a process the config launches that sends no heartbeat. "
       "Publishes only its own heartbeat.",
       /*replayable=*/false});
  double once_after_s = 0;
  double interval_s = 1.0;
  double lost_after_s = 3.0;
  app.cli()
      .add_option("--once-after", once_after_s,
                  "listen this many seconds, print the table once and exit")
      ->check(CLI::PositiveNumber);
  app.cli()
      .add_option("--interval", interval_s, "seconds between refreshes")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  app.cli()
      .add_option("--lost-after", lost_after_s, "seconds of silence before a process is LOST")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  if (auto rc = app.Init(argc, argv)) return *rc;

  ftcal::StatusBoard board(lost_after_s);
  app.bus().Subscribe<ftcal::service_status_t>(
      app.config().channels().status(),
      [&board](const ftcal::MessageInfo& info, const ftcal::service_status_t& status) {
        board.Update(status, info.recv_utime);
      });

  std::unique_ptr<ftcal::GroupBoard> group_board;
  if (app.config().has_launch() && app.config().launch().group_size() > 0) {
    group_board = std::make_unique<ftcal::GroupBoard>(app.config().launch(), lost_after_s);
    app.bus().Subscribe<ftcal::service_status_t>(
        app.config().channels().status(),
        [&group_board](const ftcal::MessageInfo& info, const ftcal::service_status_t& status) {
          group_board->Update(status, info.recv_utime);
        });
    app.bus().Subscribe<ftcal::process_state_t>(
        app.config().launch().process_state_channel(),
        [&group_board](const ftcal::MessageInfo& info, const ftcal::process_state_t& state) {
          group_board->Update(state, info.recv_utime);
        });
  }

  const bool tty = ::isatty(STDOUT_FILENO) == 1;
  auto print = [&] {
    std::string table = board.Render(app.bus().NowUtime());
    if (group_board) table += "\n" + group_board->Render(app.bus().NowUtime());
    // On a terminal: cursor home, clear, redraw. Otherwise tables one after another.
    std::fputs(tty ? "\x1b[H\x1b[2J" : (once_after_s > 0 ? "" : "\n"), stdout);
    std::fputs(table.c_str(), stdout);
    std::fflush(stdout);
  };
  if (once_after_s > 0) {
    app.AddPeriodic(once_after_s, [&] {
      print();
      ftcal::RequestShutdown();
    });
  } else {
    app.AddPeriodic(interval_s, print);
  }
  return app.Run();
}
