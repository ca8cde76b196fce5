// ftcal-supervisor-events: run by supervisord as an [eventlistener:...] (ftcal-launch writes
// the section), it publishes every PROCESS_STATE change of its group as process_state_t on LCM,
// so the recording holds process health beside the data. stdout is supervisor's protocol
// channel: everything for humans goes to stderr.
#include <unistd.h>

#include <chrono>
#include <iostream>
#include <string>

#include <lcm/lcm-cpp.hpp>

#include "common/exit_codes.h"
#include "supervisor_events/event_listener.h"

int main(int argc, char** argv) try {
  CLI::App cli(
      "supervisor event listener: publishes PROCESS_STATE events of --group as "
      "process_state_t on --channel. Run by supervisord, not by hand.",
      "ftcal-supervisor-events");
  std::string group, host_name, url = "udpm://239.255.76.67:7667?ttl=0", channel = "PROCESS_STATE";
  cli.add_option("--group", group, "the supervisor group to report (default: every group)");
  cli.add_option("--host-name", host_name, "host name to put in the messages (default: hostname)");
  cli.add_option("--lcm-url", url, "LCM URL")->capture_default_str();
  cli.add_option("--channel", channel, "LCM channel")->capture_default_str();
  double pace_s = 0;
  cli.add_option("--pace", pace_s,
                 "instead: write a byte to stdout every this many seconds, forever (run by "
                 "supervisord as [program:GROUP-pacer] with stdout_logfile=NONE)")
      ->check(CLI::Range(0.01, 10.0));
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;
  if (pace_s > 0) {
    // supervisord spawns a replacement for a dead process only at the top of its next loop,
    // which waits for output from some child or its 1 s poll timeout (2 s when the reap missed
    // the first wake-up). This output is that wake-up: a restart within about two paces.
    while (true) {
      if (::write(STDOUT_FILENO, "\n", 1) < 0) return ftcal::kExitDone;  // supervisord went away
      ::usleep(static_cast<useconds_t>(pace_s * 1e6));
    }
  }
  if (host_name.empty()) {
    char buf[256] = {};
    ::gethostname(buf, sizeof(buf) - 1);
    host_name = buf;
  }
  lcm::LCM lcm(url);
  if (!lcm.good()) {
    std::cerr << "ftcal-supervisor-events: cannot open LCM URL " << url << "\n";
    return ftcal::kExitDeviceIo;
  }
  ftcal::supervisor::EventTranslator translator(host_name, group);
  std::ios::sync_with_stdio(false);
  while (true) {
    std::cout << "READY\n" << std::flush;
    std::string header;
    if (!std::getline(std::cin, header)) return ftcal::kExitDone;  // supervisord went away
    const auto tokens = ftcal::supervisor::ParseTokens(header);
    std::size_t len = 0;
    try {
      len = tokens.count("len") ? std::stoul(tokens.at("len")) : 0;
    } catch (const std::exception&) {
      std::cerr << "ftcal-supervisor-events: bad header: " << header << "\n";
      return ftcal::kExitRefused;
    }
    std::string payload(len, '\0');
    if (len > 0 && !std::cin.read(payload.data(), static_cast<std::streamsize>(len))) {
      return ftcal::kExitDone;
    }
    const int64_t now = std::chrono::duration_cast<std::chrono::microseconds>(
                            std::chrono::system_clock::now().time_since_epoch())
                            .count();
    if (auto m = translator.Translate(header, payload, now)) {
      if (lcm.publish(channel, &*m) != 0) {
        std::cerr << "ftcal-supervisor-events: publish on " << channel << " failed\n";
      }
    }
    std::cout << "RESULT 2\nOK" << std::flush;
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-supervisor-events");
}
