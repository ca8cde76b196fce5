// Steps that many multi-process tests take the same way: checking they run inside their own
// network namespace, stopping a child that must exit cleanly, and reading back an LCM log.
// Header-only, as it needs gtest and LCM, which ftcal_child_process does not link.
#pragma once

#include <sched.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <cstdint>
#include <cstdlib>
#include <functional>
#include <iostream>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/service_status_t.hpp"

namespace ftcal::testing {

// For ASSERT_TRUE: multicast outside a private namespace would reach (and be reached by) every
// other test and host on the machine.
inline ::testing::AssertionResult InNetns() {
  const char* netns = std::getenv("FTCAL_NETNS");
  if (netns != nullptr && std::string(netns) == "1") return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure()
         << "this test sends UDP multicast: run it through scripts/netns-exec (ctest does)";
}

// A fixture for a multi-process test in its own network namespace: each test gets a fresh
// directory for its processes' files (Path()), removed when the test passed and kept, and
// named, when it failed.
class NetnsDirTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(InNetns());
    dir_ = MakeTempDir();
  }
  void TearDown() override {
    if (dir_.empty()) return;
    if (HasFailure()) {
      std::cerr << "logs kept in " << dir_ << "\n";
    } else {
      RemoveTree(dir_);
    }
  }
  std::string Path(const std::string& name) const { return dir_ + "/" + name; }
  std::string dir_;
};

// A service that fails to stop on SIGTERM, or stops with an error, fails the test: a clean
// shutdown is part of every service's contract.
inline void Terminate(Child& child, const std::string& what, const std::string& err_path) {
  if (!child.running()) return;
  child.Signal(SIGTERM);
  const auto status = child.Wait(15);
  ASSERT_TRUE(status.has_value()) << what << " did not end on SIGTERM";
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << what << ": " << DescribeWaitStatus(*status) << "\n"
      << ReadFile(err_path);
}

// True when the event is exactly one whole message of type T.
template <typename T>
bool Decode(const lcm::LogEvent* e, T* m) {
  return m->decode(e->data, 0, e->datalen) == e->datalen;
}

// Calls `on_event` with each event of the log at `path`, in order; a log that does not open
// fails the test (a run's recording must exist).
template <class F>
void ForEachLogEvent(const std::string& path, F on_event) {
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return;
  while (const lcm::LogEvent* e = log.readNextEvent()) on_event(e);
}

struct LoggedEvent {
  std::string channel;
  int64_t timestamp;
  std::vector<uint8_t> data;
};

// Every event of a log, raw; none when the log cannot be opened (the caller's checks on what
// it expected then fail).
inline std::vector<LoggedEvent> ReadLogEvents(const std::string& path) {
  std::vector<LoggedEvent> events;
  lcm::LogFile log(path, "r");
  if (!log.good()) return events;
  for (const lcm::LogEvent* e = log.readNextEvent(); e != nullptr; e = log.readNextEvent()) {
    const auto* p = static_cast<const uint8_t*>(e->data);
    events.push_back({e->channel, e->timestamp, std::vector<uint8_t>(p, p + e->datalen)});
  }
  return events;
}

// The first heartbeat (FTCAL_STATUS) heard from each of `pids` on `lcm` within `timeout_s`; a
// pid missing from the result was not heard. A process heard is past its subscriptions and in
// its loop: tests wait for this rather than a fixed time, since a process under a sanitizer
// or on a loaded machine takes seconds to start.
inline std::map<pid_t, service_status_t> AwaitHeartbeats(
    lcm::LCM& lcm, const std::vector<pid_t>& pids, double timeout_s,
    const std::string& channel = "FTCAL_STATUS") {
  struct Ear {
    const std::vector<pid_t>* pids;
    std::map<pid_t, service_status_t> heard;
    void On(const lcm::ReceiveBuffer* rbuf, const std::string&) {
      service_status_t s;
      if (s.decode(rbuf->data, 0, rbuf->data_size) != static_cast<int>(rbuf->data_size)) return;
      for (pid_t p : *pids) {
        if (s.pid == p && !heard.count(p)) heard.emplace(p, s);
      }
    }
  } ear{&pids, {}};
  auto* sub = lcm.subscribe(channel, &Ear::On, &ear);
  const auto start = std::chrono::steady_clock::now();
  while (ear.heard.size() < pids.size() &&
         std::chrono::steady_clock::now() - start < std::chrono::duration<double>(timeout_s)) {
    lcm.handleTimeout(100);
  }
  lcm.unsubscribe(sub);
  return ear.heard;
}

// The heartbeat's counter `name`, or -1 when it carries none.
inline int64_t StatusCounter(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  return -1;
}

// The heartbeats (FTCAL_STATUS) of the processes under test, the latest per pid, heard on the
// caller's LCM instance while it waits.
class StatusWatch {
 public:
  explicit StatusWatch(lcm::LCM& lcm) : lcm_(lcm) {
    sub_ = lcm_.subscribe("FTCAL_STATUS", &StatusWatch::On, this);
    sub_->setQueueCapacity(10000);
  }
  ~StatusWatch() { lcm_.unsubscribe(sub_); }
  StatusWatch(const StatusWatch&) = delete;
  StatusWatch& operator=(const StatusWatch&) = delete;

  // Waits for a heartbeat of `pid` received after this call for which `pred` holds.
  std::optional<service_status_t> Await(pid_t pid,
                                        const std::function<bool(const service_status_t&)>& pred,
                                        double timeout_s = 30) {
    latest_.erase(pid);
    const auto deadline =
        std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < deadline) {
      lcm_.handleTimeout(100);
      const auto it = latest_.find(pid);
      if (it != latest_.end() && pred(it->second)) return it->second;
    }
    return std::nullopt;
  }
  std::optional<service_status_t> AwaitCounter(pid_t pid, const std::string& name, int64_t value) {
    return Await(pid, [&](const service_status_t& s) { return StatusCounter(s, name) == value; });
  }

 private:
  void On(const lcm::ReceiveBuffer* rbuf, const std::string&) {
    service_status_t s;
    if (s.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) !=
        static_cast<int>(rbuf->data_size)) {
      return;
    }
    latest_[static_cast<pid_t>(s.pid)] = s;
  }
  lcm::LCM& lcm_;
  lcm::Subscription* sub_;
  std::map<pid_t, service_status_t> latest_;
};

// Runs this test and everything it starts from here on (children inherit it) ahead of whatever
// else the machine runs: builds, other tests, CI's busy neighbours. The twin stands in for
// devices that have processors of their own, and a lab runs its group with priority (the
// bridges' --realtime). SCHED_FIFO at the lowest real-time priority: beside two busy loops on
// this 2-core VM the twin's Dynamixel thread, even at nice -10, went unanswered for half a second
// at a time (every servo lost mid-plan), and under SCHED_FIFO not once; the kernel's real-time
// throttling still leaves the rest of the machine its share. Needs root, as CI has; elsewhere
// nice -10, or the normal priority, and the test says so.
inline void AheadOfTheMachine() {
  sched_param param{};
  param.sched_priority = 1;
  if (::sched_setscheduler(0, SCHED_FIFO, &param) == 0) return;
  const std::string fifo_error = std::strerror(errno);
  errno = 0;
  if (::setpriority(PRIO_PROCESS, 0, -10) == 0) {
    std::cout << "note: at nice -10, not SCHED_FIFO (" << fifo_error
              << "): a loaded machine can stall the twin\n";
    return;
  }
  std::cout << "note: not ahead of the machine (SCHED_FIFO: " << fifo_error
            << "; nice -10: " << std::strerror(errno) << "): a loaded machine can stall the twin\n";
}

}  // namespace ftcal::testing
