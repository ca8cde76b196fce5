#include "ati_bridge.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>

#include <spdlog/fmt/fmt.h>

#include "ati_transducer.h"
#include "ftcal/legs.h"

namespace ftcal {

using namespace ati_internal;

// ---- LatencyHistogram ----

void LatencyHistogram::Add(std::int64_t ns) {
  const std::int64_t us = std::max<std::int64_t>(0, ns / 1000);
  ++bins_[static_cast<std::size_t>(std::min<std::int64_t>(us, kMaxUs))];
  ++count_;
}

double LatencyHistogram::QuantileUs(double q) const {
  if (count_ == 0) return 0;
  const auto rank = static_cast<std::uint64_t>(std::ceil(q * static_cast<double>(count_)));
  std::uint64_t seen = 0;
  for (int us = 0; us <= kMaxUs; ++us) {
    seen += bins_[static_cast<std::size_t>(us)];
    if (seen >= std::max<std::uint64_t>(rank, 1)) return us + 1;
  }
  return kMaxUs + 1;
}

void LatencyHistogram::Merge(const LatencyHistogram& other) {
  for (std::size_t i = 0; i < bins_.size(); ++i) bins_[i] += other.bins_[i];
  count_ += other.count_;
}

void AtiBridge::LogState(Transducer& t, const char* kind, spdlog::level::level_enum level,
                         const std::string& text) {
  Transducer::KindLog& k = t.state_logs[kind];
  const auto now = Clock::now();
  if (k.logged && now - k.last < kStateLogPeriod) {
    ++k.unlogged;
    return;
  }
  if (k.unlogged > 0) {
    log_->log(level, "{}: {} ({} more times since the last such line)", t.leg, text, k.unlogged);
  } else {
    log_->log(level, "{}: {}", t.leg, text);
  }
  k.logged = true;
  k.last = now;
  k.unlogged = 0;
}

std::string AtiBridge::Problems() const {
  std::string out;
  for (const auto& t : transducers_) {
    if (!t->problem.empty()) out += (out.empty() ? "" : "; ") + t->leg + ": " + t->problem;
  }
  return out;
}

AtiBridge::AtiBridge(const config::Config& config, const std::vector<std::string>& legs,
                     Publisher publish, std::shared_ptr<spdlog::logger> log,
                     AtiBridgeOptions options)
    : options_(options), publish_(std::move(publish)), log_(std::move(log)) {
  if (!publish_) throw AtiBridgeError("ati bridge: no publisher");
  std::vector<std::string> names = legs;
  if (names.empty()) {
    for (const auto& leg : config.robot().leg()) names.push_back(leg.name());
  }
  for (const std::string& name : names) {
    const config::Leg* found = nullptr;
    for (const auto& leg : config.robot().leg()) {
      if (leg.name() == name) found = &leg;
    }
    if (found == nullptr) throw AtiBridgeError("leg '" + name + "' is not in the config");
    if (!found->has_ati())
      throw AtiBridgeError("leg " + name + " has no ati transducer in the config");
    for (const auto& t : transducers_) {
      if (t->leg == name) throw AtiBridgeError("leg " + name + " given twice");
    }
    const config::AtiTransducer& ati = found->ati();
    auto t = std::make_unique<Transducer>();
    t->leg = name;
    t->channel = config.channels().ft_prefix() + name;
    t->address = ati.address();
    if (ati.rdt_port() == 0 || ati.rdt_port() > 65535 || ati.http_port() == 0 ||
        ati.http_port() > 65535) {
      throw AtiBridgeError("leg " + name + ": ati port out of range");
    }
    t->rdt_port = static_cast<std::uint16_t>(ati.rdt_port());
    t->http_port = static_cast<std::uint16_t>(ati.http_port());
    t->url = "http://" + t->address + ":" + std::to_string(t->http_port) + "/netftapi2.xml";
    if (ati.sign() != 1 && ati.sign() != -1) {
      throw AtiBridgeError("leg " + name + ": ati sign must be +1 or -1, got " +
                           std::to_string(ati.sign()));
    }
    t->sign = ati.sign();
    t->device.sin_family = AF_INET;
    t->device.sin_port = htons(t->rdt_port);
    if (::inet_pton(AF_INET, t->address.c_str(), &t->device.sin_addr) != 1) {
      throw AtiBridgeError("leg " + name + ": ati address '" + t->address +
                           "' is not an IPv4 address");
    }
    t->FromConfig(name, ati);

    t->msg.leg = name;
    // Sized for the largest batch once: a batch of fewer records overwrites the front.
    constexpr std::size_t kMaxN = ft_batch_t::MAX_N;
    t->msg.n = ft_batch_t::MAX_N;
    t->msg.sample_utime.resize(kMaxN);
    t->msg.rdt_sequence.resize(kMaxN);
    t->msg.ft_sequence.resize(kMaxN);
    t->msg.status.resize(kMaxN);
    t->msg.counts.assign(kMaxN, std::vector<std::int32_t>(6, 0));
    t->msg.wrench.assign(kMaxN, std::vector<double>(6, 0.0));
    t->msg.gap.resize(kMaxN);
    t->msg.flags.resize(kMaxN);
    t->encoded.resize(static_cast<std::size_t>(t->msg.getEncodedSize()));
    t->msg.n = 0;
    t->slots.resize(kBatch * kSlotBytes);
    for (int i = 0; i < kBatch; ++i) {
      t->iovs[i] = {t->slots.data() + i * kSlotBytes, kSlotBytes};
    }
    transducers_.push_back(std::move(t));
  }
  if (transducers_.empty()) throw AtiBridgeError("no transducers to serve");
}

AtiBridge::~AtiBridge() {
  Stop();
  for (auto& t : transducers_) {
    if (t->fd >= 0) ::close(t->fd);
  }
}

std::size_t AtiBridge::size() const { return transducers_.size(); }
const std::string& AtiBridge::leg(std::size_t i) const { return transducers_.at(i)->leg; }
bool AtiBridge::up(std::size_t i) const { return transducers_.at(i)->up; }
int AtiBridge::records_per_datagram(std::size_t i) const {
  return transducers_.at(i)->records_per_datagram;
}
const AtiTransducerCounters& AtiBridge::counters(std::size_t i) const {
  return transducers_.at(i)->c;
}

bool AtiBridge::AllUp() const {
  for (const auto& t : transducers_) {
    if (!t->up) return false;
  }
  return true;
}

void AtiBridge::ReadCalibration(Transducer& t) {
  const rdt::NetFtConfig page =
      FetchNetFtPage(t.leg, t.address, t.http_port, t.url, options_.http_timeout_s,
                     options_.calibration_page_max_bytes);
  t.TakePage(page, t.leg, t.address, t.url);
  t.calibration_backoff = kCalibrationRetry;
  ++t.c.calibration_reads;
  log_->info("{}: {} counts/N, {} counts/Nm, rated range {} N / {} N*m, RDT {} Hz, {} (from {})",
             t.leg, t.counts_per_force, t.counts_per_torque, t.rated_range[2], t.rated_range[5],
             page.rdt_rate_hz,
             t.records_per_datagram == 1
                 ? std::string("real-time, 1 record per datagram")
                 : fmt::format("buffered, {} records per datagram", t.records_per_datagram),
             t.url);
}

rdt::Command AtiBridge::StartCommand(const Transducer& t) {
  return t.records_per_datagram > 1 ? rdt::Command::kBuffered : rdt::Command::kRealtime;
}

double AtiBridge::SilenceTimeoutS(const Transducer& t) const {
  // A buffered box at a low rate sends a datagram only every k / rate s: never call that silence.
  if (t.records_per_datagram > 1 && t.rdt_rate_hz > 0) {
    return std::max(options_.silence_timeout_s, 3.0 * t.records_per_datagram / t.rdt_rate_hz);
  }
  return options_.silence_timeout_s;
}

void AtiBridge::Start() {
  if (started_) return;
  for (auto& tp : transducers_) {
    Transducer& t = *tp;
    // Throws: no streaming without counts per unit, nor against a box set up otherwise.
    if (!t.calibrated || t.page_needed) ReadCalibration(t);

    t.fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (t.fd < 0) throw AtiBridgeError("leg " + t.leg + ": socket: " + std::strerror(errno));
    // Large receive buffer: a scheduling hiccup of the bridge must not cost records. SO_RCVBUF
    // is capped at net.core.rmem_max (~200 kB by default, ~40 ms at 7000 records/s, since each
    // datagram is charged its whole buffer); SO_RCVBUFFORCE passes the cap where we have
    // CAP_NET_ADMIN (as root, or as the owner of our network namespace).
    if (::setsockopt(t.fd, SOL_SOCKET, SO_RCVBUFFORCE, &options_.receive_buffer_bytes,
                     sizeof options_.receive_buffer_bytes) != 0) {
      ::setsockopt(t.fd, SOL_SOCKET, SO_RCVBUF, &options_.receive_buffer_bytes,
                   sizeof options_.receive_buffer_bytes);
    }
    const int one = 1;
    ::setsockopt(t.fd, SOL_SOCKET, SO_TIMESTAMPNS, &one, sizeof one);
    sockaddr_in any{};
    any.sin_family = AF_INET;
    any.sin_addr.s_addr = htonl(INADDR_ANY);
    any.sin_port = 0;  // ephemeral
    if (::bind(t.fd, reinterpret_cast<const sockaddr*>(&any), sizeof any) != 0) {
      throw AtiBridgeError("leg " + t.leg + ": bind: " + std::strerror(errno));
    }
    int granted = 0;
    socklen_t len = sizeof granted;
    ::getsockopt(t.fd, SOL_SOCKET, SO_RCVBUF, &granted, &len);
    if (granted < options_.receive_buffer_bytes) {
      log_->info("{}: receive buffer {} bytes of the {} asked (raise net.core.rmem_max)", t.leg,
                 granted, options_.receive_buffer_bytes);
    }

    const auto now = Clock::now();
    SendRequest(t, StartCommand(t));
    t.last_record = now;
    t.next_request = now + Seconds(SilenceTimeoutS(t));
    t.backoff_s = SilenceTimeoutS(t);
    t.up = true;  // until it stays silent
  }
  started_ = true;
}

void AtiBridge::SendRequest(Transducer& t, rdt::Command command) {
  const auto bytes = rdt::EncodeRequest(command, 0);
  const ssize_t sent = ::sendto(t.fd, bytes.data(), bytes.size(), MSG_DONTWAIT,
                                reinterpret_cast<const sockaddr*>(&t.device), sizeof t.device);
  if (command == rdt::Command::kRealtime || command == rdt::Command::kBuffered) {
    ++t.c.start_requests;
    t.last_request = Clock::now();
    // The box restarts rdt_sequence at 1 (§1.5).
    t.tracker.Reset();
    t.restart_pending = true;
  }
  if (sent != static_cast<ssize_t>(bytes.size())) {
    ++t.c.send_errors;
    t.problem =
        fmt::format("sending the RDT command 0x{:04x} to {}:{} failed: {}",
                    static_cast<unsigned>(command), t.address, t.rdt_port, std::strerror(errno));
    LogState(t, "send", spdlog::level::warn, t.problem);
  }
}

void AtiBridge::Stop() {
  if (!started_) return;
  for (auto& t : transducers_) {
    if (t->fd >= 0) SendRequest(*t, rdt::Command::kStop);
  }
  started_ = false;
}

int AtiBridge::Poll(int timeout_ms) {
  if (!started_) throw AtiBridgeError("Poll() before Start()");
  std::uint64_t before = 0, after = 0;
  for (const auto& t : transducers_) before += t->c.published;
  Step(timeout_ms);
  for (const auto& t : transducers_) after += t->c.published;
  return static_cast<int>(after - before);
}

void AtiBridge::AddPollFds(std::vector<pollfd>* fds) {
  poll_ns_ = RealtimeNs();
  for (const auto& t : transducers_) fds->push_back({t->fd, POLLIN, 0});
}

void AtiBridge::OnPolled(const pollfd* fds, std::size_t n) {
  if (n != transducers_.size()) throw AtiBridgeError("OnPolled() without AddPollFds()");
  for (std::size_t i = 0; i < n; ++i) {
    // Not readable when poll() last looked, which was after poll_ns_: empty then.
    Transducer& t = *transducers_[i];
    if ((fds[i].revents & POLLIN) == 0) t.drained_at_ns = std::max(t.drained_at_ns, poll_ns_);
  }
  for (std::size_t i = 0; i < n; ++i) {
    if (fds[i].revents & (POLLIN | POLLERR)) HandleSocket(*transducers_[i]);
  }
}

Clock::time_point AtiBridge::NextDeadline() const {
  auto wake = Clock::time_point::max();
  for (const auto& t : transducers_) {
    wake = std::min(wake, std::max(t->last_record + Seconds(SilenceTimeoutS(*t)), t->next_request));
    if (!t->calibrated) wake = std::min(wake, t->next_calibration_try);
  }
  return wake;
}

void AtiBridge::OnDeadline(Clock::time_point now) {
  for (auto& t : transducers_) Service(*t, now);
}

bool AtiBridge::Degraded(std::string* why) {
  if (AllUp()) return false;
  if (why) *why = Problems();
  return true;
}

void AtiBridge::ReportCounters(ServiceStats& stats) {
  std::uint64_t received = 0;
  for (const auto& t : transducers_) received += t->c.received;
  // msgs_in counts device records: catch the stats up (CountIn has no bulk form).
  for (; reported_in_ < received; ++reported_in_) stats.CountIn();
  for (const auto& [name, value] : CounterTable()) stats.Counter(name) = value;
}

void AtiBridge::Service(Transducer& t, Clock::time_point now) {
  if (!t.calibrated && now >= t.next_calibration_try) {
    try {
      ReadCalibration(t);
    } catch (const AtiBridgeError& e) {
      // A box still booting refuses for a while: ask less and less often.
      t.calibration_backoff =
          std::min<Clock::duration>(2 * t.calibration_backoff, kCalibrationRetryMax);
      t.next_calibration_try = now + t.calibration_backoff;
      t.problem = std::string(e.what()) + " (not publishing until it can be read)";
      LogState(t, "calibration", spdlog::level::err, t.problem);
    }
  }
  const auto deadline = std::max(t.last_record + Seconds(SilenceTimeoutS(t)), t.next_request);
  if (now < deadline) return;
  // Records may have arrived since poll() looked (a process descheduled between poll() and
  // here would otherwise take its own lateness for the box's silence).
  HandleSocket(t);
  if (Clock::now() < std::max(t.last_record + Seconds(SilenceTimeoutS(t)), t.next_request)) {
    return;
  }
  if (!t.silent) {
    t.silent = true;
    ++t.c.silences;
    t.problem = fmt::format("no record for {:.0f} ms: sending start again",
                            std::chrono::duration<double, std::milli>(now - t.last_record).count());
    LogState(t, "silent", spdlog::level::warn, t.problem);
  }
  SendRequest(t, StartCommand(t));
  ++t.unanswered;
  if (t.up && t.unanswered >= options_.down_after_requests) {
    t.up = false;
    t.problem =
        fmt::format("the box at {}:{} does not answer: reported down", t.address, t.rdt_port);
    LogState(t, "down", spdlog::level::err, t.problem);
  }
  t.next_request = now + Seconds(t.backoff_s);
  t.backoff_s = std::min(2 * t.backoff_s, options_.max_backoff_s);
}

std::vector<std::pair<std::string, std::int64_t>> AtiBridge::CounterTable() const {
  std::vector<std::pair<std::string, std::int64_t>> out;
  for (const auto& t : transducers_) {
    const AtiTransducerCounters& c = t->c;
    const std::pair<const char*, std::uint64_t> rows[] = {
        {"datagrams", c.datagrams},
        {"received", c.received},
        {"published", c.published},
        {"lost", c.lost},
        {"duplicates", c.duplicates},
        {"late", c.late},
        {"stale", c.stale},
        {"wrong_length", c.wrong_length},
        {"foreign", c.foreign},
        {"uncalibrated", c.uncalibrated},
        {"status_nonzero", c.status_nonzero},
        {"saturated", c.saturated},
        {"start_requests", c.start_requests},
        {"restarts", c.restarts},
        {"silences", c.silences},
        {"reboots", c.reboots},
        {"calibration_reads", c.calibration_reads},
        {"recv_errors", c.recv_errors},
        {"send_errors", c.send_errors},
        {"publish_errors", c.publish_errors},
        {"held_in_stack", c.held_in_stack},
        {"up", t->up ? 1u : 0u},
    };
    for (const auto& [name, value] : rows) {
      out.emplace_back(t->leg + "." + name, static_cast<std::int64_t>(value));
    }
  }
  out.emplace_back("latency_p50_us", static_cast<std::int64_t>(user_latency_.QuantileUs(0.5)));
  out.emplace_back("latency_p99_us", static_cast<std::int64_t>(user_latency_.QuantileUs(0.99)));
  out.emplace_back("kernel_latency_p50_us",
                   static_cast<std::int64_t>(kernel_latency_.QuantileUs(0.5)));
  out.emplace_back("kernel_latency_p99_us",
                   static_cast<std::int64_t>(kernel_latency_.QuantileUs(0.99)));
  return out;
}

}  // namespace ftcal
