#include "ati_bridge.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <httplib.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <map>
#include <mutex>
#include <thread>

#include <spdlog/fmt/fmt.h>

#include "ftcal/device_clock.h"
#include "ftcal/legs.h"

namespace ftcal {
namespace {

using Clock = std::chrono::steady_clock;

constexpr int kBatch = 64;             // datagrams per recvmmsg
constexpr int kMaxBatchesPerCall = 4;  // per socket, before the others get their turn
constexpr std::size_t kSlotBytes =
    1536;  // an Ethernet frame: the largest buffered datagram we take (40 records: 1440 bytes)
static_assert(kSlotBytes > rdt::kMaxDatagramBytes, "a slot must hold the largest datagram");
constexpr auto kCalibrationRetry = std::chrono::seconds(1);
constexpr auto kCalibrationRetryMax = std::chrono::seconds(16);
constexpr auto kStateLogPeriod = std::chrono::seconds(30);
// The Net F/T's internal sample counter (ft_sequence) runs at 7000 Hz whatever the RDT rate
// (docs/device-protocols.md §1.3): the clock each record's sample time is mapped from.
constexpr std::int64_t kFtCounterHz = 7000;

std::int64_t RealtimeNs() {
  timespec ts;
  ::clock_gettime(CLOCK_REALTIME, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
}

Clock::duration Seconds(double s) {
  return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

}  // namespace

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

// ---- one transducer ----

struct AtiBridge::Transducer {
  std::string leg;
  std::string channel;
  std::string address;
  std::uint16_t rdt_port = 0;
  std::uint16_t http_port = 0;
  std::string url;
  int sign = 1;
  sockaddr_in device{};

  bool counts_from_config = false;
  bool range_from_config = false;
  // Records per datagram: the config's (k_from_config), else resolved from the page's rate at
  // the first read (0 until then). 1: real-time mode, else buffered.
  bool k_from_config = false;
  int records_per_datagram = 0;
  int rdt_rate_hz = 0;  // comrdtrate, once a page was read
  // The page is read at start (and again after a reboot) when it supplies something: counts per
  // unit, rated range, the default k, or the buffer size a buffered stream must match.
  bool page_needed = true;
  bool calibrated = false;
  double counts_per_force = 0;
  double counts_per_torque = 0;
  std::array<double, 6> rated_range{};
  Clock::time_point next_calibration_try{};

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
  Clock::time_point last_record{};
  Clock::time_point next_request{};
  Clock::time_point last_request{};
  double backoff_s = 0;
  int unanswered = 0;

  ft_batch_t msg;  // the batch being filled: msg.n records so far
  std::vector<std::uint8_t> encoded;
  std::array<std::int64_t, ft_batch_t::MAX_N> ticks{};  // each batched record's counter, unwrapped
  std::int64_t ft_unwrapped = 0;  // last_ft, unwrapped (a reboot makes it fall)
  DeviceClock clock{DeviceClockOptions{static_cast<double>(kFtCounterHz)}};

  // recvmmsg slots.
  std::vector<std::uint8_t> slots;
  std::array<mmsghdr, kBatch> headers{};
  std::array<iovec, kBatch> iovs{};
  std::array<sockaddr_in, kBatch> sources{};
  std::array<std::array<char, CMSG_SPACE(sizeof(timespec))>, kBatch> controls{};

  AtiTransducerCounters c;
  // What is wrong with this transducer now ("" when streaming and calibrated): the status's
  // last_error.
  std::string problem;
  // State-change lines (silent, down, streaming again, send failures, calibration failures) of
  // a flapping or refusing box: per kind, one line per kStateLogPeriod with the count between.
  struct KindLog {
    Clock::time_point last{};
    bool logged = false;
    std::uint64_t unlogged = 0;
  };
  std::map<std::string, KindLog> state_logs;
  Clock::duration calibration_backoff = kCalibrationRetry;
  // Once-per-kind logging of bad input.
  bool logged_wrong_length = false, logged_duplicate = false, logged_late = false,
       logged_stale = false, logged_status = false, logged_foreign = false,
       logged_saturated = false, logged_publish = false, logged_recv = false;
};

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
    if (ati.has_counts_per_force() != ati.has_counts_per_torque()) {
      throw AtiBridgeError("leg " + name +
                           ": give both counts_per_force and counts_per_torque, or neither");
    }
    if (ati.has_counts_per_force()) {
      if (!(ati.counts_per_force() > 0 && ati.counts_per_torque() > 0 &&
            std::isfinite(ati.counts_per_force()) && std::isfinite(ati.counts_per_torque()))) {
        throw AtiBridgeError("leg " + name + ": counts per unit must be positive and finite");
      }
      t->counts_from_config = true;
      t->calibrated = true;
      t->counts_per_force = ati.counts_per_force();
      t->counts_per_torque = ati.counts_per_torque();
    }
    if (ati.rated_range_size() == 6) {
      t->range_from_config = true;
      for (int i = 0; i < 6; ++i) t->rated_range[static_cast<std::size_t>(i)] = ati.rated_range(i);
    } else if (ati.rated_range_size() != 0) {
      throw AtiBridgeError("leg " + name + ": rated_range needs 6 values, has " +
                           std::to_string(ati.rated_range_size()));
    }
    if (ati.has_records_per_datagram()) {
      const auto k = ati.records_per_datagram();
      if (k < 1 || k > static_cast<unsigned>(rdt::kMaxRecordsPerDatagram)) {
        throw AtiBridgeError("leg " + name + ": records_per_datagram " + std::to_string(k) +
                             " outside 1.." + std::to_string(rdt::kMaxRecordsPerDatagram));
      }
      t->k_from_config = true;
      t->records_per_datagram = static_cast<int>(k);
    }
    t->page_needed = !t->counts_from_config || !t->range_from_config || !t->k_from_config ||
                     t->records_per_datagram > 1;
    if (t->counts_from_config && !t->range_from_config) {
      // Counts from the config but no range: the page still supplies cfgmr.
      t->calibrated = false;
    }
    if (t->counts_from_config && t->range_from_config) {
      try {
        rdt::CheckCountsPerUnit(t->counts_per_force, t->counts_per_torque, t->rated_range,
                                "leg " + name + " (config)");
      } catch (const rdt::RdtError& e) {
        throw AtiBridgeError(e.what());
      }
    }

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
  // One deadline on the whole fetch: httplib's timeouts are per read, so a page trickling a
  // byte at a time would hold start-up for as long as it likes. A watchdog stops the client at
  // the deadline whatever it is doing (connecting, reading headers or body).
  const auto deadline = Clock::now() + Seconds(options_.http_timeout_s);
  httplib::Client client(t.address, t.http_port);
  const auto timeout = std::chrono::duration<double>(options_.http_timeout_s);
  client.set_connection_timeout(std::chrono::duration_cast<std::chrono::microseconds>(timeout));
  client.set_read_timeout(std::chrono::duration_cast<std::chrono::microseconds>(timeout));
  std::mutex mu;
  std::condition_variable cv;
  bool done = false;
  std::atomic<bool> too_slow{false};
  std::thread watchdog([&] {
    std::unique_lock<std::mutex> lock(mu);
    if (!cv.wait_until(lock, deadline, [&] { return done; })) {
      too_slow = true;
      client.stop();
    }
  });
  // The page is a few kB; a bigger one is not a Net F/T page and is not held in memory.
  std::string body;
  bool too_big = false;
  auto res = client.Get("/netftapi2.xml", [&](const char* data, std::size_t n) {
    if (body.size() + n > options_.calibration_page_max_bytes) {
      too_big = true;
      return false;
    }
    body.append(data, n);
    return !too_slow.load();
  });
  {
    std::lock_guard<std::mutex> lock(mu);
    done = true;
  }
  cv.notify_one();
  watchdog.join();
  if (too_big) {
    throw AtiBridgeError("leg " + t.leg + ": calibration page " + t.url + " is larger than " +
                         std::to_string(options_.calibration_page_max_bytes) +
                         " bytes: not a Net F/T page; refused");
  }
  if (too_slow) {
    throw AtiBridgeError("leg " + t.leg + ": calibration page " + t.url +
                         fmt::format(" not read within {} s ({} bytes came): refused",
                                     options_.http_timeout_s, body.size()));
  }
  if (!res) {
    throw AtiBridgeError("leg " + t.leg + ": cannot read the calibration page " + t.url + ": " +
                         httplib::to_string(res.error()));
  }
  if (res->status != 200) {
    throw AtiBridgeError("leg " + t.leg + ": calibration page " + t.url + " answered HTTP " +
                         std::to_string(res->status));
  }
  res->body = std::move(body);
  rdt::NetFtConfig page;
  try {
    page = rdt::ParseNetFtXml(res->body, t.url);
  } catch (const rdt::RdtError& e) {
    throw AtiBridgeError("leg " + t.leg + ": " + e.what());
  }
  const std::array<double, 6> range = t.range_from_config ? t.rated_range : page.rated_range;
  try {
    // The page's own values were checked by the parser; a mix with the config's is checked
    // here.
    rdt::CheckCountsPerUnit(t.counts_from_config ? t.counts_per_force : page.counts_per_force,
                            t.counts_from_config ? t.counts_per_torque : page.counts_per_torque,
                            range, "leg " + t.leg + " (" + t.url + " and the config)");
  } catch (const rdt::RdtError& e) {
    throw AtiBridgeError(e.what());
  }
  CheckRdtSettings(t, page);
  if (!t.counts_from_config) {
    t.counts_per_force = page.counts_per_force;
    t.counts_per_torque = page.counts_per_torque;
  }
  t.rated_range = range;
  t.calibrated = true;
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

void AtiBridge::CheckRdtSettings(Transducer& t, const rdt::NetFtConfig& page) {
  t.rdt_rate_hz = page.rdt_rate_hz;
  std::string why = "the config's records_per_datagram";
  if (!t.k_from_config) {
    why = fmt::format("records_per_datagram by default (comrdtrate {} / 1000, rounded)",
                      page.rdt_rate_hz);
    // Resolved once: the start command's mode depends on it.
    if (t.records_per_datagram == 0) {
      t.records_per_datagram = rdt::DefaultRecordsPerDatagram(page.rdt_rate_hz);
    }
  }
  const int k = t.records_per_datagram;
  // Real-time mode sends one record per datagram whatever the buffer size (§1.2): only buffered
  // mode depends on the box's setting.
  if (k == 1) return;
  const std::string box = fmt::format("leg {}: the box at {} ({})", t.leg, t.address, t.url);
  if (!page.rdt_buffer_size) {
    throw AtiBoxMismatchError(fmt::format(
        "{} does not give its RDT buffer size (comrdtbsiz), and {} is {} (buffered mode): "
        "cannot check it; set records_per_datagram: 1 for real-time mode",
        box, why, k));
  }
  if (*page.rdt_buffer_size != k) {
    throw AtiBoxMismatchError(fmt::format(
        "{} has RDT buffer size (comrdtbsiz) {}, but {} is {}: set the box's buffer size to {} or "
        "the config's records_per_datagram to {} (1: real-time mode)",
        box, *page.rdt_buffer_size, why, k, k, *page.rdt_buffer_size));
  }
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

void AtiBridge::HandleSocket(Transducer& t) {
  // A bounded number of batches per call: a bridge that has fallen behind serves its sockets in
  // turn (poll() returns at once while any has data) instead of draining the first one while
  // the last one's buffer overflows.
  for (int batches = 0; batches < kMaxBatchesPerCall; ++batches) {
    for (int i = 0; i < kBatch; ++i) {
      msghdr& h = t.headers[i].msg_hdr;
      h.msg_name = &t.sources[i];
      h.msg_namelen = sizeof(sockaddr_in);
      h.msg_iov = &t.iovs[i];
      h.msg_iovlen = 1;
      h.msg_control = t.controls[i].data();
      h.msg_controllen = t.controls[i].size();
      h.msg_flags = 0;
    }
    const std::int64_t asked_ns = RealtimeNs();
    const int n = ::recvmmsg(t.fd, t.headers.data(), kBatch, MSG_DONTWAIT, nullptr);
    if (n < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
        // ECONNREFUSED after an ICMP "port unreachable" for our request (the box is down).
        ++t.c.recv_errors;
        if (!t.logged_recv) {
          t.logged_recv = true;
          log_->warn("{}: receive error: {} (counted from now on)", t.leg, std::strerror(errno));
        }
        continue;
      }
      if (errno != EINTR) t.drained_at_ns = std::max(t.drained_at_ns, asked_ns);
      return;
    }
    const std::int64_t user_ns = RealtimeNs();
    const auto batch_time = Clock::now();
    const std::uint64_t accepted_before = t.tracker.accepted();
    for (int i = 0; i < n; ++i) {
      ++t.c.datagrams;
      const msghdr& h = t.headers[i].msg_hdr;
      std::int64_t kernel_ns = user_ns;
      for (cmsghdr* cm = CMSG_FIRSTHDR(&h); cm != nullptr;
           cm = CMSG_NXTHDR(const_cast<msghdr*>(&h), cm)) {
        if (cm->cmsg_level == SOL_SOCKET && cm->cmsg_type == SCM_TIMESTAMPNS) {
          timespec ts;
          std::memcpy(&ts, CMSG_DATA(cm), sizeof ts);
          kernel_ns = std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
        }
      }
      const sockaddr_in& from = t.sources[i];
      if (from.sin_addr.s_addr != t.device.sin_addr.s_addr || from.sin_port != t.device.sin_port) {
        if (!t.logged_foreign) {
          t.logged_foreign = true;
          log_->warn("{}: datagram from {}:{}, not the box: dropped (counted from now on)", t.leg,
                     inet_ntoa(from.sin_addr), ntohs(from.sin_port));
        }
        ++t.c.foreign;
        continue;
      }
      const std::size_t len = t.headers[i].msg_len;
      if (len == 0 || len % rdt::kRecordBytes != 0 || (h.msg_flags & MSG_TRUNC) != 0) {
        ++t.c.wrong_length;
        if (!t.logged_wrong_length) {
          t.logged_wrong_length = true;
          log_->warn(
              "{}: a {}-byte datagram is not a whole number of 36-byte records: dropped "
              "(counted from now on)",
              t.leg, len);
        }
        continue;
      }
      const std::uint8_t* data = t.slots.data() + static_cast<std::size_t>(i) * kSlotBytes;
      // A socket queue is first in, first out: a datagram stamped before the last look that
      // emptied the queue was not in it then.
      const bool held = kernel_ns < t.drained_at_ns;
      // The records of a (buffered) datagram travel on as one message (at most MAX_N, the
      // protocol's largest buffer, so one message unless a box sends more than it may).
      for (std::size_t off = 0; off < len; off += rdt::kRecordBytes) {
        HandleRecord(t, data + off);
        if (t.msg.n == ft_batch_t::MAX_N) PublishBatch(t, kernel_ns, user_ns, held);
      }
      PublishBatch(t, kernel_ns, user_ns, held);
    }
    if (t.tracker.accepted() != accepted_before) {
      t.last_record = batch_time;
      t.backoff_s = SilenceTimeoutS(t);
      t.unanswered = 0;
      if (!t.up || t.silent) LogState(t, "streaming", spdlog::level::info, "streaming again");
      t.silent = false;
      t.up = t.calibrated;
      if (t.up) t.problem.clear();
    }
    if (n < kBatch) {
      t.drained_at_ns = std::max(t.drained_at_ns, asked_ns);
      return;
    }
  }
}

void AtiBridge::HandleRecord(Transducer& t, const std::uint8_t* bytes) {
  const rdt::Record rec = rdt::DecodeRecord(bytes);
  ++t.c.received;
  using V = rdt::SequenceTracker::Verdict;
  // kRestart: two start commands were in flight (a re-send while the box was slow to answer the
  // first) and the tracker had locked onto the stream of the first; the box serves the last.
  const rdt::SequenceTracker::Result r = t.tracker.Update(rec.rdt_sequence, rec.ft_sequence);
  if (!r.accept()) {
    switch (r.verdict) {
      case V::kDuplicate:
        ++t.c.duplicates;
        if (!t.logged_duplicate) {
          t.logged_duplicate = true;
          log_->warn("{}: duplicated record (rdt_sequence {}) dropped (counted from now on)", t.leg,
                     rec.rdt_sequence);
        }
        break;
      case V::kLate:
        ++t.c.late;
        if (!t.logged_late) {
          t.logged_late = true;
          log_->warn("{}: late (reordered) record (rdt_sequence {}) dropped (counted from now on)",
                     t.leg, rec.rdt_sequence);
        }
        break;
      default:
        ++t.c.stale;
        // No earlier re-send for these: the box may simply not have served our start yet, and
        // every re-send begins yet another stream; the back-off paces them.
        if (!t.logged_stale) {
          t.logged_stale = true;
          log_->info(
              "{}: record of a previous stream (rdt_sequence {}) dropped (counted from now "
              "on)",
              t.leg, rec.rdt_sequence);
        }
        break;
    }
    return;
  }
  t.c.lost += r.lost;
  if (r.verdict == V::kStart || r.verdict == V::kRestart) ++t.c.restarts;
  if (r.verdict == V::kRestart) t.restart_pending = true;

  // A box that rebooted restarts ft_sequence near 0 (§1.7): its configuration may have changed.
  if (t.have_ft && static_cast<std::int32_t>(rec.ft_sequence - t.last_ft) < 0) {
    ++t.c.reboots;
    log_->warn(
        "{}: ft_sequence went back from {} to {}: the box restarted; reading its "
        "calibration page again",
        t.leg, t.last_ft, rec.ft_sequence);
    if (t.page_needed) {
      try {
        ReadCalibration(t);
      } catch (const AtiBridgeError& e) {
        t.calibrated = false;
        t.up = false;
        t.calibration_backoff = kCalibrationRetry;
        t.next_calibration_try = Clock::now() + t.calibration_backoff;
        t.problem = std::string(e.what()) + " (not publishing until it can be read)";
        LogState(t, "calibration", spdlog::level::err, t.problem);
      }
    }
  }
  t.ft_unwrapped = t.have_ft
                       ? t.ft_unwrapped + static_cast<std::int32_t>(rec.ft_sequence - t.last_ft)
                       : rec.ft_sequence;
  t.have_ft = true;
  t.last_ft = rec.ft_sequence;

  if (!t.calibrated) {
    ++t.c.uncalibrated;
    t.pending_gap += 1 + r.lost;
    return;
  }

  const rdt::Vector6d w =
      rdt::CountsToWrench(rec.counts, t.counts_per_force, t.counts_per_torque, t.sign);
  std::int32_t flags = 0;
  const bool saturated =
      rdt::StatusSaturated(rec.status) || rdt::ExceedsRatedRange(w, t.rated_range);
  if (saturated) {
    flags |= ft_batch_t::FLAG_SATURATED;
    ++t.c.saturated;
    if (!t.logged_saturated) {
      t.logged_saturated = true;
      log_->warn(
          "{}: saturated sample (status bit 17 or beyond the rated range), published "
          "flagged (counted from now on)",
          t.leg);
    }
  }
  if (rec.status != 0) {
    flags |= ft_batch_t::FLAG_STATUS_ERROR;
    ++t.c.status_nonzero;
    if (!t.logged_status) {
      t.logged_status = true;
      std::string bits;
      for (const auto& s : rdt::DescribeStatus(rec.status)) bits += (bits.empty() ? "" : "; ") + s;
      log_->warn("{}: status word 0x{:08x} ({}), published flagged (counted from now on)", t.leg,
                 rec.status, bits);
    }
  }
  const std::int64_t gap = t.pending_gap + r.lost;
  t.pending_gap = 0;
  if (gap > 0) flags |= ft_batch_t::FLAG_GAP;
  if (t.restart_pending) {
    flags |= ft_batch_t::FLAG_RESTARTED;
    t.restart_pending = false;
  }

  ft_batch_t& m = t.msg;
  const auto i = static_cast<std::size_t>(m.n);
  t.ticks[i] = t.ft_unwrapped;
  m.rdt_sequence[i] = rec.rdt_sequence;
  m.ft_sequence[i] = rec.ft_sequence;
  m.status[i] = rec.status;
  for (std::size_t j = 0; j < 6; ++j) {
    m.counts[i][j] = rec.counts[j];
    m.wrench[i][j] = w(static_cast<int>(j));
  }
  m.gap[i] = static_cast<std::int32_t>(std::min<std::int64_t>(gap, INT32_MAX));
  m.flags[i] = flags;
  ++m.n;
}

void AtiBridge::PublishBatch(Transducer& t, std::int64_t kernel_ns, std::int64_t user_ns,
                             bool held) {
  ft_batch_t& m = t.msg;
  if (m.n == 0) return;
  const auto n = static_cast<std::size_t>(m.n);
  // The box sends a datagram as soon as its last record is taken: the receipt bounds that
  // record's time from above (plus the least transport delay, which the map keeps), and the
  // clock map of many datagrams gives each record its instant on the counter's own rate, so
  // a reader that orders by time (the corrector, the aligner) sees the samples 1/7000 s apart
  // however the datagrams queued. Never after the receipt, never at or before the previous
  // record's time: the stream's times only rise.
  const std::int64_t receipt_us = kernel_ns / 1000;
  t.clock.Observe(t.ticks[n - 1], receipt_us);
  for (std::size_t i = 0; i < n; ++i) {
    // Each record capped so as to leave the later ones of the datagram 1 us each before the
    // receipt: when several map at or after it (a datagram less delayed than the map's line,
    // between two refits), capping them all at the receipt let the rising rule push the later
    // ones past it (receipt + 1, + 2, ...).
    const auto later = static_cast<std::int64_t>(n - 1 - i);
    const std::int64_t mapped = std::min(t.clock.Map(t.ticks[i]), receipt_us - later);
    m.sample_utime[i] = std::max(mapped, t.last_utime + 1);
    t.last_utime = m.sample_utime[i];
  }
  m.receipt_utime = receipt_us;
  const int size = m.getEncodedSize();
  const bool encoded = m.encode(t.encoded.data(), 0, size) == size;
  m.n = 0;
  if (!encoded) {
    ++t.c.publish_errors;
    return;
  }
  try {
    publish_(t.channel, t.encoded.data(), size);
    t.c.published += n;
  } catch (const std::exception& e) {
    ++t.c.publish_errors;
    if (!t.logged_publish) {
      t.logged_publish = true;
      log_->error("{}: publish failed: {} (counted from now on)", t.leg, e.what());
    }
    return;
  }
  const std::int64_t done_ns = RealtimeNs();
  for (std::size_t i = 0; i < n; ++i) {
    kernel_latency_.Add(done_ns - kernel_ns);
    user_latency_.Add(done_ns - user_ns);
    if (held) {
      ++t.c.held_in_stack;
      held_latency_.Add(done_ns - kernel_ns);
    }
  }
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
