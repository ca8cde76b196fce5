// The Dynamixel bridge's full read-write cycle on the emulated bus: SYNC WRITE of six goal
// positions, SYNC READ of the six present blocks, and every --hw-error-every cycles the SYNC
// READ of addresses 64-70, one cycle per 1.05 ms (the servos' tick is 1 ms) over a
// pseudo-terminal with the twin's MX-106 emulator answering in a second thread. Prints cycles/s and
// the per-cycle latency p50/p99/max. On real hardware the wire time dominates (about 2.5 ms per
// cycle at 1 Mbit/s, see docs/device-protocols.md §2.1); this measures the software path: codec,
// pty, emulator, bridge.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <mutex>
#include <regex>
#include <sstream>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <spdlog/sinks/null_sink.h>

#include "dynamixel_bridge.h"
#include "dynamixel_emulator.h"
#include "ftcal/config.h"

int main(int argc, char** argv) {
  CLI::App cli("Dynamixel bridge cycle benchmark (six servos, emulated bus on a pty)",
               "dynamixel_bridge_bench");
  double duration_s = 5.0;
  int hw_every = 10;
  cli.add_option("--duration", duration_s, "seconds of back-to-back cycles")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  cli.add_option("--hw-error-every", hw_every, "hardware-error read every n-th cycle")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  CLI11_PARSE(cli, argc, argv);

  char dir_template[] = "/tmp/ftcal-dxl-bench-XXXXXX";
  if (::mkdtemp(dir_template) == nullptr) {
    std::perror("mkdtemp");
    return 1;
  }
  const std::string link = std::string(dir_template) + "/tty";

  try {
    ftcal::sim::DynamixelBusEmulator emulator({});
    ftcal::sim::PtyBus pty(emulator, link);
    pty.Open();
    std::atomic<bool> stop{false};
    const auto t0 = std::chrono::steady_clock::now();
    std::thread server([&] {
      while (!stop) {
        pty.ServeOnce(1, [&t0] {
          return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        });
      }
    });

    std::ifstream in(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    std::stringstream ss;
    ss << in.rdbuf();
    const std::string text =
        std::regex_replace(ss.str(), std::regex("device: \"[^\"]*\""), "device: \"" + link + "\"");
    const auto config = ftcal::LoadConfigText(text, "sim.pbtxt with the bench's pty");
    ftcal::ServiceStats stats(std::make_shared<spdlog::logger>(
        "dxl-bench", std::make_shared<spdlog::sinks::null_sink_mt>()));
    std::int64_t published = 0, stale = 0;
    ftcal::DynamixelBridgeOptions options;
    options.hardware_error_every = hw_every;
    ftcal::DynamixelBridge bridge(
        config, options, stats,
        [&](const ftcal::servo_state_t& m) {
          ++published;
          for (int f : m.flags) stale += (f & ftcal::servo_state_t::FLAG_STALE) != 0;
        },
        [] { return std::int64_t{0}; });
    if (!bridge.Connect() || !bridge.missing_at_start().empty()) {
      std::fprintf(stderr, "dynamixel_bridge_bench: the emulated bus did not answer\n");
      stop = true;
      server.join();
      return 1;
    }

    ftcal::servo_command_t cmd;
    cmd.num_servos = 6;
    cmd.id = {1, 2, 3, 4, 5, 6};
    cmd.goal_angle_rad.assign(6, 0.0);
    cmd.torque_enable = true;
    std::vector<double> latency_us;
    const auto start = std::chrono::steady_clock::now();
    const auto end = start + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                 std::chrono::duration<double>(duration_s));
    for (std::int64_t i = 0; std::chrono::steady_clock::now() < end; ++i) {
      for (int k = 0; k < 6; ++k) cmd.goal_angle_rad[k] = 0.3 * std::sin(0.01 * i + k);
      const auto a = std::chrono::steady_clock::now();
      bridge.OnCommand(cmd);
      bridge.Cycle();
      const auto b = std::chrono::steady_clock::now();
      latency_us.push_back(std::chrono::duration<double, std::micro>(b - a).count());
      // A servo's Realtime Tick counts ms and the bridge takes a second block within one tick
      // for a late reply, so cycles start at most once per tick (plus a margin).
      std::this_thread::sleep_until(a + std::chrono::microseconds(1050));
    }
    const double elapsed_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    stop = true;
    server.join();

    std::sort(latency_us.begin(), latency_us.end());
    auto pct = [&](double p) {
      return latency_us[std::min(latency_us.size() - 1,
                                 static_cast<std::size_t>(p * (latency_us.size() - 1) + 0.5))];
    };
    std::printf(
        "dynamixel_bridge_bench: six MX-106 on an emulated bus (pty), goal write + present "
        "read per cycle, hardware-error read every %d\n",
        hw_every);
    std::printf("  cycles            %zu in %.2f s\n", latency_us.size(), elapsed_s);
    std::printf("  cycles/s          %.0f\n", latency_us.size() / elapsed_s);
    std::printf("  latency p50       %.1f us\n", pct(0.50));
    std::printf("  latency p99       %.1f us\n", pct(0.99));
    std::printf("  latency max       %.1f us\n", latency_us.back());
    std::printf("  published %lld, stale servo-samples %lld\n", static_cast<long long>(published),
                static_cast<long long>(stale));
    // Back to back, a servo can be read twice within its 1 ms tick: the bridge takes the second
    // block for a late reply and flags that sample STALE (see DynamixelBridge::ReadPresent).
    std::printf("  repeated-tick replies %lld\n",
                static_cast<long long>(stats.counters().count("repeated_tick")
                                           ? stats.counters().at("repeated_tick")
                                           : 0));
    if (published != static_cast<std::int64_t>(latency_us.size())) {
      std::fprintf(stderr, "dynamixel_bridge_bench: a cycle published nothing\n");
      return 1;
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "dynamixel_bridge_bench: %s\n", e.what());
    return 1;
  }
  std::remove(link.c_str());
  std::remove(dir_template);
  return 0;
}
