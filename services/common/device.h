// A device that paces a process: a bridge's sockets or serial line, which ServiceApp::RunDevice
// waits on together with the process's one LCM socket (the pattern of Drake's iiwa driver: one
// poll() over the robot's and LCM's descriptors, written once here instead of in every bridge).
//
// Every turn of the loop: AddPollFds() just before the wait, OnPolled() with what the kernel
// said, OnDeadline() when NextDeadline() has come. Degraded() is asked every turn (a change is
// published at once) and ReportCounters() before every heartbeat. Exceptions pass to the caller
// of Step() or RunDevice(): a device that can go on catches its own.
#pragma once

#include <poll.h>

#include <chrono>
#include <cstddef>
#include <string>
#include <utility>
#include <vector>

namespace ftcal {

class ServiceStats;

class Device {
 public:
  using Clock = std::chrono::steady_clock;

  virtual ~Device() = default;

  // Appends the descriptors to wait on and the events wanted (none while, say, a port is being
  // reopened). Called just before each wait.
  virtual void AddPollFds(std::vector<pollfd>* fds) = 0;
  // After each wait, with this device's entries as AddPollFds appended them and the kernel's
  // revents (all 0 after a timeout).
  virtual void OnPolled(const pollfd* fds, std::size_t n) = 0;
  // The latest time the loop may sleep to without anything readable; OnDeadline() runs then.
  virtual Clock::time_point NextDeadline() const = 0;
  virtual void OnDeadline(Clock::time_point now) = 0;
  // True while the device does not serve as configured; `why`, when given, says what is wrong.
  // Asked every turn: cheap when `why` is null.
  virtual bool Degraded(std::string* why) = 0;
  // The device's counters into the heartbeat's.
  virtual void ReportCounters(ServiceStats& /*stats*/) {}
  // The loop ends: what the device is told on the way out (the ATI boxes' stop command).
  virtual void Close() {}

  // One turn without a bus, waiting at most `max_wait_ms`: for tests and tools that drive a
  // device by hand. Returns the number of the device's descriptors that were ready.
  int Step(int max_wait_ms);
};

// Degraded() for a device that states its health as a reason ("" when healthy).
inline bool DegradedBecause(std::string reason, std::string* why) {
  if (reason.empty()) return false;
  if (why) *why = std::move(reason);
  return true;
}

// The wait of one turn: until `wake` (clamped to now) or a descriptor in `fds` is ready.
// Returns ppoll's result with EINTR as 0; after an error every revents is 0.
int WaitFds(std::vector<pollfd>& fds, Device::Clock::time_point wake);

}  // namespace ftcal
