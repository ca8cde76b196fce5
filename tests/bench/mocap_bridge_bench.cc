// The mocap bridge at 100 and 1000 frames/s against the QTM emulator over loopback TCP,
// publishing on LCM (multicast: run it through scripts/netns-exec, as ctest does).
//
// A plain program rather than Google Benchmark: what matters is a real-time stream's delivery,
// CPU share and per-frame latency, which a repeat-until-stable loop does not measure.
// Latency: from the moment the emulator asks its source for a frame (before encoding and
// sending) to the moment the bridge has published the mocap_body_t.
#include <sys/resource.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "bridge_bench.h"
#include "ftcal/geometry.h"
#include "mocap_bridge.h"
#include "qtm_emulator.h"

namespace {

using Clock = std::chrono::steady_clock;

using ftcal::bench::NowNs;
using ftcal::bench::Pct;
using ftcal::bench::ThreadCpuS;

struct Result {
  double rate_hz;
  int64_t sent = 0, published = 0, lost = 0, decode_errors = 0;
  double bridge_cpu_pct = 0, emulator_cpu_pct = 0;
  double p50_us = 0, p99_us = 0, max_us = 0;
};

Result RunAt(double rate_hz, double seconds, lcm::LCM& lcm) {
  const int64_t ticks = static_cast<int64_t>(rate_hz * seconds);
  std::vector<std::atomic<int64_t>> asked_ns(static_cast<size_t>(ticks));
  for (auto& a : asked_ns) a.store(0);

  ftcal::sim::QtmEmulatorOptions eo;
  eo.port = 0;
  eo.rate_hz = rate_hz;
  ftcal::sim::QtmEmulator emulator(eo, [&](int64_t k) -> std::optional<ftcal::sim::QtmPose> {
    if (k >= ticks) return std::nullopt;
    asked_ns[static_cast<size_t>(k)].store(NowNs());
    ftcal::sim::QtmPose p;
    p.R_GC = ftcal::RotationFromRollPitchYaw(0.02, -0.01, 0.001 * double(k));
    p.p_GoCo_G_m = {0.001 * double(k % 1000), 0.5, 0.3};
    for (int i = 0; i < 12; ++i)
      p.markers_G_m.push_back(p.p_GoCo_G_m + Eigen::Vector3d(0.1 * i, 0, 0));
    return p;
  });
  Result r;
  r.rate_hz = rate_hz;
  std::atomic<bool> done{false};
  double emulator_cpu_s = 0;
  const auto t0 = Clock::now();
  std::thread server([&] {
    const double c0 = ThreadCpuS();
    emulator.Run();
    emulator_cpu_s = ThreadCpuS() - c0;
    done = true;
  });

  auto log =
      std::make_shared<spdlog::logger>("bench", std::make_shared<spdlog::sinks::null_sink_mt>());
  ftcal::ServiceStats stats(log);
  std::vector<double> latency_us;
  latency_us.reserve(static_cast<size_t>(ticks));
  ftcal::MocapBridgeOptions bo;
  bo.address = "127.0.0.1";
  bo.port = emulator.port();
  ftcal::MocapBridge bridge(
      bo, stats,
      [&](const ftcal::mocap_body_t& m) {
        lcm.publish("MOCAP_BODY", &m);
        const int64_t k = m.frame_number - 1;
        if (k >= 0 && k < ticks) {
          latency_us.push_back(1e-3 * double(NowNs() - asked_ns[static_cast<size_t>(k)].load()));
        }
      },
      [] { return int64_t{0}; });
  const double bridge_cpu_s = ftcal::bench::StepUntilDoneAndDrain(bridge, done);
  const double wall_s = std::chrono::duration<double>(Clock::now() - t0).count();
  server.join();

  r.sent = emulator.counters().frames_sent;
  r.published = stats.counters().at("published");
  r.lost = stats.counters().at("frames_lost");
  r.decode_errors = stats.counters().at("decode_errors");
  r.bridge_cpu_pct = 100.0 * bridge_cpu_s / wall_s;
  r.emulator_cpu_pct = 100.0 * emulator_cpu_s / wall_s;
  r.p50_us = Pct(latency_us, 0.50);
  r.p99_us = Pct(latency_us, 0.99);
  r.max_us = latency_us.empty() ? 0 : latency_us.back();
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  const double seconds = argc > 1 ? std::atof(argv[1]) : 5.0;
  int rc = 0;
  const auto lcm_ptr = ftcal::bench::OpenBenchLcm(
      "mocap_bridge_bench publishes UDP multicast: run it through "
      "scripts/netns-exec (ctest does)\n",
      &rc);
  if (!lcm_ptr) return rc;
  lcm::LCM& lcm = *lcm_ptr;
  std::printf(
      "mocap_bridge_bench: QTM emulator -> loopback TCP -> MocapBridge -> LCM, %.1f s per rate\n",
      seconds);
  std::printf("%8s %8s %9s %6s %8s %10s %12s %8s %8s %8s\n", "rate_hz", "sent", "published", "lost",
              "corrupt", "bridge_cpu", "emulator_cpu", "p50_us", "p99_us", "max_us");
  bool ok = true;
  for (double rate : {100.0, 1000.0}) {
    const Result r = RunAt(rate, seconds, lcm);
    std::printf("%8.0f %8lld %9lld %6lld %8lld %9.2f%% %11.2f%% %8.0f %8.0f %8.0f\n", r.rate_hz,
                (long long)r.sent, (long long)r.published, (long long)r.lost,
                (long long)r.decode_errors, r.bridge_cpu_pct, r.emulator_cpu_pct, r.p50_us,
                r.p99_us, r.max_us);
    ok &= r.published == r.sent && r.lost == 0;
  }
  std::fflush(stdout);
  return ok ? 0 : 1;
}
