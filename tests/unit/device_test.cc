// Device::Step, the one turn of a device loop (services/common/device.h), over a real pipe: it
// wakes for bytes at once, for the device's deadline when it comes and not before, and
// otherwise after the most the caller allows.
#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <vector>

#include <gtest/gtest.h>

#include "common/device.h"

namespace ftcal {
namespace {

using Clock = Device::Clock;

double Since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

class PipeDevice : public Device {
 public:
  PipeDevice() { EXPECT_EQ(::pipe2(fds_, O_NONBLOCK | O_CLOEXEC), 0); }
  ~PipeDevice() override {
    ::close(fds_[0]);
    ::close(fds_[1]);
  }
  void Write(char c) { ASSERT_EQ(::write(fds_[1], &c, 1), 1); }

  void AddPollFds(std::vector<pollfd>* fds) override { fds->push_back({fds_[0], POLLIN, 0}); }
  void OnPolled(const pollfd* fds, std::size_t n) override {
    ASSERT_EQ(n, 1u);
    ASSERT_EQ(fds[0].fd, fds_[0]);
    ++polled;
    if (fds[0].revents & POLLIN) {
      char c;
      while (::read(fds_[0], &c, 1) == 1) read.push_back(c);
    }
  }
  Clock::time_point NextDeadline() const override { return deadline; }
  void OnDeadline(Clock::time_point now) override {
    deadline_ran_at.push_back(now);
    deadline = Clock::time_point::max();
  }
  bool Degraded(std::string*) override { return false; }

  Clock::time_point deadline = Clock::time_point::max();
  std::vector<Clock::time_point> deadline_ran_at;
  std::vector<char> read;
  int polled = 0;

 private:
  int fds_[2] = {-1, -1};
};

TEST(DeviceStep, WakesForBytesAtOnceAndOtherwiseAfterTheLongestWaitAllowed) {
  PipeDevice d;
  auto t0 = Clock::now();
  EXPECT_EQ(d.Step(50), 0);
  EXPECT_GE(Since(t0), 0.045) << "nothing to read, no deadline: the whole wait";
  EXPECT_EQ(d.polled, 1) << "OnPolled runs after a timeout too";
  EXPECT_TRUE(d.read.empty());
  EXPECT_TRUE(d.deadline_ran_at.empty());

  d.Write('x');
  t0 = Clock::now();
  EXPECT_EQ(d.Step(5000), 1);
  EXPECT_LT(Since(t0), 2.0) << "bytes waiting: no wait";
  EXPECT_EQ(d.read, std::vector<char>{'x'});
  EXPECT_TRUE(d.deadline_ran_at.empty()) << "no deadline was due";
}

TEST(DeviceStep, RunsTheDeadlineWhenItComesAndNotBefore) {
  PipeDevice d;
  const auto t0 = Clock::now();
  d.deadline = t0 + std::chrono::milliseconds(40);
  EXPECT_EQ(d.Step(5000), 0);
  ASSERT_EQ(d.deadline_ran_at.size(), 1u) << "the deadline cut the wait short and ran";
  EXPECT_GE(d.deadline_ran_at[0], t0 + std::chrono::milliseconds(40)) << "not before it came";
  EXPECT_LT(Since(t0), 2.0);

  // A deadline further than the wait allowed: the turn ends without running it.
  d.deadline = Clock::now() + std::chrono::seconds(10);
  d.Step(10);
  EXPECT_EQ(d.deadline_ran_at.size(), 1u);

  // One already past runs without a wait.
  d.deadline = Clock::now() - std::chrono::milliseconds(1);
  const auto t1 = Clock::now();
  d.Step(5000);
  EXPECT_EQ(d.deadline_ran_at.size(), 2u);
  EXPECT_LT(Since(t1), 2.0);
}

}  // namespace
}  // namespace ftcal
