// The NatNet bridge at 240 and 1000 frames/s against the Motive emulator over loopback UDP
// (unicast and multicast, bitstream 4.1), publishing on LCM (multicast: run it through
// scripts/netns-exec, as ctest does).
//
// A plain program rather than Google Benchmark: a real-time stream's delivery and per-frame
// latency are what matter. Two latencies per frame:
//   receipt-to-publish  from the bridge's clock read right after recvfrom() returned the
//                       datagram to the return of lcm.publish() (decode, map, convert, encode)
//   source-to-publish   from the emulator asking its source for the frame (before encoding and
//                       sending) to the same point: adds the emulator and the loopback
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
#include "natnet_bridge.h"
#include "natnet_emulator.h"

namespace {

using Clock = std::chrono::steady_clock;

using ftcal::bench::NowNs;
using ftcal::bench::Pct;
using ftcal::bench::ThreadCpuS;

struct Result {
  double rate_hz = 0;
  bool multicast = false;
  int64_t sent = 0, published = 0, lost = 0, decode_errors = 0;
  double bridge_cpu_pct = 0;
  double r50 = 0, r99 = 0, rmax = 0;  // receipt-to-publish, us
  double s50 = 0, s99 = 0;            // source-to-publish, us
};

Result RunAt(double rate_hz, bool multicast, double seconds, lcm::LCM& lcm) {
  const int64_t ticks = static_cast<int64_t>(rate_hz * seconds);
  std::vector<std::atomic<int64_t>> asked_ns(static_cast<size_t>(ticks));
  for (auto& a : asked_ns) a.store(0);
  ftcal::sim::NatNetEmulatorOptions eo;
  eo.rate_hz = rate_hz;
  eo.multicast = multicast;
  for (int i = 0; i < 12; ++i) eo.body_points_C_m.push_back(Eigen::Vector3d(0.1 * i, 0.05, 0.02));
  ftcal::sim::NatNetEmulator emulator(eo, [&](int64_t k) -> std::optional<ftcal::sim::NatNetPose> {
    if (k >= ticks) return std::nullopt;
    asked_ns[static_cast<size_t>(k)].store(NowNs());
    ftcal::sim::NatNetPose p;
    p.R_GC = ftcal::RotationFromRollPitchYaw(0.02, -0.01, 0.001 * double(k));
    p.p_GoCo_G_m = {0.001 * double(k % 1000), 0.5, 0.3};
    for (int i = 0; i < 12; ++i) {
      p.markers_G_m.push_back(p.p_GoCo_G_m + p.R_GC * Eigen::Vector3d(0.1 * i, 0.05, 0.02));
    }
    return p;
  });
  std::atomic<bool> done{false};
  const auto t0 = Clock::now();
  std::thread server([&] {
    emulator.Run();
    done = true;
  });

  auto log =
      std::make_shared<spdlog::logger>("bench", std::make_shared<spdlog::sinks::null_sink_mt>());
  ftcal::ServiceStats stats(log);
  std::vector<double> receipt_us, source_us;
  receipt_us.reserve(static_cast<size_t>(ticks));
  source_us.reserve(static_cast<size_t>(ticks));
  ftcal::NatNetBridgeOptions bo;
  bo.address = "127.0.0.1";
  bo.multicast = multicast;
  bo.command_port = emulator.command_port();
  bo.data_port = emulator.data_port();
  int64_t receipt_ns = 0;  // the bridge reads its clock once per datagram, right after recvfrom
  ftcal::NatNetBridge bridge(
      bo, stats,
      [&](const ftcal::mocap_body_t& m) {
        lcm.publish("MOCAP_BODY", &m);
        const int64_t now = NowNs();
        receipt_us.push_back(1e-3 * double(now - receipt_ns));
        const int64_t k = m.frame_number - 1;
        if (k >= 0 && k < ticks)
          source_us.push_back(1e-3 * double(now - asked_ns[size_t(k)].load()));
      },
      [&] {
        receipt_ns = NowNs();
        return std::chrono::duration_cast<std::chrono::microseconds>(
                   std::chrono::system_clock::now().time_since_epoch())
            .count();
      });
  bridge.Open();
  const double bridge_cpu_s = ftcal::bench::StepUntilDoneAndDrain(bridge, done);
  const double wall_s = std::chrono::duration<double>(Clock::now() - t0).count();
  server.join();

  Result r;
  r.rate_hz = rate_hz;
  r.multicast = multicast;
  r.sent = emulator.counters().frames_sent;
  r.published = stats.counters().at("published");
  r.lost = stats.counters().at("frames_lost");
  r.decode_errors = stats.counters().at("decode_errors");
  r.bridge_cpu_pct = 100.0 * bridge_cpu_s / wall_s;
  r.r50 = Pct(receipt_us, 0.5);
  r.r99 = Pct(receipt_us, 0.99);
  r.rmax = receipt_us.empty() ? 0 : receipt_us.back();
  r.s50 = Pct(source_us, 0.5);
  r.s99 = Pct(source_us, 0.99);
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  const double seconds = argc > 1 ? std::atof(argv[1]) : 5.0;
  int rc = 0;
  const auto lcm_ptr = ftcal::bench::OpenBenchLcm(
      "natnet_bridge_bench uses UDP multicast: run it through "
      "scripts/netns-exec (ctest does)\n",
      &rc);
  if (!lcm_ptr) return rc;
  lcm::LCM& lcm = *lcm_ptr;
  std::printf(
      "natnet_bridge_bench: Motive emulator (NatNet 4.1) -> loopback UDP -> NatNetBridge "
      "-> LCM, %.1f s per case\n",
      seconds);
  std::printf("%8s %10s %7s %9s %5s %8s %10s %14s %14s %14s %13s %13s\n", "rate_hz", "transport",
              "sent", "published", "lost", "corrupt", "bridge_cpu", "receipt_p50_us",
              "receipt_p99_us", "receipt_max_us", "source_p50_us", "source_p99_us");
  bool ok = true;
  for (double rate : {240.0, 1000.0}) {
    for (bool multicast : {false, true}) {
      const Result r = RunAt(rate, multicast, seconds, lcm);
      std::printf("%8.0f %10s %7lld %9lld %5lld %8lld %9.2f%% %14.1f %14.1f %14.1f %13.1f %13.1f\n",
                  r.rate_hz, multicast ? "multicast" : "unicast", (long long)r.sent,
                  (long long)r.published, (long long)r.lost, (long long)r.decode_errors,
                  r.bridge_cpu_pct, r.r50, r.r99, r.rmax, r.s50, r.s99);
      // Multicast frames before the handshake are not published: allow the first 0.5 s.
      ok &= r.lost == 0 && r.decode_errors == 0 && r.published + int64_t(rate / 2) >= r.sent;
    }
  }
  std::fflush(stdout);
  return ok ? 0 : 1;
}
