// ftcal-ati-bridge's work: ATI Net F/T transducers over RDT (docs/device-protocols.md §1) in,
// ft_batch_t on FT_<LEG> out.
//
// Per transducer: a UDP socket bound to an ephemeral port, from which the start command is
// sent, so the box streams back to it (§1.2): real-time (0x0002, one record per datagram) when
// the config's records_per_datagram k is 1, buffered (0x0003, k records per datagram) when it is
// 2..40, count 0 either way. Counts per unit come from the config or else from the box's
// calibration page (GET /netftapi2.xml, netft_config.h); without them the bridge refuses to start.
// In buffered mode the page's RDT buffer size (comrdtbsiz) must equal k, and k defaults to the
// page's output rate (comrdtrate) / 1000, rounded, at least 1. The records of a datagram are
// published together, as one ft_batch_t (one message per datagram, not per record). Every record is
// checked (length, sequence) before it is published: lost, duplicated, late (reordered), stale and
// wrong-length records are counted and never published; a published sample is always a record as
// the device sent it, converted. After ~100 ms of silence the start is re-sent with a bounded
// back-off and the transducer is reported down until records come back; when ft_sequence jumps
// backwards (the box rebooted) the calibration page is read again. Stop (0x0000) is sent on
// shutdown.
//
// Sample times: each record's place on the box's internal 7 kHz counter (ft_sequence), mapped
// onto the host clock by a DeviceClock fitted to (the datagram's last counter, its kernel
// receipt stamp), published beside the receipt time (docs/method.md, "Clocks and delays").
//
// The receive path allocates nothing: recvmmsg into fixed buffers, an ft_batch_t per
// transducer reused, its encoding into a fixed buffer. Latency from receipt (kernel timestamp
// SO_TIMESTAMPNS, and the clock when recvmmsg returned) to the end of the publish call is kept
// in fixed histograms.
#pragma once

#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include <spdlog/logger.h>

#include "common/device.h"
#include "common/service_stats.h"
#include "ftcal/ft_batch_t.hpp"
#include "netft_config.h"
#include "proto/config.pb.h"
#include "rdt_codec.h"

namespace ftcal {

// AtiBridgeError and AtiBoxMismatchError, which the bridge throws, are in netft_config.h.

struct AtiBridgeOptions {
  double silence_timeout_s = 0.1;  // no record for this long: re-send the start command
  double max_backoff_s = 1.0;      // re-sends back off 0.1, 0.2, 0.4 ... up to this
  int down_after_requests = 2;     // unanswered re-sends before the transducer is reported down
  double http_timeout_s = 1.0;     // the whole calibration-page fetch, not each read
  std::size_t calibration_page_max_bytes = 64 << 10;  // a real netftapi2.xml is a few kB
  int receive_buffer_bytes = 8 << 20;                 // SO_RCVBUF (the kernel caps it at rmem_max)
};

// Per transducer. All but the latency are also published in the heartbeat.
struct AtiTransducerCounters {
  std::uint64_t datagrams = 0;  // received on the socket
  // Well-formed records. Each is published or counted in exactly one of duplicates, late,
  // stale, uncalibrated or publish_errors.
  std::uint64_t received = 0;
  std::uint64_t published = 0;
  std::uint64_t lost = 0;  // by rdt_sequence (a reordered record counts here first)
  std::uint64_t duplicates = 0;
  std::uint64_t late = 0;          // older than the last accepted (reordered): dropped
  std::uint64_t stale = 0;         // leftovers of a previous stream: dropped
  std::uint64_t wrong_length = 0;  // datagrams not a multiple of 36 bytes: dropped
  std::uint64_t foreign = 0;       // datagrams from another address than the box: dropped
  // Accepted records not published because the calibration page could not be read (yet).
  std::uint64_t uncalibrated = 0;
  std::uint64_t status_nonzero = 0;  // published with FLAG_STATUS_ERROR
  std::uint64_t saturated = 0;       // published with FLAG_SATURATED
  std::uint64_t start_requests = 0;
  std::uint64_t restarts = 0;  // streams begun (first record after a start)
  std::uint64_t silences = 0;  // times the stream went quiet past the timeout
  std::uint64_t reboots = 0;   // ft_sequence went backwards
  std::uint64_t calibration_reads = 0;
  std::uint64_t recv_errors = 0;
  std::uint64_t send_errors = 0;
  std::uint64_t publish_errors = 0;
  // Records the kernel timestamped before this socket was last drained empty: they were still in
  // the network stack (a deferred softirq) when the bridge looked, so their wait was not the
  // bridge's. Diagnostic for the latency tail.
  std::uint64_t held_in_stack = 0;
};

// Latency histogram, 1 us bins up to kMaxUs (the last bin holds everything beyond).
class LatencyHistogram {
 public:
  static constexpr int kMaxUs = 20000;
  void Add(std::int64_t ns);
  std::uint64_t count() const { return count_; }
  // The q-quantile in microseconds (upper edge of its bin); 0 when empty.
  double QuantileUs(double q) const;
  void Merge(const LatencyHistogram& other);

 private:
  std::array<std::uint64_t, kMaxUs + 1> bins_{};
  std::uint64_t count_ = 0;
};

class AtiBridge : public Device {
 public:
  // Called for every datagram's records: channel, LCM-encoded ft_batch_t bytes. Must not keep
  // the pointer.
  using Publisher = std::function<void(const std::string& channel, const void* data, int size)>;

  // `legs`: names of the transducers to serve (empty: every leg of the config). Throws
  // AtiBridgeError for an unknown leg, a leg without `ati`, or a bad address or sign.
  AtiBridge(const config::Config& config, const std::vector<std::string>& legs, Publisher publish,
            std::shared_ptr<spdlog::logger> log, AtiBridgeOptions options = {});
  ~AtiBridge() override;
  AtiBridge(const AtiBridge&) = delete;
  AtiBridge& operator=(const AtiBridge&) = delete;

  // Opens the sockets, reads each calibration page the config does not replace (counts per
  // unit, rated range, or the RDT settings of a buffered or defaulted records_per_datagram), and
  // sends the start commands. Throws AtiBridgeError naming the transducer and URL when a page
  // cannot be read or parsed: the bridge refuses to stream with guessed counts per unit; and
  // AtiBoxMismatchError when the box's RDT buffer size is not the config's.
  void Start();
  // Waits up to `timeout_ms` for datagrams, handles all that are there, and re-sends starts
  // that are due (one Device::Step). Returns the number of records published.
  int Poll(int timeout_ms);
  // Sends stop to every transducer (idempotent).
  void Stop();

  // The Device a ServiceApp's loop waits on: one socket per transducer; the deadline is the
  // earliest re-send of a start (or retry of a calibration page); degraded while any
  // transducer is silent; the counters are CounterTable()'s, and msgs_in counts records.
  void AddPollFds(std::vector<pollfd>* fds) override;
  void OnPolled(const pollfd* fds, std::size_t n) override;
  Clock::time_point NextDeadline() const override;
  void OnDeadline(Clock::time_point now) override;
  bool Degraded(std::string* why) override;
  void ReportCounters(ServiceStats& stats) override;
  void Close() override { Stop(); }

  // True when every transducer is streaming (none silent past the timeout).
  bool AllUp() const;
  // What is wrong now, per transducer ("HL: no record for 150 ms: ..."); "" when all is well.
  std::string Problems() const;
  std::size_t size() const;
  const std::string& leg(std::size_t i) const;
  bool up(std::size_t i) const;
  // Records per datagram of transducer i: the config's, or once Start() read the page, the
  // default from the box's rate (0 before that).
  int records_per_datagram(std::size_t i) const;
  const AtiTransducerCounters& counters(std::size_t i) const;
  // Receipt -> published, from the kernel's receive timestamp and from recvmmsg's return.
  const LatencyHistogram& kernel_latency() const { return kernel_latency_; }
  const LatencyHistogram& user_latency() const { return user_latency_; }
  // Receipt -> published (kernel timestamp) of the records counted in held_in_stack only.
  const LatencyHistogram& held_latency() const { return held_latency_; }
  // Names and values for the heartbeat: "<LEG>.<counter>" for every counter, plus
  // latency_p50_us/latency_p99_us (user-space) and kernel_latency_p99_us.
  std::vector<std::pair<std::string, std::int64_t>> CounterTable() const;

 private:
  struct Transducer;  // ati_transducer.h
  // The receive path (ati_receive.cc): drains t's socket in batches of datagrams.
  void HandleSocket(Transducer& t);
  // Checks a record and, when it is to be published, appends it to t's batch.
  void HandleRecord(Transducer& t, const std::uint8_t* bytes);
  // Stamps the batch's records (the clock map) and publishes it as one message.
  void PublishBatch(Transducer& t, std::int64_t kernel_ns, std::int64_t user_ns, bool held);
  void SendRequest(Transducer& t, rdt::Command command);
  // Reads t's calibration page and takes what the config does not give (NetFtSettings).
  // Throws AtiBridgeError, AtiBoxMismatchError.
  void ReadCalibration(Transducer& t);
  static rdt::Command StartCommand(const Transducer& t);
  double SilenceTimeoutS(const Transducer& t) const;
  void Service(Transducer& t, std::chrono::steady_clock::time_point now);
  // Logs a state change of kind `kind`: at once, or (a box flapping or refusing) folded into
  // the next line of that kind at most once per 30 s, which gives the count in between.
  void LogState(Transducer& t, const char* kind, spdlog::level::level_enum level,
                const std::string& text);

  AtiBridgeOptions options_;
  Publisher publish_;
  std::shared_ptr<spdlog::logger> log_;
  std::vector<std::unique_ptr<Transducer>> transducers_;
  LatencyHistogram kernel_latency_;
  LatencyHistogram user_latency_;
  LatencyHistogram held_latency_;
  bool started_ = false;
  std::int64_t poll_ns_ = 0;       // CLOCK_REALTIME just before the last wait
  std::uint64_t reported_in_ = 0;  // records counted in the stats' msgs_in
};

}  // namespace ftcal
