#include "ati_emulator.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <sys/socket.h>
#include <unistd.h>

#include <httplib.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <limits>
#include <sstream>

namespace ftcal::sim {
namespace {

constexpr double kInternalRateHz = 7000.0;  // ft_sequence rate (§1.3)
// A driver that stalls longer than this does not get a burst afterwards: a NetBox keeps its
// output rate, so the records of the stall are never generated (ft_sequence still advances).
constexpr auto kMaxCatchUp = std::chrono::milliseconds(50);
constexpr int kMaxCommandsPerStep = 64;

std::string Where(const AtiEmulatorOptions& o, std::uint16_t port) {
  return o.name + " (" + o.address + ":" + std::to_string(port) + ")";
}

std::int32_t SaturatingSub(std::int32_t a, std::int32_t b) {
  const std::int64_t d = std::int64_t{a} - b;
  return static_cast<std::int32_t>(std::clamp<std::int64_t>(
      d, std::numeric_limits<std::int32_t>::min(), std::numeric_limits<std::int32_t>::max()));
}

}  // namespace

const char* AtiFaultName(AtiFault fault) {
  switch (fault) {
    case AtiFault::kNone:
      return "none";
    case AtiFault::kDrop:
      return "drop";
    case AtiFault::kDuplicate:
      return "duplicate";
    case AtiFault::kReorder:
      return "reorder";
    case AtiFault::kCorrupt:
      return "corrupt";
    case AtiFault::kSilent:
      return "silent";
  }
  return "?";
}

AtiEmulator::AtiEmulator(AtiEmulatorOptions options, AtiStateSource source, AtiEmitSink sink)
    : options_(std::move(options)),
      source_(std::move(source)),
      sink_(std::move(sink)),
      created_(Clock::now()),
      power_up_(created_),
      booting_until_(created_),
      rng_(options_.faults.seed) {
  const AtiFaultOptions& f = options_.faults;
  if (!source_) throw AtiEmulatorError(options_.name + ": no state source");
  if (options_.rdt_rate_hz < 1 || options_.rdt_rate_hz > 7000) {
    throw AtiEmulatorError(options_.name + ": rdt_rate_hz " + std::to_string(options_.rdt_rate_hz) +
                           " outside 1..7000");
  }
  if (options_.rdt_buffer_size == 0) {
    options_.rdt_buffer_size = rdt::DefaultRecordsPerDatagram(options_.rdt_rate_hz);
  }
  if (options_.rdt_buffer_size < 1 || options_.rdt_buffer_size > rdt::kMaxRecordsPerDatagram) {
    throw AtiEmulatorError(options_.name + ": rdt_buffer_size " +
                           std::to_string(options_.rdt_buffer_size) + " outside 1..40");
  }
  pending_.reserve(rdt::kMaxRecordsPerDatagram);
  held_.reserve(rdt::kMaxRecordsPerDatagram);
  for (double p : {f.drop, f.duplicate, f.reorder, f.corrupt}) {
    if (!(p >= 0 && p <= 1))
      throw AtiEmulatorError(options_.name + ": fault probability outside [0, 1]");
  }
  if (f.drop + f.duplicate + f.reorder + f.corrupt > 1) {
    throw AtiEmulatorError(options_.name + ": fault probabilities sum to more than 1");
  }
  std::sort(options_.faults.events.begin(), options_.faults.events.end(),
            [](const AtiScheduledEvent& a, const AtiScheduledEvent& b) { return a.at_s < b.at_s; });

  fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd_ < 0) throw AtiEmulatorError(options_.name + ": socket: " + std::strerror(errno));
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(options_.rdt_port);
  if (::inet_pton(AF_INET, options_.address.c_str(), &addr.sin_addr) != 1) {
    ::close(fd_);
    throw AtiEmulatorError(options_.name + ": '" + options_.address + "' is not an IPv4 address");
  }
  const int one = 1;
  ::setsockopt(fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  ::setsockopt(fd_, SOL_SOCKET, SO_SNDBUF, &options_.send_buffer_bytes,
               sizeof options_.send_buffer_bytes);
  if (::bind(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) != 0) {
    const std::string err = std::strerror(errno);
    ::close(fd_);
    throw AtiEmulatorError("cannot bind the RDT endpoint of " + Where(options_, options_.rdt_port) +
                           ": " + err);
  }

  if (options_.http_port != 0) {
    http_ = std::make_unique<httplib::Server>();
    // One worker is plenty for a page read once per connection; the default pool would start
    // a thread per core for each of the six boxes.
    http_->new_task_queue = [] { return new httplib::ThreadPool(1); };
    const std::string page = NetFtXml();
    http_->Get("/netftapi2.xml", [this, page](const httplib::Request&, httplib::Response& res) {
      ++http_requests_;
      res.set_content(page, "text/xml");
    });
    if (!http_->bind_to_port(options_.address, options_.http_port)) {
      ::close(fd_);
      throw AtiEmulatorError("cannot bind the calibration page of " +
                             Where(options_, options_.http_port));
    }
    http_thread_ = std::thread([this] { http_->listen_after_bind(); });
  }
}

AtiEmulator::~AtiEmulator() {
  if (http_) {
    http_->stop();
    if (http_thread_.joinable()) http_thread_.join();
  }
  if (fd_ >= 0) ::close(fd_);
}

AtiEmulatorCounters AtiEmulator::counters() const {
  AtiEmulatorCounters c = counters_;
  c.http_requests = http_requests_.load();
  return c;
}

std::string AtiEmulator::NetFtXml() const {
  std::ostringstream os;
  os.precision(17);
  os << "<?xml version=\"1.0\" encoding=\"ISO-8859-1\"?>\n<netft>\n"
     << "<setserial>TWIN-" << options_.name << "</setserial>\n"
     << "<setcfgsel>0</setcfgsel>\n"
     << "<runrate>7000</runrate>\n"
     << "<runstat>0x00000000</runstat>\n"
     << "<cfgnam>BigAnt twin " << options_.name << " N-Nm</cfgnam>\n"
     << "<cfgcalsel>0</cfgcalsel>\n"
     << "<cfgtfx>0;0;0;0;0;0</cfgtfx>\n"
     << "<cfgcpf>" << options_.counts_per_force << "</cfgcpf>\n"
     << "<cfgcpt>" << options_.counts_per_torque << "</cfgcpt>\n"
     << "<cfgmr>";
  for (int i = 0; i < 6; ++i) os << (i ? ";" : "") << options_.rated_range[i];
  os << "</cfgmr>\n"
     << "<scfgfu>N</scfgfu>\n<scfgtu>Nm</scfgtu>\n"
     << "<comrdte>true</comrdte>\n"
     << "<comrdtrate>" << options_.rdt_rate_hz << "</comrdtrate>\n"
     << "<comrdtbsiz>" << options_.rdt_buffer_size << "</comrdtbsiz>\n"
     << "</netft>\n";
  return os.str();
}

double AtiEmulator::Seconds(Clock::time_point t) const {
  return std::chrono::duration<double>(t - created_).count();
}

bool AtiEmulator::SilentAt(double t_s) const {
  for (const auto& e : options_.faults.events) {
    if (e.kind == AtiScheduledEvent::Kind::kSilence && t_s >= e.at_s &&
        t_s < e.at_s + e.duration_s) {
      return true;
    }
  }
  return false;
}

void AtiEmulator::Step(Clock::time_point now) {
  // Reboots due: the stream ends where the box went down.
  const auto& events = options_.faults.events;
  while (next_event_ < events.size() && events[next_event_].at_s <= Seconds(now)) {
    const AtiScheduledEvent& e = events[next_event_++];
    if (e.kind != AtiScheduledEvent::Kind::kReboot) continue;
    const auto down = created_ + std::chrono::duration_cast<Clock::duration>(
                                     std::chrono::duration<double>(e.at_s));
    EmitDue(down);
    Flush();
    streaming_ = false;
    booting_until_ = down + std::chrono::duration_cast<Clock::duration>(
                                std::chrono::duration<double>(options_.faults.boot_time_s));
    power_up_ = booting_until_;
    bias_ = {};
    ++counters_.reboots;
  }
  HandleCommands(now);
  EmitDue(now);
}

void AtiEmulator::EndOfData() {
  Flush();
  streaming_ = false;
  ended_ = true;
}

void AtiEmulator::HandleCommands(Clock::time_point now) {
  for (int n = 0; n < kMaxCommandsPerStep; ++n) {
    std::uint8_t buf[64];
    sockaddr_in from{};
    socklen_t from_len = sizeof from;
    const ssize_t got = ::recvfrom(fd_, buf, sizeof buf, MSG_DONTWAIT | MSG_TRUNC,
                                   reinterpret_cast<sockaddr*>(&from), &from_len);
    if (got < 0) return;  // EAGAIN: nothing pending (anything else: try next step)
    if (ended_ || now < booting_until_ || SilentAt(Seconds(now))) {
      ++counters_.ignored_commands;
      continue;
    }
    rdt::Request req;
    try {
      req = rdt::DecodeRequest(buf, static_cast<std::size_t>(got));
    } catch (const rdt::RdtError&) {
      ++counters_.bad_commands;
      continue;
    }
    ++counters_.commands;
    switch (req.command) {
      case rdt::Command::kRealtime:
      case rdt::Command::kBuffered:
        EmitDue(now);  // the old stream's records up to now still go to the old client
        Flush();
        client_ = from;
        streaming_ = true;
        ++stream_;
        ++counters_.starts;
        stream_k_ = req.command == rdt::Command::kBuffered ? options_.rdt_buffer_size : 1;
        if (req.command == rdt::Command::kBuffered) ++counters_.buffered_starts;
        rdt_sequence_ = 0;
        stream_start_ = now;
        stream_records_ = 0;
        next_record_ = now;
        limited_ = req.sample_count > 0;
        remaining_ = req.sample_count;
        break;
      case rdt::Command::kStop:
        EmitDue(now);
        Flush();
        streaming_ = false;
        ++counters_.stops;
        break;
      case rdt::Command::kBias:
        bias_ = last_counts_;
        break;
      case rdt::Command::kResetThreshold:
      case rdt::Command::kMultiUnit:  // not emulated: answered with nothing
        break;
    }
  }
}

void AtiEmulator::EmitDue(Clock::time_point now) {
  if (!streaming_ || ended_) return;
  if (now - next_record_ > kMaxCatchUp) {
    // Skip the stall (see kMaxCatchUp): resume the schedule at now.
    stream_start_ = now;
    stream_records_ = 0;
    next_record_ = now;
  }
  const double period_ns = 1e9 / options_.rdt_rate_hz;
  while (streaming_ && next_record_ <= now) {
    const Clock::time_point t = next_record_;
    ++stream_records_;
    next_record_ = stream_start_ + std::chrono::nanoseconds(static_cast<std::int64_t>(
                                       std::llround(stream_records_ * period_ns)));
    if (t < power_up_) continue;  // cannot happen after a start, kept for safety

    const auto ft_index =
        static_cast<std::uint64_t>(std::chrono::duration<double>(t - power_up_).count() *
                                   kInternalRateHz * (1.0 + 1e-6 * options_.counter_rate_ppm));
    AtiEmitted e;
    e.t_s = Seconds(t);
    e.stream = stream_;
    const AtiDeviceSample s = source_(ft_index, e.t_s);
    last_counts_ = s.counts;
    e.record.rdt_sequence = ++rdt_sequence_;
    e.record.ft_sequence = static_cast<std::uint32_t>(ft_index);
    e.record.status = s.status;
    for (int i = 0; i < 6; ++i) e.record.counts[i] = SaturatingSub(s.counts[i], bias_[i]);
    ++counters_.records;
    pending_.push_back(e);
    if (static_cast<int>(pending_.size()) == stream_k_) SendPending(/*draw=*/true);
    if (limited_ && --remaining_ == 0) {
      Flush();
      streaming_ = false;
    }
  }
}

void AtiEmulator::SendPending(bool draw) {
  if (pending_.empty()) return;
  const AtiFaultOptions& f = options_.faults;
  AtiFault fault = AtiFault::kNone;
  // The datagram leaves with its last record: the network's state then decides.
  if (SilentAt(pending_.back().t_s)) {
    fault = AtiFault::kSilent;
  } else if (draw && !have_held_) {  // the datagram after a held one goes out as it is
    std::uniform_real_distribution<double> uniform(0.0, 1.0);
    const double u = uniform(rng_);
    double edge = f.drop;
    if (u < edge) {
      fault = AtiFault::kDrop;
    } else if (u < (edge += f.duplicate)) {
      fault = AtiFault::kDuplicate;
    } else if (u < (edge += f.reorder)) {
      fault = AtiFault::kReorder;
    } else if (u < (edge += f.corrupt)) {
      fault = AtiFault::kCorrupt;
    }
  }
  ++datagram_;
  for (AtiEmitted& e : pending_) {
    e.fault = fault;
    e.datagram = datagram_;
  }
  if (fault == AtiFault::kReorder) {
    held_.swap(pending_);
    have_held_ = true;
  } else {
    Emit(pending_);
    if (fault == AtiFault::kNone && have_held_) {
      have_held_ = false;
      Emit(held_);
      held_.clear();
    }
  }
  pending_.clear();
}

void AtiEmulator::Flush() {
  SendPending(/*draw=*/false);
  FlushHeld();
}

// A datagram held back for reordering when its stream ends: nothing overtook it, so it goes out
// in order and the truth says so.
void AtiEmulator::FlushHeld() {
  if (!have_held_) return;
  have_held_ = false;
  for (AtiEmitted& e : held_) e.fault = AtiFault::kNone;
  Emit(held_);
  held_.clear();
}

// Sends one datagram's records as their fault says (a corrupt one 1..35 bytes short or long)
// and reports them.
void AtiEmulator::Emit(std::vector<AtiEmitted>& records) {
  std::uint8_t buf[rdt::kMaxDatagramBytes + rdt::kRecordBytes];
  const std::size_t bytes = records.size() * rdt::kRecordBytes;
  for (std::size_t i = 0; i < records.size(); ++i) {
    rdt::EncodeRecord(records[i].record, buf + i * rdt::kRecordBytes);
  }
  const AtiFault fault = records.front().fault;
  counters_.faults[static_cast<int>(fault)] += records.size();
  switch (fault) {
    case AtiFault::kDrop:
    case AtiFault::kSilent:
      break;
    case AtiFault::kDuplicate:
      Send(buf, bytes);
      Send(buf, bytes);
      break;
    case AtiFault::kCorrupt: {
      const auto by = 1 + static_cast<std::size_t>(rng_() % (rdt::kRecordBytes - 1));
      const bool longer = (rng_() & 1u) != 0;
      if (longer) {
        for (std::size_t i = bytes; i < bytes + by; ++i) buf[i] = static_cast<std::uint8_t>(rng_());
      }
      Send(buf, longer ? bytes + by : bytes - by);
      break;
    }
    case AtiFault::kNone:
    case AtiFault::kReorder:
      Send(buf, bytes);
      break;
  }
  if (sink_) {
    for (const AtiEmitted& e : records) sink_(e);
  }
}

void AtiEmulator::Send(const std::uint8_t* data, std::size_t size) {
  const ssize_t sent = ::sendto(fd_, data, size, MSG_DONTWAIT,
                                reinterpret_cast<const sockaddr*>(&client_), sizeof client_);
  if (sent == static_cast<ssize_t>(size)) {
    ++counters_.datagrams;
  } else {
    // A full send buffer or a refused port (a client gone): the datagram is lost on the wire,
    // as it would be from a real box.
    ++counters_.send_errors;
  }
}

}  // namespace ftcal::sim
