// What the bridge benches (mocap_bridge_bench, natnet_bridge_bench) measure with: per-thread
// CPU time, a nanosecond clock for latencies, percentiles, and the LCM they publish on.
// Header-only: each bench is one source file listed in its own .cmake.
#pragma once

#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include <lcm/lcm-cpp.hpp>

namespace ftcal::bench {

inline double ThreadCpuS() {
  rusage u{};
  ::getrusage(RUSAGE_THREAD, &u);
  return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * double(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

inline int64_t NowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

// The q-quantile of `v` (sorted in place), 0 when empty.
inline double Pct(std::vector<double>& v, double q) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[std::min(v.size() - 1, size_t(q * double(v.size())))];
}

// Steps `bridge` (10 ms at a time) until `done`, then 200 ms more for what is still in flight;
// returns the CPU seconds this thread spent doing so.
template <class Bridge, class Flag>
double StepUntilDoneAndDrain(Bridge& bridge, const Flag& done) {
  const double c0 = ThreadCpuS();
  while (!done) bridge.Step(10);
  const auto drain = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - drain < std::chrono::milliseconds(200)) {
    bridge.Step(10);
  }
  return ThreadCpuS() - c0;
}

// The LCM a bench publishes on, or null with `*exit_code` set: 2 (after `outside_netns`, on
// stderr) outside scripts/netns-exec, where its multicast would reach the machine's other
// tests; 1 when LCM does not open.
inline std::unique_ptr<lcm::LCM> OpenBenchLcm(const char* outside_netns, int* exit_code) {
  const char* netns = std::getenv("FTCAL_NETNS");
  if (netns == nullptr || std::string(netns) != "1") {
    std::fprintf(stderr, "%s", outside_netns);
    *exit_code = 2;
    return nullptr;
  }
  auto lcm = std::make_unique<lcm::LCM>("udpm://239.255.76.67:7667?ttl=0");
  if (!lcm->good()) {
    std::fprintf(stderr, "LCM did not open\n");
    *exit_code = 1;
    return nullptr;
  }
  return lcm;
}

}  // namespace ftcal::bench
