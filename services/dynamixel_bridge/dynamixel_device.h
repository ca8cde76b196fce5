// The Dynamixel bus as the Device ServiceApp's loop waits on (common/device.h): the serial port's
// descriptor, a read-write cycle at dynamixel.rate_hz as the deadline, and at each cycle the
// CommandGate's decision taken first (a command, a hold, a refused ARM) and the bridge's
// findings handed back to the gate.
#pragma once

#include <chrono>
#include <string>
#include <vector>

#include "common/device.h"
#include "common/service_stats.h"
#include "dynamixel_bridge/command_gate.h"
#include "dynamixel_bridge/dynamixel_bridge.h"

namespace ftcal {

class DynamixelDevice : public Device {
 public:
  // `now_s` is the clock the gate runs on (seconds, steady). `degraded_after_s`: the bridge is
  // reported degraded once the bus has been degraded for that long (dynamixel.deadman_s, the
  // rule the gate's FAULT follows): one stale cycle on a loaded bus is not a degraded bridge,
  // and a commander that stops on DEGRADED (the sequencer) must not stop on it. A lost servo
  // or a port down stays degraded, so it is reported within that.
  DynamixelDevice(DynamixelBridge& bridge, CommandGate& gate, ServiceStats& stats, double rate_hz,
                  double degraded_after_s, std::function<double()> now_s);

  void AddPollFds(std::vector<pollfd>* fds) override;
  void OnPolled(const pollfd* fds, std::size_t n) override;
  Clock::time_point NextDeadline() const override { return next_cycle_; }
  void OnDeadline(Clock::time_point now) override;
  bool Degraded(std::string* why) override;

 private:
  DynamixelBridge& bridge_;
  CommandGate& gate_;
  ServiceStats& stats_;
  Clock::duration period_;
  double degraded_after_s_;
  std::function<double()> now_s_;
  Clock::time_point next_cycle_ = Clock::now();
  double degraded_since_s_ = -1.0;
  bool polled_port_ = false;  // AddPollFds appended the port
};

}  // namespace ftcal
