#include "rdt_codec.h"

#include <pugixml.hpp>

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <sstream>

namespace ftcal::rdt {
namespace {

std::uint16_t GetU16Be(const std::uint8_t* p) {
  return static_cast<std::uint16_t>((p[0] << 8) | p[1]);
}
std::uint32_t GetU32Be(const std::uint8_t* p) {
  return (std::uint32_t{p[0]} << 24) | (std::uint32_t{p[1]} << 16) | (std::uint32_t{p[2]} << 8) |
         std::uint32_t{p[3]};
}
void PutU16Be(std::uint16_t v, std::uint8_t* p) {
  p[0] = static_cast<std::uint8_t>(v >> 8);
  p[1] = static_cast<std::uint8_t>(v);
}
void PutU32Be(std::uint32_t v, std::uint8_t* p) {
  p[0] = static_cast<std::uint8_t>(v >> 24);
  p[1] = static_cast<std::uint8_t>(v >> 16);
  p[2] = static_cast<std::uint8_t>(v >> 8);
  p[3] = static_cast<std::uint8_t>(v);
}

bool IsKnownCommand(std::uint16_t c) {
  switch (static_cast<Command>(c)) {
    case Command::kStop:
    case Command::kRealtime:
    case Command::kBuffered:
    case Command::kMultiUnit:
    case Command::kResetThreshold:
    case Command::kBias:
      return true;
  }
  return false;
}

std::string_view Trim(std::string_view s) {
  const char* ws = " \t\r\n";
  const auto b = s.find_first_not_of(ws);
  if (b == std::string_view::npos) return {};
  const auto e = s.find_last_not_of(ws);
  return s.substr(b, e - b + 1);
}

[[noreturn]] void Fail(std::string_view source, std::string_view field, std::string_view what) {
  std::ostringstream os;
  os << source << ": <" << field << "> " << what;
  throw RdtError(os.str());
}

double ParseDouble(std::string_view text, std::string_view source, std::string_view field) {
  const std::string_view t = Trim(text);
  double v = 0;
  const auto [ptr, ec] = std::from_chars(t.data(), t.data() + t.size(), v);
  if (t.empty() || ec != std::errc() || ptr != t.data() + t.size() || !std::isfinite(v)) {
    Fail(source, field, "is not a finite number: '" + std::string(text) + "'");
  }
  return v;
}

long long ParseInt(std::string_view text, std::string_view source, std::string_view field,
                   int base = 10) {
  std::string_view t = Trim(text);
  if (base == 16 && t.size() > 2 && t[0] == '0' && (t[1] == 'x' || t[1] == 'X')) t.remove_prefix(2);
  long long v = 0;
  const auto [ptr, ec] = std::from_chars(t.data(), t.data() + t.size(), v, base);
  if (t.empty() || ec != std::errc() || ptr != t.data() + t.size()) {
    Fail(source, field, "is not an integer: '" + std::string(text) + "'");
  }
  return v;
}

}  // namespace

int DefaultRecordsPerDatagram(int rdt_rate_hz) {
  const long long k = std::llround(rdt_rate_hz / 1000.0);
  return static_cast<int>(std::clamp<long long>(k, 1, kMaxRecordsPerDatagram));
}

std::array<std::uint8_t, kRequestBytes> EncodeRequest(Command command, std::uint32_t sample_count) {
  std::array<std::uint8_t, kRequestBytes> out{};
  PutU16Be(kRequestHeader, out.data());
  PutU16Be(static_cast<std::uint16_t>(command), out.data() + 2);
  PutU32Be(sample_count, out.data() + 4);
  return out;
}

Request DecodeRequest(const std::uint8_t* data, std::size_t size) {
  if (data == nullptr || size != kRequestBytes) {
    throw RdtError("RDT request: length " + std::to_string(size) + " bytes, expected 8");
  }
  const std::uint16_t header = GetU16Be(data);
  if (header != kRequestHeader) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "RDT request: header 0x%04X, expected 0x1234", header);
    throw RdtError(buf);
  }
  const std::uint16_t command = GetU16Be(data + 2);
  if (!IsKnownCommand(command)) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "RDT request: unknown command 0x%04X", command);
    throw RdtError(buf);
  }
  return Request{static_cast<Command>(command), GetU32Be(data + 4)};
}

Record DecodeRecord(const std::uint8_t* p) {
  Record r;
  r.rdt_sequence = GetU32Be(p);
  r.ft_sequence = GetU32Be(p + 4);
  r.status = GetU32Be(p + 8);
  for (int i = 0; i < 6; ++i) {
    // Two's complement by conversion: well defined since C++20 and what every C++17
    // compiler does; static_cast keeps it explicit.
    r.counts[i] = static_cast<std::int32_t>(GetU32Be(p + 12 + 4 * i));
  }
  return r;
}

void EncodeRecord(const Record& r, std::uint8_t* p) {
  PutU32Be(r.rdt_sequence, p);
  PutU32Be(r.ft_sequence, p + 4);
  PutU32Be(r.status, p + 8);
  for (int i = 0; i < 6; ++i) PutU32Be(static_cast<std::uint32_t>(r.counts[i]), p + 12 + 4 * i);
}

std::vector<Record> DecodeDatagram(const std::uint8_t* data, std::size_t size) {
  if (size == 0 || size % kRecordBytes != 0 || data == nullptr) {
    throw RdtError("RDT datagram: length " + std::to_string(size) +
                   " bytes is not a positive multiple of the 36-byte record");
  }
  std::vector<Record> records(size / kRecordBytes);
  for (std::size_t k = 0; k < records.size(); ++k) {
    records[k] = DecodeRecord(data + k * kRecordBytes);
  }
  return records;
}

std::vector<std::uint8_t> EncodeDatagram(const std::vector<Record>& records) {
  std::vector<std::uint8_t> out(records.size() * kRecordBytes);
  for (std::size_t k = 0; k < records.size(); ++k) {
    EncodeRecord(records[k], out.data() + k * kRecordBytes);
  }
  return out;
}

SequenceTracker::Result SequenceTracker::Begin(Verdict verdict, std::uint32_t rdt_sequence,
                                               std::uint32_t ft_sequence) {
  seen_.reset();
  seen_.set(0);
  started_ = true;
  last_ = rdt_sequence;
  last_ft_ = ft_sequence;
  ++accepted_;
  lost_ += rdt_sequence - 1;
  return {verdict, rdt_sequence - 1};
}

SequenceTracker::Result SequenceTracker::Update(std::uint32_t rdt_sequence,
                                                std::uint32_t ft_sequence) {
  const bool in_start_window = rdt_sequence >= 1 && rdt_sequence <= kStartWindow;
  if (!started_) {
    if (in_start_window) return Begin(Verdict::kStart, rdt_sequence, ft_sequence);
    ++stale_;
    return {Verdict::kStale, 0};
  }
  // Modular difference: correct across the 2^32 wrap as long as fewer than 2^31 records
  // separate the two.
  const auto delta = static_cast<std::int32_t>(rdt_sequence - last_);
  if (delta == 0) {
    ++duplicates_;
    return {Verdict::kDuplicate, 0};
  }
  if (delta < 0) {
    if (in_start_window && static_cast<std::int32_t>(ft_sequence - last_ft_) > 0) {
      ++restarts_;
      return Begin(Verdict::kRestart, rdt_sequence, ft_sequence);
    }
    // Within the window the tracker knows whether it took this sequence already (a duplicated
    // datagram) or counted it lost (a reordered one, arriving late).
    const auto behind = static_cast<std::uint32_t>(-static_cast<std::int64_t>(delta));
    if (behind < kDuplicateWindow && seen_.test(behind)) {
      ++duplicates_;
      return {Verdict::kDuplicate, 0};
    }
    ++late_;
    return {Verdict::kLate, 0};
  }
  // Ahead by sequence but sampled before the newest accepted: a straggler of the stream that a
  // kRestart left behind.
  if (static_cast<std::int32_t>(ft_sequence - last_ft_) < 0) {
    ++late_;
    return {Verdict::kLate, 0};
  }
  last_ = rdt_sequence;
  last_ft_ = ft_sequence;
  if (static_cast<std::uint32_t>(delta) < kDuplicateWindow) {
    seen_ <<= static_cast<std::size_t>(delta);
  } else {
    seen_.reset();
  }
  seen_.set(0);
  ++accepted_;
  if (delta == 1) return {Verdict::kNext, 0};
  const auto missing = static_cast<std::uint32_t>(delta - 1);
  lost_ += missing;
  return {Verdict::kGap, missing};
}

void SequenceTracker::Reset() {
  seen_.reset();
  started_ = false;
  last_ = 0;
  last_ft_ = 0;
}

Vector6d CountsToWrench(const std::array<std::int32_t, 6>& counts, double counts_per_force,
                        double counts_per_torque, int sign) {
  if (!(std::isfinite(counts_per_force) && counts_per_force > 0)) {
    throw RdtError("counts per force must be positive and finite, got " +
                   std::to_string(counts_per_force));
  }
  if (!(std::isfinite(counts_per_torque) && counts_per_torque > 0)) {
    throw RdtError("counts per torque must be positive and finite, got " +
                   std::to_string(counts_per_torque));
  }
  if (sign != 1 && sign != -1) {
    throw RdtError("transducer sign must be +1 or -1, got " + std::to_string(sign));
  }
  // To double before the sign: -1 * INT32_MIN overflows in int (found by rdt_fuzz).
  Vector6d w;
  for (int i = 0; i < 3; ++i) w(i) = sign * (static_cast<double>(counts[i]) / counts_per_force);
  for (int i = 3; i < 6; ++i) w(i) = sign * (static_cast<double>(counts[i]) / counts_per_torque);
  return w;
}

StatusSeverity ClassifyStatus(std::uint32_t status) {
  if (status == 0) return StatusSeverity::kOk;
  if (status == (kStatusSummary | kStatusMonitorLatched)) return StatusSeverity::kWarning;
  return StatusSeverity::kError;
}

bool StatusSaturated(std::uint32_t status) { return (status & kStatusSaturation) != 0; }

std::vector<std::string> DescribeStatus(std::uint32_t status) {
  // Bit names from §1.6 (third-party decoder, [S]); index = bit number.
  static const char* const kNames[32] = {
      nullptr,
      "HTTP protocol failure",
      "internal temperature error",
      "reference voltage / power monitoring error",
      "serial link data unavailable",
      "analog board supply too low",
      "analog board supply too high",
      "artificial analog ground out of range",
      "strain gage excitation current too low",
      "strain gage excitation current too high",
      "analog board watchdog timeout",
      "serial flash (SPI) failure",
      "serial EEPROM (I2C) failure",
      "stack check error",
      "watchdog timeout",
      nullptr,
      "monitor condition latched",
      "transducer saturation or A/D error",
      "DeviceNet protocol failure",
      "EtherNet/IP protocol failure",
      "RDT communication error",
      "CAN communication error",
      "network communication failure",
      "configuration incompatible with calibration",
      "settings validation error",
      "halted because of configuration errors",
      "program memory verification error",
      "serial link communication error",
      "analog board error",
      "digital board error",
      "CPU or RAM error",
      "summary: error or condition present",
  };
  std::vector<std::string> out;
  for (int bit = 31; bit >= 0; --bit) {
    if ((status >> bit) & 1u) {
      out.push_back(kNames[bit] ? kNames[bit]
                                : "bit " + std::to_string(bit) + " (not in the decoded table)");
    }
  }
  return out;
}

bool ExceedsRatedRange(const Vector6d& wrench, const std::array<double, 6>& rated_range) {
  for (int i = 0; i < 6; ++i) {
    // A NaN axis cannot be trusted either.
    if (!(std::abs(wrench(i)) < rated_range[i])) return true;
  }
  return false;
}

void CheckCountsPerUnit(double counts_per_force, double counts_per_torque,
                        const std::array<double, 6>& rated_range, std::string_view source) {
  constexpr double kMinSpan = 1 << 10;
  constexpr double kMaxSpan = 2147483647.0;
  auto check = [&](double cpu, int first_axis, const char* field, const char* unit) {
    double smallest = rated_range[first_axis], largest = rated_range[first_axis];
    for (int i = first_axis; i < first_axis + 3; ++i) {
      smallest = std::min(smallest, rated_range[i]);
      largest = std::max(largest, rated_range[i]);
    }
    const double lo = kMinSpan / smallest, hi = kMaxSpan / largest;
    if (!(cpu >= lo && cpu <= hi)) {
      std::ostringstream os;
      os << source << ": " << field << " " << cpu << " counts/" << unit
         << " is outside the plausible range [" << lo << ", " << hi << "] for rated ranges of "
         << smallest << " to " << largest << " " << unit << " (each must span 2^10 to 2^31 counts)";
      throw RdtError(os.str());
    }
  };
  check(counts_per_force, 0, "counts per force (cfgcpf)", "N");
  check(counts_per_torque, 3, "counts per torque (cfgcpt)", "Nm");
}

NetFtConfig ParseNetFtXml(std::string_view xml, std::string_view source) {
  pugi::xml_document doc;
  const pugi::xml_parse_result parsed = doc.load_buffer(xml.data(), xml.size());
  if (!parsed) {
    std::ostringstream os;
    os << source << ": malformed XML at byte " << parsed.offset << ": " << parsed.description();
    throw RdtError(os.str());
  }
  const pugi::xml_node root = doc.child("netft");
  if (!root) throw RdtError(std::string(source) + ": no <netft> root element");

  auto required = [&](const char* name) -> std::string_view {
    const pugi::xml_node n = root.child(name);
    if (!n) Fail(source, name, "is missing");
    return n.child_value();
  };
  auto optional = [&](const char* name) -> std::optional<std::string_view> {
    const pugi::xml_node n = root.child(name);
    if (!n) return std::nullopt;
    return std::string_view(n.child_value());
  };

  NetFtConfig c;
  c.counts_per_force = ParseDouble(required("cfgcpf"), source, "cfgcpf");
  c.counts_per_torque = ParseDouble(required("cfgcpt"), source, "cfgcpt");
  if (c.counts_per_force <= 0) Fail(source, "cfgcpf", "must be positive");
  if (c.counts_per_torque <= 0) Fail(source, "cfgcpt", "must be positive");

  c.force_unit = std::string(Trim(required("scfgfu")));
  c.torque_unit = std::string(Trim(required("scfgtu")));
  if (c.force_unit != "N") {
    Fail(source, "scfgfu",
         "force unit is '" + c.force_unit +
             "'; only N is accepted (set the Net F/T configuration to N, Nm)");
  }
  if (c.torque_unit != "Nm") {
    Fail(source, "scfgtu",
         "torque unit is '" + c.torque_unit +
             "'; only Nm is accepted (set the Net F/T configuration to N, Nm)");
  }

  const std::string_view mr = required("cfgmr");
  std::size_t axis = 0, begin = 0;
  while (true) {
    const std::size_t end = mr.find(';', begin);
    const std::string_view item =
        mr.substr(begin, end == std::string_view::npos ? mr.npos : end - begin);
    if (axis == 6) Fail(source, "cfgmr", "has more than 6 values: '" + std::string(mr) + "'");
    c.rated_range[axis] = ParseDouble(item, source, "cfgmr");
    if (c.rated_range[axis] <= 0) {
      Fail(source, "cfgmr", "rated range of axis " + std::to_string(axis) + " must be positive");
    }
    ++axis;
    if (end == std::string_view::npos) break;
    begin = end + 1;
  }
  if (axis != 6) Fail(source, "cfgmr", "has " + std::to_string(axis) + " values, expected 6");

  const long long rate = ParseInt(required("comrdtrate"), source, "comrdtrate");
  if (rate <= 0 || rate > 100000)
    Fail(source, "comrdtrate", "out of range: " + std::to_string(rate));
  c.rdt_rate_hz = static_cast<int>(rate);
  const long long sel = ParseInt(required("setcfgsel"), source, "setcfgsel");
  if (sel < 0 || sel > 1000) Fail(source, "setcfgsel", "out of range: " + std::to_string(sel));
  c.active_config = static_cast<int>(sel);

  if (auto v = optional("cfgcalsel")) {
    const long long x = ParseInt(*v, source, "cfgcalsel");
    if (x < 0 || x > 1000) Fail(source, "cfgcalsel", "out of range: " + std::to_string(x));
    c.calibration_index = static_cast<int>(x);
  }
  if (auto v = optional("comrdtbsiz")) {
    const long long x = ParseInt(*v, source, "comrdtbsiz");
    if (x < 1 || x > 10000) Fail(source, "comrdtbsiz", "out of range: " + std::to_string(x));
    c.rdt_buffer_size = static_cast<int>(x);
  }
  if (auto v = optional("runstat")) {
    const long long x = ParseInt(*v, source, "runstat", 16);
    if (x < 0 || x > 0xFFFFFFFFLL) Fail(source, "runstat", "out of range");
    c.run_status = static_cast<std::uint32_t>(x);
  }
  if (auto v = optional("cfgnam")) c.config_name = std::string(Trim(*v));
  CheckCountsPerUnit(c.counts_per_force, c.counts_per_torque, c.rated_range, source);
  return c;
}

}  // namespace ftcal::rdt
