// Running a motion-capture bridge class in the test's own thread against an emulator serving
// from another: the same loop for the QTM and the NatNet bridge, so that their tests compare
// like with like.
#pragma once

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <vector>

#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

namespace ftcal::testing {

// Steps `bridge` until `served` is set (the emulator's run ended), noting each change of its
// health reason in `health`, then 0.2 s more for what is still in flight on loopback.
template <class Bridge>
void StepUntilServed(Bridge& bridge, const std::atomic<bool>& served,
                     std::vector<std::string>* health) {
  while (!served) {
    bridge.Step(5);
    const std::string reason = bridge.health_reason();
    if (health->empty() || health->back() != reason) health->push_back(reason);
  }
  const auto drain = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - drain < std::chrono::milliseconds(200)) {
    bridge.Step(5);
  }
}

// A logger for a bridge's ServiceStats that keeps the test's output to gtest's.
inline std::shared_ptr<spdlog::logger> QuietLogger(const std::string& name) {
  return std::make_shared<spdlog::logger>(name, std::make_shared<spdlog::sinks::null_sink_mt>());
}

}  // namespace ftcal::testing
