#include "dynamixel_bridge/dynamixel_device.h"

#include <utility>

#include "common/bus.h"

namespace ftcal {

DynamixelDevice::DynamixelDevice(DynamixelBridge& bridge, CommandGate& gate, ServiceStats& stats,
                                 double rate_hz, double degraded_after_s,
                                 std::function<double()> now_s)
    : bridge_(bridge),
      gate_(gate),
      stats_(stats),
      period_(std::chrono::duration_cast<Clock::duration>(
          std::chrono::duration<double>(1.0 / rate_hz))),
      degraded_after_s_(degraded_after_s),
      now_s_(std::move(now_s)) {
  gate_.SetArmBlock(bridge_.ArmBlocker());
}

void DynamixelDevice::AddPollFds(std::vector<pollfd>* fds) {
  // Bytes nobody asked for, and hang-ups, between cycles; none while the port is being reopened.
  polled_port_ = bridge_.fd() >= 0;
  if (polled_port_) fds->push_back({bridge_.fd(), POLLIN, 0});
}

void DynamixelDevice::OnPolled(const pollfd* fds, std::size_t n) {
  if (polled_port_ && n == 1 && fds[0].revents != 0) bridge_.OnDeviceReadable();
}

void DynamixelDevice::OnDeadline(Clock::time_point now) {
  if (now < next_cycle_) return;
  if (auto cmd = gate_.Tick(now_s_(), bridge_.Degraded())) {
    try {
      bridge_.OnCommand(*cmd);
    } catch (const BadInput& e) {
      stats_.Drop(e.kind(), e.what());
    }
  }
  bridge_.Cycle();
  // Before the next command is taken: a servo stopped by its watchdog holds until a new ARM,
  // and no ARM while the servos' own limits are not the config's.
  gate_.SetArmBlock(bridge_.ArmBlocker());
  if (auto why = bridge_.TakeWatchdogExpiry()) gate_.Hold(*why);
  if (!bridge_.Degraded()) {
    degraded_since_s_ = -1.0;
  } else if (degraded_since_s_ < 0.0) {
    degraded_since_s_ = now_s_();
  }
  next_cycle_ += period_;
  const auto after = Clock::now();
  if (next_cycle_ <= after) {  // the cycle overran its slot: skip ahead, do not burst
    ++stats_.Counter("late_cycles");
    next_cycle_ = after + period_;
  }
}

bool DynamixelDevice::Degraded(std::string* why) {
  return degraded_since_s_ >= 0.0 && now_s_() - degraded_since_s_ >= degraded_after_s_ &&
         bridge_.Degraded(why);
}

}  // namespace ftcal
