// Health gates: what a started process must show on the bus before its dependents start. The
// watcher hears every channel (arrival times only, on this host's clock) and the FTCAL_STATUS
// heartbeats (through the wire guard), and judges a gate from what it heard.
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "common/lcm_bus.h"
#include "common/service_stats.h"
#include "ftcal/service_status_t.hpp"
#include "proto/config.pb.h"

namespace ftcal::launch {

struct GateVerdict {
  bool passed = false;
  std::string figure;  // what was measured: "FT_HL 231 Hz (46% of 500 Hz)", "no heartbeat"
};

class GateWatcher {
 public:
  GateWatcher(const std::string& lcm_url, const std::string& status_channel,
              const std::vector<LcmBus::Route>& routes = {});

  // Handles messages for `seconds`, or until `done` (checked after each message and every
  // 50 ms) says so.
  void Pump(double seconds, const std::function<bool()>& done = nullptr);

  // The gate judged now, for the process with `pid` and heartbeat name `status_name`;
  // `since_utime` is when the process started (nothing heard before counts).
  GateVerdict Judge(const config::HealthGate& gate, int64_t pid, const std::string& status_name,
                    int64_t since_utime) const;

  // Pumps until the gate passes or its within_s is over (from `since_utime`), calling `alive`
  // about once a second: a false from it ends the wait (the process died). The verdict's figure
  // is the last measurement.
  GateVerdict Await(const config::HealthGate& gate, int64_t pid, const std::string& status_name,
                    int64_t since_utime, const std::function<bool(std::string*)>& alive);

  // The newest heartbeat of (name, pid), if any.
  std::optional<service_status_t> Heartbeat(const std::string& name, int64_t pid) const;
  int64_t Now() const;

 private:
  struct Arrivals {
    std::deque<int64_t> utimes;  // the last minute
  };
  std::unique_ptr<ServiceStats> stats_;
  std::unique_ptr<LcmBus> bus_;
  std::map<std::string, Arrivals> channels_;
  std::map<std::pair<std::string, int64_t>, std::pair<service_status_t, int64_t>> heartbeats_;
};

}  // namespace ftcal::launch
