// ATI Net F/T Raw Data Transfer (RDT) codec: requests, records, sequence tracking, unit
// conversion, status word and the calibration page netftapi2.xml.
//
// Pure bytes in, structs out: no sockets here, so the bridge and the simulator's NetBox
// emulation share it and tests drive it without a network. Wire facts and their confidence
// marks are in docs/device-protocols.md section 1; the references below (§1.x) point there.
#pragma once

#include <Eigen/Core>

#include <array>
#include <bitset>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace ftcal::rdt {

using Vector6d = Eigen::Matrix<double, 6, 1>;

// Bad bytes or a bad calibration page; the message names the field, the value and where.
class RdtError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

constexpr std::uint16_t kUdpPort = 49152;
constexpr std::uint16_t kRequestHeader = 0x1234;
constexpr std::size_t kRequestBytes = 8;
constexpr std::size_t kRecordBytes = 36;
// Buffered mode (§1.3): a datagram carries k records, k being the box's RDT buffer size
// (comrdtbsiz), 1..40 on the Net F/T.
constexpr int kMaxRecordsPerDatagram = 40;
constexpr std::size_t kMaxDatagramBytes = kMaxRecordsPerDatagram * kRecordBytes;

// The records per datagram a box at `rdt_rate_hz` records/s should send when the config does not
// say: about one datagram per millisecond, rate / 1000 rounded, at least 1 (1: real-time mode).
int DefaultRecordsPerDatagram(int rdt_rate_hz);

// RDT commands (§1.2, the manual's table). 0x0001 of ATI's old Java sample is deliberately
// absent: the manual does not list it.
enum class Command : std::uint16_t {
  kStop = 0x0000,
  kRealtime = 0x0002,
  kBuffered = 0x0003,
  kMultiUnit = 0x0004,
  kResetThreshold = 0x0041,
  kBias = 0x0042,
};

// The 8-byte request, BE: header 0x1234, command, sample count (0 = until stopped).
std::array<std::uint8_t, kRequestBytes> EncodeRequest(Command command,
                                                      std::uint32_t sample_count = 0);

// Inverse of EncodeRequest (for the simulator's NetBox). Throws RdtError on a wrong length,
// header or an unknown command.
struct Request {
  Command command;
  std::uint32_t sample_count;
};
Request DecodeRequest(const std::uint8_t* data, std::size_t size);

// One 36-byte record (§1.3), fields as the device sent them.
struct Record {
  std::uint32_t rdt_sequence = 0;
  std::uint32_t ft_sequence = 0;
  std::uint32_t status = 0;
  std::array<std::int32_t, 6> counts{};  // Fx Fy Fz Tx Ty Tz
};

// Splits a datagram into its k records (k >= 1). Throws RdtError naming the length when it is
// not a positive multiple of 36.
std::vector<Record> DecodeDatagram(const std::uint8_t* data, std::size_t size);

// One record from exactly kRecordBytes bytes at `data` (the caller has checked the length):
// the allocation-free path of the bridge's receive loop.
Record DecodeRecord(const std::uint8_t* data);
// Writes one record's kRecordBytes bytes to `out` (the emulator's allocation-free path).
void EncodeRecord(const Record& record, std::uint8_t* out);

// Records back to back, BE (what a NetBox sends; used by the simulator).
std::vector<std::uint8_t> EncodeDatagram(const std::vector<Record>& records);

// Loss, duplicate and reordering detection on rdt_sequence (§1.5), modular 32-bit.
//
// After Reset() (call it whenever a start command is sent) the tracker waits for the new
// stream: a record whose sequence is in [1, kStartWindow] is taken as its start (leading loss
// = sequence - 1); anything else is a leftover of the previous stream still in flight and is
// dropped, since locking onto it would make the new stream look "late" for a long time.
//
// A record behind the newest accepted one is either late (reordered) or the start of a newer
// stream (two start commands were in flight and the box served the second after the tracker had
// locked onto the first). rdt_sequence alone cannot tell them apart: "2, 1" is the first two
// records swapped or record 1 of a new stream. ft_sequence can: the box's sample counter does not
// go back between streams, and a reordered record was sampled before the one that overtook it.
// So a backward record is a restart only when its sequence is in the start window and its
// ft_sequence is newer than the newest accepted record's; otherwise it is late and never
// accepted after a newer one. For the same reason a record ahead by sequence but behind by
// ft_sequence (a straggler of the previous stream after a restart) is late.
//
// Any other backward record is a duplicate when the tracker accepted its sequence before (within
// the last kDuplicateWindow sequences) and late when it did not (it was counted lost). In
// buffered mode a duplicated datagram of k records arrives k-1 records behind the newest: each of
// its records is a duplicate, as a duplicated real-time record is.
class SequenceTracker {
 public:
  static constexpr std::uint32_t kStartWindow = 1024;
  static constexpr std::uint32_t kDuplicateWindow = 256;  // > 2 datagrams of 40 records

  enum class Verdict {
    kStart,      // first record of the stream: accept
    kNext,       // sequence advanced by exactly 1: accept
    kGap,        // advanced by more than 1: accept, `lost` records are missing before it
    kRestart,    // a newer stream began without a Reset(): accept as its first record
    kDuplicate,  // same sequence as the last accepted one: drop
    kLate,       // older than the last accepted one (reordered): drop
    kStale,      // before a start was seen, outside the start window: drop
  };
  struct Result {
    Verdict verdict;
    std::uint32_t lost;  // records missing just before this one (kStart/kGap/kRestart), else 0
    bool accept() const {
      return verdict == Verdict::kStart || verdict == Verdict::kNext || verdict == Verdict::kGap ||
             verdict == Verdict::kRestart;
    }
  };

  SequenceTracker() = default;
  Result Update(std::uint32_t rdt_sequence, std::uint32_t ft_sequence);
  void Reset();

  std::uint64_t accepted() const { return accepted_; }
  std::uint64_t lost() const { return lost_; }
  std::uint64_t duplicates() const { return duplicates_; }
  std::uint64_t late() const { return late_; }
  std::uint64_t stale() const { return stale_; }
  std::uint64_t restarts() const { return restarts_; }  // kRestart verdicts
  bool started() const { return started_; }
  std::uint32_t last_sequence() const { return last_; }

 private:
  Result Begin(Verdict verdict, std::uint32_t rdt_sequence, std::uint32_t ft_sequence);
  // Bit d set: sequence last_ - d was accepted in this stream (cleared on every new stream).
  std::bitset<kDuplicateWindow> seen_;
  bool started_ = false;
  std::uint32_t last_ = 0;
  std::uint32_t last_ft_ = 0;  // ft_sequence of the newest accepted record
  std::uint64_t accepted_ = 0, lost_ = 0, duplicates_ = 0, late_ = 0, stale_ = 0, restarts_ = 0;
};

// counts -> [f (N); tau (N*m)] = sign * [counts_f / cpf; counts_t / cpt] (§1.4). sign is the
// config's +1/-1; cpf and cpt must be positive and finite. Throws RdtError otherwise.
Vector6d CountsToWrench(const std::array<std::int32_t, 6>& counts, double counts_per_force,
                        double counts_per_torque, int sign = 1);

// Status word (§1.6).
constexpr std::uint32_t kStatusSummary = 0x80000000u;
constexpr std::uint32_t kStatusMonitorLatched = 0x00010000u;
constexpr std::uint32_t kStatusSaturation = 0x00020000u;
enum class StatusSeverity { kOk, kWarning, kError };
// 0 -> kOk; exactly summary + monitor latch -> kWarning; anything else -> kError.
StatusSeverity ClassifyStatus(std::uint32_t status);
bool StatusSaturated(std::uint32_t status);
// One text per set bit, highest bit first; bits the table does not name say so.
std::vector<std::string> DescribeStatus(std::uint32_t status);

// True when any axis' magnitude is at or beyond its rated range (same units as the wrench).
bool ExceedsRatedRange(const Vector6d& wrench, const std::array<double, 6>& rated_range);

// The active configuration as read from netftapi2.xml (§1.4, HTTP).
struct NetFtConfig {
  double counts_per_force = 0;              // cfgcpf
  double counts_per_torque = 0;             // cfgcpt
  std::string force_unit;                   // scfgfu, always "N" after parsing
  std::string torque_unit;                  // scfgtu, always "Nm" after parsing
  std::array<double, 6> rated_range{};      // cfgmr, N and N*m
  int rdt_rate_hz = 0;                      // comrdtrate
  int active_config = 0;                    // setcfgsel
  std::optional<int> calibration_index;     // cfgcalsel
  std::optional<int> rdt_buffer_size;       // comrdtbsiz
  std::optional<std::uint32_t> run_status;  // runstat (hex text)
  std::string config_name;                  // cfgnam, may be empty
};

// Counts per unit are plausible when each axis' rated range spans between 2^10 counts (coarser
// is no force/torque sensor) and 2^31 counts (beyond, the rated load would overflow the i32
// counts): a 1e300 cfgcpf (every force read as 0) is refused. Throws RdtError naming `source`,
// the value and the plausible range.
void CheckCountsPerUnit(double counts_per_force, double counts_per_torque,
                        const std::array<double, 6>& rated_range, std::string_view source);

// Parses the page. `source` names it in error messages (e.g. "http://10.0.0.7/netftapi2.xml").
// Throws RdtError on malformed XML, a missing or unparsable required field (cfgcpf, cfgcpt,
// scfgfu, scfgtu, cfgmr, comrdtrate, setcfgsel), counts per unit outside CheckCountsPerUnit's
// range, or units other
// than N and Nm (we refuse rather than convert: the calibration is done in SI).
NetFtConfig ParseNetFtXml(std::string_view xml, std::string_view source);

}  // namespace ftcal::rdt
