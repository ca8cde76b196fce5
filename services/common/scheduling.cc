#include "common/scheduling.h"

#include <sched.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>

namespace ftcal {

namespace {

// The kernel's struct sched_attr (SCHED_ATTR_SIZE_VER0): glibc 2.36 (Debian 12) has neither a
// sched_setattr() wrapper nor the struct, and <linux/sched/types.h> clashes with <sched.h>.
struct SchedAttr {
  std::uint32_t size;
  std::uint32_t sched_policy;
  std::uint64_t sched_flags;
  std::int32_t sched_nice;
  std::uint32_t sched_priority;
  std::uint64_t sched_runtime;  // for SCHED_OTHER since Linux 6.12: the requested slice
  std::uint64_t sched_deadline;
  std::uint64_t sched_period;
};
static_assert(sizeof(SchedAttr) == 48, "SCHED_ATTR_SIZE_VER0");

bool GetSchedAttr(SchedAttr& a) {
  a = {};
  return ::syscall(SYS_sched_getattr, 0, &a, sizeof a, 0) == 0;
}

}  // namespace

bool LockMemory() {
  // Two calls: MCL_ONFAULT applies to MCL_CURRENT too, so the first populates what is mapped now.
  return ::mlockall(MCL_CURRENT) == 0 && ::mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) == 0;
}

SchedulingGranted ApplyScheduling(const SchedulingOptions& options, spdlog::logger& log) {
  if (options.realtime && (options.realtime_priority < 1 || options.realtime_priority > 99)) {
    throw std::invalid_argument("realtime priority " + std::to_string(options.realtime_priority) +
                                " is outside 1..99");
  }
  if (!(options.slice_us >= 0 && options.slice_us <= 100'000)) {
    throw std::invalid_argument("scheduler slice " + std::to_string(options.slice_us) +
                                " us is outside 0..100000");
  }
  SchedulingGranted granted;
  if (options.realtime) {
    // Locked first: a page fault on the receive path would cost more than the whole publish.
    if (LockMemory()) {
      granted.locked = true;
    } else {
      log.warn("--realtime: mlockall refused ({}): pages may fault on the receive path",
               std::strerror(errno));
    }
    sched_param param{};
    param.sched_priority = options.realtime_priority;
    // Reset on fork: nothing this process starts should inherit a real-time policy.
    if (::sched_setscheduler(0, SCHED_FIFO | SCHED_RESET_ON_FORK, &param) == 0) {
      granted.fifo = true;
      log.info("--realtime: SCHED_FIFO priority {}{}", options.realtime_priority,
               granted.locked ? ", memory locked" : "");
      return granted;
    }
    log.warn(
        "--realtime: SCHED_FIFO refused ({}; needs root or CAP_SYS_NICE): running as an "
        "ordinary process{}",
        std::strerror(errno), options.slice_us > 0 ? " with a short slice" : "");
  }
  if (options.slice_us > 0) {
    SchedAttr a;
    if (!GetSchedAttr(a) || a.sched_policy != SCHED_OTHER) {
      log.warn(
          "scheduler slice: not asked (cannot read this thread's policy, or it is not "
          "SCHED_OTHER)");
      return granted;
    }
    // Only the slice changes: the nice value read back is passed on as it was.
    a.size = sizeof a;
    a.sched_flags = 0;
    a.sched_runtime = static_cast<std::uint64_t>(options.slice_us * 1000.0);
    SchedAttr back;
    // The kernel clamps the request to 0.1..100 ms; an older kernel ignores it.
    const std::uint64_t expected = std::clamp<std::uint64_t>(a.sched_runtime, 100'000, 100'000'000);
    if (::syscall(SYS_sched_setattr, 0, &a, 0) == 0 && GetSchedAttr(back) &&
        back.sched_runtime == expected) {
      granted.slice = true;
      log.debug("scheduler slice {} us", back.sched_runtime / 1000.0);
    } else {
      log.info(
          "scheduler slice of {} us not taken (needs Linux >= 6.12): the kernel's default "
          "applies",
          options.slice_us);
    }
  }
  return granted;
}

}  // namespace ftcal
