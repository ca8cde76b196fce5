// ftcal::ApplyScheduling (services/common, every bridge's --realtime and --slice-us): what it
// reports granted is what the kernel has in force for the calling thread, read back independently
// with sched_getscheduler/sched_getattr; options out of range are refused by name. Each case runs
// in a thread of its own, since the policy is per thread (mlockall, when granted, locks this small
// test process: harmless).
#include <sched.h>
#include <sys/syscall.h>
#include <sys/utsname.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>

#include <gtest/gtest.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>

#include "common/scheduling.h"

namespace ftcal {
namespace {

// The kernel's struct sched_attr, VER0 (as the bridge declares it; read here on our own).
struct KernelSchedAttr {
  std::uint32_t size, sched_policy;
  std::uint64_t sched_flags;
  std::int32_t sched_nice;
  std::uint32_t sched_priority;
  std::uint64_t sched_runtime, sched_deadline, sched_period;
};

KernelSchedAttr ReadAttr() {
  KernelSchedAttr a{};
  EXPECT_EQ(::syscall(SYS_sched_getattr, 0, &a, sizeof a, 0), 0);
  return a;
}

// Linux 6.12 added the SCHED_OTHER slice request.
bool KernelTakesSlices() {
  utsname u{};
  ::uname(&u);
  int major = 0, minor = 0;
  std::sscanf(u.release, "%d.%d", &major, &minor);
  return major > 6 || (major == 6 && minor >= 12);
}

struct Outcome {
  SchedulingGranted granted;
  int policy = -1;  // sched_getscheduler, SCHED_RESET_ON_FORK included
  sched_param param{};
  KernelSchedAttr attr{};
  std::string log;
  std::string error;
};

// Runs ApplyScheduling on a fresh thread and reads back what that thread got.
Outcome RunOnThread(const SchedulingOptions& options) {
  Outcome out;
  std::thread([&] {
    std::ostringstream text;
    auto log = std::make_shared<spdlog::logger>(
        "sched", std::make_shared<spdlog::sinks::ostream_sink_st>(text));
    try {
      out.granted = ApplyScheduling(options, *log);
    } catch (const std::invalid_argument& e) {
      out.error = e.what();
    }
    out.policy = ::sched_getscheduler(0);
    ::sched_getparam(0, &out.param);
    out.attr = ReadAttr();
    log->flush();
    out.log = text.str();
  }).join();
  return out;
}

TEST(Scheduling, SliceRequestIsWhatTheKernelReadsBack) {
  SchedulingOptions o;
  o.slice_us = 300;
  const Outcome out = RunOnThread(o);
  ASSERT_TRUE(out.error.empty()) << out.error;
  EXPECT_FALSE(out.granted.fifo);
  EXPECT_EQ(out.policy, SCHED_OTHER);
  EXPECT_EQ(out.granted.slice, KernelTakesSlices());
  if (KernelTakesSlices()) {
    EXPECT_EQ(out.attr.sched_runtime, 300'000u);
  }
  // This thread's main sibling is untouched: the policy is per thread.
  EXPECT_NE(ReadAttr().sched_runtime, 300'000u);
}

TEST(Scheduling, NoSliceLeavesTheKernelDefault) {
  SchedulingOptions o;
  o.slice_us = 0;
  const Outcome out = RunOnThread(o);
  ASSERT_TRUE(out.error.empty()) << out.error;
  EXPECT_FALSE(out.granted.slice);
  EXPECT_FALSE(out.granted.fifo);
  EXPECT_EQ(out.policy, SCHED_OTHER);
  EXPECT_EQ(out.attr.sched_runtime, ReadAttr().sched_runtime);
}

TEST(Scheduling, RealtimeIsFifoAtThePriorityWhenGrantedElseAWarningAndTheSlice) {
  SchedulingOptions o;
  o.realtime = true;
  o.realtime_priority = 7;
  o.slice_us = 250;
  const Outcome out = RunOnThread(o);
  ASSERT_TRUE(out.error.empty()) << out.error;
  if (out.granted.fifo) {
    // Reset on fork: what the bridge might start does not inherit real time.
    EXPECT_EQ(out.policy, SCHED_FIFO | SCHED_RESET_ON_FORK);
    EXPECT_EQ(out.param.sched_priority, 7);
    EXPECT_FALSE(out.granted.slice);
    EXPECT_NE(out.log.find("SCHED_FIFO priority 7"), std::string::npos) << out.log;
  } else {
    EXPECT_EQ(out.policy & ~SCHED_RESET_ON_FORK, SCHED_OTHER);
    EXPECT_NE(out.log.find("SCHED_FIFO refused"), std::string::npos) << out.log;
    EXPECT_EQ(out.granted.slice, KernelTakesSlices());
  }
  // As root (CI) nothing refuses it.
  if (::geteuid() == 0) {
    EXPECT_TRUE(out.granted.fifo);
    EXPECT_TRUE(out.granted.locked);
  }
}

TEST(Scheduling, OptionsOutOfRangeAreRefusedByName) {
  SchedulingOptions o;
  o.realtime = true;
  o.realtime_priority = 0;
  Outcome out = RunOnThread(o);
  EXPECT_NE(out.error.find("realtime priority 0"), std::string::npos) << out.error;
  EXPECT_EQ(out.policy, SCHED_OTHER);  // nothing applied

  o = {};
  o.slice_us = -5;
  out = RunOnThread(o);
  EXPECT_NE(out.error.find("slice"), std::string::npos) << out.error;

  o = {};
  o.slice_us = 200'000;
  out = RunOnThread(o);
  EXPECT_NE(out.error.find("slice"), std::string::npos) << out.error;
}

}  // namespace
}  // namespace ftcal
