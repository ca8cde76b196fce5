// The live pipeline's latency with real processes, as a user runs it (issue 11, "Speed"): the
// twin's six emulated ATI boxes at --ati-rate (7000) records/s each, its Dynamixel bus and QTM
// server (ftcal-sim live --scenario commanded), the ATI bridge (one per transducer, --legs X
// --realtime, as the README recommends; --bridges 1 for one bridge serving all six), the
// Dynamixel and mocap bridges, ftcal-corrector with the twin's true calibration, and an LCM
// subscriber in this program. Must run inside scripts/netns-exec (ctest does).
//
// 1. End-to-end latency, per leg-sample (each record of a message counted once), over the
//    samples whose sample_utime falls in the --duration s window after --warmup s. An FT_<LEG>
//    message (ft_batch_t) carries one RDT datagram's records: its receipt_utime is the kernel's
//    receive timestamp of that datagram in the bridge's socket (SO_TIMESTAMPNS, CLOCK_REALTIME;
//    services/ati_bridge), and each record's sample_utime its instant on the box's 7 kHz
//    counter mapped to the host clock, never after the receipt. contact_wrench_t carries the
//    receipt_utime of the FT message its samples came in, and each sample's utime is that
//    record's sample_utime. The latencies are measured from the receipt, so they are on one
//    clock and leave out the time a record waited in the box for its datagram to fill (up to
//    (k - 1) / rate for k records a datagram), which no stage after the box can shorten:
//      - FT_<LEG>:        receipt_utime -> this program's handler for the FT message (bridge +
//                         LCM hop), for each of its records;
//      - CONTACT_WRENCH:  the FT message's receipt_utime -> this program's handler for the
//                         CONTACT_WRENCH (+ corrector), for each of its samples.
//    Each also to LCM's ReceiveBuffer::recv_utime, liblcm's stamp of the datagram as it read it,
//    before the handler ran. Every FT and CONTACT_WRENCH is decoded in the handler, as a real
//    consumer would: this subscriber is one more SCHED_OTHER process on the two cores.
//    Loss: per leg the twin's records in the window are told by the RDT sequence numbers of
//    the FT records heard (last - first + 1: records lost right at the window's two edges are
//    not seen); FT records heard and CONTACT_WRENCH samples heard are counted against that. Over
//    the whole run the twin's own count of records sent is compared with everything heard.
// 2. Command latency: a signed MOVE published on SERVO_CMD (from a key the config trusts, which
//    ARMed the bridge; heartbeats keep the dead-man fed) -> the Sync Write of Goal Position
//    carrying the new goals, seen on the serial line. The Dynamixel bridge's port is a
//    pseudo-terminal of this program's that forwards every byte to and from the twin's, so the
//    instant measured is when the write's bytes reached the bus (read here on the master side,
//    CLOCK_REALTIME), against the publish time taken just before lcm_publish. It includes the
//    LCM hop, the envelope check, the command gate and the wait for the bridge's next cycle
//    (dynamixel.rate_hz, 100 Hz on the twin: up to 10 ms), and this program's own wake-up on the
//    pty; not the servo's motion. The MOVEs alternate between two poses, one every
//    --command-period s, after the ATI bridges and the corrector stopped (the twin's boxes
//    stop sending); --commands-under-load sends them while the 6 x 7 kHz load goes on, which on
//    a busy 2-core machine degrades the bus until the bridge's gate goes to FAULT (counted as
//    MOVEs without a write).
//
// 3. With --record, the recording's loss (issue 14, "Recording loses nothing"): scripts/record
//    (ftcal-record with a 32 MB receive buffer, SCHED_FIFO where allowed) records the whole run
//    beside this subscriber; its FT_<LEG> and CONTACT_WRENCH in the window are counted the
//    same way.
//
//   scripts/netns-exec build/tests/bench/live_latency_bench [--duration 12] [--bridges 6|1]
//       [--record]
//
// The figures depend on what else the machine runs: the load average is printed with them.
//
// The figures below were measured while FT_<LEG> carried one record a message (ft_sample_t),
// each latency from that record's own stamp (for a buffered datagram's earlier records, before
// its receipt by their distance on the counter: up to (k - 1) / rate of waiting in the box
// included); they are not remeasured since FT_<LEG> became ft_batch_t.
//
// Measured 2026-12-02 on the 2-vCPU CI VM while a full test suite ran beside it (load average
// 4-5 before and during each run, so every figure is inflated), defaults (12 s counted):
//   six --realtime bridges: the bridges published every record the twin sent (336270, 0 lost
//     by RDT sequence; their own receipt->publish p99 350-630 us), but the corrector corrected
//     89.5 % of them and this subscriber heard 51 % of the FT and 41 % of the CONTACT_WRENCH of
//     the window; the kernel counted 100155 datagrams dropped at full socket buffers (every
//     LCM process on the group, the bridges included, gets every datagram). FT at this
//     subscriber p50 3.7 ms p99 132 ms; CONTACT_WRENCH p50 89 ms p99 1.14 s, max 1.16 s.
//   one --realtime bridge for all six: published all 386033, corrector 82 %, this subscriber
//     53 % FT / 41 % CONTACT_WRENCH; FT p50 0.9 ms p99 110 ms; CONTACT_WRENCH p50 40 ms p99 0.66 s.
//   --subscriber-realtime: worse (FT p50 0.64 s: the subscriber saturated, a standing queue).
//   SERVO_CMD MOVE -> Sync Write on the bus, ATI stages stopped: p50 5-6.4 ms, p99 10.2-10.4 ms,
//     max 10.4 ms, 100 of 100 written (the 100 Hz cycle bounds it). Under the ATI load the
//     gate went to FAULT repeatedly (bus replies late) and most MOVEs were never written.
// So the goal (zero loss, p99 < 200 us) is far off downstream of the bridges on a loaded
// 2-core machine; the bridges themselves lose nothing. A quiet machine remains to be measured.
//
// Measured 2026-12-02 again, nothing else running (load average 1-2.3), six bridges, --record
// (ftcal-record): the recording held every FT_<LEG> record of the window (252668 of 252668
// before the change below, 168842 and 254302 of as many after). The corrector corrected 57 %
// of the records and its CONTACT_WRENCH reached this subscriber 4.19 s late at p50 (p99
// 4.76 s): a standing queue. Since it sheds what waited longer than corrector.max_ft_age_s
// (Bus::ShedLate), two runs: p50 50 ms, p99 267 and 162 ms, 33-44 % corrected, the rest shed
// and counted.
//
// Measured 2026-12-04, one run each in turn, load average 1.8, six bridges: --lcm-url
// udpm://239.255.76.67:7667?ttl=0 (the default) against
// mpudpm://239.255.76.67:7667?ttl=0&nports=64 (LCM's multi-port provider: a process joins only
// the ports of the channels it reads). Kernel drops at full socket buffers 126152 against
// 14328; corrector 254611 of 379683 leg-samples corrected (67 %) against 394006 of 443268
// (89 %); this subscriber heard 37 % against 56 % of the window's FT, FT p50 3.1 ms p99 94 ms
// against 0.7 ms and 5.6 ms, CONTACT_WRENCH p99 121 ms against 54 ms. Far better, and still
// far from the goal: the twin's six boxes share the two cores with everything else.
//
// Where the CPU goes (the figures since 2026-12-05 print it): each stage's share of one core
// over the window, from /proc, and two figures of the machine taken before the run, the CPU
// price of one datagram through the loopback and one thread-to-thread hop's latency.
// Measured 2026-12-05, load average 1.3-3, six --realtime bridges, --duration 8, per box rate:
//   CPU (of 200 %), CONTACT_WRENCH lost, its p99   udpm                    mpudpm (nports=64)
//   6 x 1000/s                                     121 %, 0.02 %, 1.9 ms   115 %, 0.00 %, 1.9 ms
//   6 x 2000/s                                     167 %, 0.8 %, 8.9 ms    154 %, 0.4 %, 3.0 ms
//   6 x 3500/s                                     186 %, 12.7 %, 50 ms    189 %, 18.5 %, 50 ms
//   6 x 7000/s                                     194 %, 72 %, 86 ms      193 %, 47 %, 54 ms
// The machine: a datagram sent and received through the loopback 4.0-6.8 us of CPU, a hop
// between two threads p50 12-13 us, p99 25-53 us. perf record -a at 6 x 7000/s: 72.6 % of all
// CPU in the kernel (38 % in pvm_irq_enable alone: this VM is paravirtualised, so every kernel
// entry and wake-up is expensive), 18.6 % in libc's system-call wrappers, 3.1 % in liblcm, and
// every ftcal program together 3.6 %. liblcm's UDP provider pays several system calls per
// message and receiver (its receive thread's select and recvmsg, the notify pipe's write and
// read, the handler thread's wake-up): a recorder at 6 x 1000/s spent 62 % of its CPU in
// pvm_irq_enable. So on this machine the pipeline loses samples at 2/7 of the goal's rate,
// fills the two cores at half of it, and its p99 misses 200 us already at a seventh of it;
// ftcal's own code is not where the time goes.
//
// Measured 2026-12-06, a 10-minute soak (--record --routes --duration 600), six --realtime
// bridges, 7 records a datagram, load average 1.5-1.9: in the window 25086056 records sent, as
// many FT and CONTACT_WRENCH heard here (0 missing); bridges 0 lost; receipt -> CONTACT_WRENCH
// p50 164 us, p99 924 us; CPU bridges 16.6 + corrector 14.4 + recorder 18.2 = 49.2 % of a core.
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <sched.h>
#include <signal.h>
#include <stdlib.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <regex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/lcm_bus.h"
#include "ftcal/config.h"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "signed_commander.h"
#include "sim/live.h"
#include "sim/twin.h"

namespace {

// The box restarts its RDT sequence at 1 with each start command (the bridge sends one again
// after a silence, §1.5), so a window's records are counted stretch by stretch between restarts
// (the sequence falling back by far more than any reordering). Taking last - first + 1 over the
// whole window hid millions of records after a restart (a 10-minute soak read 8.2 M sent
// against 24.8 M heard; the recording's count read 2^24 + 6 against 25 M recorded).
constexpr std::int64_t kRdtRestart = 10'000;

// Records the box sent, by the RDT sequence numbers heard in arrival order.
std::int64_t SentByRdtSequence(const std::vector<std::int64_t>& seq) {
  std::int64_t sent = 0, first = -1, last = -1;
  for (const std::int64_t s : seq) {
    if (last >= 0 && s + kRdtRestart < last) {
      sent += last - first + 1;
      first = last = -1;
    }
    if (first < 0) first = s;
    first = std::min(first, s);
    last = std::max(last, s);
  }
  if (first >= 0) sent += last - first + 1;
  return sent;
}

using ftcal::testing::Child;

constexpr char kDefaultUrl[] = "udpm://239.255.76.67:7667?ttl=0";
// This program hears 42000 FT and 42000 CONTACT_WRENCH a second: a large socket buffer (8 MB,
// the namespace's rmem_max), so that a late wake-up here shows as latency before it is loss.
std::string ListenUrl(const std::string& url) {
  return url + (url.find('?') == std::string::npos ? "?" : "&") + "recv_buf_size=8388608";
}
const std::vector<std::string> kLegs = {"HL", "ML", "FL", "HR", "MR", "FR"};

std::int64_t NowUs() {
  timespec ts{};
  ::clock_gettime(CLOCK_REALTIME, &ts);
  return std::int64_t{ts.tv_sec} * 1'000'000 + ts.tv_nsec / 1000;
}
void SleepS(double s) { std::this_thread::sleep_for(std::chrono::duration<double>(s)); }

std::string Quantiles(std::vector<std::int64_t> v) {
  if (v.empty()) return "no samples";
  std::sort(v.begin(), v.end());
  auto q = [&](double f) { return v[static_cast<std::size_t>(f * double(v.size() - 1))]; };
  char line[160];
  std::snprintf(line, sizeof line, "p50 %lld us  p99 %lld us  max %lld us  (n %zu)",
                (long long)q(0.5), (long long)q(0.99), (long long)v.back(), v.size());
  return line;
}

// What this program hears on LCM: per leg, each FT and CONTACT_WRENCH with its sample time,
// liblcm's receive stamp and the handler's clock; and the Dynamixel bridge's gate mode.
class Listener {
 public:
  // One leg-sample: an FT record, or a CONTACT_WRENCH sample.
  struct Event {
    std::int64_t utime;         // the transducer sample's (sample_utime)
    std::int64_t receipt;       // its datagram's receipt in the bridge (receipt_utime)
    std::int64_t lcm_recv;      // LCM's receive stamp
    std::int64_t handled;       // this program's clock in the handler
    std::int64_t rdt_sequence;  // FT only
  };
  // `ft_url` and `cw_url`: where FT_<LEG> and CONTACT_WRENCH travel (the config's lcm_route),
  // when not on `url`.
  // `expected_per_leg`: the samples a leg will bring over the run, reserved up front. A vector
  // grown while the run streams copies everything it holds: at 4 M samples a leg (a 10-minute
  // soak) that stalled this thread for up to 460 ms, and LCM's queue dropped 0.5 % meanwhile.
  Listener(const std::string& url, bool realtime, std::size_t expected_per_leg,
           const std::string& ft_url = "", const std::string& cw_url = "")
      : lcm_(ListenUrl(url)) {
    lcm::LCM* ft = &lcm_;
    lcm::LCM* cw = &lcm_;
    if (!ft_url.empty())
      ft = routed_.emplace_back(std::make_unique<lcm::LCM>(ListenUrl(ft_url))).get();
    if (!cw_url.empty())
      cw = routed_.emplace_back(std::make_unique<lcm::LCM>(ListenUrl(cw_url))).get();
    // Queues as deep as the stages' (LcmBus::kSubscriptionQueueCapacity), not LCM's 30: this
    // subscriber stands for a consumer built on ftcal's Bus.
    ft->subscribe("FT_.*", &Listener::OnFt, this)
        ->setQueueCapacity(ftcal::LcmBus::kSubscriptionQueueCapacity);
    cw->subscribe("CONTACT_WRENCH", &Listener::OnContact, this)
        ->setQueueCapacity(ftcal::LcmBus::kSubscriptionQueueCapacity);
    lcm_.subscribe("FTCAL_STATUS", &Listener::OnStatus, this);
    for (auto& v : ft_) v.reserve(expected_per_leg);
    for (auto& v : cw_) v.reserve(expected_per_leg);
    thread_ = std::thread([this, realtime] {
      if (realtime) {
        sched_param p{};
        p.sched_priority = 30;
        realtime_ = ::sched_setscheduler(0, SCHED_FIFO, &p) == 0;
      }
      std::vector<lcm::LCM*> all = {&lcm_};
      for (auto& r : routed_) all.push_back(r.get());
      std::vector<pollfd> fds;
      for (lcm::LCM* l : all) fds.push_back({l->getFileno(), POLLIN, 0});
      while (!stop_) {
        if (::poll(fds.data(), fds.size(), 50) <= 0) continue;
        for (std::size_t i = 0; i < fds.size(); ++i) {
          if (fds[i].revents & POLLIN) all[i]->handleTimeout(0);
        }
      }
    });
  }
  ~Listener() { Stop(); }
  bool realtime() const { return realtime_; }
  void Stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  bool good() { return lcm_.good(); }
  // The Dynamixel bridge's command-gate mode (0 disarmed, 1 armed, ...), -1 before its status.
  int dxl_mode() const { return dxl_mode_; }

  std::array<std::vector<Event>, 6> ft_, cw_;
  std::int64_t undecodable = 0;

  static int LegOf(const std::string& name) {
    for (int k = 0; k < 6; ++k) {
      if (kLegs[k] == name) return k;
    }
    return -1;
  }

 private:
  void OnFt(const lcm::ReceiveBuffer* rb, const std::string&) {
    const std::int64_t now = NowUs();
    ftcal::ft_batch_t m;
    if (m.decode(rb->data, 0, rb->data_size) != static_cast<int>(rb->data_size)) {
      ++undecodable;
      return;
    }
    const int k = LegOf(m.leg);
    if (k < 0) return;
    for (int i = 0; i < m.n; ++i) {
      ft_[k].push_back(
          {m.sample_utime[i], m.receipt_utime, rb->recv_utime, now, m.rdt_sequence[i]});
    }
  }
  void OnContact(const lcm::ReceiveBuffer* rb, const std::string&) {
    const std::int64_t now = NowUs();
    ftcal::contact_wrench_t m;
    if (m.decode(rb->data, 0, rb->data_size) != static_cast<int>(rb->data_size) || m.leg < 0 ||
        m.leg >= 6) {
      ++undecodable;
      return;
    }
    for (int i = 0; i < m.n; ++i) {
      cw_[m.leg].push_back({m.utime[i], m.receipt_utime, rb->recv_utime, now, -1});
    }
  }
  void OnStatus(const lcm::ReceiveBuffer* rb, const std::string&) {
    ftcal::service_status_t m;
    if (m.decode(rb->data, 0, rb->data_size) != static_cast<int>(rb->data_size)) return;
    if (m.name.find("dynamixel") == std::string::npos) return;
    for (int i = 0; i < m.num_counters; ++i) {
      if (m.counter_name[i] == "mode") dxl_mode_ = static_cast<int>(m.counter_value[i]);
    }
  }

  lcm::LCM lcm_;
  std::vector<std::unique_ptr<lcm::LCM>> routed_;
  std::atomic<bool> stop_{false};
  std::atomic<int> dxl_mode_{-1};
  std::atomic<bool> realtime_{false};
  std::thread thread_;
};

// A pseudo-terminal between the Dynamixel bridge and the twin's bus: every byte is forwarded
// both ways, and each Sync Write of Goal Position from the bridge is recorded with the time its
// bytes were read here (CLOCK_REALTIME) and its goals.
class BusTap {
 public:
  struct GoalWrite {
    std::int64_t t_us;
    std::vector<std::pair<int, std::int32_t>> goals;  // (id, count)
  };
  BusTap(const std::string& link, const std::string& device) {
    master_ = ::posix_openpt(O_RDWR | O_NOCTTY);
    if (master_ < 0 || ::grantpt(master_) != 0 || ::unlockpt(master_) != 0) {
      throw std::runtime_error("cannot make a pseudo-terminal");
    }
    const std::string slave = ::ptsname(master_);
    // Our own slave descriptor keeps the master readable while the bridge reopens its port.
    slave_ = ::open(slave.c_str(), O_RDWR | O_NOCTTY);
    MakeRaw(slave_);
    ::unlink(link.c_str());
    if (::symlink(slave.c_str(), link.c_str()) != 0) throw std::runtime_error("symlink " + link);
    device_ = ::open(device.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (device_ < 0) throw std::runtime_error("cannot open the twin's bus " + device);
    MakeRaw(device_);
    thread_ = std::thread([this] { Run(); });
  }
  ~BusTap() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
    for (int fd : {master_, slave_, device_}) {
      if (fd >= 0) ::close(fd);
    }
  }
  std::vector<GoalWrite> writes() {
    std::lock_guard<std::mutex> lock(mu_);
    return writes_;
  }

 private:
  static void MakeRaw(int fd) {
    termios t{};
    if (::tcgetattr(fd, &t) == 0) {
      ::cfmakeraw(&t);
      ::tcsetattr(fd, TCSANOW, &t);
    }
  }
  static void WriteAll(int fd, const std::uint8_t* p, ssize_t n) {
    while (n > 0) {
      const ssize_t w = ::write(fd, p, static_cast<std::size_t>(n));
      if (w < 0) {
        if (errno == EAGAIN || errno == EINTR) {
          pollfd pf{fd, POLLOUT, 0};
          ::poll(&pf, 1, 10);
          continue;
        }
        return;
      }
      p += w;
      n -= w;
    }
  }
  // Protocol 2.0 packets: FF FF FD 00 ID LEN_L LEN_H INST PARAMS.. CRC_L CRC_H. A Sync Write
  // (0x83) of Goal Position: params are address (116), data length (4), then ID + 4 bytes each.
  // Goal counts (0..4095) never hold the FF FF FD that byte stuffing escapes.
  void Parse(std::int64_t t_us) {
    for (;;) {
      std::size_t i = 0;
      while (i + 4 <= from_bridge_.size() &&
             !(from_bridge_[i] == 0xFF && from_bridge_[i + 1] == 0xFF &&
               from_bridge_[i + 2] == 0xFD && from_bridge_[i + 3] == 0x00)) {
        ++i;
      }
      from_bridge_.erase(from_bridge_.begin(), from_bridge_.begin() + static_cast<long>(i));
      if (from_bridge_.size() < 8) return;
      const std::size_t len = from_bridge_[5] | (from_bridge_[6] << 8);
      if (from_bridge_.size() < 7 + len) return;
      const std::uint8_t* p = from_bridge_.data();
      if (p[7] == 0x83 && len >= 3 + 4) {
        const int address = p[8] | (p[9] << 8), data_len = p[10] | (p[11] << 8);
        if (address == 116 && data_len == 4) {
          GoalWrite w{t_us, {}};
          for (std::size_t o = 12; o + 5 <= 7 + len - 2; o += 5) {
            const std::int32_t c = static_cast<std::int32_t>(
                p[o + 1] | (p[o + 2] << 8) | (p[o + 3] << 16) | (std::uint32_t{p[o + 4]} << 24));
            w.goals.emplace_back(p[o], c);
          }
          std::lock_guard<std::mutex> lock(mu_);
          writes_.push_back(std::move(w));
        }
      }
      from_bridge_.erase(from_bridge_.begin(), from_bridge_.begin() + static_cast<long>(7 + len));
    }
  }
  void Run() {
    std::uint8_t buf[4096];
    while (!stop_) {
      pollfd pf[2] = {{master_, POLLIN, 0}, {device_, POLLIN, 0}};
      if (::poll(pf, 2, 50) <= 0) continue;
      if (pf[0].revents & POLLIN) {
        const ssize_t n = ::read(master_, buf, sizeof buf);
        const std::int64_t t = NowUs();
        if (n > 0) {
          WriteAll(device_, buf, n);
          from_bridge_.insert(from_bridge_.end(), buf, buf + n);
          Parse(t);
        }
      }
      if (pf[1].revents & POLLIN) {
        const ssize_t n = ::read(device_, buf, sizeof buf);
        if (n > 0) WriteAll(master_, buf, n);
      }
      if ((pf[0].revents | pf[1].revents) & (POLLHUP | POLLERR)) SleepS(0.001);
    }
  }

  int master_ = -1, slave_ = -1, device_ = -1;
  std::vector<std::uint8_t> from_bridge_;
  std::mutex mu_;
  std::vector<GoalWrite> writes_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

// The kernel's UDP counters of this network namespace (/proc/net/snmp: InDatagrams InErrors
// RcvbufErrors; only this program's processes run in it) and the per-CPU backlog drops
// (/proc/net/softnet_stat, second column, summed; machine-wide): where datagrams that every
// bridge published went missing before a subscriber's socket. The loopback's multicast copies
// are queued to that backlog and delivered by softirq.
struct KernelDrops {
  long long in_datagrams = 0, in_errors = 0, rcvbuf_errors = 0, backlog_drops = 0;
};
KernelDrops ReadKernelDrops() {
  KernelDrops d;
  std::istringstream snmp(ftcal::testing::ReadFile("/proc/net/snmp"));
  std::vector<std::string> names;
  for (std::string line; std::getline(snmp, line);) {
    if (line.rfind("Udp: ", 0) != 0) continue;
    std::istringstream words(line.substr(5));
    std::vector<std::string> f;
    for (std::string w; words >> w;) f.push_back(w);
    if (names.empty()) {
      names = f;
      continue;
    }
    for (std::size_t i = 0; i < f.size() && i < names.size(); ++i) {
      if (names[i] == "InDatagrams") d.in_datagrams = std::stoll(f[i]);
      if (names[i] == "InErrors") d.in_errors = std::stoll(f[i]);
      if (names[i] == "RcvbufErrors") d.rcvbuf_errors = std::stoll(f[i]);
    }
    break;
  }
  std::istringstream softnet(ftcal::testing::ReadFile("/proc/net/softnet_stat"));
  for (std::string line; std::getline(softnet, line);) {
    std::istringstream words(line);
    std::string processed, dropped;
    if (words >> processed >> dropped) d.backlog_drops += std::stoll(dropped, nullptr, 16);
  }
  return d;
}

// Every process's parent and CPU seconds (user + system, every thread: utime and stime of
// /proc/<pid>/stat, in clock ticks), read once per snapshot.
using ProcTable = std::map<pid_t, std::pair<pid_t, double>>;
ProcTable ReadProcTable() {
  ProcTable procs;
  const double tick = static_cast<double>(::sysconf(_SC_CLK_TCK));
  for (const auto& entry : std::filesystem::directory_iterator("/proc")) {
    const std::string name = entry.path().filename().string();
    if (name.find_first_not_of("0123456789") != std::string::npos) continue;
    const std::string stat = ftcal::testing::ReadFile(entry.path().string() + "/stat");
    const auto close = stat.rfind(')');
    if (close == std::string::npos) continue;
    std::istringstream f(stat.substr(close + 2));
    std::string field;
    std::vector<std::string> v;
    while (f >> field && v.size() < 13) v.push_back(field);
    if (v.size() < 13) continue;  // state ppid ... utime(12th after the name) stime(13th)
    procs[static_cast<pid_t>(std::stol(name))] = {static_cast<pid_t>(std::stol(v[1])),
                                                  (std::stod(v[11]) + std::stod(v[12])) / tick};
  }
  return procs;
}

// The CPU seconds of a process and of every process below it: what each stage costs the two
// cores, so that loss can be told from a machine that has not the CPU for the rate.
double TreeCpuS(const ProcTable& procs, pid_t root) {
  double sum = 0;
  for (const auto& [pid, p] : procs) {
    for (pid_t at = pid; at > 1;) {
      if (at == root) {
        sum += p.second;
        break;
      }
      const auto it = procs.find(at);
      if (it == procs.end()) break;
      at = it->second.first;
    }
  }
  return sum;
}

double SelfCpuS() {
  rusage u{};
  ::getrusage(RUSAGE_SELF, &u);
  return static_cast<double>(u.ru_utime.tv_sec + u.ru_stime.tv_sec) +
         1e-6 * static_cast<double>(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// The machine's "cpu" line of /proc/stat: user, nice, system, idle, iowait, irq, softirq.
std::array<long long, 7> MachineTicks() {
  std::istringstream in(ftcal::testing::ReadFile("/proc/stat"));
  std::string cpu;
  std::array<long long, 7> t{};
  in >> cpu;
  for (auto& v : t) in >> v;
  return t;
}

// This machine's price of one UDP datagram through the loopback's multicast, sent and
// received (the hop every stage of the pipeline pays per sample, once per receiver): one
// socket sends 200-byte datagrams to a group another socket of the same thread joined, each
// read back before the next. CPU of this thread (the loopback delivers in the sender's
// softirq, so it is counted here) per datagram, in us.
double DatagramCostUs(int count) {
  const int rx = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  const int tx = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  double cost = -1;
  sockaddr_in group{};
  group.sin_family = AF_INET;
  group.sin_port = htons(7699);
  ::inet_pton(AF_INET, "239.255.76.68", &group.sin_addr);
  sockaddr_in any = group;
  any.sin_addr.s_addr = htonl(INADDR_ANY);
  ip_mreq join{};
  join.imr_multiaddr = group.sin_addr;
  join.imr_interface.s_addr = htonl(INADDR_ANY);
  const int one = 1, ttl = 0;
  timeval timeout{1, 0};
  if (rx >= 0 && tx >= 0 && ::setsockopt(rx, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) == 0 &&
      ::bind(rx, reinterpret_cast<sockaddr*>(&any), sizeof any) == 0 &&
      ::setsockopt(rx, IPPROTO_IP, IP_ADD_MEMBERSHIP, &join, sizeof join) == 0 &&
      ::setsockopt(rx, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout) == 0 &&
      ::setsockopt(tx, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl) == 0 &&
      ::setsockopt(tx, IPPROTO_IP, IP_MULTICAST_LOOP, &one, sizeof one) == 0) {
    char out[200] = {}, in[256];
    auto thread_cpu = [] {
      timespec t{};
      ::clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
      return static_cast<double>(t.tv_sec) * 1e6 + static_cast<double>(t.tv_nsec) * 1e-3;
    };
    const double from = thread_cpu();
    int done = 0;
    for (; done < count; ++done) {
      if (::sendto(tx, out, sizeof out, 0, reinterpret_cast<sockaddr*>(&group), sizeof group) !=
              static_cast<ssize_t>(sizeof out) ||
          ::recv(rx, in, sizeof in, 0) != static_cast<ssize_t>(sizeof out)) {
        break;
      }
    }
    if (done == count) cost = (thread_cpu() - from) / count;
  }
  if (rx >= 0) ::close(rx);
  if (tx >= 0) ::close(tx);
  return cost;
}

// This machine's floor for a hop's latency: two threads ping-pong a 200-byte datagram over
// the loopback (unicast, blocking reads, SCHED_OTHER), `count` round trips; half of each round
// trip, in us, as Quantiles() prints them. Every stage of the pipeline is at least one such
// hop (plus LCM's own hand-over to its handler thread), so no p99 below is under this one's.
std::string HopLatency(int count) {
  auto open_bound = [](sockaddr_in* addr) {
    const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    addr->sin_family = AF_INET;
    addr->sin_port = 0;
    addr->sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof *addr;
    if (fd < 0 || ::bind(fd, reinterpret_cast<sockaddr*>(addr), sizeof *addr) != 0 ||
        ::getsockname(fd, reinterpret_cast<sockaddr*>(addr), &len) != 0) {
      if (fd >= 0) ::close(fd);
      return -1;
    }
    timeval timeout{1, 0};
    ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
    return fd;
  };
  sockaddr_in a{}, b{};
  const int fa = open_bound(&a), fb = open_bound(&b);
  std::vector<std::int64_t> half;
  if (fa >= 0 && fb >= 0) {
    std::thread echo([&] {
      char buf[256];
      for (int i = 0; i < count; ++i) {
        const ssize_t n = ::recv(fb, buf, sizeof buf, 0);
        if (n <= 0 || ::sendto(fb, buf, n, 0, reinterpret_cast<sockaddr*>(&a), sizeof a) != n) {
          break;
        }
      }
    });
    char out[200] = {}, in[256];
    for (int i = 0; i < count; ++i) {
      const std::int64_t t0 = NowUs();
      if (::sendto(fa, out, sizeof out, 0, reinterpret_cast<sockaddr*>(&b), sizeof b) !=
              static_cast<ssize_t>(sizeof out) ||
          ::recv(fa, in, sizeof in, 0) != static_cast<ssize_t>(sizeof out)) {
        break;
      }
      half.push_back((NowUs() - t0) / 2);
    }
    echo.join();
  }
  if (fa >= 0) ::close(fa);
  if (fb >= 0) ::close(fb);
  return Quantiles(half);
}

void Stop(std::unique_ptr<Child>& c, double timeout_s = 10) {
  if (!c || !c->running()) return;
  c->Signal(SIGTERM);
  if (!c->Wait(timeout_s)) {
    c->Signal(SIGKILL);
    c->Wait(5);
  }
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App cli("The live pipeline's end-to-end and command latency with real processes",
               "live_latency_bench");
  double warmup_s = 4, duration_s = 12, command_period_s = 0.15;
  int bridges = 6, rate_hz = 7000, commands = 100;
  bool no_realtime = false;
  std::uint64_t seed = 5;
  cli.add_option("--warmup", warmup_s, "seconds of streaming before the counted window")
      ->capture_default_str();
  cli.add_option("--duration", duration_s, "seconds counted")->capture_default_str();
  cli.add_option("--bridges", bridges, "6: one ATI bridge per transducer; 1: one for all six")
      ->check(CLI::IsMember({1, 6}))
      ->capture_default_str();
  cli.add_flag("--no-realtime", no_realtime, "run the ATI bridge(s) without --realtime");
  cli.add_option("--ati-rate", rate_hz, "records/s per box")->capture_default_str();
  cli.add_option("--commands", commands, "MOVEs for the command latency")->capture_default_str();
  cli.add_option("--command-period", command_period_s, "s between MOVEs")->capture_default_str();
  cli.add_option("--seed", seed, "twin seed")->capture_default_str();
  bool commands_under_load = false;
  cli.add_flag("--commands-under-load", commands_under_load,
               "send the MOVEs while the ATI bridges and the corrector still run (default: after "
               "they stopped)");
  bool subscriber_realtime = false;
  cli.add_flag("--subscriber-realtime", subscriber_realtime,
               "run this program's subscriber thread SCHED_FIFO (priority 30, below the ATI "
               "bridges' default): tells a starved subscriber from a slow pipeline");
  std::string url = kDefaultUrl;
  cli.add_option("--lcm-url", url,
                 "the LCM URL of every process (the config's lcm_url is replaced by it), e.g. "
                 "mpudpm://239.255.76.67:7667?ttl=0&nports=64 for LCM's multi-port provider")
      ->capture_default_str();
  bool routes = false;
  cli.add_flag("--routes", routes,
               "FT_<LEG> and CONTACT_WRENCH(_SUM) on ports of their own (config lcm_route, as "
               "config/bigant.pbtxt ships): only their readers receive them");
  bool keep = false;
  bool record = false;
  cli.add_flag("--record", record,
               "also record the run with scripts/record (lcm-logger, its receive buffer and "
               "real-time priority where allowed) and count what the recording lost");
  cli.add_flag("--keep", keep, "keep the temporary directory (the processes' logs) and print it");
  CLI11_PARSE(cli, argc, argv);
  const char* netns = std::getenv("FTCAL_NETNS");
  if (netns == nullptr || std::string(netns) != "1") {
    std::fprintf(stderr, "run me through scripts/netns-exec: I send UDP multicast\n");
    return 2;
  }

  // Before anything else runs: the machine's own price of a datagram hop.
  const double datagram_us = DatagramCostUs(20000);
  const std::string hop_latency = HopLatency(20000);
  const std::string dir = ftcal::testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  int rc = 0;
  {
    // The twin's config; the Dynamixel bridge's port is this program's tap, a longer reply
    // timeout for the tap's extra hop on a loaded machine, no velocity limit to speak of (a
    // MOVE's goal is written whole, in one Sync Write), and the commander's key trusted.
    ftcal::testing::SignedCommander commander(url);
    std::string text =
        ftcal::testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    text = std::regex_replace(text, std::regex("device: \"[^\"]*\""),
                              "device: \"" + path("bridge-tty") + "\"");
    text = std::regex_replace(text, std::regex("reply_timeout_s: [0-9.]+"),
                              "reply_timeout_s: 0.05\n  max_velocity_rad_s: 1000");
    text = std::regex_replace(text, std::regex("lcm_url: \"[^\"]*\""), "lcm_url: \"" + url + "\"");
    std::string ft_url, cw_url;
    if (routes) {
      const std::smatch m = [&] {
        std::smatch r;
        std::regex_match(url, r, std::regex("udpm://([^:]+):([0-9]+)(.*)"));
        return r;
      }();
      if (m.empty()) {
        std::fprintf(stderr, "--routes needs a udpm:// --lcm-url, got %s\n", url.c_str());
        return 2;
      }
      const int port = std::stoi(m[2]);
      ft_url = "udpm://" + m[1].str() + ":" + std::to_string(port + 1) + m[3].str();
      cw_url = "udpm://" + m[1].str() + ":" + std::to_string(port + 2) + m[3].str();
      text += "\nlcm_route { channels: \"FT_.*\" url: \"" + ft_url + "\" }\n";
      text += "lcm_route { channels: \"CONTACT_WRENCH(_SUM)?\" url: \"" + cw_url + "\" }\n";
    }
    const std::string config_path = path("config.pbtxt");
    {
      std::ofstream out(config_path);
      out << commander.Trusted(text);
    }
    const ftcal::config::Config config = ftcal::LoadConfigFile(config_path);

    // The true calibration: the twin ftcal-sim live builds from the same seed.
    ftcal::sim::LiveOptions live_defaults;
    ftcal::TwinOptions twin_options;
    twin_options.seed = seed;
    twin_options.counts_per_force = live_defaults.counts_per_force;
    twin_options.counts_per_torque = live_defaults.counts_per_torque;
    ftcal::BigAntTwin(config, twin_options).WriteTruthFile(path("truth.pbtxt"));

    auto sim = std::make_unique<Child>(
        std::vector<std::string>{FTCAL_SIM, "live", "--config", config_path, "--pty-link",
                                 path("twin-tty"), "--ready", path("ready"), "--scenario",
                                 "commanded", "--seed", std::to_string(seed), "--ati-rate",
                                 std::to_string(rate_hz)},
        path("sim.out"), path("sim.err"));
    for (int i = 0; i < 600 && ::access(path("ready").c_str(), F_OK) != 0; ++i) {
      if (sim->Wait(0.05)) break;
    }
    if (::access(path("ready").c_str(), F_OK) != 0) {
      std::fprintf(stderr, "ftcal-sim not ready: %s\n",
                   ftcal::testing::ReadFile(path("sim.err")).c_str());
      Stop(sim);
      ftcal::testing::RemoveTree(dir);
      return 1;
    }
    auto tap = std::make_unique<BusTap>(path("bridge-tty"), path("twin-tty"));
    // The whole run a leg's box streams, and a tenth more.
    const auto expected_per_leg =
        static_cast<std::size_t>(1.1 * rate_hz * (warmup_s + duration_s + 5));
    auto listener =
        std::make_unique<Listener>(url, subscriber_realtime, expected_per_leg, ft_url, cw_url);
    if (!listener->good() || !commander.good()) {
      std::fprintf(stderr, "LCM unavailable\n");
      return 1;
    }
    SleepS(0.2);

    // The recorder first: it is to hold every record the bridges publish.
    std::unique_ptr<Child> recorder;
    if (record) {
      recorder = std::make_unique<Child>(
          std::vector<std::string>{std::string(FTCAL_SOURCE_DIR) + "/scripts/record", "--config",
                                   config_path, path("session.lcmlog")},
          path("record.out"), path("record.err"));
      SleepS(0.5);
    }
    const KernelDrops kernel_before = ReadKernelDrops();
    std::vector<std::unique_ptr<Child>> ati;
    std::vector<std::string> ati_argv = {
        FTCAL_ATI_BRIDGE, "--config", config_path, "--lcm-url", url, "--silence-timeout", "1.0"};
    if (!no_realtime) ati_argv.push_back("--realtime");
    if (bridges == 1) {
      ati.push_back(std::make_unique<Child>(ati_argv, path("ati.out"), path("ati.err")));
    } else {
      for (const auto& leg : kLegs) {
        auto a = ati_argv;
        a.insert(a.end(), {"--legs", leg});
        ati.push_back(
            std::make_unique<Child>(a, path("ati-" + leg + ".out"), path("ati-" + leg + ".err")));
      }
    }
    auto dxl = std::make_unique<Child>(
        std::vector<std::string>{FTCAL_DYNAMIXEL_BRIDGE, "--config", config_path, "--lcm-url", url},
        path("dxl.out"), path("dxl.err"));
    auto mocap = std::make_unique<Child>(
        std::vector<std::string>{FTCAL_MOCAP_BRIDGE, "--config", config_path, "--lcm-url", url},
        path("mocap.out"), path("mocap.err"));
    auto corrector = std::make_unique<Child>(
        std::vector<std::string>{FTCAL_CORRECTOR, "--config", config_path, "--calibration",
                                 path("truth.pbtxt"), "--lcm-url", url},
        path("corrector.out"), path("corrector.err"));

    const std::int64_t window_from = NowUs() + static_cast<std::int64_t>(warmup_s * 1e6);
    const std::int64_t window_to = window_from + static_cast<std::int64_t>(duration_s * 1e6);
    // What each stage costs over the counted window (CPU s, in the order of `roles`).
    const std::vector<std::string> roles = {"twin",           "ATI bridge(s)", "Dynamixel bridge",
                                            "mocap bridge",   "corrector",     "recorder",
                                            "this subscriber"};
    auto cpu_now = [&] {
      const ProcTable procs = ReadProcTable();
      double bridges_cpu = 0;
      for (const auto& a : ati) bridges_cpu += TreeCpuS(procs, a->pid());
      return std::vector<double>{TreeCpuS(procs, sim->pid()),
                                 bridges_cpu,
                                 TreeCpuS(procs, dxl->pid()),
                                 TreeCpuS(procs, mocap->pid()),
                                 TreeCpuS(procs, corrector->pid()),
                                 recorder ? TreeCpuS(procs, recorder->pid()) : 0.0,
                                 SelfCpuS()};
    };
    SleepS(std::max(0.0, double(window_from - NowUs()) * 1e-6));
    const std::vector<double> cpu_from = cpu_now();
    const auto ticks_from = MachineTicks();
    const KernelDrops kernel_from = ReadKernelDrops();
    const std::int64_t cpu_window_from = NowUs();
    SleepS(std::max(0.0, double(window_to - NowUs()) * 1e-6));
    const std::vector<double> cpu_to = cpu_now();
    const auto ticks_to = MachineTicks();
    const KernelDrops kernel_to = ReadKernelDrops();
    const double cpu_window_s = double(NowUs() - cpu_window_from) * 1e-6;
    // The ATI stages end here (the bridges send the boxes RDT stop), unless the commands are to
    // run under the ATI load: on two busy cores that load starves the twin's servo emulator
    // (and this program's bus tap) until the Dynamixel bridge's replies come late, it degrades
    // past dynamixel.deadman_s and its command gate goes to FAULT, which disarms it: then no
    // goal is written at all, and the figure would be the gate's, not the path's.
    auto stop_ati = [&] {
      for (auto& a : ati) Stop(a);
      Stop(corrector);
    };
    if (!commands_under_load) stop_ati();
    SleepS(0.5);

    // ---- command latency ----
    std::vector<int> ids;
    for (int k = 0; k < config.robot().leg_size(); ++k)
      ids.push_back(static_cast<int>(config.robot().leg(k).servo().id()));
    const std::vector<double> pose_a = {0.3, -0.2, 0.25, -0.3, 0.2, -0.25};
    const std::vector<double> pose_b = {-0.25, 0.3, -0.2, 0.25, -0.3, 0.2};
    std::vector<std::int64_t> published;
    // Heartbeats from before the ARM: the gate holds an armed bridge whose commander is silent
    // for dynamixel.deadman_s, far less than the 1 s between the status reports that say armed
    // (a heartbeat before the ARM is only refused and counted).
    commander.StartHeartbeat(0.05);
    bool armed = false;
    for (int attempt = 0; attempt < 6 && !armed; ++attempt) {
      commander.Arm();
      for (int i = 0; i < 20 && !armed; ++i) {
        SleepS(0.1);
        armed = listener->dxl_mode() == 1;
      }
    }
    if (armed) {
      for (int i = 0; i < commands; ++i) {
        const std::vector<double>& goal = i % 2 == 0 ? pose_a : pose_b;
        published.push_back(NowUs());
        commander.Move(ids, goal);
        SleepS(command_period_s);
      }
    }
    commander.StopHeartbeat();
    commander.Send(ftcal::servo_command_t::DISARM);
    SleepS(0.3);

    // The devices stop before the bridges that are left, so every record the twin sent has
    // had time to arrive (with the ATI bridges stopped first, the records sent after a bridge
    // closed its socket are the difference between the twin's count and the bridges').
    Stop(sim, 15);
    SleepS(0.5);
    stop_ati();
    Stop(dxl);
    Stop(mocap);
    Stop(recorder);
    listener->Stop();
    const KernelDrops kernel_after = ReadKernelDrops();
    const auto goal_writes = tap->writes();
    tap.reset();

    // ---- figures ----
    std::printf(
        "live_latency_bench: twin (ftcal-sim live, scenario commanded, seed %llu), 6 boxes "
        "x %d records/s; %s%s; Dynamixel and mocap bridges; ftcal-corrector with the "
        "true calibration; subscriber %s; %.0f s counted after %.0f s of warm-up\n",
        (unsigned long long)seed, rate_hz,
        bridges == 6 ? "six ATI bridges (--legs X)" : "one ATI bridge for all six legs",
        no_realtime ? "" : " --realtime", listener->realtime() ? "SCHED_FIFO" : "SCHED_OTHER",
        duration_s, warmup_s);
    std::vector<std::int64_t> ft_lat, ft_lat_lcm, cw_lat, cw_lat_lcm, corr_lat;
    long long window_sent = 0, window_ft = 0, window_cw = 0, gaps = 0;
    long long run_ft = 0, run_cw = 0;
    std::printf(
        "%-4s %12s %10s %10s %10s   (in the window; twin: by RDT sequence, restarts apart)\n",
        "leg", "twin", "FT heard", "FT gaps", "CW heard");
    for (int k = 0; k < 6; ++k) {
      const auto& ft = listener->ft_[k];
      const auto& cw = listener->cw_[k];
      run_ft += static_cast<long long>(ft.size());
      run_cw += static_cast<long long>(cw.size());
      std::map<std::int64_t, std::int64_t> ft_heard_at;  // utime -> handled
      std::vector<std::int64_t> in_window;
      std::int64_t prev = -1, n_ft = 0, n_gap = 0;
      for (const auto& e : ft) {
        if (e.utime < window_from || e.utime >= window_to) continue;
        in_window.push_back(e.rdt_sequence);
        if (prev >= 0 && e.rdt_sequence + kRdtRestart < prev) prev = -1;
        if (prev >= 0 && e.rdt_sequence > prev + 1) n_gap += e.rdt_sequence - prev - 1;
        prev = std::max(prev, e.rdt_sequence);
        ++n_ft;
        ft_lat.push_back(e.handled - e.receipt);
        ft_lat_lcm.push_back(e.lcm_recv - e.receipt);
        ft_heard_at[e.utime] = e.handled;
      }
      std::int64_t n_cw = 0;
      for (const auto& e : cw) {
        if (e.utime < window_from || e.utime >= window_to) continue;
        ++n_cw;
        cw_lat.push_back(e.handled - e.receipt);
        cw_lat_lcm.push_back(e.lcm_recv - e.receipt);
        const auto it = ft_heard_at.find(e.utime);
        if (it != ft_heard_at.end()) corr_lat.push_back(e.handled - it->second);
      }
      const std::int64_t sent = SentByRdtSequence(in_window);
      window_sent += sent;
      window_ft += n_ft;
      window_cw += n_cw;
      gaps += n_gap;
      std::printf("%-4s %12lld %10lld %10lld %10lld\n", kLegs[k].c_str(), (long long)sent,
                  (long long)n_ft, (long long)n_gap, (long long)n_cw);
    }
    std::printf(
        "loss in the window: twin sent %lld, FT_<LEG> heard %lld (missing %lld, %.4f%%), "
        "CONTACT_WRENCH heard %lld (missing %lld, %.4f%%)\n",
        window_sent, window_ft, window_sent - window_ft,
        window_sent > 0 ? 100.0 * double(window_sent - window_ft) / double(window_sent) : 0.0,
        window_cw, window_sent - window_cw,
        window_sent > 0 ? 100.0 * double(window_sent - window_cw) / double(window_sent) : 0.0);
    if (record) {
      // The recording, counted as this subscriber's heard: the window's FT by RDT sequence
      // against the twin's (the same first..last as above), its CONTACT_WRENCH against them.
      std::array<std::vector<std::int64_t>, 6> seq;
      std::array<long long, 6> rec_cw{};
      long long undecodable = 0;
      lcm::LogFile log(path("session.lcmlog"), "r");
      while (log.good()) {
        const lcm::LogEvent* e = log.readNextEvent();
        if (e == nullptr) break;
        if (e->channel.rfind("FT_", 0) == 0) {
          ftcal::ft_batch_t m;
          if (m.decode(e->data, 0, e->datalen) != e->datalen) {
            ++undecodable;
            continue;
          }
          const int k = Listener::LegOf(m.leg);
          for (int i = 0; k >= 0 && i < m.n; ++i) {
            if (m.sample_utime[i] >= window_from && m.sample_utime[i] < window_to)
              seq[k].push_back(m.rdt_sequence[i]);
          }
        } else if (e->channel == "CONTACT_WRENCH") {
          ftcal::contact_wrench_t m;
          if (m.decode(e->data, 0, e->datalen) != e->datalen || m.leg < 0 || m.leg >= 6) {
            ++undecodable;
            continue;
          }
          for (int i = 0; i < m.n; ++i) {
            if (m.utime[i] >= window_from && m.utime[i] < window_to) ++rec_cw[m.leg];
          }
        }
      }
      long long rec_sent = 0, rec_ft = 0, rec_cw_total = 0;
      for (int k = 0; k < 6; ++k) {
        if (seq[k].empty()) continue;
        rec_sent += SentByRdtSequence(seq[k]);
        rec_ft += static_cast<long long>(seq[k].size());
        rec_cw_total += rec_cw[k];
      }
      // scripts/record's own test: it runs lcm-logger under chrt when this succeeds.
      const bool fifo = ::system("chrt -f 10 true >/dev/null 2>&1") == 0;
      std::printf(
          "recording (scripts/record: ftcal-record, recv_buf_size 32 MB%s) in the window: "
          "twin sent %lld (by the recorded RDT sequences), FT_<LEG> recorded %lld "
          "(missing %lld, %.4f%%), CONTACT_WRENCH recorded %lld (missing %lld, %.4f%%), "
          "undecodable %lld; the recorder said: %s\n",
          fifo ? ", SCHED_FIFO" : "", rec_sent, rec_ft, rec_sent - rec_ft,
          rec_sent > 0 ? 100.0 * double(rec_sent - rec_ft) / double(rec_sent) : 0.0, rec_cw_total,
          rec_sent - rec_cw_total,
          rec_sent > 0 ? 100.0 * double(rec_sent - rec_cw_total) / double(rec_sent) : 0.0,
          undecodable, ftcal::testing::ReadFile(path("record.err")).c_str());
      if (rec_ft == 0) rc = 1;
    }
    // The twin's own count over the whole run (warm-up and the command phase included).
    long long twin_records = 0;
    {
      std::istringstream in(ftcal::testing::ReadFile(path("sim.out")));
      const std::regex re("^  ati [A-Z]+: records ([0-9]+) datagrams ([0-9]+)");
      for (std::string line; std::getline(in, line);) {
        std::smatch m;
        // Records, not datagrams: a buffered box sends k records per datagram.
        if (std::regex_search(line, m, re)) twin_records += std::stoll(m[1]);
      }
    }
    std::printf(
        "loss over the whole run: twin sent %lld records, FT_<LEG> heard %lld, "
        "CONTACT_WRENCH heard %lld, undecodable %lld\n",
        twin_records, run_ft, run_cw, (long long)listener->undecodable);
    // The stages' own accounts, from their exit summaries: where the samples went.
    {
      long long received = 0, published = 0, lost = 0;
      std::vector<std::string> latency;
      for (std::size_t i = 0; i < ati.size(); ++i) {
        std::istringstream in(ftcal::testing::ReadFile(
            path(bridges == 1 ? std::string("ati.err") : "ati-" + kLegs[i] + ".err")));
        const std::regex counts(": received ([0-9]+) published ([0-9]+) lost ([0-9]+)");
        for (std::string line; std::getline(in, line);) {
          std::smatch m;
          if (std::regex_search(line, m, counts)) {
            received += std::stoll(m[1]);
            published += std::stoll(m[2]);
            lost += std::stoll(m[3]);
          }
          const auto at = line.find("latency receipt->published: ");
          if (at != std::string::npos) latency.push_back(line.substr(at + 28));
        }
      }
      std::printf(
          "ATI bridge(s), their own count over the run: received %lld published %lld "
          "lost (by RDT sequence) %lld\n",
          received, published, lost);
      for (std::size_t i = 0; i < latency.size(); ++i) {
        std::printf("  bridge %zu receipt->lcm_publish returned (its own measure): %s\n", i,
                    latency[i].c_str());
      }
      std::istringstream in(ftcal::testing::ReadFile(path("corrector.err")));
      for (std::string line; std::getline(in, line);) {
        const auto at = line.find(" leg-samples corrected");
        if (at != std::string::npos) {
          const auto from = line.rfind(' ', at - 1);
          std::printf("ftcal-corrector, its own count over the run:%s\n",
                      line.substr(from == std::string::npos ? 0 : from).c_str());
        }
      }
    }
    std::printf(
        "kernel, from the bridges' start to their end: UDP datagrams delivered to sockets "
        "%lld, dropped at a full socket buffer %lld (InErrors %lld), dropped at a full "
        "CPU backlog %lld (machine-wide)\n",
        kernel_after.in_datagrams - kernel_before.in_datagrams,
        kernel_after.rcvbuf_errors - kernel_before.rcvbuf_errors,
        kernel_after.in_errors - kernel_before.in_errors,
        kernel_after.backlog_drops - kernel_before.backlog_drops);
    {
      // The CPU budget of the window: each stage's share of one core, the machine's split, and
      // the cost per leg-sample the twin sent. Under loss the stages were starved, so the cost
      // per sample offered is a lower bound; at a rate where nothing is lost it is the price.
      std::string shares;
      double total = 0, twin = 0;
      for (std::size_t i = 0; i < roles.size(); ++i) {
        if (roles[i] == "recorder" && !recorder) continue;
        const double share = (cpu_to[i] - cpu_from[i]) / cpu_window_s;
        total += share;
        if (i == 0) twin = share;
        char buf[96];
        std::snprintf(buf, sizeof buf, "%s%s %.1f", shares.empty() ? "" : ", ", roles[i].c_str(),
                      100 * share);
        shares += buf;
      }
      long long dt[7], all = 0;
      for (int i = 0; i < 7; ++i) all += dt[i] = ticks_to[i] - ticks_from[i];
      auto pct = [&](long long v) { return all > 0 ? 100.0 * double(v) / double(all) : 0.0; };
      const long cores = ::sysconf(_SC_NPROCESSORS_ONLN);
      std::printf(
          "CPU in the window (%% of one core): %s; sum %.1f of %ld cores' %ld; machine: user "
          "%.0f%% system %.0f%% softirq %.0f%% idle %.0f%%\n",
          shares.c_str(), 100 * total, cores, 100 * cores, pct(dt[0] + dt[1]), pct(dt[2]),
          pct(dt[6]), pct(dt[3] + dt[4]));
      if (window_sent > 0) {
        const double per = total * cpu_window_s / double(window_sent) * 1e6;
        const double per_no_twin = (total - twin) * cpu_window_s / double(window_sent) * 1e6;
        const double delivered =
            double(kernel_to.in_datagrams - kernel_from.in_datagrams) / double(window_sent);
        std::printf(
            "CPU per leg-sample the twin sent in the window: %.1f us (%.1f us without the "
            "twin)%s; UDP datagrams delivered to sockets per leg-sample %.2f, at %.2f us each "
            "on this machine (one sent and received through the loopback, measured before the "
            "run): the datagram hops alone cost %.1f us per leg-sample, %.2f cores at "
            "6 x 7000/s\n",
            per, per_no_twin,
            window_sent - window_cw > window_sent / 100
                ? " [over 1% lost: the stages were starved, a lower bound]"
                : "",
            delivered, datagram_us, delivered * datagram_us, delivered * datagram_us * 42000e-6);
      }
    }
    std::printf(
        "this machine before the run, one UDP hop between two threads over the loopback (half a "
        "round trip, nothing else running): %s\n",
        hop_latency.c_str());
    std::printf(
        "RDT receipt in the bridge -> FT_<LEG> in this subscriber's handler (bridge + LCM "
        "hop): %s\n",
        Quantiles(ft_lat).c_str());
    std::printf(
        "  the same to liblcm's receive stamp (recv_utime) in this subscriber:  "
        "%s\n",
        Quantiles(ft_lat_lcm).c_str());
    std::printf(
        "RDT receipt in the bridge -> CONTACT_WRENCH in this subscriber's handler "
        "(+ corrector): %s\n",
        Quantiles(cw_lat).c_str());
    std::printf("  the same to liblcm's receive stamp (recv_utime) in this subscriber:  %s\n",
                Quantiles(cw_lat_lcm).c_str());
    std::printf(
        "FT_<LEG> handled -> its CONTACT_WRENCH handled here (the corrector's stage, as "
        "seen from one subscriber): %s\n",
        Quantiles(corr_lat).c_str());

    if (!armed) {
      std::printf(
          "command latency: not measured, the Dynamixel bridge never reported armed (its "
          "log: --keep)\n");
      rc = 1;
    } else {
      // For each MOVE the first goal write after its publish whose goals differ from the write
      // before the publish (the poses alternate, so every MOVE changes every goal).
      std::vector<std::int64_t> cmd_lat;
      std::string unmatched_at;
      int unmatched = 0;
      for (std::size_t i = 0; i < published.size(); ++i) {
        const std::int64_t t = published[i];
        const std::int64_t until = i + 1 < published.size() ? published[i + 1] : t + 1'000'000;
        std::optional<std::vector<std::pair<int, std::int32_t>>> before;
        std::optional<std::int64_t> at;
        for (const auto& w : goal_writes) {
          if (w.t_us < t) {
            before = w.goals;
          } else if (w.t_us < until && (!before || w.goals != *before)) {
            at = w.t_us;
            break;
          }
        }
        if (at) {
          cmd_lat.push_back(*at - t);
        } else {
          ++unmatched;
          unmatched_at += " " + std::to_string(i);
        }
      }
      std::printf(
          "SERVO_CMD MOVE published -> its Sync Write of Goal Position on the bus "
          "(Dynamixel bridge at %.0f Hz, %s): %s; %d of %zu MOVEs without a write of their "
          "goals before the next MOVE%s%s\n",
          config.dynamixel().rate_hz(),
          commands_under_load ? "under the ATI load" : "ATI stages stopped",
          Quantiles(cmd_lat).c_str(), unmatched, published.size(), unmatched > 0 ? ": MOVE" : "",
          unmatched_at.c_str());
      if (cmd_lat.empty()) rc = 1;
    }
    double load[3] = {0, 0, 0};
    if (::getloadavg(load, 3) == 3) {
      std::printf(
          "machine load average %.2f %.2f %.2f on %ld cores (the figures are only as "
          "good as the machine is quiet)\n",
          load[0], load[1], load[2], ::sysconf(_SC_NPROCESSORS_ONLN));
    }
    if (window_ft == 0 || window_cw == 0) {
      std::fprintf(stderr, "nothing heard: corrector %s\nati %s\n",
                   ftcal::testing::ReadFile(path("corrector.err")).c_str(),
                   ftcal::testing::ReadFile(path(bridges == 6 ? "ati-HL.err" : "ati.err")).c_str());
      rc = 1;
    }
  }
  if (keep) {
    std::printf("processes' logs kept in %s\n", dir.c_str());
  } else {
    ftcal::testing::RemoveTree(dir);
  }
  return rc;
}
