// One emulated ATI Net F/T box: the RDT endpoint (UDP, docs/device-protocols.md §1.2-1.3) and
// its calibration page (HTTP GET /netftapi2.xml, §1.4), so the real ati_bridge runs unchanged
// against the BigAnt twin.
//
// The emulator has no streaming thread of its own: a driver calls Step(now) often (every few
// hundred microseconds); Step reads the pending commands and sends every record that fell due
// since the last call. One thread can so drive six boxes at 7000 Hz each, and a test can drive
// one directly. The HTTP page is served by cpp-httplib on its own thread.
//
// Device model. The internal sample counter ft_sequence runs at 7000 Hz from "power-up" (the
// emulator's construction or the end of a reboot). A start command (0x0002 real-time or 0x0003
// buffered, count N records) makes the box stream to the address and port the command came
// from, at rdt_rate_hz, rdt_sequence 1 for the first record; real-time sends each record in a
// datagram of its own, buffered sends a datagram once rdt_buffer_size records are due (the page's
// comrdtbsiz). A later start (from anyone) replaces it; stop (0x0000) ends it; bias (0x0042)
// tares the present counts. A datagram part-filled when its stream ends (stop, a new start, the
// count reached, a reboot, the end of the data) is sent as it is [U: the manual does not say].
// The state of each internal sample (counts, status word) comes from a callback, so the twin, a
// test or a replayed series can feed it.
//
// Faults (deterministic for a seed): per datagram (a record in real-time mode), with the given
// probabilities and mutually exclusive, drop / duplicate / reorder (sent after the next one) /
// corrupt (wrong length); scheduled in emulator time, silence (the network is down both ways for
// a while: records are generated and lost, commands unanswered) and reboot (streaming ends, the
// box is deaf for boot_time_s, then ft_sequence restarts at 0 and nothing streams until a new
// start). Every record generated is reported to a sink with what was done to its datagram: the
// truth series.
#pragma once

#include <netinet/in.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <random>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "rdt_codec.h"

namespace httplib {
class Server;
}

namespace ftcal::sim {

// The transducer's state at one internal sample.
struct AtiDeviceSample {
  std::array<std::int32_t, 6> counts{};  // Fx Fy Fz Tx Ty Tz, before the software bias
  std::uint32_t status = 0;
};
// Supplies internal sample `ft_sample` (counted from power-up), `t_s` = its time in seconds
// since the emulator's construction (continuous across reboots, for feeding a scenario).
using AtiStateSource = std::function<AtiDeviceSample(std::uint64_t ft_sample, double t_s)>;

enum class AtiFault : std::uint8_t {
  kNone = 0,
  kDrop = 1,       // not sent
  kDuplicate = 2,  // sent twice, back to back
  kReorder = 3,    // sent after the next record
  kCorrupt = 4,    // sent with a wrong length (truncated or padded)
  kSilent = 5,     // lost: the network was down (a scheduled silence)
};
const char* AtiFaultName(AtiFault fault);

struct AtiScheduledEvent {
  enum class Kind { kSilence, kReboot };
  Kind kind = Kind::kSilence;
  double at_s = 0;        // emulator time (s since construction)
  double duration_s = 0;  // silence length; ignored for a reboot (boot_time_s applies)
};

struct AtiFaultOptions {
  std::uint64_t seed = 1;
  // Probability per datagram of each fault (exclusive; their sum must be <= 1).
  double drop = 0, duplicate = 0, reorder = 0, corrupt = 0;
  std::vector<AtiScheduledEvent> events;
  double boot_time_s = 0.3;
};

struct AtiEmulatorOptions {
  std::string name = "HL";  // for messages and the page's cfgnam
  std::string address = "127.0.1.1";
  std::uint16_t rdt_port = rdt::kUdpPort;
  std::uint16_t http_port = 8080;  // 0: no calibration page
  double counts_per_force = 1e6;
  double counts_per_torque = 1e6;
  std::array<double, 6> rated_range{130, 130, 400, 10, 10, 10};
  int rdt_rate_hz = 7000;         // comrdtrate, 1..7000
  double counter_rate_ppm = 0.0;  // the box's crystal: its 7 kHz counter runs this fast
  // comrdtbsiz, records per datagram in buffered mode, 1..40; 0: rdt::DefaultRecordsPerDatagram
  // of the rate (what ftcal's config assumes when it does not say).
  int rdt_buffer_size = 0;
  int send_buffer_bytes = 1 << 20;
  AtiFaultOptions faults;
};

// One generated record and what was done with it.
struct AtiEmitted {
  double t_s = 0;            // emulator time of the record's internal sample
  std::uint32_t stream = 0;  // 1 for the first start command answered, +1 per start
  rdt::Record record;
  AtiFault fault = AtiFault::kNone;  // what was done to its datagram
  std::uint32_t datagram = 0;        // 1 for the box's first datagram, +1 per datagram
};
using AtiEmitSink = std::function<void(const AtiEmitted&)>;

struct AtiEmulatorCounters {
  std::uint64_t commands = 0;          // valid requests received
  std::uint64_t bad_commands = 0;      // undecodable datagrams on the RDT port
  std::uint64_t ignored_commands = 0;  // received while silent or booting
  std::uint64_t starts = 0;
  std::uint64_t stops = 0;
  std::uint64_t records = 0;          // generated while streaming
  std::uint64_t datagrams = 0;        // sent (a duplicate counts twice)
  std::uint64_t buffered_starts = 0;  // starts in buffered mode (0x0003)
  std::uint64_t send_errors = 0;
  std::uint64_t http_requests = 0;        // pages served
  std::array<std::uint64_t, 6> faults{};  // records, by AtiFault of their datagram
  std::uint64_t reboots = 0;
};

class AtiEmulatorError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class AtiEmulator {
 public:
  using Clock = std::chrono::steady_clock;

  // Binds the RDT socket and starts the HTTP page. Throws AtiEmulatorError naming the address
  // and port when either cannot be bound, or an option that is out of range.
  AtiEmulator(AtiEmulatorOptions options, AtiStateSource source, AtiEmitSink sink = nullptr);
  ~AtiEmulator();
  AtiEmulator(const AtiEmulator&) = delete;
  AtiEmulator& operator=(const AtiEmulator&) = delete;

  // Handles pending commands, then sends every record due up to `now`. Never blocks.
  void Step(Clock::time_point now);
  // Stops generating records for good (the end of a scenario): flushes a held record, and
  // from now on commands are counted and ignored.
  void EndOfData();

  int fd() const { return fd_; }
  bool streaming() const { return streaming_; }
  AtiEmulatorCounters counters() const;
  const AtiEmulatorOptions& options() const { return options_; }
  // The page served at /netftapi2.xml (§1.4 element names).
  std::string NetFtXml() const;

 private:
  double Seconds(Clock::time_point t) const;
  void HandleCommands(Clock::time_point now);
  void EmitDue(Clock::time_point now);
  // Sends the datagram being filled (a fault drawn when `draw`), or a part-filled one as it is.
  void SendPending(bool draw);
  // Sends what the stream left: the part-filled datagram, then a held (reordered) one.
  void Flush();
  void FlushHeld();
  // Sends the records of one datagram as their (shared) fault says and reports them.
  void Emit(std::vector<AtiEmitted>& records);
  void Send(const std::uint8_t* data, std::size_t size);
  bool SilentAt(double t_s) const;

  AtiEmulatorOptions options_;
  AtiStateSource source_;
  AtiEmitSink sink_;
  int fd_ = -1;
  std::unique_ptr<httplib::Server> http_;
  std::thread http_thread_;

  Clock::time_point created_;
  Clock::time_point power_up_;  // ft_sequence 0
  Clock::time_point booting_until_;
  bool streaming_ = false;
  bool ended_ = false;
  sockaddr_in client_{};
  std::uint32_t stream_ = 0;
  std::uint32_t rdt_sequence_ = 0;
  std::uint32_t remaining_ = 0;  // records left for a count > 0; 0 = unlimited
  bool limited_ = false;
  Clock::time_point stream_start_;
  std::uint64_t stream_records_ = 0;  // generated in this stream (schedules the next one)
  Clock::time_point next_record_;
  std::array<std::int32_t, 6> bias_{};
  std::array<std::int32_t, 6> last_counts_{};  // before the bias, for the next bias command
  int stream_k_ = 1;                           // records per datagram of this stream
  std::vector<AtiEmitted> pending_;            // the datagram being filled
  bool have_held_ = false;
  std::vector<AtiEmitted> held_;  // a datagram held back to be sent after the next one
  std::uint32_t datagram_ = 0;
  std::size_t next_event_ = 0;
  std::mt19937_64 rng_;
  AtiEmulatorCounters counters_;
  std::atomic<std::uint64_t> http_requests_{0};  // the HTTP thread counts here
};

}  // namespace ftcal::sim
