// One transducer of the ATI bridge, shared by the bridge's two files: ati_bridge.cc (set-up,
// start and stop, liveness, counters) and ati_receive.cc (the receive path: recvmmsg, records,
// batches, publish). Not for use outside this folder.
#pragma once

#include <netinet/in.h>
#include <sys/socket.h>
#include <time.h>

#include <array>
#include <chrono>
#include <cstdint>
#include <map>
#include <string>
#include <vector>

#include "ati_bridge.h"
#include "ftcal/device_clock.h"
#include "netft_config.h"

namespace ftcal {
namespace ati_internal {

using Clock = std::chrono::steady_clock;

inline constexpr int kBatch = 64;             // datagrams per recvmmsg
inline constexpr int kMaxBatchesPerCall = 4;  // per socket, before the others get their turn
inline constexpr std::size_t kSlotBytes =
    1536;  // an Ethernet frame: the largest buffered datagram we take (40 records: 1440 bytes)
static_assert(kSlotBytes > rdt::kMaxDatagramBytes, "a slot must hold the largest datagram");
inline constexpr auto kCalibrationRetry = std::chrono::seconds(1);
inline constexpr auto kCalibrationRetryMax = std::chrono::seconds(16);
inline constexpr auto kStateLogPeriod = std::chrono::seconds(30);
// The Net F/T's internal sample counter (ft_sequence) runs at 7000 Hz whatever the RDT rate
// (docs/device-protocols.md §1.3): the clock each record's sample time is mapped from.
inline constexpr std::int64_t kFtCounterHz = 7000;

inline std::int64_t RealtimeNs() {
  timespec ts;
  ::clock_gettime(CLOCK_REALTIME, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

inline Clock::duration Seconds(double s) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

}  // namespace ati_internal

// Its settings (counts per unit, rated range, records per datagram: netft_config.h), and its
// stream.
struct AtiBridge::Transducer : NetFtSettings {
  std::string leg;
  std::string channel;
  std::string address;
  std::uint16_t rdt_port = 0;
  std::uint16_t http_port = 0;
  std::string url;
  int sign = 1;
  sockaddr_in device{};

  ati_internal::Clock::time_point next_calibration_try{};

  int fd = -1;
  rdt::SequenceTracker tracker;
  bool have_ft = false;
  std::uint32_t last_ft = 0;
  std::int64_t last_utime = 0;   // the stamp of the last record handed on (they only rise)
  std::int64_t pending_gap = 0;  // accepted but unpublished (no calibration) since the last sample
  bool restart_pending = false;  // the next published sample carries FLAG_RESTARTED
  // A time at which the socket was known empty: just before a recvmmsg that drained it (took
  // fewer than a batch), or the start of a poll() that did not find it readable.
  std::int64_t drained_at_ns = 0;

  // Liveness.
  bool up = false;
  bool silent = false;
  ati_internal::Clock::time_point last_record{};
  ati_internal::Clock::time_point next_request{};
  ati_internal::Clock::time_point last_request{};
  double backoff_s = 0;
  int unanswered = 0;

  ft_batch_t msg;  // the batch being filled: msg.n records so far
  std::vector<std::uint8_t> encoded;
  std::array<std::int64_t, ft_batch_t::MAX_N> ticks{};  // each batched record's counter, unwrapped
  std::int64_t ft_unwrapped = 0;  // last_ft, unwrapped (a reboot makes it fall)
  DeviceClock clock{DeviceClockOptions{static_cast<double>(ati_internal::kFtCounterHz)}};

  // recvmmsg slots.
  std::vector<std::uint8_t> slots;
  std::array<mmsghdr, ati_internal::kBatch> headers{};
  std::array<iovec, ati_internal::kBatch> iovs{};
  std::array<sockaddr_in, ati_internal::kBatch> sources{};
  std::array<std::array<char, CMSG_SPACE(sizeof(timespec))>, ati_internal::kBatch> controls{};

  AtiTransducerCounters c;
  // What is wrong with this transducer now ("" when streaming and calibrated): the status's
  // last_error.
  std::string problem;
  // State-change lines (silent, down, streaming again, send failures, calibration failures) of
  // a flapping or refusing box: per kind, one line per kStateLogPeriod with the count between.
  struct KindLog {
    ati_internal::Clock::time_point last{};
    bool logged = false;
    std::uint64_t unlogged = 0;
  };
  std::map<std::string, KindLog> state_logs;
  ati_internal::Clock::duration calibration_backoff = ati_internal::kCalibrationRetry;
  // Once-per-kind logging of bad input.
  bool logged_wrong_length = false, logged_duplicate = false, logged_late = false,
       logged_stale = false, logged_status = false, logged_foreign = false,
       logged_saturated = false, logged_publish = false, logged_recv = false;
};

}  // namespace ftcal
