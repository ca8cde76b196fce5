// How a device-paced process (a bridge) asks to be scheduled: its flags --realtime,
// --realtime-priority and --slice-us (ServiceApp::OfferSchedulingFlags).
//
// A bridge's latency is set by how soon it runs once its device has spoken, not by its own
// work: the ATI bridge spends ~5 us per record, nearly all of it the kernel's (LCM's multicast
// sendmsg, looped back and delivered in the sender's softirq, then recvmmsg); see
// tests/bench/ati_bridge_bench.cc. On a shared machine a waking bridge otherwise waits for the
// running task's slice to end; an ATI bridge starved below its ~22 % of a core (six boxes at
// 7000 Hz) falls behind for good, and a Dynamixel bridge held off its bus for the servos' Bus
// Watchdog time stops the legs.
#pragma once

#include <spdlog/logger.h>

namespace ftcal {

struct SchedulingOptions {
  // SCHED_FIFO at realtime_priority and mlockall (a lab's robot computer; needs root or
  // CAP_SYS_NICE and CAP_IPC_LOCK). Refused: a warning, and the slice below applies instead.
  bool realtime = false;
  int realtime_priority = 40;
  // Under SCHED_OTHER, the EEVDF slice asked for (Linux >= 6.12: a shorter slice lets a waking
  // task preempt the running one; unprivileged). 0: the kernel's default. Off by default: on a
  // machine busy enough to starve the bridge it did not help (it changes when the bridge runs,
  // not how much); figures in tests/bench/ati_bridge_bench.cc.
  double slice_us = 0;
};
struct SchedulingGranted {
  bool fifo = false;    // SCHED_FIFO is in force
  bool locked = false;  // mlockall succeeded
  bool slice = false;   // the kernel took the slice request
};
// Applies `options` to the calling thread (refusals are logged as warnings, never thrown).
// Throws std::invalid_argument for options out of range (priority outside 1..99, slice negative
// or over 100 ms).
SchedulingGranted ApplyScheduling(const SchedulingOptions& options, spdlog::logger& log);

// mlockall for a process that receives from the network: the pages mapped now are populated and
// locked, pages mapped later are locked as they are first touched (MCL_ONFAULT), not populated
// at mmap. Without MCL_ONFAULT, MCL_FUTURE made LCM's reassembly buffer for a fragmented message
// resident whole at its first fragment: one unauthenticated datagram announcing 256 MiB cost a
// locked process 256 MiB (issue 36, finding 4). False (errno set) when refused.
bool LockMemory();

}  // namespace ftcal
