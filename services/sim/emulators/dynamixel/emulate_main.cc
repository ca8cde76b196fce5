// ftcal-emulate-dynamixel: the twin's six MX-106(2.0) servos on a pseudo-terminal, for the
// bridge's tests and benchmark. Positions follow SERVO_CMD goals (scenario "dynamics") or the
// BigAnt twin's shaft angles in real time ("tripod-walk", "standing"); faults on request. At
// the end (duration reached, SIGINT or SIGTERM) every reply the servos produced is written,
// with its fate, to the --truth CSV (atomically).
#include <signal.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <sstream>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/default_config.h"
#include "common/exit_codes.h"
#include "dynamixel_emulator.h"
#include "ftcal/config.h"
#include "ftcal/legs.h"
#include "sim/flags.h"
#ifdef FTCAL_EMULATOR_HAVE_TWIN
#include "sim/live.h"
#include "sim/twin.h"
#endif

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

using ftcal::sim::ParseFlagNumber;
using ftcal::sim::SplitFlag;

struct Window {
  double start_s, end_s;
};

void WriteTruth(const std::string& path, const std::vector<ftcal::sim::DxlReplyRecord>& records) {
  const std::string tmp = path + ".tmp" + std::to_string(::getpid());
  {
    std::ofstream f(tmp);
    if (!f) throw std::runtime_error("cannot create " + tmp);
    f << "t_s,id,instruction,address,length,fate,error,noise_bytes,tick_ms,position,velocity,"
         "current,torque_enable,hardware_error,position_exact_counts\n";
    char line[256];
    for (const auto& r : records) {
      std::snprintf(line, sizeof line, "%.6f,%u,%u,%u,%u,%s,%u,%zu,%u,%d,%d,%d,%u,%u,%.6f\n", r.t_s,
                    r.id, r.instruction, r.address, r.length, ftcal::sim::DxlReplyFateName(r.fate),
                    r.error, r.noise_bytes, r.tick_ms, r.position, r.velocity, r.current,
                    r.torque_enable, r.hardware_error, r.position_exact_counts);
      f << line;
    }
    f.flush();
    if (!f) throw std::runtime_error("write failed: " + tmp);
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    throw std::runtime_error("cannot rename " + tmp + " onto " + path);
  }
}

}  // namespace

int main(int argc, char** argv) try {
  CLI::App cli(
      "Emulates the BigAnt Dynamixel bus (six MX-106, Protocol 2.0) on a pseudo-terminal "
      "linked at --link. Writes every reply the servos produced to --truth (CSV).",
      "ftcal-emulate-dynamixel");
  std::string link, config_path, truth_path, scenario = "dynamics";
  double duration_s = 0, time_constant_s = 0.05;
  std::string clock_from = "start";
  int tick_start_ms = 0;
  ftcal::sim::DxlFaultRates rates;
  std::vector<std::string> missing, silent, hw_errors, disconnects;
  cli.add_option("--link", link, "symlink to create for the slave side (the bridge's device)")
      ->required();
  cli.add_option("--config", config_path, "config file: servo ids, zero counts, directions")
      ->check(CLI::ExistingFile);
  cli.add_option("--scenario", scenario,
                 "dynamics: servos follow Goal Position (first-order, capped at Profile Velocity); "
                 "tripod-walk, standing: "
                 "positions are the twin's shaft angles in real time")
      ->capture_default_str()
      ->check(CLI::IsMember({"dynamics", "tripod-walk", "standing"}));
  cli.add_option("--duration", duration_s,
                 "seconds to run; 0 = until SIGINT/SIGTERM (the twin's motion then repeats "
                 "every 120 s)")
      ->check(CLI::NonNegativeNumber);
  cli.add_option("--truth", truth_path, "CSV of every reply produced (written at the end)");
  cli.add_option("--seed", rates.seed, "fault and twin seed")->capture_default_str();
  cli.add_option("--drop", rates.drop_reply, "probability a reply is dropped")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--corrupt", rates.corrupt_crc, "probability a reply's CRC is corrupted")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--noise", rates.noise, "probability of noise bytes before a reply")
      ->check(CLI::Range(0.0, 1.0));
  cli.add_option("--missing", missing, "ID:START:END  servo ID does not answer in [START, END) s");
  cli.add_option("--silent", silent, "START:END  no servo answers in [START, END) s");
  cli.add_option("--hw-error", hw_errors,
                 "ID:T[:BITS]  at T s servo ID raises hardware error BITS (default 32, "
                 "overload): torque off, alert, until REBOOT");
  cli.add_option("--disconnect", disconnects,
                 "START:END  the port vanishes in [START, END) s and comes back as a new pty");
  cli.add_option("--time-constant", time_constant_s, "first-order time constant, s")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cli.add_option("--tick-start", tick_start_ms, "Realtime Tick at start, ms (to test its wrap)")
      ->check(CLI::Range(0, 32767));
  cli.add_option("--clock", clock_from,
                 "where time 0 of every timed option (--duration, --missing, --silent, "
                 "--hw-error, --disconnect, the scenario, the Realtime Tick) is: the emulator's "
                 "start, or the first bytes a master sends on the bus (a fault then meets the "
                 "bridge however long it took to start)")
      ->capture_default_str()
      ->check(CLI::IsMember({"start", "first-request"}));
  cli.footer(ftcal::ExitCodeTable());
  if (auto rc = ftcal::ParseCommandLine(cli, argc, argv)) return *rc;

  try {
    const ftcal::config::Config config = ftcal::LoadConfigOrDefault(config_path);

    ftcal::sim::DxlEmulatorOptions options;
    options.ids.clear();
    std::array<std::int32_t, ftcal::kNumLegs> zero{};
    std::array<int, ftcal::kNumLegs> direction{};
    for (int k = 0; k < config.robot().leg_size(); ++k) {
      const auto& servo = config.robot().leg(k).servo();
      options.ids.push_back(static_cast<std::uint8_t>(servo.id()));
      zero[k] = servo.zero_count();
      direction[k] = servo.direction();
    }
    options.time_constant_s = time_constant_s;
    options.initial_tick_ms = static_cast<std::uint16_t>(tick_start_ms);
    options.rates = rates;
    for (const auto& m : missing) {
      const auto f = SplitFlag(m, ':');
      if (f.size() != 3) throw std::invalid_argument("--missing " + m + ": want ID:START:END");
      options.events.push_back({ftcal::sim::DxlFaultKind::kMissingServo,
                                ParseFlagNumber(f[1], "--missing"),
                                ParseFlagNumber(f[2], "--missing"),
                                static_cast<std::uint8_t>(ParseFlagNumber(f[0], "--missing")), 0});
    }
    for (const auto& s : silent) {
      const auto f = SplitFlag(s, ':');
      if (f.size() != 2) throw std::invalid_argument("--silent " + s + ": want START:END");
      options.events.push_back({ftcal::sim::DxlFaultKind::kSilent,
                                ParseFlagNumber(f[0], "--silent"),
                                ParseFlagNumber(f[1], "--silent"), 0, 0});
    }
    for (const auto& h : hw_errors) {
      const auto f = SplitFlag(h, ':');
      if (f.size() != 2 && f.size() != 3) {
        throw std::invalid_argument("--hw-error " + h + ": want ID:T[:BITS]");
      }
      const double bits = f.size() == 3 ? ParseFlagNumber(f[2], "--hw-error") : 32;
      if (bits < 1 || bits > 255) throw std::invalid_argument("--hw-error " + h + ": BITS 1-255");
      options.events.push_back({ftcal::sim::DxlFaultKind::kHardwareError,
                                ParseFlagNumber(f[1], "--hw-error"), 0,
                                static_cast<std::uint8_t>(ParseFlagNumber(f[0], "--hw-error")),
                                static_cast<std::uint8_t>(bits)});
    }
    std::vector<Window> down;
    for (const auto& d : disconnects) {
      const auto f = SplitFlag(d, ':');
      if (f.size() != 2) throw std::invalid_argument("--disconnect " + d + ": want START:END");
      down.push_back(
          {ParseFlagNumber(f[0], "--disconnect"), ParseFlagNumber(f[1], "--disconnect")});
    }

    ftcal::sim::DynamixelBusEmulator emulator(options);
    std::vector<ftcal::sim::DxlReplyRecord> records;
    emulator.SetReplyObserver(
        [&records](const ftcal::sim::DxlReplyRecord& r) { records.push_back(r); });

    // Twin-driven positions: the scenario's 100 Hz shaft angles, interpolated in time, looped
    // after its end (services/sim/live.h).
#ifdef FTCAL_EMULATOR_HAVE_TWIN
    std::unique_ptr<ftcal::sim::TwinSeries> series;
#endif
    if (scenario != "dynamics") {
#ifdef FTCAL_EMULATOR_HAVE_TWIN
      ftcal::TwinOptions twin_options;
      twin_options.seed = rates.seed;
      ftcal::BigAntTwin twin(config, twin_options);
      series = std::make_unique<ftcal::sim::TwinSeries>(
          twin, scenario == "tripod-walk" ? "walk" : "stand",
          duration_s > 0 ? duration_s + 1.0 : 120.0);
      std::vector<int> leg_of_id(256, -1);
      for (std::size_t k = 0; k < options.ids.size(); ++k) {
        leg_of_id[options.ids[k]] = static_cast<int>(k);
      }
      emulator.SetStateSource(
          [&series, leg_of_id, zero, direction](
              std::uint8_t id, double now_s) -> std::optional<ftcal::sim::DxlDrivenState> {
            const int k = leg_of_id[id];
            if (k < 0) return std::nullopt;
            double rate = 0;
            const double angle = series->AngleAt(k, now_s, &rate);
            return ftcal::sim::DxlStateFromAngle(angle, rate, zero[k], direction[k]);
          });
#else
      throw std::invalid_argument("--scenario " + scenario +
                                  ": this build has no BigAnt twin (services/sim)");
#endif
    }

    struct sigaction sa {};
    sa.sa_handler = OnSignal;
    sigemptyset(&sa.sa_mask);
    ::sigaction(SIGINT, &sa, nullptr);
    ::sigaction(SIGTERM, &sa, nullptr);

    ftcal::sim::PtyBus bus(emulator, link);
    bus.Open();
    std::printf("ftcal-emulate-dynamixel: %zu servos on %s (linked at %s), scenario %s\n",
                options.ids.size(), bus.slave_path().c_str(), link.c_str(), scenario.c_str());
    std::fflush(stdout);

    // With --clock first-request, time stands at 0 until the first bytes arrive (ServeOnce
    // reads the clock only then).
    using SteadyClock = std::chrono::steady_clock;
    std::optional<SteadyClock::time_point> t0;
    if (clock_from == "start") t0 = SteadyClock::now();
    const auto clock_s = [&t0] {
      const auto now = SteadyClock::now();
      if (!t0) t0 = now;
      return std::chrono::duration<double>(now - *t0).count();
    };
    while (!g_stop) {
      const double now_s = t0 ? clock_s() : 0.0;
      if (duration_s > 0 && now_s >= duration_s) break;
      bool in_down = false;
      for (const auto& w : down) in_down = in_down || (now_s >= w.start_s && now_s < w.end_s);
      if (in_down && bus.is_open()) {
        bus.Close();
        std::printf("ftcal-emulate-dynamixel: port closed at %.3f s\n", now_s);
        std::fflush(stdout);
      } else if (!in_down && !bus.is_open()) {
        bus.Open();
        std::printf("ftcal-emulate-dynamixel: port back at %.3f s on %s\n", now_s,
                    bus.slave_path().c_str());
        std::fflush(stdout);
      }
      if (bus.is_open()) {
        bus.ServeOnce(2, clock_s);
      } else {
        ::usleep(2000);
      }
    }
    bus.Close();
    const auto& c = emulator.fault_counts();
    std::printf(
        "ftcal-emulate-dynamixel: %zu replies; dropped %lld corrupted %lld noise bursts "
        "%lld missing %lld silent %lld hardware errors %lld bus watchdog expiries %lld\n",
        records.size(), static_cast<long long>(c.dropped), static_cast<long long>(c.corrupted),
        static_cast<long long>(c.noise_bursts), static_cast<long long>(c.missing),
        static_cast<long long>(c.silent), static_cast<long long>(c.hardware_errors),
        static_cast<long long>(c.bus_watchdog_expiries));
    if (!truth_path.empty()) WriteTruth(truth_path, records);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "ftcal-emulate-dynamixel: %s\n", e.what());
    return 2;
  }
  return 0;
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-emulate-dynamixel");
}
