// ftcal-ati-bridge against the twin's emulated Net F/T boxes (ftcal-emulate-ati), as real
// processes over real UDP and LCM multicast inside a private network namespace (ctest runs this
// binary through scripts/netns-exec). The emulator writes the truth series of every record it
// generated and what it did to it; the test compares what the bridge published (heard on LCM)
// and what it counted (its final heartbeat) with that truth.
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <mutex>
#include <set>
#include <sstream>
#include <thread>

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/resource.h>
#include <sys/socket.h>

#include <google/protobuf/text_format.h>
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "ati_bridge.h"
#include "ati_emulator.h"
#include "ati_truth.h"
#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/config.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/service_status_t.hpp"

// After Eigen (through ati_bridge.h): the split-mode httplib.h pulls in headers whose macros
// break Eigen's templates when they come first.
#include <httplib.h>

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
// The listener asks for a large receive buffer: it hears every sample of six transducers.
constexpr char kListenUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=8388608";
constexpr double kCountsPerUnit = 1e6;  // the emulator's default cfgcpf and cfgcpt

using testing::SleepS;

// One row of the emulator's truth CSV.
using TruthRow = testing::AtiTruthRow;

// One record of a published ft_batch_t, with what its message said of it: the tests compare
// the bridge's output with the emulator's truth record by record.
struct FtRec {
  std::string leg;
  std::int64_t message = 0;  // the published message it came in, numbered in the order heard
  int n = 0;                 // records in that message
  int index = 0;             // its place in that message
  std::int64_t receipt_utime = 0;
  std::int64_t sample_utime = 0;
  std::int64_t rdt_sequence = 0;
  std::int64_t ft_sequence = 0;
  std::int64_t status = 0;
  std::array<std::int32_t, 6> counts{};
  std::array<double, 6> wrench{};
  std::int32_t gap = 0;
  std::int32_t flags = 0;
};

// Appends the records of published message number `message`. A message of no records or of
// more than MAX_N fails the test (LCM's decoder has already made every array n long).
void AppendRecords(const ft_batch_t& m, std::int64_t message, std::vector<FtRec>* out) {
  EXPECT_GE(m.n, 1) << m.leg << ": a message without records";
  EXPECT_LE(m.n, int{ft_batch_t::MAX_N}) << m.leg;
  for (int i = 0; i < m.n; ++i) {
    FtRec r;
    r.leg = m.leg;
    r.message = message;
    r.n = m.n;
    r.index = i;
    r.receipt_utime = m.receipt_utime;
    r.sample_utime = m.sample_utime[i];
    r.rdt_sequence = m.rdt_sequence[i];
    r.ft_sequence = m.ft_sequence[i];
    r.status = m.status[i];
    for (int j = 0; j < 6; ++j) {
      r.counts[j] = m.counts[i][j];
      r.wrench[j] = m.wrench[i][j];
    }
    r.gap = m.gap[i];
    r.flags = m.flags[i];
    out->push_back(r);
  }
}

// The box's internal sample counter (ft_sequence): 7000 ticks a second whatever its RDT rate.
constexpr double kTickUs = 1e6 / 7000;
// How far the spacing of two records of one datagram may be from their distance on that
// counter. The bridge maps a record's counter to host time by its DeviceClock: t = a + b x, x
// the counter over 7000 Hz, each result rounded to a whole us (device_clock.cc, Map). Two
// records dt ticks apart are therefore b * dt * kTickUs apart, give or take 1 us of rounding.
// b is the box's rate against the host's: 1 exactly until the map spans 2 s, then fitted from
// the least delayed datagrams. Crystals keep b within 100 ppm of 1, and the host clock is
// slewed by at most 500 ppm; 1000 ppm is twice the worst of that.
double SpacingToleranceUs(std::int64_t dt_ticks) {
  return 1.0 + 1e-3 * static_cast<double>(dt_ticks) * kTickUs;
}

// The times of one leg's published records, each with the datagram the truth says it came in:
//  - one message per datagram: a datagram's records came in one message, which held nothing
//    else (so they share its receipt_utime), and its n is the number of them;
//  - sample_utime rises strictly over the stream and is never after its message's receipt;
//  - within a message, consecutive records are spaced by their distance on the box's counter as
//    the clock map gives it (SpacingToleranceUs). The bridge's clamps (never after the receipt,
//    always after the previous record) can only pull a datagram's records closer together, so
//    a spacing never exceeds that distance; a datagram spaced by it throughout is counted.
// Returns how many datagrams of `k` records were spaced by the counter throughout.
int ExpectStampsByCounter(const std::vector<std::pair<std::uint32_t, FtRec>>& by_datagram, int k) {
  std::map<std::uint32_t, std::vector<const FtRec*>> groups;
  std::map<std::int64_t, std::set<std::uint32_t>> datagrams_of_message;
  for (std::size_t i = 0; i < by_datagram.size(); ++i) {
    const FtRec& m = by_datagram[i].second;
    if (i > 0) {
      EXPECT_GT(m.sample_utime, by_datagram[i - 1].second.sample_utime)
          << "rdt " << m.rdt_sequence << ": sample times only rise";
    }
    EXPECT_LE(m.sample_utime, m.receipt_utime)
        << "rdt " << m.rdt_sequence << " (record " << m.index << " of " << m.n
        << "): sampled after its datagram was received";
    groups[by_datagram[i].first].push_back(&m);
    datagrams_of_message[m.message].insert(by_datagram[i].first);
  }
  for (const auto& [message, datagrams] : datagrams_of_message) {
    EXPECT_EQ(datagrams.size(), 1u)
        << "message " << message << " holds records of " << datagrams.size() << " datagrams";
  }
  int by_counter = 0;
  for (const auto& [datagram, records] : groups) {
    const FtRec& first = *records.front();
    // The listener hears a message whole or not at all: all of the datagram's records or none.
    EXPECT_EQ(first.n, static_cast<int>(records.size()))
        << "datagram " << datagram << " (rdt " << first.rdt_sequence << ")";
    bool exact = static_cast<int>(records.size()) == k;
    for (std::size_t i = 0; i < records.size(); ++i) {
      const FtRec& m = *records[i];
      EXPECT_EQ(m.message, first.message)
          << "datagram " << datagram << " split, rdt " << m.rdt_sequence;
      EXPECT_EQ(m.receipt_utime, first.receipt_utime) << "rdt " << m.rdt_sequence;
      EXPECT_EQ(m.index, static_cast<int>(i)) << "rdt " << m.rdt_sequence;
      if (i == 0) continue;
      const FtRec& prev = *records[i - 1];
      const auto ticks = static_cast<std::uint32_t>(m.ft_sequence - prev.ft_sequence);
      const double nominal_us = ticks * kTickUs;
      const double tolerance_us = SpacingToleranceUs(ticks);
      const auto spacing = static_cast<double>(m.sample_utime - prev.sample_utime);
      EXPECT_LE(spacing, nominal_us + tolerance_us)
          << "rdt " << m.rdt_sequence << ": " << ticks << " ticks after the previous record";
      exact = exact && std::abs(spacing - nominal_us) <= tolerance_us;
    }
    by_counter += exact;
  }
  return by_counter;
}

std::vector<TruthRow> ReadTruth(const std::string& path) {
  std::ifstream in(path);
  EXPECT_TRUE(in.good()) << path;
  std::string line;
  std::getline(in, line);
  EXPECT_EQ(line.rfind("leg,stream,t_s,rdt_sequence,ft_sequence,status,fx_counts", 0), 0u) << line;
  std::vector<TruthRow> rows;
  while (std::getline(in, line)) {
    const auto f = testing::SplitCsv(line);
    if (f.size() != testing::kAtiTruthColumns) {
      ADD_FAILURE() << "bad truth line: " << line;
      continue;
    }
    rows.push_back(testing::ParseAtiTruthRow(f));
  }
  return rows;
}

// A record heard on LCM, and when its message was handled.
struct Heard {
  FtRec msg;
  Clock::time_point when;
};

// Listens on LCM for FT_<LEG> samples and FTCAL_STATUS heartbeats.
class Collector {
 public:
  Collector() : lcm_(kListenUrl) {
    EXPECT_TRUE(lcm_.good());
    // LCM's default queue of 30 messages per subscription drops messages of six boxes' bursts
    // (one message per datagram each) while this thread is busy.
    lcm_.subscribe("FT_.*", &Collector::OnSample, this)->setQueueCapacity(100000);
    lcm_.subscribe("FTCAL_STATUS", &Collector::OnStatus, this)->setQueueCapacity(10000);
    thread_ = std::thread([this] {
      while (!stop_) lcm_.handleTimeout(50);
    });
  }
  ~Collector() {
    stop_ = true;
    thread_.join();
  }
  void OnSample(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ft_batch_t m;
    if (m.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) {
      ++undecodable_;
      return;
    }
    const auto when = Clock::now();
    std::vector<FtRec> records;
    std::lock_guard<std::mutex> lock(mu_);
    AppendRecords(m, messages_++, &records);
    if (channel != "FT_" + m.leg) ++wrong_channel_;
    for (const FtRec& r : records) samples_.push_back({r, when});
  }
  void OnStatus(const lcm::ReceiveBuffer* rbuf, const std::string&) {
    service_status_t m;
    if (m.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) return;
    std::lock_guard<std::mutex> lock(mu_);
    statuses_.push_back({m, Clock::now()});
  }
  std::vector<Heard> Samples() {
    std::lock_guard<std::mutex> lock(mu_);
    return samples_;
  }
  std::vector<std::pair<service_status_t, Clock::time_point>> Statuses() {
    std::lock_guard<std::mutex> lock(mu_);
    return statuses_;
  }
  int undecodable() const { return undecodable_; }
  int wrong_channel() {
    std::lock_guard<std::mutex> lock(mu_);
    return wrong_channel_;
  }

 private:
  lcm::LCM lcm_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  std::mutex mu_;
  std::vector<Heard> samples_;  // per record
  std::int64_t messages_ = 0;
  std::vector<std::pair<service_status_t, Clock::time_point>> statuses_;
  std::atomic<int> undecodable_{0};
  int wrong_channel_ = 0;
};

std::int64_t Counter(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  ADD_FAILURE() << "no counter " << name << " in the heartbeat of " << s.name;
  return -1;
}

int CountOccurrences(const std::string& text, const std::string& part) {
  int n = 0;
  for (auto at = text.find(part); at != std::string::npos; at = text.find(part, at + 1)) ++n;
  return n;
}

// Waits until a heartbeat of process `pid` satisfies `done`; false at the deadline.
bool WaitForHeartbeat(Collector& c, pid_t pid,
                      const std::function<bool(const service_status_t&)>& done, double timeout_s) {
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(timeout_s));
  while (Clock::now() < deadline) {
    for (const auto& [s, when] : c.Statuses()) {
      if (s.pid == pid && done(s)) return true;
    }
    SleepS(0.05);
  }
  return false;
}

// The counter of a heartbeat, or -1 when it has none of that name (no test failure: a heartbeat
// being waited for may come from before the counter's first value).
std::int64_t CounterOr(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  return -1;
}

config::Config SimConfig();

// config/sim.pbtxt with `k` records per datagram on every leg, written to `path`.
std::string WriteConfigWithRecordsPerDatagram(const std::string& path, int k) {
  config::Config cfg = SimConfig();
  for (auto& leg : *cfg.mutable_robot()->mutable_leg()) {
    leg.mutable_ati()->set_records_per_datagram(static_cast<std::uint32_t>(k));
  }
  std::string text;
  EXPECT_TRUE(google::protobuf::TextFormat::PrintToString(cfg, &text));
  std::ofstream(path) << text;
  return path;
}

class AtiBridgeTest : public testing::NetnsDirTest {
 protected:
  // Starts the emulator and waits until its boxes are bound.
  std::unique_ptr<Child> StartEmulator(std::vector<std::string> args) {
    std::vector<std::string> argv = {FTCAL_EMULATE_ATI, "--ready", Path("ready"), "--truth",
                                     Path("truth.csv")};
    argv.insert(argv.end(), args.begin(), args.end());
    auto child = std::make_unique<Child>(argv, Path("emulator.out"), Path("emulator.err"));
    const auto deadline = Clock::now() + std::chrono::seconds(20);
    while (::access(Path("ready").c_str(), F_OK) != 0) {
      if (!child->running() || Clock::now() > deadline) {
        ADD_FAILURE() << "emulator not ready: " << ReadFile(Path("emulator.err"));
        return child;
      }
      if (child->Wait(0.02)) {
        ADD_FAILURE() << "emulator ended: " << ReadFile(Path("emulator.err"));
        return child;
      }
    }
    return child;
  }
  std::unique_ptr<Child> StartBridge(const std::string& tag, std::vector<std::string> args) {
    std::vector<std::string> argv = {FTCAL_ATI_BRIDGE, "--lcm-url", kUrl, "--log-level", "info"};
    argv.insert(argv.end(), args.begin(), args.end());
    return std::make_unique<Child>(argv, Path(tag + ".out"), Path(tag + ".err"));
  }
  static void Terminate(Child& child, const std::string& what) {
    child.Signal(SIGTERM);
    const auto status = child.Wait(10);
    ASSERT_TRUE(status.has_value()) << what << " did not end on SIGTERM";
    EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
        << what << ": " << DescribeWaitStatus(*status);
  }
  // The last heartbeat of process `pid`.
  static service_status_t LastStatus(Collector& c, pid_t pid) {
    service_status_t last;
    last.pid = -1;
    for (const auto& [s, when] : c.Statuses()) {
      if (s.pid == pid) last = s;
    }
    EXPECT_EQ(last.pid, pid) << "no heartbeat heard from pid " << pid;
    return last;
  }
};

// Every sample heard must be a record the emulator generated and delivered intact, converted
// exactly: counts equal, wrench = counts / cpf (the sign is +1 in sim.pbtxt), status equal.
// Returns the number of samples that matched.
int ExpectSamplesMatchTruth(const std::vector<Heard>& heard, const std::vector<TruthRow>& truth) {
  std::multimap<std::tuple<std::string, std::uint32_t, std::uint32_t>, const TruthRow*> index;
  for (const TruthRow& r : truth)
    index.emplace(std::make_tuple(r.leg, r.rdt_sequence, r.ft_sequence), &r);
  int matched = 0;
  for (const Heard& h : heard) {
    const FtRec& m = h.msg;
    const auto range =
        index.equal_range(std::make_tuple(m.leg, static_cast<std::uint32_t>(m.rdt_sequence),
                                          static_cast<std::uint32_t>(m.ft_sequence)));
    const TruthRow* row = nullptr;
    for (auto it = range.first; it != range.second; ++it) {
      bool same = it->second->status == static_cast<std::uint32_t>(m.status);
      for (int i = 0; i < 6; ++i) same = same && it->second->counts[i] == m.counts[i];
      if (same) row = it->second;
    }
    if (row == nullptr) {
      ADD_FAILURE() << m.leg << " published rdt " << m.rdt_sequence << " ft " << m.ft_sequence
                    << " which the emulator never sent with these counts";
      continue;
    }
    EXPECT_TRUE(row->fault == "none" || row->fault == "duplicate")
        << m.leg << " rdt " << m.rdt_sequence << " was sent as '" << row->fault << "'";
    for (int i = 0; i < 6; ++i) {
      // One count is the resolution; the conversion itself must be exact to rounding.
      EXPECT_NEAR(m.wrench[i], row->counts[i] / kCountsPerUnit, 1e-9) << m.leg << " axis " << i;
    }
    EXPECT_EQ(m.status, 0);
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_STATUS_ERROR) != 0, m.status != 0);
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_GAP) != 0, m.gap > 0);
    ++matched;
  }
  return matched;
}

std::map<std::string, std::vector<FtRec>> ByLeg(const std::vector<Heard>& heard) {
  std::map<std::string, std::vector<FtRec>> out;
  for (const Heard& h : heard) out[h.msg.leg].push_back(h.msg);
  return out;
}

// One leg's samples as heard on LCM: in order, each record once, with the gap of the records that
// went missing before each. The listener itself may miss a message on a loaded machine (LCM over
// UDP), so the gap is checked where the truth says nothing publishable was between two samples
// heard. Returns the number of gaps checked.
int ExpectInOrderWithGaps(const std::vector<FtRec>& samples, const std::vector<TruthRow>& truth,
                          const std::string& leg) {
  std::set<std::int64_t> publishable;
  for (const TruthRow& r : truth) {
    if (r.leg == leg && (r.fault == "none" || r.fault == "duplicate")) {
      publishable.insert(r.rdt_sequence);
    }
  }
  {
    std::set<std::int64_t> missing = publishable;
    for (const auto& m : samples) missing.erase(m.rdt_sequence);
    std::ostringstream os;
    for (auto v : missing) os << v << " ";
    if (!missing.empty()) std::cerr << leg << " not heard on LCM: " << os.str() << "\n";
  }
  std::int64_t prev = 0;
  int gaps_checked = 0;
  for (std::size_t i = 0; i < samples.size(); ++i) {
    const FtRec& m = samples[i];
    EXPECT_GT(m.rdt_sequence, prev) << leg << ": published twice or out of order";
    if (m.rdt_sequence <= prev) return gaps_checked;
    const auto between =
        std::distance(publishable.upper_bound(prev), publishable.lower_bound(m.rdt_sequence));
    if (between == 0) {
      EXPECT_EQ(m.gap, m.rdt_sequence - prev - 1) << "rdt " << m.rdt_sequence;
      EXPECT_EQ((m.flags & ft_batch_t::FLAG_GAP) != 0, m.rdt_sequence - prev > 1);
      if (m.gap > 0) ++gaps_checked;
    }
    // Only the stream's first publishable record carries the restart flag.
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_RESTARTED) != 0, m.rdt_sequence == *publishable.begin());
    prev = m.rdt_sequence;
  }
  return gaps_checked;
}

TEST_F(AtiBridgeTest, InjectedFaultsAreCountedExactlyAndOnlyIntactRecordsArePublished) {
  auto emulator =
      StartEmulator({"--rate", "500", "--duration", "4", "--seed", "7", "--drop", "0.02",
                     "--duplicate", "0.02", "--reorder", "0.02", "--corrupt", "0.02"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  SleepS(0.2);
  // A long silence timeout: a loaded machine must not make the bridge restart the stream.
  auto bridge = StartBridge("bridge", {"--silence-timeout", "1.0"});
  SleepS(4.8);  // past the end of the data
  Terminate(*bridge, "bridge");
  Terminate(*emulator, "emulator");
  SleepS(0.2);

  const auto truth = ReadTruth(Path("truth.csv"));
  const auto heard = collector.Samples();
  const service_status_t last = LastStatus(collector, bridge->pid());
  EXPECT_EQ(int{last.state}, int{service_status_t::STOPPING});
  EXPECT_EQ(collector.undecodable(), 0);
  EXPECT_EQ(collector.wrong_channel(), 0);
  // Every counter is in the first heartbeat already (docs/writing-a-bridge.md).
  for (const auto& [first, when] : collector.Statuses()) {
    if (first.pid != bridge->pid()) continue;
    const std::set<std::string> names(first.counter_name.begin(),
                                      first.counter_name.begin() + first.num_counters);
    for (int i = 0; i < last.num_counters; ++i) {
      EXPECT_EQ(names.count(last.counter_name[i]), 1u)
          << last.counter_name[i] << " is not in the first heartbeat";
    }
    break;
  }

  const int matched = ExpectSamplesMatchTruth(heard, truth);
  EXPECT_EQ(matched, static_cast<int>(heard.size()));

  const auto by_leg = ByLeg(heard);
  for (const char* leg : {"HL", "ML", "FL", "HR", "MR", "FR"}) {
    SCOPED_TRACE(leg);
    testing::AtiLegTally tally = testing::TallyLeg(truth, leg);
    auto& faults = tally.faults;
    ASSERT_EQ(tally.streams.size(), 1u)
        << "the bridge restarted the stream: counts are not comparable";
    ASSERT_GT(faults["none"], 1000);
    // Each kind of fault happened (2% of ~1900 records) and was counted as what it is.
    const std::string p = std::string(leg) + ".";
    testing::ExpectFaultsCounted(tally,
                                 [&](const std::string& name) { return Counter(last, p + name); });
    EXPECT_EQ(Counter(last, p + "published"), faults["none"] + faults["duplicate"]);
    EXPECT_EQ(Counter(last, p + "restarts"), 1);
    EXPECT_EQ(Counter(last, p + "calibration_reads"), 1);

    // Heard on LCM: in order, with the gap of the records that went missing before each.
    const auto& samples = by_leg.at(leg);
    const std::int64_t expected = faults["none"] + faults["duplicate"];
    EXPECT_GE(static_cast<std::int64_t>(samples.size()), expected * 9 / 10);
    EXPECT_LE(static_cast<std::int64_t>(samples.size()), expected);
    EXPECT_GT(ExpectInOrderWithGaps(samples, truth, leg), 5);
  }
}

TEST_F(AtiBridgeTest, SilenceIsReportedDegradedAndRebootRereadsTheCalibrationPage) {
  auto emulator = StartEmulator({"--legs", "HL,ML", "--rate", "1000", "--duration", "7",
                                 "--silence", "HL:2.0:2.0", "--reboot", "ML:3.0"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  SleepS(0.2);
  auto bridge = StartBridge("bridge", {"--legs", "HL,ML"});
  SleepS(6.5);
  Terminate(*bridge, "bridge");
  Terminate(*emulator, "emulator");

  const auto truth = ReadTruth(Path("truth.csv"));
  const auto heard = collector.Samples();
  EXPECT_EQ(ExpectSamplesMatchTruth(heard, truth), static_cast<int>(heard.size()));

  // The heartbeat went DEGRADED during the silence and back to RUNNING after it; while
  // DEGRADED it said why (it once said nothing), and once healthy nothing.
  bool degraded = false, running_after = false;
  for (const auto& [s, when] : collector.Statuses()) {
    if (s.pid != bridge->pid()) continue;
    if (s.state == service_status_t::DEGRADED) {
      degraded = true;
      EXPECT_TRUE(s.last_error.rfind("HL: ", 0) == 0 || s.last_error.rfind("ML: ", 0) == 0)
          << "'" << s.last_error << "'";
    }
    if (degraded && s.state == service_status_t::RUNNING) {
      running_after = true;
      EXPECT_EQ(s.last_error, "");
    }
  }
  EXPECT_TRUE(degraded);
  EXPECT_TRUE(running_after);
  const service_status_t last = LastStatus(collector, bridge->pid());
  EXPECT_GE(Counter(last, "HL.silences"), 1);
  EXPECT_EQ(Counter(last, "HL.reboots"), 0);
  EXPECT_EQ(Counter(last, "ML.reboots"), 1);
  EXPECT_EQ(Counter(last, "ML.calibration_reads"), 2);

  const auto by_leg = ByLeg(heard);
  // HL: the stream resumed after the silence as a new stream, its gap visible in ft_sequence.
  {
    const auto& s = by_leg.at("HL");
    bool resumed = false;
    for (std::size_t i = 1; i < s.size(); ++i) {
      const auto ticks = static_cast<std::int32_t>(s[i].ft_sequence - s[i - 1].ft_sequence);
      if (ticks < 7000 * 1.5) continue;  // the 2 s silence must show in ft_sequence
      resumed = true;
      EXPECT_TRUE(s[i].flags & ft_batch_t::FLAG_RESTARTED);
      EXPECT_LT(s[i].rdt_sequence, s[i - 1].rdt_sequence);
    }
    EXPECT_TRUE(resumed);
    EXPECT_GT(s.back().sample_utime - s.front().sample_utime, 4'000'000);
  }
  // ML: after the reboot ft_sequence restarted near 0 and the samples carry on.
  {
    const auto& s = by_leg.at("ML");
    int backwards = 0;
    for (std::size_t i = 1; i < s.size(); ++i) {
      if (static_cast<std::int32_t>(s[i].ft_sequence - s[i - 1].ft_sequence) < 0) {
        ++backwards;
        EXPECT_TRUE(s[i].flags & ft_batch_t::FLAG_RESTARTED);
        EXPECT_LT(s[i].ft_sequence, 7000 * 1.5);
      }
    }
    EXPECT_EQ(backwards, 1);
  }
}

TEST_F(AtiBridgeTest, KilledBridgeRestartsWithinASecondAndItsGapShows) {
  auto emulator = StartEmulator({"--rate", "1000"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  SleepS(0.2);
  auto first = StartBridge("bridge1", {});
  SleepS(1.5);
  first->Signal(SIGKILL);  // a crash: no stop command, no goodbye
  ASSERT_TRUE(first->Wait(5).has_value());
  const auto killed_at = Clock::now();
  SleepS(0.3);
  const auto restarted_at = Clock::now();
  auto second = StartBridge("bridge2", {});
  SleepS(2.0);
  Terminate(*second, "second bridge");
  Terminate(*emulator, "emulator");

  const auto heard = collector.Samples();
  const service_status_t second_status = LastStatus(collector, second->pid());
  EXPECT_EQ(ExpectSamplesMatchTruth(heard, ReadTruth(Path("truth.csv"))),
            static_cast<int>(heard.size()));
  for (const char* leg : {"HL", "ML", "FL", "HR", "MR", "FR"}) {
    SCOPED_TRACE(leg);
    const Heard* before = nullptr;
    const Heard* after = nullptr;
    for (const Heard& h : heard) {
      if (h.msg.leg != leg) continue;
      if (h.when < killed_at) before = &h;
      if (h.when > restarted_at && after == nullptr) after = &h;
    }
    ASSERT_NE(before, nullptr);
    ASSERT_NE(after, nullptr);
    EXPECT_LT(std::chrono::duration<double>(after->when - restarted_at).count(), 1.0);
    // A new stream (the listener may have missed its very first sample on a loaded machine;
    // the bridge's own counters below say the stream began at 1 with nothing lost).
    EXPECT_LT(after->msg.rdt_sequence, before->msg.rdt_sequence);
    EXPECT_EQ((after->msg.flags & ft_batch_t::FLAG_RESTARTED) != 0, after->msg.rdt_sequence == 1);
    EXPECT_EQ(Counter(second_status, std::string(leg) + ".restarts"), 1);
    EXPECT_EQ(Counter(second_status, std::string(leg) + ".lost"), 0);
    EXPECT_EQ(Counter(second_status, std::string(leg) + ".stale"), 0);
    EXPECT_GT(Counter(second_status, std::string(leg) + ".published"), 1000);
    // The time without a bridge shows in the device's own clock.
    EXPECT_GT(after->msg.ft_sequence - before->msg.ft_sequence, 7000 * 0.3);
    EXPECT_GT(after->msg.sample_utime - before->msg.sample_utime, 300'000);
  }
}

TEST_F(AtiBridgeTest, RefusesToStreamWithoutTheCalibrationPage) {
  auto emulator = StartEmulator({"--legs", "HL", "--no-http"});
  ASSERT_FALSE(HasFailure());
  auto bridge = StartBridge("bridge", {"--legs", "HL"});
  const auto status = bridge->Wait(10);
  ASSERT_TRUE(status.has_value()) << "the bridge kept running without counts per unit";
  // docs/exit-codes.md: 4, the device (its calibration page) cannot be read.
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 4) << DescribeWaitStatus(*status);
  const std::string err = ReadFile(Path("bridge.err"));
  EXPECT_NE(err.find("leg HL"), std::string::npos) << err;
  EXPECT_NE(err.find("http://127.0.1.1:8080/netftapi2.xml"), std::string::npos) << err;
  Terminate(*emulator, "emulator");
  // The box never received a start command.
  EXPECT_NE(ReadFile(Path("emulator.err")).find("HL records 0 datagrams 0 starts 0"),
            std::string::npos)
      << ReadFile(Path("emulator.err"));
}

// A buffered run of the emulator's `legs` at `k` records per datagram, against its truth: the
// bridge counted every fault of the truth as what it is, published every intact record once, and
// every record heard is one the box sent, each datagram one message stamped with its receipt.
void ExpectBufferedRunMatchesTruth(const std::vector<TruthRow>& truth,
                                   const std::vector<Heard>& heard, const service_status_t& last,
                                   const std::vector<std::string>& legs, int k) {
  EXPECT_EQ(ExpectSamplesMatchTruth(heard, truth), static_cast<int>(heard.size()));
  const auto by_leg = ByLeg(heard);
  for (const std::string& leg : legs) {
    SCOPED_TRACE(leg);
    testing::AtiLegTally tally = testing::TallyLeg(truth, leg);
    auto& faults = tally.faults;
    ASSERT_EQ(tally.streams.size(), 1u)
        << "the bridge restarted the stream: counts are not comparable";
    // The box sent k records per datagram (a part-filled last one at the end of the data).
    std::map<std::uint32_t, int> sizes;
    std::map<std::uint32_t, std::uint32_t> datagram_of;  // rdt_sequence -> datagram
    for (const TruthRow& r : truth) {
      if (r.leg != leg) continue;
      ++sizes[r.datagram];
      datagram_of[r.rdt_sequence] = r.datagram;
    }
    ASSERT_GT(sizes.size(), 100u);
    for (auto it = sizes.begin(); it != std::prev(sizes.end()); ++it) {
      ASSERT_EQ(it->second, k) << "datagram " << it->first;
    }
    EXPECT_LE(sizes.rbegin()->second, k);

    const std::string p = leg + ".";
    testing::ExpectFaultsCounted(tally,
                                 [&](const std::string& name) { return Counter(last, p + name); });
    const std::int64_t publishable = faults["none"] + faults["duplicate"];
    EXPECT_EQ(Counter(last, p + "published"), publishable);
    EXPECT_EQ(Counter(last, p + "restarts"), 1);
    // Datagrams as the box sent them (a duplicate twice), less the dropped ones.
    std::int64_t sent = 0;
    for (const auto& [fault, ids] : tally.datagrams) {
      if (fault == "none" || fault == "reorder" || fault == "corrupt") sent += ids.size();
      if (fault == "duplicate") sent += 2 * static_cast<std::int64_t>(ids.size());
    }
    EXPECT_EQ(Counter(last, p + "datagrams"), sent);

    const auto& samples = by_leg.at(leg);
    // LCM over UDP may lose a few on a loaded machine; the counters above are the exact account.
    EXPECT_GE(static_cast<std::int64_t>(samples.size()), publishable * 8 / 10);
    EXPECT_GT(ExpectInOrderWithGaps(samples, truth, leg), 5);
    // A lost datagram is k records lost: the gap of the sample after a dropped datagram (with
    // nothing else missing around it) is k.
    int gaps_of_k = 0, messages = 0, messages_of_k = 0;
    std::vector<std::pair<std::uint32_t, FtRec>> by_datagram;
    for (std::size_t i = 0; i < samples.size(); ++i) {
      const FtRec& m = samples[i];
      if (i > 0 && m.gap == k && m.rdt_sequence - samples[i - 1].rdt_sequence == k + 1) {
        ++gaps_of_k;
      }
      const std::uint32_t datagram = datagram_of.at(static_cast<std::uint32_t>(m.rdt_sequence));
      // One message per datagram, of as many records as the box sent in it (k; fewer only in
      // the part-filled last one).
      if (m.index == 0) {
        ++messages;
        messages_of_k += m.n == k;
        EXPECT_EQ(m.n, sizes.at(datagram)) << "datagram " << datagram;
      }
      by_datagram.emplace_back(datagram, m);
    }
    EXPECT_GT(gaps_of_k, 0);
    // Every message heard but the part-filled last one: k records. (Most datagrams' messages
    // were heard: a few percent of the datagrams were faulted, LCM may lose some.)
    EXPECT_GE(messages_of_k, messages - 1);
    EXPECT_GT(messages_of_k, static_cast<int>(sizes.size()) / 2);
    EXPECT_GT(ExpectStampsByCounter(by_datagram, k), 0);
  }
}

// The twin's boxes at 7000 records/s with no records_per_datagram in the config: the box and the
// bridge both take 7 (rate / 1000), and the box streams buffered.
TEST_F(AtiBridgeTest, TwinBoxesAt7000StreamBufferedAndEveryFaultIsCounted) {
  auto emulator = StartEmulator({"--legs", "HL,ML", "--rate", "7000", "--duration", "3", "--seed",
                                 "11", "--drop", "0.01", "--duplicate", "0.01", "--reorder", "0.01",
                                 "--corrupt", "0.01"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  SleepS(0.2);
  auto bridge = StartBridge("bridge", {"--legs", "HL,ML", "--silence-timeout", "1.0"});
  // The end of the data: once the bridge calls each box silent it has read all they sent.
  EXPECT_TRUE(WaitForHeartbeat(
      collector, bridge->pid(),
      [](const service_status_t& s) {
        return CounterOr(s, "HL.silences") >= 1 && CounterOr(s, "ML.silences") >= 1;
      },
      30))
      << ReadFile(Path("bridge.err"));
  Terminate(*bridge, "bridge");
  Terminate(*emulator, "emulator");
  const std::string err = ReadFile(Path("emulator.err"));
  EXPECT_NE(err.find("RDT buffer size 7"), std::string::npos) << err;
  for (const char* leg : {"HL", "ML"}) {
    EXPECT_NE(err.find(std::string(leg) + " records"), std::string::npos);
  }
  EXPECT_EQ(CountOccurrences(err, "buffered_starts 1\n"), 2) << err;
  ExpectBufferedRunMatchesTruth(ReadTruth(Path("truth.csv")), collector.Samples(),
                                LastStatus(collector, bridge->pid()), {"HL", "ML"}, 7);
}

// A box that streams 35 records per datagram at 7000 records/s (200 datagrams/s), named so in the
// config: every record published once with the box's values, every fault counted.
TEST_F(AtiBridgeTest, ABoxOf35RecordsPerDatagramAt7000IsPublishedRecordForRecord) {
  const std::string config = WriteConfigWithRecordsPerDatagram(Path("k35.pbtxt"), 35);
  auto emulator = StartEmulator({"--config", config, "--legs", "HL", "--rate", "7000", "--duration",
                                 "4", "--seed", "5", "--drop", "0.03", "--duplicate", "0.03",
                                 "--reorder", "0.03", "--corrupt", "0.03"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  SleepS(0.2);
  auto bridge =
      StartBridge("bridge", {"--config", config, "--legs", "HL", "--silence-timeout", "1.0"});
  EXPECT_TRUE(WaitForHeartbeat(
      collector, bridge->pid(),
      [](const service_status_t& s) { return CounterOr(s, "HL.silences") >= 1; }, 30))
      << ReadFile(Path("bridge.err"));
  Terminate(*bridge, "bridge");
  Terminate(*emulator, "emulator");
  const std::string err = ReadFile(Path("emulator.err"));
  EXPECT_NE(err.find("RDT buffer size 35"), std::string::npos) << err;
  EXPECT_NE(err.find("buffered_starts 1\n"), std::string::npos) << err;
  EXPECT_NE(ReadFile(Path("bridge.err")).find("buffered, 35 records per datagram"),
            std::string::npos);
  ExpectBufferedRunMatchesTruth(ReadTruth(Path("truth.csv")), collector.Samples(),
                                LastStatus(collector, bridge->pid()), {"HL"}, 35);
}

// The box's RDT buffer size is not what the config implies (35 against 7 for 7000 records/s): the
// bridge refuses to start, naming the box and both values in its log and its last (FAILED)
// heartbeat, with the config's exit code.
TEST_F(AtiBridgeTest, RefusesABoxWhoseBufferSizeIsNotTheConfigs) {
  auto emulator = StartEmulator({"--legs", "HL", "--rate", "7000", "--records-per-datagram", "35"});
  ASSERT_FALSE(HasFailure());
  Collector collector;
  auto bridge = StartBridge("bridge", {"--legs", "HL"});
  const auto status = bridge->Wait(10);
  ASSERT_TRUE(status.has_value()) << "the bridge streamed from a box set up otherwise";
  // docs/exit-codes.md: 3, config.
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 3) << DescribeWaitStatus(*status);
  EXPECT_TRUE(WaitForHeartbeat(
      collector, bridge->pid(),
      [](const service_status_t& s) {
        return s.state == service_status_t::FAILED &&
               s.last_error.find("RDT buffer size (comrdtbsiz) 35") != std::string::npos;
      },
      5))
      << "no FAILED heartbeat naming the box's buffer size";
  const std::string err = ReadFile(Path("bridge.err"));
  for (const char* part : {"leg HL", "127.0.1.1", "http://127.0.1.1:8080/netftapi2.xml",
                           "RDT buffer size (comrdtbsiz) 35",
                           "records_per_datagram by default (comrdtrate 7000 / 1000, rounded) "
                           "is 7"}) {
    EXPECT_NE(err.find(part), std::string::npos) << part << " not in: " << err;
  }
  Terminate(*emulator, "emulator");
  EXPECT_NE(ReadFile(Path("emulator.err")).find("HL records 0 datagrams 0 starts 0"),
            std::string::npos)
      << ReadFile(Path("emulator.err"));
}

// ---- In process: the emulator and the bridge class driven by one loop, no LCM ----

// A fixed device state: the counts of internal sample n are kBase + n on Fx (so every record
// is told apart), the rest constant.
sim::AtiDeviceSample FixedState(std::uint64_t n, std::array<std::int32_t, 6> base,
                                std::uint32_t status = 0) {
  sim::AtiDeviceSample s;
  s.counts = base;
  s.counts[0] += static_cast<std::int32_t>(n % 1000);
  s.status = status;
  return s;
}

// Receives records on a plain UDP socket (the test is the RDT client here).
class RdtClient {
 public:
  RdtClient() {
    fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_in any{};
    any.sin_family = AF_INET;
    EXPECT_EQ(::bind(fd_, reinterpret_cast<sockaddr*>(&any), sizeof any), 0);
  }
  ~RdtClient() { ::close(fd_); }
  void Send(rdt::Command c, std::uint32_t count, const std::string& address) {
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(rdt::kUdpPort);
    ::inet_pton(AF_INET, address.c_str(), &to.sin_addr);
    const auto bytes = rdt::EncodeRequest(c, count);
    ::sendto(fd_, bytes.data(), bytes.size(), 0, reinterpret_cast<sockaddr*>(&to), sizeof to);
  }
  // Steps the emulator for `seconds`, collecting every record that arrives (and, when asked,
  // the records per datagram).
  std::vector<rdt::Record> Run(sim::AtiEmulator& box, double seconds,
                               std::vector<std::size_t>* sizes = nullptr) {
    std::vector<rdt::Record> out;
    const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                        std::chrono::duration<double>(seconds));
    while (Clock::now() < end) {
      box.Step(Clock::now());
      pollfd p{fd_, POLLIN, 0};
      ::poll(&p, 1, 1);
      std::uint8_t buf[2048];
      ssize_t n;
      while ((n = ::recv(fd_, buf, sizeof buf, MSG_DONTWAIT)) >= 0) {
        if (n == 0 || n % rdt::kRecordBytes != 0) continue;
        for (const auto& r : rdt::DecodeDatagram(buf, static_cast<std::size_t>(n))) {
          out.push_back(r);
        }
        if (sizes) sizes->push_back(static_cast<std::size_t>(n) / rdt::kRecordBytes);
      }
    }
    return out;
  }

 private:
  int fd_ = -1;
};

TEST(AtiEmulatorInProcess, CountedStartBiasAndStopBehaveAsTheManualSays) {
  sim::AtiEmulatorOptions o;
  o.name = "HL";
  o.address = "127.0.1.1";
  o.http_port = 0;
  o.rdt_rate_hz = 1000;
  const std::array<std::int32_t, 6> base{1000000, -2000000, 3000000, 40000, -50000, 60000};
  sim::AtiEmulator box(o, [&](std::uint64_t n, double) { return FixedState(n, base); });
  RdtClient client;

  // Start with count 5: exactly five records, rdt_sequence 1..5, ft_sequence 7 apart (7000 Hz
  // internal, 1000 Hz out), then the box stops by itself.
  client.Send(rdt::Command::kRealtime, 5, o.address);
  auto got = client.Run(box, 0.1);
  ASSERT_EQ(got.size(), 5u);
  for (std::size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].rdt_sequence, i + 1);
    if (i > 0) {
      EXPECT_EQ(got[i].ft_sequence - got[i - 1].ft_sequence, 7u);
    }
    EXPECT_EQ(got[i].counts, FixedState(got[i].ft_sequence, base).counts);
  }
  EXPECT_FALSE(box.streaming());

  // Bias tares the present counts: afterwards only the Fx ramp's change since then remains.
  client.Send(rdt::Command::kBias, 0, o.address);
  client.Send(rdt::Command::kRealtime, 0, o.address);
  got = client.Run(box, 0.05);
  ASSERT_GT(got.size(), 10u);
  EXPECT_EQ(got.front().rdt_sequence, 1u);  // every start restarts the stream
  for (const auto& r : got) {
    for (int i = 1; i < 6; ++i) EXPECT_EQ(r.counts[i], 0) << "axis " << i;
    EXPECT_LT(std::abs(r.counts[0]), 1000);
  }
  // Stop: what fell due before the box read it still comes (it is on its way), then nothing.
  client.Send(rdt::Command::kStop, 0, o.address);
  client.Run(box, 0.05);
  EXPECT_FALSE(box.streaming());
  EXPECT_TRUE(client.Run(box, 0.05).empty());
  const auto c = box.counters();
  EXPECT_EQ(c.starts, 2u);
  EXPECT_EQ(c.stops, 1u);
}

// Buffered (0x0003): datagrams of the buffer size the page states, each record numbered on; a
// counted stream ends with the part-filled datagram its count leaves. Real-time (0x0002) from the
// same box: one record per datagram whatever the buffer size.
TEST(AtiEmulatorInProcess, BufferedStartSendsDatagramsOfTheBufferSizeThePageStates) {
  sim::AtiEmulatorOptions o;
  o.name = "HL";
  o.address = "127.0.1.1";
  o.http_port = 0;
  o.rdt_rate_hz = 7000;
  o.rdt_buffer_size = 35;
  const std::array<std::int32_t, 6> base{1000, 2000, 3000, 4000, 5000, 6000};
  sim::AtiEmulator box(o, [&](std::uint64_t n, double) { return FixedState(n, base); });
  EXPECT_NE(box.NetFtXml().find("<comrdtbsiz>35</comrdtbsiz>"), std::string::npos);
  EXPECT_NE(box.NetFtXml().find("<comrdtrate>7000</comrdtrate>"), std::string::npos);
  RdtClient client;

  client.Send(rdt::Command::kBuffered, 100, o.address);
  std::vector<std::size_t> sizes;
  auto got = client.Run(box, 0.1, &sizes);
  ASSERT_EQ(got.size(), 100u);
  EXPECT_EQ(sizes, (std::vector<std::size_t>{35, 35, 30}));
  for (std::size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].rdt_sequence, i + 1);
    if (i > 0) {
      EXPECT_EQ(got[i].ft_sequence - got[i - 1].ft_sequence, 1u);  // 7000 of 7000 Hz
    }
    EXPECT_EQ(got[i].counts, FixedState(got[i].ft_sequence, base).counts);
  }
  EXPECT_FALSE(box.streaming());

  sizes.clear();
  client.Send(rdt::Command::kRealtime, 50, o.address);
  got = client.Run(box, 0.05, &sizes);
  ASSERT_EQ(got.size(), 50u);
  EXPECT_EQ(sizes, std::vector<std::size_t>(50, 1));
  EXPECT_EQ(got.front().rdt_sequence, 1u);
  const auto c = box.counters();
  EXPECT_EQ(c.starts, 2u);
  EXPECT_EQ(c.buffered_starts, 1u);
  EXPECT_EQ(c.datagrams, 3u + 50u);

  // Left to itself, the box's buffer size follows its rate as ftcal's config default does.
  o.rdt_buffer_size = 0;
  o.address = "127.0.1.2";
  sim::AtiEmulator seven(o, [&](std::uint64_t n, double) { return FixedState(n, base); });
  EXPECT_EQ(seven.options().rdt_buffer_size, 7);
}

// One published message.
struct Published {
  std::string channel;
  ft_batch_t msg;
};

// The records of the published messages, in order; each message on its leg's channel.
std::vector<FtRec> Records(const std::vector<Published>& published) {
  std::vector<FtRec> out;
  for (std::size_t i = 0; i < published.size(); ++i) {
    EXPECT_EQ(published[i].channel, "FT_" + published[i].msg.leg);
    AppendRecords(published[i].msg, static_cast<std::int64_t>(i), &out);
  }
  return out;
}

// The bridge class against one emulated box, driven in one loop for `seconds`, then the box's
// data ends and the bridge reads what is still on its way; returns what it published (and its
// counters).
std::vector<Published> RunBridge(const config::Config& cfg, sim::AtiEmulator& box, double seconds,
                                 AtiTransducerCounters* counters = nullptr,
                                 AtiBridgeOptions options = {}) {
  std::vector<Published> out;
  auto log =
      std::make_shared<spdlog::logger>("ati-test", std::make_shared<spdlog::sinks::null_sink_mt>());
  AtiBridge bridge(
      cfg, {"HL"},
      [&out](const std::string& channel, const void* data, int size) {
        Published p{channel, {}};
        EXPECT_EQ(p.msg.decode(data, 0, size), size);
        out.push_back(p);
      },
      log, options);
  bridge.Start();
  const auto end = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(seconds));
  while (Clock::now() < end) {
    box.Step(Clock::now());
    bridge.Poll(1);
  }
  box.Step(Clock::now());
  box.EndOfData();
  // Loopback delivers at once; the socket is empty when a poll finds nothing for 20 ms.
  while (bridge.Poll(20) > 0) {
  }
  bridge.Stop();
  if (counters) *counters = bridge.counters(0);
  return out;
}

config::Config SimConfig() {
  return LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
}

TEST(AtiBridgeInProcess, ConfigSignAndCountsPerUnitOverrideThePage) {
  sim::AtiEmulatorOptions o;
  o.address = "127.0.1.1";
  o.http_port = 8080;
  o.rdt_rate_hz = 1000;
  o.counts_per_force = 1e6;  // the page says 1e6 ...
  const std::array<std::int32_t, 6> base{2000000, -4000000, 6000000, 8000, -10000, 12000};
  sim::AtiEmulator box(o, [&](std::uint64_t n, double) { return FixedState(n, base); });
  config::Config cfg = SimConfig();
  auto* ati = cfg.mutable_robot()->mutable_leg(0)->mutable_ati();
  ASSERT_EQ(cfg.robot().leg(0).name(), "HL");
  ati->set_sign(-1);
  ati->set_counts_per_force(2e6);  // ... the config says 2e6 counts/N and 4000 counts/Nm
  ati->set_counts_per_torque(4000);
  ati->set_records_per_datagram(1);  // real-time mode: nothing else to read from the page
  const auto out = RunBridge(cfg, box, 0.2);
  const auto records = Records(out);
  ASSERT_GT(records.size(), 100u);
  for (const auto& p : out) {
    EXPECT_EQ(p.channel, "FT_HL");
    EXPECT_EQ(p.msg.leg, "HL");
    EXPECT_EQ(p.msg.n, 1);  // real time: a record per datagram, a message per datagram
  }
  for (const FtRec& m : records) {
    for (int i = 0; i < 3; ++i) EXPECT_DOUBLE_EQ(m.wrench[i], -m.counts[i] / 2e6);
    for (int i = 3; i < 6; ++i) EXPECT_DOUBLE_EQ(m.wrench[i], -m.counts[i] / 4000.0);
    // 2 N/-3 N/-2.5 N*m: within the rated range; healthy status.
    EXPECT_EQ(m.flags & ~ft_batch_t::FLAG_RESTARTED, 0);
  }
  EXPECT_EQ(records.front().flags, int{ft_batch_t::FLAG_RESTARTED});
  // Counts per unit, rated range and real-time mode all come from the config: the page is never
  // read.
  EXPECT_EQ(box.counters().http_requests, 0u);
}

// The exact account of a box that streams 35 records per datagram at 7000 records/s, with whole
// datagrams dropped, duplicated, overtaken and corrupted: every record the box sent intact is
// published once, in order, with the box's values, each datagram as one message of its k
// records stamped with its receipt and the records' sample times; every fault counted as what
// it is.
TEST(AtiBridgeInProcess, ABoxOf35RecordsPerDatagramIsPublishedOnceRecordForRecord) {
  constexpr int k = 35;
  sim::AtiEmulatorOptions o;
  o.address = "127.0.1.1";
  o.http_port = 8080;
  o.rdt_rate_hz = 7000;
  o.rdt_buffer_size = k;
  o.faults.seed = 3;
  o.faults.drop = o.faults.duplicate = o.faults.reorder = o.faults.corrupt = 0.03;
  const std::array<std::int32_t, 6> base{2000000, -4000000, 6000000, 8000, -10000, 12000};
  std::vector<testing::AtiTruthRow> truth;
  sim::AtiEmulator box(
      o,
      [&](std::uint64_t n, double) { return FixedState(n, base, n % 97 == 0 ? 0x80020000u : 0); },
      [&truth](const sim::AtiEmitted& e) {
        testing::AtiTruthRow r;
        r.leg = "HL";
        r.stream = static_cast<int>(e.stream);
        r.t_s = e.t_s;
        r.rdt_sequence = e.record.rdt_sequence;
        r.ft_sequence = e.record.ft_sequence;
        r.status = e.record.status;
        r.counts = e.record.counts;
        r.fault = sim::AtiFaultName(e.fault);
        r.datagram = e.datagram;
        truth.push_back(r);
      });
  config::Config cfg = SimConfig();
  cfg.mutable_robot()->mutable_leg(0)->mutable_ati()->set_records_per_datagram(k);
  AtiTransducerCounters c;
  AtiBridgeOptions options;
  options.silence_timeout_s = 1.0;  // a loaded machine must not restart the stream
  const auto out = RunBridge(cfg, box, 3.0, &c, options);

  // What the box sent intact, in the order of its sequence, once each.
  std::map<std::uint32_t, const testing::AtiTruthRow*> intact;
  std::map<std::uint32_t, std::uint32_t> datagram_of;
  for (const auto& r : truth) {
    datagram_of[r.rdt_sequence] = r.datagram;
    if (r.fault == "none" || r.fault == "duplicate") intact[r.rdt_sequence] = &r;
  }
  ASSERT_GT(intact.size(), 15000u);
  const auto records = Records(out);
  ASSERT_EQ(records.size(), intact.size());
  // One datagram of k records is ONE message of n = k: as many messages as datagrams with
  // intact records, each of k records but the part-filled last one at the end of the data.
  std::set<std::uint32_t> intact_datagrams;
  for (const auto& [seq, r] : intact) intact_datagrams.insert(r->datagram);
  EXPECT_EQ(out.size(), intact_datagrams.size());
  for (std::size_t i = 0; i + 1 < out.size(); ++i) {
    EXPECT_EQ(out[i].msg.n, k) << "message " << i << " of " << out.size();
  }
  EXPECT_GE(out.back().msg.n, 1);
  EXPECT_LE(out.back().msg.n, k);
  auto it = intact.begin();
  std::uint32_t prev = 0;
  std::vector<std::pair<std::uint32_t, FtRec>> by_datagram;
  int gaps_of_k = 0, saturated = 0;
  for (const FtRec& m : records) {
    const testing::AtiTruthRow& r = *it->second;
    ASSERT_EQ(static_cast<std::uint32_t>(m.rdt_sequence), r.rdt_sequence);
    EXPECT_EQ(static_cast<std::uint32_t>(m.ft_sequence), r.ft_sequence);
    EXPECT_EQ(static_cast<std::uint32_t>(m.status), r.status);
    for (int i = 0; i < 6; ++i) {
      EXPECT_EQ(m.counts[i], r.counts[i]);
      EXPECT_DOUBLE_EQ(m.wrench[i], r.counts[i] / kCountsPerUnit);
    }
    // The gap is what the truth says went missing since the previous intact record.
    EXPECT_EQ(m.gap, static_cast<std::int64_t>(r.rdt_sequence - prev - 1)) << r.rdt_sequence;
    if (m.gap == k) ++gaps_of_k;
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_GAP) != 0, m.gap > 0);
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_STATUS_ERROR) != 0, r.status != 0);
    if (m.flags & ft_batch_t::FLAG_SATURATED) ++saturated;
    EXPECT_EQ((m.flags & ft_batch_t::FLAG_RESTARTED) != 0, prev == 0);
    by_datagram.emplace_back(datagram_of.at(r.rdt_sequence), m);
    prev = r.rdt_sequence;
    ++it;
  }
  EXPECT_GT(gaps_of_k, 5);  // a dropped or corrupt datagram alone: k records missing
  std::set<std::uint32_t> datagrams;
  for (const auto& [d, m] : by_datagram) datagrams.insert(d);
  EXPECT_GT(datagrams.size(), 400u);
  EXPECT_GT(ExpectStampsByCounter(by_datagram, k), 100);

  testing::AtiLegTally tally = testing::TallyLeg(truth, "HL");
  ASSERT_EQ(tally.streams.size(), 1u);
  const std::map<std::string, std::int64_t> counters = {{"duplicates", c.duplicates},
                                                        {"late", c.late},
                                                        {"wrong_length", c.wrong_length},
                                                        {"lost", c.lost},
                                                        {"received", c.received}};
  testing::ExpectFaultsCounted(tally, [&](const std::string& n) { return counters.at(n); });
  EXPECT_EQ(c.published, records.size());  // counts records, not messages
  EXPECT_EQ(c.status_nonzero, static_cast<std::uint64_t>(saturated));  // bit 17 set in each
  EXPECT_GT(saturated, 100);
  EXPECT_EQ(c.saturated, static_cast<std::uint64_t>(saturated));
  EXPECT_EQ(c.restarts, 1u);
  EXPECT_EQ(c.stale, 0u);
  EXPECT_EQ(box.counters().buffered_starts, 1u);
}

// k = 1 is the real-time mode whatever the box's buffer size: the bridge sends 0x0002 and the box
// sends one record per datagram.
TEST(AtiBridgeInProcess, OneRecordPerDatagramIsRealTimeModeWhateverTheBoxsBufferSize) {
  sim::AtiEmulatorOptions o;
  o.address = "127.0.1.1";
  o.http_port = 8080;
  o.rdt_rate_hz = 7000;  // its buffer size: 7
  const std::array<std::int32_t, 6> base{0, 0, 1000000, 0, 0, 0};
  sim::AtiEmulator box(o, [&](std::uint64_t n, double) { return FixedState(n, base); });
  config::Config cfg = SimConfig();
  cfg.mutable_robot()->mutable_leg(0)->mutable_ati()->set_records_per_datagram(1);
  AtiTransducerCounters c;
  const auto out = RunBridge(cfg, box, 0.3, &c);
  ASSERT_GT(out.size(), 1000u);
  for (const auto& p : out) EXPECT_EQ(p.msg.n, 1);  // a message per one-record datagram
  EXPECT_EQ(c.published, out.size());
  EXPECT_EQ(c.datagrams, c.received);
  EXPECT_EQ(c.lost, 0u);
  EXPECT_EQ(box.counters().buffered_starts, 0u);
  EXPECT_EQ(box.counters().starts, 1u);
}

TEST(AtiBridgeInProcess, SaturationFromStatusBitOrRatedRangeAndStatusErrorAreFlagged) {
  for (int variant = 0; variant < 2; ++variant) {
    SCOPED_TRACE(variant == 0 ? "status bit 17" : "Fz beyond the 400 N rated range");
    sim::AtiEmulatorOptions o;
    o.address = "127.0.1.1";
    o.http_port = 8080;
    o.rdt_rate_hz = 1000;
    const std::array<std::int32_t, 6> base{0, 0, variant == 0 ? 100000000 : 450000000, 0, 0, 0};
    const std::uint32_t status = variant == 0 ? 0x80020000u : 0u;
    sim::AtiEmulator box(o, [&](std::uint64_t n, double) { return FixedState(n, base, status); });
    const auto records = Records(RunBridge(SimConfig(), box, 0.15));
    ASSERT_GT(records.size(), 50u);
    for (const FtRec& m : records) {
      EXPECT_TRUE(m.flags & ft_batch_t::FLAG_SATURATED);
      EXPECT_EQ((m.flags & ft_batch_t::FLAG_STATUS_ERROR) != 0, variant == 0);
      EXPECT_EQ(m.status, static_cast<std::int64_t>(status));
      EXPECT_DOUBLE_EQ(m.wrench[2], m.counts[2] / 1e6);
    }
    EXPECT_EQ(box.counters().http_requests, 1u);  // counts per unit from the page
  }
}

TEST(AtiBridgeInProcess, UnknownLegAndBadSignAreRefusedByName) {
  auto log = std::make_shared<spdlog::logger>("ati-test2",
                                              std::make_shared<spdlog::sinks::null_sink_mt>());
  auto publish = [](const std::string&, const void*, int) {};
  try {
    AtiBridge bridge(SimConfig(), {"XX"}, publish, log);
    ADD_FAILURE() << "unknown leg accepted";
  } catch (const AtiBridgeError& e) {
    EXPECT_NE(std::string(e.what()).find("'XX'"), std::string::npos) << e.what();
  }
  config::Config cfg = SimConfig();
  cfg.mutable_robot()->mutable_leg(1)->mutable_ati()->set_sign(2);
  try {
    AtiBridge bridge(cfg, {"ML"}, publish, log);
    ADD_FAILURE() << "sign 2 accepted";
  } catch (const AtiBridgeError& e) {
    EXPECT_NE(std::string(e.what()).find("ML"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("sign"), std::string::npos) << e.what();
  }
}

// A web server on loopback serving the calibration page the way a broken or hostile box might:
// `body_bytes` bytes, `chunk` at a time, `pause_s` between chunks.
class PageServer {
 public:
  PageServer(std::size_t body_bytes, std::size_t chunk, double pause_s) {
    server_.Get("/netftapi2.xml", [=](const httplib::Request&, httplib::Response& res) {
      res.set_content_provider(
          body_bytes, "text/xml", [=](std::size_t offset, std::size_t, httplib::DataSink& sink) {
            static const std::string block(1 << 16, ' ');
            if (stop_) return false;
            if (pause_s > 0 && offset > 0) SleepS(pause_s);
            const std::size_t n = std::min({chunk, block.size(), body_bytes - offset});
            return sink.write(block.data(), n);
          });
    });
    port_ = server_.bind_to_any_port("127.0.0.1");
    thread_ = std::thread([this] { server_.listen_after_bind(); });
    while (!server_.is_running()) SleepS(0.001);
  }
  ~PageServer() {
    stop_ = true;
    server_.stop();
    thread_.join();
  }
  int port() const { return port_; }

 private:
  httplib::Server server_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  int port_ = 0;
};

// Starts a bridge for HL whose calibration page is served by `server`; returns the refusal and
// how long Start() took.
std::pair<std::string, double> StartAgainst(const PageServer& server) {
  config::Config cfg = SimConfig();
  auto* ati = cfg.mutable_robot()->mutable_leg(0)->mutable_ati();
  ati->set_address("127.0.0.1");
  ati->set_http_port(server.port());
  auto log =
      std::make_shared<spdlog::logger>("ati-page", std::make_shared<spdlog::sinks::null_sink_mt>());
  AtiBridge bridge(
      cfg, {"HL"}, [](const std::string&, const void*, int) {}, log);
  const auto t0 = Clock::now();
  std::string error;
  try {
    bridge.Start();
  } catch (const AtiBridgeError& e) {
    error = e.what();
  }
  return {error, std::chrono::duration<double>(Clock::now() - t0).count()};
}

long MaxRssKb() {
  rusage u{};
  ::getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

// A 400 MB page took 538-833 MB of memory: the bridge stops reading at its cap (64 kB).
TEST(AtiBridgeInProcess, AHugeCalibrationPageIsRefusedAtItsCapWithoutTheMemory) {
  PageServer server(400u << 20, 1 << 16, 0.0);
  const long before_kb = MaxRssKb();
  const auto [error, seconds] = StartAgainst(server);
  const long grew_kb = MaxRssKb() - before_kb;
  std::printf("[ figure ] 400 MB calibration page: refused after %.3f s, peak RSS grew %ld kB\n",
              seconds, grew_kb);
  EXPECT_NE(error.find("larger than 65536 bytes"), std::string::npos) << error;
  EXPECT_NE(error.find("leg HL"), std::string::npos) << error;
  EXPECT_LT(grew_kb, 16 << 10) << "kB";
  EXPECT_LT(seconds, 1.0);
}

// A page trickling a byte every 0.5 s held start-up for 30 s: one deadline (http_timeout_s,
// 1 s) now covers the whole fetch.
TEST(AtiBridgeInProcess, ATricklingCalibrationPageIsRefusedAtTheDeadline) {
  PageServer server(60, 1, 0.5);
  const auto [error, seconds] = StartAgainst(server);
  std::printf("[ figure ] calibration page trickling 1 byte / 0.5 s: refused after %.3f s\n",
              seconds);
  EXPECT_NE(error.find("not read within 1 s"), std::string::npos) << error;
  EXPECT_GE(seconds, 0.9);
  EXPECT_LT(seconds, 1.8);
}

}  // namespace
}  // namespace ftcal
