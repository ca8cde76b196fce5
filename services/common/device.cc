#include "common/device.h"

#include <algorithm>
#include <cerrno>
#include <ctime>

namespace ftcal {

int WaitFds(std::vector<pollfd>& fds, Device::Clock::time_point wake) {
  const auto wait = std::chrono::duration_cast<std::chrono::nanoseconds>(
      std::max(Device::Clock::duration::zero(), wake - Device::Clock::now()));
  // ppoll for nanoseconds: poll()'s whole milliseconds would wake a 1 kHz device a tick late.
  const timespec ts{static_cast<time_t>(wait.count() / 1'000'000'000),
                    static_cast<long>(wait.count() % 1'000'000'000)};
  const int ready = ::ppoll(fds.empty() ? nullptr : fds.data(), fds.size(), &ts, nullptr);
  if (ready < 0) {
    for (auto& p : fds) p.revents = 0;  // nothing the caller may read as ready
    return errno == EINTR ? 0 : ready;
  }
  return ready;
}

int Device::Step(int max_wait_ms) {
  std::vector<pollfd> fds;
  AddPollFds(&fds);
  const auto wake =
      std::min(NextDeadline(), Clock::now() + std::chrono::milliseconds(std::max(0, max_wait_ms)));
  const int ready = WaitFds(fds, wake);
  OnPolled(fds.data(), fds.size());
  const auto now = Clock::now();
  if (now >= NextDeadline()) OnDeadline(now);
  return ready < 0 ? 0 : ready;
}

}  // namespace ftcal
