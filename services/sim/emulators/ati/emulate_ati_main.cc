// ftcal-emulate-ati: the twin's six ATI Net F/T boxes on loopback, in real time, for the
// bridge's tests and benchmark. Each leg's box streams the counts of a BigAnt twin scenario
// (services/sim/twin.h) over RDT and serves its calibration page; faults are injected as the
// flags say; at exit (SIGINT/SIGTERM) the truth series of every record generated, with what was
// done to it, is written atomically to --truth.
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "ati_emulator.h"
#include "ftcal/config.h"
#include "ftcal/legs.h"
#include "sim/live.h"
#include "sim/twin.h"

namespace {

using ftcal::sim::AtiEmitted;
using ftcal::sim::AtiEmulator;
using ftcal::sim::AtiScheduledEvent;

std::atomic<bool> g_stop{false};
void OnSignal(int) { g_stop = true; }

using ftcal::sim::ParseFlagNumber;
using ftcal::sim::SplitFlag;

// Writes `text` to `path` through a temporary file, fsync and rename.
void WriteAtomically(const std::string& path, const std::string& text) {
  const std::string tmp = path + ".tmp." + std::to_string(::getpid());
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) throw std::runtime_error(tmp + ": " + std::strerror(errno));
  std::size_t done = 0;
  while (done < text.size()) {
    const ssize_t n = ::write(fd, text.data() + done, text.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const std::string err = std::strerror(errno);
      ::close(fd);
      ::unlink(tmp.c_str());
      throw std::runtime_error(tmp + ": " + err);
    }
    done += static_cast<std::size_t>(n);
  }
  if (::fsync(fd) != 0 || ::close(fd) != 0 || ::rename(tmp.c_str(), path.c_str()) != 0) {
    const std::string err = std::strerror(errno);
    ::unlink(tmp.c_str());
    throw std::runtime_error(path + ": " + err);
  }
}

}  // namespace

int main(int argc, char** argv) try {
  CLI::App cli(
      "Emulates the BigAnt twin's ATI Net F/T boxes: per leg an RDT endpoint (UDP) at the "
      "config's address and rdt_port and its calibration page (GET /netftapi2.xml) at "
      "http_port, streaming the counts of a twin scenario in real time. Writes the truth "
      "series (every record generated and the fault applied to it) to --truth at exit.",
      "ftcal-emulate-ati");
  std::string config_path;  // empty: the built-in config/sim.pbtxt
  std::string legs_flag;
  std::string scenario = "walk";
  double duration_s = 0;
  int rate_hz = 7000;
  int records_per_datagram = 0;
  std::uint64_t seed = 1;
  double drop = 0, duplicate = 0, reorder = 0, corrupt = 0;
  std::vector<std::string> silences, reboots;
  std::string truth_path, ready_path;
  double cpf = 1e6, cpt = 1e6;
  bool no_http = false;
  cli.add_option("--config", config_path, "configuration (addresses, ports, rated ranges)")
      ->capture_default_str();
  cli.add_option("--legs", legs_flag, "comma-separated legs to emulate (default: all)");
  cli.add_option("--scenario", scenario, "twin scenario: walk (TripodWalk) or standing")
      ->check(CLI::IsMember({"walk", "standing"}))
      ->capture_default_str();
  cli.add_option("--duration", duration_s,
                 "seconds of data; afterwards the boxes stay up but send nothing "
                 "(default: until stopped)")
      ->check(CLI::NonNegativeNumber);
  cli.add_option("--rate", rate_hz, "RDT output rate, records/s (comrdtrate)")
      ->check(CLI::Range(1, 7000))
      ->capture_default_str();
  cli.add_option("--records-per-datagram", records_per_datagram,
                 "RDT buffer size of every box (comrdtbsiz), 1..40: records per datagram in "
                 "buffered mode (default: the config's records_per_datagram, else --rate / 1000, "
                 "rounded, at least 1)")
      ->check(CLI::Range(1, 40));
  cli.add_option("--seed", seed, "seed of the twin and the faults")->capture_default_str();
  cli.add_option("--drop", drop, "probability a datagram is not sent")->check(CLI::Range(0.0, 1.0));
  cli.add_option("--duplicate", duplicate, "probability a datagram is sent twice")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--reorder", reorder, "probability a datagram is sent after the next one")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--corrupt", corrupt, "probability a datagram is sent with a wrong length")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--silence", silences, "LEG:AT_S:DURATION_S, the network of LEG down a while");
  cli.add_option("--reboot", reboots, "LEG:AT_S, LEG's box reboots (ft_sequence restarts)");
  cli.add_option("--counts-per-force", cpf, "cfgcpf of every box")->capture_default_str();
  cli.add_option("--counts-per-torque", cpt, "cfgcpt of every box")->capture_default_str();
  cli.add_flag("--no-http", no_http, "serve no calibration page");
  cli.add_option("--truth", truth_path, "CSV of every record generated, written at exit");
  cli.add_option("--ready", ready_path, "file written once every endpoint is bound");
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;

  try {
    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);
    std::vector<int> legs;
    if (legs_flag.empty()) {
      for (int k = 0; k < ftcal::kNumLegs; ++k) legs.push_back(k);
    } else {
      for (const std::string& name : SplitFlag(legs_flag, ',')) {
        const auto k = ftcal::LegIndex(name);
        if (!k) throw std::invalid_argument("--legs: unknown leg '" + name + "'");
        legs.push_back(*k);
      }
    }

    // The scenario's counts at 100 Hz, leg by leg; held between frames (the box's 7000 Hz
    // samples of a 100 Hz twin) and repeated when the run outlasts them (services/sim/live.h).
    ftcal::TwinOptions twin_options;
    twin_options.seed = seed;
    twin_options.counts_per_force = cpf;
    twin_options.counts_per_torque = cpt;
    const ftcal::BigAntTwin twin(config, twin_options);
    const double span_s = duration_s > 0 ? duration_s + 1.0 : 60.0;
    const auto series = std::make_shared<const ftcal::sim::TwinSeries>(
        twin, scenario == "walk" ? "walk" : "stand", span_s);

    std::vector<ftcal::sim::AtiTruthRow> truth;
    if (!truth_path.empty())
      truth.reserve(static_cast<std::size_t>(legs.size() * rate_hz * (span_s + 1)));
    std::vector<ftcal::sim::AtiFaultOptions> faults(ftcal::kNumLegs);
    for (int k = 0; k < ftcal::kNumLegs; ++k) {
      faults[k].seed = seed * 1000 + static_cast<std::uint64_t>(k);
      faults[k].drop = drop;
      faults[k].duplicate = duplicate;
      faults[k].reorder = reorder;
      faults[k].corrupt = corrupt;
    }
    for (const std::string& s : silences) {
      const auto parts = SplitFlag(s, ':');
      const auto k = parts.size() == 3 ? ftcal::LegIndex(parts[0]) : std::nullopt;
      if (!k) throw std::invalid_argument("--silence '" + s + "': expected LEG:AT_S:DURATION_S");
      faults[*k].events.push_back({AtiScheduledEvent::Kind::kSilence,
                                   ParseFlagNumber(parts[1], "--silence " + s),
                                   ParseFlagNumber(parts[2], "--silence " + s)});
    }
    for (const std::string& s : reboots) {
      const auto parts = SplitFlag(s, ':');
      const auto k = parts.size() == 2 ? ftcal::LegIndex(parts[0]) : std::nullopt;
      if (!k) throw std::invalid_argument("--reboot '" + s + "': expected LEG:AT_S");
      faults[*k].events.push_back(
          {AtiScheduledEvent::Kind::kReboot, ParseFlagNumber(parts[1], "--reboot " + s), 0});
    }

    std::vector<std::unique_ptr<AtiEmulator>> boxes;
    for (int k : legs) {
      const ftcal::config::Leg& leg = config.robot().leg(k);
      if (!leg.has_ati())
        throw std::invalid_argument("leg " + leg.name() + " has no ati in the config");
      ftcal::sim::AtiEmulatorOptions o;
      o.name = leg.name();
      o.address = leg.ati().address();
      o.rdt_port = static_cast<std::uint16_t>(leg.ati().rdt_port());
      o.http_port = no_http ? 0 : static_cast<std::uint16_t>(leg.ati().http_port());
      o.counts_per_force = cpf;
      o.counts_per_torque = cpt;
      if (leg.ati().rated_range_size() == 6) {
        for (int i = 0; i < 6; ++i) o.rated_range[i] = leg.ati().rated_range(i);
      }
      o.rdt_rate_hz = rate_hz;
      o.rdt_buffer_size = records_per_datagram > 0
                              ? records_per_datagram
                              : static_cast<int>(leg.ati().records_per_datagram());
      o.faults = faults[k];
      auto source = [series, k](std::uint64_t, double t_s) {
        ftcal::sim::AtiDeviceSample s;
        s.counts = series->At(t_s).counts[k];
        return s;
      };
      ftcal::sim::AtiEmitSink emit;
      if (!truth_path.empty()) emit = [&truth, k](const AtiEmitted& e) { truth.push_back({k, e}); };
      boxes.push_back(std::make_unique<AtiEmulator>(o, source, emit));
    }

    struct sigaction sa {};
    sa.sa_handler = OnSignal;
    ::sigaction(SIGINT, &sa, nullptr);
    ::sigaction(SIGTERM, &sa, nullptr);
    if (!ready_path.empty()) WriteAtomically(ready_path, "ready\n");
    std::fprintf(stderr, "ftcal-emulate-ati: %zu boxes up, %d records/s, RDT buffer size %d\n",
                 boxes.size(), rate_hz,
                 boxes.empty() ? 0 : boxes.front()->options().rdt_buffer_size);

    std::vector<pollfd> fds;
    fds.reserve(boxes.size());
    for (const auto& b : boxes) fds.push_back({b->fd(), POLLIN, 0});
    const auto start = AtiEmulator::Clock::now();
    bool ended = false;
    // A short wait between steps keeps the records close to their schedule at 7000 Hz.
    const timespec wait{0, 200'000};
    while (!g_stop) {
      ::ppoll(fds.data(), fds.size(), &wait, nullptr);
      const auto now = AtiEmulator::Clock::now();
      if (!ended && duration_s > 0 &&
          std::chrono::duration<double>(now - start).count() >= duration_s) {
        for (auto& b : boxes) {
          b->Step(now);
          b->EndOfData();
        }
        ended = true;
        std::fprintf(stderr, "ftcal-emulate-ati: end of data after %.1f s\n", duration_s);
      }
      for (auto& b : boxes) b->Step(now);
    }

    for (const auto& b : boxes) {
      const auto c = b->counters();
      std::fprintf(stderr,
                   "ftcal-emulate-ati: %s records %llu datagrams %llu starts %llu stops %llu "
                   "drop %llu duplicate %llu reorder %llu corrupt %llu silent %llu reboots %llu "
                   "send_errors %llu http %llu buffered_starts %llu\n",
                   b->options().name.c_str(), (unsigned long long)c.records,
                   (unsigned long long)c.datagrams, (unsigned long long)c.starts,
                   (unsigned long long)c.stops, (unsigned long long)c.faults[1],
                   (unsigned long long)c.faults[2], (unsigned long long)c.faults[3],
                   (unsigned long long)c.faults[4], (unsigned long long)c.faults[5],
                   (unsigned long long)c.reboots, (unsigned long long)c.send_errors,
                   (unsigned long long)c.http_requests, (unsigned long long)c.buffered_starts);
    }
    boxes.clear();  // no more sink calls after this
    if (!truth_path.empty()) WriteAtomically(truth_path, ftcal::sim::AtiTruthCsv(truth));
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-emulate-ati: %s\n", e.what());
    return 1;
  }
  return 0;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-emulate-ati");
}
