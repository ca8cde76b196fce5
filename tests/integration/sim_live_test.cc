// ftcal-sim live with the three real bridges and lcm-logger, as real processes over UDP, a
// pseudo-terminal, TCP and LCM multicast inside a private network namespace (ctest runs this
// binary through scripts/netns-exec). Faults are injected on all three devices. The recorded log
// is compared with two independent truths:
//   - the truth series ftcal-sim wrote (every record, reply and frame it produced, with the
//     fault done to it): what was published must be exactly what was sent intact, and every
//     fault must show in the bridges' own counters (their last FTCAL_STATUS in the log);
//   - the twin itself, rebuilt here from the same seed: the wrenches within one count's
//     quantization of the twin's unquantized readings, the angles within one encoder count of
//     its shaft angles, the attitude within 1e-6 of its R_GC (f32 on the wire).
#include <signal.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <memory>
#include <regex>
#include <set>
#include <sstream>
#include <thread>
#include <type_traits>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "ati_truth.h"
#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/config.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/geometry.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "protocol2.h"
#include "sim/live.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::Decode;
using testing::Terminate;
using Clock = std::chrono::steady_clock;

// A large receive buffer: the logger hears six transducers at 500 records/s each.
constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=8388608";
constexpr double kCountsPerUnit = 1e6;  // ftcal-sim live's default cfgcpf and cfgcpt
constexpr double kOneCountRad = 2.0 * M_PI / 4096.0;
// The faults are drawn per record from this seed, whatever the timing. With it a box's first
// record is reordered (record 1 arrives after 2): the bridge must count it late, as any other,
// not take it for a new stream and publish it after record 2.
constexpr std::uint64_t kSeed = 3;
constexpr double kRunS = 30.0;  // issue #4
constexpr int kAtiRateHz = 500;

using testing::SleepS;

using testing::SplitCsv;

// Calls `row` with the fields of every line of the truth CSV at `path` after its header, and
// the line itself for the message when the row is refused.
template <class F>
void ForEachCsvRow(const std::string& path, F row) {
  std::ifstream in(path);
  EXPECT_TRUE(in.good()) << path;
  std::string line;
  std::getline(in, line);
  while (std::getline(in, line)) row(SplitCsv(line), line);
}

using AtiRow = testing::AtiTruthRow;
std::vector<AtiRow> ReadAtiTruth(const std::string& path) {
  std::vector<AtiRow> rows;
  ForEachCsvRow(path, [&rows](const std::vector<std::string>& f, const std::string& line) {
    if (f.size() != testing::kAtiTruthColumns)
      throw std::runtime_error("bad ati truth line: " + line);
    rows.push_back(testing::ParseAtiTruthRow(f));
  });
  return rows;
}

struct DxlRow {
  double t_s;
  int id, address;
  std::string fate;
  int tick_ms, position;
  double exact;
};
std::vector<DxlRow> ReadDxlTruth(const std::string& path) {
  std::vector<DxlRow> rows;
  ForEachCsvRow(path, [&rows](const std::vector<std::string>& f, const std::string& line) {
    if (f.size() != 15) throw std::runtime_error("bad dynamixel truth line: " + line);
    rows.push_back({std::stod(f[0]), std::stoi(f[1]), std::stoi(f[3]), f[5], std::stoi(f[8]),
                    std::stoi(f[9]), std::stod(f[14])});
  });
  return rows;
}

struct QtmRow {
  std::int64_t tick = 0, frame_number = 0, timestamp_us = 0;
  bool corrupt = false, tracked = false;
  Vec3 p_mm;
  Mat3 R;
};
std::map<std::int64_t, QtmRow> ReadQtmTruth(const std::string& path) {
  std::map<std::int64_t, QtmRow> rows;
  ForEachCsvRow(path, [&rows](const std::vector<std::string>& f, const std::string& line) {
    // f32 values written with 9 significant digits give the float back when read as a float.
    if (f.size() < 18) throw std::runtime_error("short qtm truth row: " + line);
    auto num = [&](int i) { return f[i] == "nan" ? NAN : static_cast<double>(std::stof(f[i])); };
    QtmRow r;
    r.tick = std::stoll(f[0]);
    r.frame_number = std::stoll(f[1]);
    r.timestamp_us = std::stoll(f[2]);
    r.corrupt = f[3] != "0";
    r.tracked = f[4] != "0";
    r.p_mm = Vec3(num(5), num(6), num(7));
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) r.R(i, j) = num(8 + 3 * j + i);
    }
    EXPECT_TRUE(rows.emplace(r.frame_number, r).second)
        << "frame " << r.frame_number << " sent twice";
  });
  return rows;
}

// One record of a recorded ft_batch_t (a message per RDT datagram), with its message's leg.
struct FtRecord {
  std::string leg;
  std::int64_t rdt_sequence = 0, ft_sequence = 0, status = 0;
  std::array<std::int32_t, 6> counts{};
  std::array<double, 6> wrench{};
};

// The recorded log, decoded; FT_<LEG> record by record.
struct Recorded {
  std::vector<FtRecord> ft;
  std::vector<servo_state_t> servo;
  std::vector<mocap_body_t> mocap;
  std::vector<service_status_t> status;
  int wrong_channel = 0, undecodable = 0;
};
Recorded ReadLog(const std::string& path) {
  Recorded r;
  // The event decoded into `out`, or counted as undecodable; false then.
  auto keep = [&r](const lcm::LogEvent* e, auto* out) {
    typename std::remove_pointer_t<decltype(out)>::value_type m;
    if (!Decode(e, &m)) {
      ++r.undecodable;
      return false;
    }
    out->push_back(m);
    return true;
  };
  testing::ForEachLogEvent(path, [&](const lcm::LogEvent* e) {
    const std::string& ch = e->channel;
    if (ch.rfind("FT_", 0) == 0) {
      ft_batch_t m;
      if (!Decode(e, &m) || m.n < 1 || m.n > ft_batch_t::MAX_N) {
        ++r.undecodable;
        return;
      }
      if (ch != "FT_" + m.leg) ++r.wrong_channel;
      for (int i = 0; i < m.n; ++i) {
        FtRecord f;
        f.leg = m.leg;
        f.rdt_sequence = m.rdt_sequence[i];
        f.ft_sequence = m.ft_sequence[i];
        f.status = m.status[i];
        for (int j = 0; j < 6; ++j) {
          f.counts[j] = m.counts[i][j];
          f.wrench[j] = m.wrench[i][j];
        }
        r.ft.push_back(f);
      }
    } else if (ch == "SERVO_STATE") {
      keep(e, &r.servo);
    } else if (ch == "MOCAP_BODY") {
      keep(e, &r.mocap);
    } else if (ch == "FTCAL_STATUS") {
      keep(e, &r.status);
    }
  });
  return r;
}

// The last heartbeat of process `pid` in the log.
service_status_t LastStatus(const Recorded& r, pid_t pid) {
  service_status_t last;
  last.pid = -1;
  for (const auto& s : r.status) {
    if (s.pid == pid) last = s;
  }
  EXPECT_EQ(last.pid, pid) << "no heartbeat recorded from pid " << pid;
  return last;
}
std::int64_t Counter(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  ADD_FAILURE() << "no counter " << name << " in the heartbeat of " << s.name;
  return -1;
}

// Counters a service creates when first counted: absent means none.
std::int64_t CounterOr0(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  return 0;
}

// The sim config with the Dynamixel device at `device` and the reply timeout longer than the
// config's 10 ms, so that a loaded test machine does not turn a reply into a late one.
std::string TestConfigText(const std::string& device) {
  std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  text = std::regex_replace(text, std::regex("device: \"[^\"]*\""), "device: \"" + device + "\"");
  text = std::regex_replace(text, std::regex("reply_timeout_s: [0-9.]+"), "reply_timeout_s: 0.05");
  return text;
}

// Waits (30 s at most) for ftcal-sim live's --ready file; fails naming its stderr if it ends
// or is late.
void WaitUntilReady(Child& sim, const std::string& ready, const std::string& err) {
  const auto deadline = Clock::now() + std::chrono::seconds(30);
  while (::access(ready.c_str(), F_OK) != 0) {
    ASSERT_FALSE(sim.Wait(0.02).has_value()) << "ftcal-sim ended: " << testing::ReadFile(err);
    ASSERT_LT(Clock::now(), deadline) << "ftcal-sim not ready: " << testing::ReadFile(err);
  }
}

// The twin walking (seed kSeed, transducers at kAtiRateHz) in `dir`, its config written to
// `config_path` with the Dynamixel pty at dir/tty; returned once it is ready.
std::unique_ptr<Child> StartWalkingTwin(const std::string& dir, const std::string& config_path) {
  std::ofstream(config_path) << TestConfigText(dir + "/tty");
  auto sim = std::make_unique<Child>(
      std::vector<std::string>{FTCAL_SIM, "live", "--config", config_path, "--pty-link",
                               dir + "/tty", "--ready", dir + "/ready", "--scenario", "walk",
                               "--seed", std::to_string(kSeed), "--ati-rate",
                               std::to_string(kAtiRateHz)},
      dir + "/sim.out", dir + "/sim.err");
  WaitUntilReady(*sim, dir + "/ready", dir + "/sim.err");
  return sim;
}

TEST(SimLive, ThreeBridgesRecordTheTwinsTruthAndCountEveryFault) {
  testing::AheadOfTheMachine();
  ASSERT_TRUE(testing::InNetns());
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) not found at configure time";
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const std::string link = path("tty");
  const std::string config_path = path("config.pbtxt");
  std::ofstream(config_path) << TestConfigText(link);
  const config::Config config = LoadConfigFile(config_path);

  // The twin's devices, faults on all three.
  Child sim({FTCAL_SIM,         "live",
             "--config",        config_path,
             "--pty-link",      link,
             "--truth-dir",     dir,
             "--ready",         path("ready"),
             "--scenario",      "walk",
             "--seed",          std::to_string(kSeed),
             "--ati-rate",      std::to_string(kAtiRateHz),
             "--ati-drop",      "0.005",
             "--ati-duplicate", "0.005",
             "--ati-reorder",   "0.005",
             "--ati-corrupt",   "0.005",
             "--dxl-drop",      "0.01",
             "--dxl-corrupt",   "0.01",
             "--dxl-noise",     "0.02",
             "--dxl-missing",   "3:8:9",
             "--dxl-silent",    "15:15.5",
             "--qtm-gap",       "0.01",
             "--qtm-corrupt",   "0.01",
             "--qtm-untracked", "5:0.5"},
            path("sim.out"), path("sim.err"));
  WaitUntilReady(sim, path("ready"), path("sim.err"));
  if (HasFatalFailure()) return;
  Child logger({FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", path("run.lcmlog")}, path("logger.out"),
               path("logger.err"));
  SleepS(0.3);
  const std::string url = "udpm://239.255.76.67:7667?ttl=0";
  // A long silence timeout: a loaded machine must not make the bridge restart the stream.
  Child ati(
      {FTCAL_ATI_BRIDGE, "--config", config_path, "--lcm-url", url, "--silence-timeout", "1.0"},
      path("ati.out"), path("ati.err"));
  Child dxl({FTCAL_DYNAMIXEL_BRIDGE, "--config", config_path, "--lcm-url", url}, path("dxl.out"),
            path("dxl.err"));
  Child mocap({FTCAL_MOCAP_BRIDGE, "--config", config_path, "--lcm-url", url}, path("mocap.out"),
              path("mocap.err"));
  const auto started = Clock::now();
  SleepS(kRunS);
  // The devices stop first, so that their truth holds everything the bridges received; the
  // bridges then stop before the ATI bridge would call the silence a fault, and say goodbye in
  // a last heartbeat the logger records.
  sim.Signal(SIGTERM);
  SleepS(0.3);
  const double ran_s = std::chrono::duration<double>(Clock::now() - started).count();
  Terminate(ati, "ftcal-ati-bridge", path("ati.err"));
  Terminate(dxl, "ftcal-dynamixel-bridge", path("dxl.err"));
  Terminate(mocap, "ftcal-mocap-bridge", path("mocap.err"));
  Terminate(sim, "ftcal-sim live", path("sim.err"));
  SleepS(0.5);
  logger.Signal(SIGINT);
  ASSERT_TRUE(logger.Wait(10).has_value());
  std::cout << testing::ReadFile(path("sim.out"));

  const Recorded rec = ReadLog(path("run.lcmlog"));
  EXPECT_EQ(rec.undecodable, 0);
  EXPECT_EQ(rec.wrong_channel, 0);

  // The twin, rebuilt from the same seed: the independent truth of the values.
  sim::LiveOptions same;
  TwinOptions twin_options;
  twin_options.seed = kSeed;
  twin_options.hang_cycles = static_cast<int>(std::ceil(same.loop_s / twin_options.hang_cycle_s));
  const BigAntTwin twin(config, twin_options);
  const sim::TwinSeries series(twin, "walk", same.loop_s);

  // ---- ATI: FT_<LEG> ----
  {
    SCOPED_TRACE("ati");
    const auto truth = ReadAtiTruth(path("ati.csv"));
    const service_status_t last = LastStatus(rec, ati.pid());
    EXPECT_EQ(int{last.state}, int{service_status_t::STOPPING});
    std::multimap<std::tuple<std::string, std::uint32_t, std::uint32_t>, const AtiRow*> index;
    for (const AtiRow& r : truth)
      index.emplace(std::make_tuple(r.leg, r.rdt_sequence, r.ft_sequence), &r);
    std::map<std::string, std::int64_t> heard;
    double worst_quantization = 0;
    for (const FtRecord& m : rec.ft) {
      const auto range =
          index.equal_range(std::make_tuple(m.leg, static_cast<std::uint32_t>(m.rdt_sequence),
                                            static_cast<std::uint32_t>(m.ft_sequence)));
      const AtiRow* row = nullptr;
      for (auto it = range.first; it != range.second; ++it) {
        bool same_counts = it->second->status == static_cast<std::uint32_t>(m.status);
        for (int i = 0; i < 6; ++i)
          same_counts = same_counts && it->second->counts[i] == m.counts[i];
        if (same_counts) row = it->second;
      }
      ASSERT_NE(row, nullptr) << m.leg << " published rdt " << m.rdt_sequence
                              << " which ftcal-sim never sent with these counts";
      ASSERT_TRUE(row->fault == "none" || row->fault == "duplicate")
          << m.leg << " rdt " << m.rdt_sequence << " was sent as '" << row->fault << "'";
      ++heard[m.leg];
      // Against the twin: the frame the record was made from, unquantized. The truth's time
      // is printed to 1 us, so a sample on a frame boundary may name either neighbour.
      const int k = *LegIndex(m.leg);
      double best = INFINITY;
      for (double dt : {0.0, -2e-6, 2e-6}) {
        const Vec6& reading = series.At(row->t_s + dt).reading[k];
        double worst = 0;
        for (int i = 0; i < 6; ++i) worst = std::max(worst, std::abs(m.wrench[i] - reading[i]));
        best = std::min(best, worst);
      }
      EXPECT_LE(best, 0.5 / kCountsPerUnit + 1e-12) << m.leg << " rdt " << m.rdt_sequence;
      worst_quantization = std::max(worst_quantization, best);
      for (int i = 0; i < 6; ++i) EXPECT_NEAR(m.wrench[i], m.counts[i] / kCountsPerUnit, 1e-12);
    }
    std::cout << "ati: worst |wrench - twin reading| " << worst_quantization * kCountsPerUnit
              << " counts\n";
    for (const auto& name : kLegNames) {
      const std::string leg(name);
      SCOPED_TRACE(leg);
      testing::AtiLegTally tally = testing::TallyLeg(truth, leg);
      auto& faults = tally.faults;
      ASSERT_EQ(tally.streams.size(), 1u)
          << "the bridge restarted the stream: counts are not comparable";
      const std::string p = leg + ".";
      testing::ExpectFaultsCounted(
          tally, [&](const std::string& name) { return Counter(last, p + name); });
      const std::int64_t publishable = faults["none"] + faults["duplicate"];
      EXPECT_EQ(Counter(last, p + "published"), publishable);
      // The logger heard most of it; a sample it missed is LCM's loss over UDP on a loaded
      // machine, not the bridge's (the counters above are the exact account).
      EXPECT_LE(heard[leg], publishable);
      EXPECT_GE(heard[leg], publishable * 9 / 10);
      // Rate (loose): the bridge ran about ran_s at kAtiRateHz.
      EXPECT_GT(publishable, 0.7 * kAtiRateHz * (ran_s - 2.0));
      std::cout << "ati " << leg << ": generated "
                << faults["none"] + faults["drop"] + faults["duplicate"] + faults["reorder"] +
                       faults["corrupt"]
                << " records (drop " << faults["drop"] << ", duplicate " << faults["duplicate"]
                << ", reorder " << faults["reorder"] << ", corrupt " << faults["corrupt"]
                << "), published " << Counter(last, p + "published") << ", logged " << heard[leg]
                << "; counted duplicates " << Counter(last, p + "duplicates") << " late "
                << Counter(last, p + "late") << " wrong_length "
                << Counter(last, p + "wrong_length") << " lost " << Counter(last, p + "lost")
                << "\n";
    }
  }

  // ---- Dynamixel: SERVO_STATE ----
  {
    SCOPED_TRACE("dynamixel");
    auto truth = ReadDxlTruth(path("dynamixel.csv"));
    const service_status_t last = LastStatus(rec, dxl.pid());
    // The last present-block request may have been answered as the bridge was stopping: if
    // none of its replies was published, the bridge did not finish that cycle, so they and
    // any request after it (a hardware-error read) leave the truth (a corrupt one among them
    // may or may not have been read and counted). Keyed on the present read, not on the last
    // request of any kind: a stop between a cycle's present read and its hardware-error read
    // leaves the error read last and the unfinished present read before it (seen in CI: six
    // present replies more in the truth than the bridge's cycles).
    std::int64_t corrupted_unfinished = 0;
    {
      double last_t = -1;
      for (const auto& r : truth) {
        if (r.address == dxl::kAddrPresentBlock) last_t = std::max(last_t, r.t_s);
      }
      std::set<std::pair<int, int>> published;
      for (const servo_state_t& m : rec.servo) {
        for (int k = 0; k < 6; ++k) {
          if (!(m.flags[k] & servo_state_t::FLAG_STALE)) {
            published.insert({m.id[k], static_cast<int>(m.device_tick_ms[k] % 32768)});
          }
        }
      }
      bool taken = false;
      for (const auto& r : truth) {
        taken = taken || (r.t_s == last_t && r.address == dxl::kAddrPresentBlock &&
                          published.count({r.id, r.tick_ms}) > 0);
      }
      if (!taken) {
        const auto n = truth.size();
        for (const auto& r : truth)
          corrupted_unfinished += r.t_s >= last_t && r.fate == "corrupted";
        truth.erase(std::remove_if(truth.begin(), truth.end(),
                                   [last_t](const DxlRow& r) { return r.t_s >= last_t; }),
                    truth.end());
        std::cout << "dynamixel: the last present read's " << n - truth.size()
                  << " replies (and any after it) were not published (the bridge was stopping)\n";
      }
    }
    EXPECT_EQ(int{last.state}, int{service_status_t::STOPPING});
    // Keyed by (id, Realtime Tick): two reads of a servo within one millisecond are two
    // replies with the same tick and possibly positions a count apart, so every one is kept.
    std::map<std::pair<int, int>, std::vector<DxlRow>> sent;
    std::int64_t corrupted = 0, present_lost = 0, present_sent = 0, missing3 = 0, silent = 0;
    for (const auto& r : truth) {
      corrupted += r.fate == "corrupted";
      if (r.address != dxl::kAddrPresentBlock) continue;
      if (r.fate == "sent") {
        sent[{r.id, r.tick_ms}].push_back(r);
        ++present_sent;
      } else {
        ++present_lost;
        missing3 += r.fate == "missing";
        silent += r.fate == "silent";
      }
    }
    ASSERT_GT(corrupted, 5);
    // (The bridge waits out its reply timeout in each cycle with a reply missing: fewer cycles.)
    // Servo 3 is missing for 1 s; the bridge asks it in the first missed cycles only and then
    // marks it lost (--lost-after 5) and re-probes it with PINGs, which are not present-block
    // reads: a handful of missing replies, not a second's worth.
    ASSERT_GE(missing3, 3) << "servo 3 was missing for 1 s";
    // The same for the silent bus: six servos for the first missed cycles, then re-probes.
    ASSERT_GE(silent, 20) << "the bus was silent for 0.5 s";
    std::map<int, int> leg_of_id;
    for (int k = 0; k < kNumLegs; ++k) leg_of_id[config.robot().leg(k).servo().id()] = k;
    // The bridge's cycles after the last one with a fresh value are those after ftcal-sim
    // stopped: no reply was ever made for them.
    std::size_t last_fresh = 0;
    for (std::size_t i = 0; i < rec.servo.size(); ++i) {
      for (int k = 0; k < 6; ++k) {
        if (!(rec.servo[i].flags[k] & servo_state_t::FLAG_STALE)) last_fresh = i;
      }
    }
    // Counted over the cycles the logger heard (it may miss some: LCM over UDP).
    std::int64_t fresh = 0, stale = 0, stale_tail = 0, mispaired = 0;
    std::map<int, std::vector<const DxlRow*>> sent_by_id;  // in time order
    for (const auto& r : truth) {
      if (r.address == dxl::kAddrPresentBlock && r.fate == "sent") {
        // The n-th reply with this tick (the map is complete: no pointer moves any more).
        const auto& same_tick = sent.at({r.id, r.tick_ms});
        const DxlRow* p = &same_tick.front();
        for (const DxlRow& c : same_tick) {
          if (c.t_s == r.t_s) p = &c;
        }
        sent_by_id[r.id].push_back(p);
      }
    }
    double worst_counts = 0;
    std::map<int, std::int64_t> last_tick;
    for (std::size_t i = 0; i < rec.servo.size(); ++i) {
      const servo_state_t& m = rec.servo[i];
      for (int k = 0; k < 6; ++k) {
        const int id = m.id[k];
        if (m.flags[k] & servo_state_t::FLAG_STALE) {
          (i > last_fresh ? stale_tail : stale) += 1;
          continue;
        }
        ++fresh;
        const auto it = sent.find({id, static_cast<int>(m.device_tick_ms[k] % 32768)});
        ASSERT_NE(it, sent.end()) << "published a value no servo sent: id " << id << " tick "
                                  << m.device_tick_ms[k];
        const auto& servo = config.robot().leg(leg_of_id.at(id)).servo();
        const double zero = servo.zero_count(), dir = servo.direction();
        const auto carries = [&](const DxlRow& r) {
          return std::abs(m.angle_rad[k] - dir * (r.position - zero) * kOneCountRad) <= 1e-12;
        };
        const DxlRow* row = &it->second.front();
        for (const DxlRow& r : it->second) {
          if (carries(r)) row = &r;
        }
        if (!carries(*row)) {
          // Protocol 2.0 has no sequence number: around a late reply the bridge can pair a
          // tick with a neighbouring reply's values (reported as an issue). The value must
          // still be one this servo sent, a reply or two away; such pairings are counted.
          const auto& replies = sent_by_id[id];
          const auto at = std::find(replies.begin(), replies.end(), row);
          const DxlRow* near = nullptr;
          for (auto j = at - std::min<std::ptrdiff_t>(3, at - replies.begin());
               j != replies.end() && j <= at + 3; ++j) {
            if (carries(**j)) near = *j;
          }
          ASSERT_NE(near, nullptr)
              << "id " << id << " tick " << m.device_tick_ms[k] << ": published "
              << m.angle_rad[k] / kOneCountRad / dir + zero
              << " counts, which no nearby reply of this servo carried (that tick's: "
              << row->position << ")";
          row = near;
          ++mispaired;
        }
        // Against the twin: the shaft angle at the reply's time, within one encoder count.
        const double twin_angle = series.AngleAt(leg_of_id.at(id), row->t_s);
        EXPECT_LE(std::abs(m.angle_rad[k] - twin_angle), kOneCountRad) << "id " << id;
        worst_counts = std::max(worst_counts, std::abs(m.angle_rad[k] - twin_angle) / kOneCountRad);
        if (last_tick.count(id)) {
          EXPECT_GT(m.device_tick_ms[k], last_tick[id]);
        }
        last_tick[id] = m.device_tick_ms[k];
      }
    }
    std::cout << "dynamixel: worst |angle - twin angle| " << worst_counts << " counts\n";
    // Every published cycle asked each servo not marked lost for one reply, sent or lost; a
    // lost servo is left out of the request (counted lost_cycles): the truth and the bridge's
    // count of cycles agree exactly.
    const std::int64_t lost_cycles = CounterOr0(last, "lost_cycles");
    std::cout << "dynamixel: " << lost_cycles << " servo-cycles skipped as lost\n";
    EXPECT_EQ(6 * last.msgs_out, present_sent + present_lost + lost_cycles);
    // Every reply lost is a stale servo; so is a reply made after the bridge's deadline, which
    // the bridge counts as late, as a repeated tick, or, when it lands in the next transaction
    // (the hardware-error read), as unexpected there, that read's own replies then arriving in
    // the following present read as malformed; the bridge may also count the stale servos of a
    // last cycle it did not get to publish.
    const std::int64_t late = CounterOr0(last, "late_replies") + CounterOr0(last, "repeated_tick") +
                              CounterOr0(last, "unexpected_replies") +
                              CounterOr0(last, "malformed");
    EXPECT_LE(mispaired, late) << "a tick paired with another reply's values without a late reply";
    EXPECT_GE(Counter(last, "stale"), present_lost);
    EXPECT_LE(Counter(last, "stale"), present_lost + late + lost_cycles + 6);
    EXPECT_GE(Counter(last, "stale"), stale + stale_tail);
    EXPECT_GE(present_sent, fresh);
    EXPECT_GE(Counter(last, "crc_errors"), corrupted);
    EXPECT_LE(Counter(last, "crc_errors"), corrupted + corrupted_unfinished);
    EXPECT_LE(static_cast<std::int64_t>(rec.servo.size()), last.msgs_out);
    EXPECT_GE(static_cast<std::int64_t>(rec.servo.size()), last.msgs_out * 9 / 10);
    EXPECT_GT(static_cast<double>(last.msgs_out), 0.5 * config.dynamixel().rate_hz() * ran_s);
    std::cout << "dynamixel: present replies sent " << present_sent << " lost " << present_lost
              << " (missing " << missing3 << ", silent " << silent << "), corrupted " << corrupted
              << "; published " << rec.servo.size() << " cycles, " << fresh << " fresh, " << stale
              << " stale (+" << stale_tail << " after the end); counted stale "
              << Counter(last, "stale") << " crc_errors " << Counter(last, "crc_errors") << " late "
              << late << ", mispaired " << mispaired << "; replies sharing a tick "
              << std::count_if(sent.begin(), sent.end(),
                               [](const auto& e) { return e.second.size() > 1; })
              << "\n";
  }

  // ---- QTM: MOCAP_BODY ----
  {
    SCOPED_TRACE("qtm");
    const auto truth = ReadQtmTruth(path("qtm.csv"));
    const service_status_t last = LastStatus(rec, mocap.pid());
    EXPECT_EQ(int{last.state}, int{service_status_t::STOPPING});
    ASSERT_FALSE(rec.mocap.empty());
    std::set<std::int64_t> published;
    std::int64_t untracked = 0;
    double worst = 0;
    for (const mocap_body_t& m : rec.mocap) {
      const std::string where = "frame " + std::to_string(m.frame_number);
      ASSERT_TRUE(truth.count(m.frame_number)) << where << " was never sent";
      ASSERT_TRUE(published.insert(m.frame_number).second) << where << " published twice";
      const QtmRow& t = truth.at(m.frame_number);
      ASSERT_FALSE(t.corrupt) << where << " was sent corrupt and still published";
      EXPECT_EQ(m.device_utime, t.timestamp_us) << where;
      ASSERT_EQ(m.tracked, t.tracked) << where;
      if (!m.tracked) {
        ++untracked;
        continue;
      }
      const Mat3 R_q =
          QuaternionToRotation(Eigen::Vector4d(m.q_gc[0], m.q_gc[1], m.q_gc[2], m.q_gc[3]));
      EXPECT_LT((R_q - t.R).cwiseAbs().maxCoeff(), 1e-6) << where;
      // Against the twin: the frame of that tick.
      const Mat3& R_twin = series.At(static_cast<double>(t.tick) / 100.0).R_GC;
      EXPECT_LT((R_q - R_twin).cwiseAbs().maxCoeff(), 1e-6) << where;
      worst = std::max(worst, (R_q - R_twin).cwiseAbs().maxCoeff());
      for (int i = 0; i < 3; ++i) EXPECT_EQ(m.position_m[i], t.p_mm(i) / 1000.0) << where;
    }
    std::cout << "qtm: worst |R_GC - twin R_GC| " << worst << "\n";
    // Everything sent intact from the first frame the bridge published on was published (the
    // bridge's count; the logger may miss a few).
    const std::int64_t first = *published.begin();
    std::int64_t intact = 0, corrupt = 0, sent = 0, untracked_sent = 0;
    for (const auto& [frame, t] : truth) {
      if (frame < first) continue;
      ++sent;
      (t.corrupt ? corrupt : intact) += 1;
      untracked_sent += !t.corrupt && !t.tracked;
    }
    EXPECT_GT(corrupt, 5);
    EXPECT_GE(untracked_sent, 40) << "0.5 s untracked at 100 Hz, less a gap or two";
    EXPECT_EQ(Counter(last, "published"), intact);
    EXPECT_LE(static_cast<std::int64_t>(rec.mocap.size()), intact);
    EXPECT_GE(static_cast<std::int64_t>(rec.mocap.size()), intact * 9 / 10)
        << "the logger missed many frames";
    // (+1: the very first frame sent to the bridge may itself have been a corrupt one.)
    EXPECT_GE(Counter(last, "decode_errors"), corrupt);
    EXPECT_LE(Counter(last, "decode_errors"), corrupt + 1);
    EXPECT_EQ(Counter(last, "untracked"), untracked_sent);
    EXPECT_GT(static_cast<double>(intact), 0.5 * 100 * ran_s);
    std::cout << "qtm: sent " << sent << " frames from the bridge's first (" << corrupt
              << " corrupt), published " << Counter(last, "published") << " (" << untracked
              << " untracked), logged " << rec.mocap.size() << "; counted decode_errors "
              << Counter(last, "decode_errors") << " frames_lost " << Counter(last, "frames_lost")
              << "\n";
  }

  if (!HasFailure()) {
    testing::RemoveTree(dir);
  } else {
    std::cerr << "logs kept in " << dir << "\n";
  }
}

// systemd's notify protocol as systemd receives it: a datagram socket at NOTIFY_SOCKET.
class NotifySocket {
 public:
  explicit NotifySocket(const std::string& path) : path_(path) {
    fd_ = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    sockaddr_un addr{};
    addr.sun_family = AF_UNIX;
    std::snprintf(addr.sun_path, sizeof(addr.sun_path), "%s", path.c_str());
    bound_ = fd_ >= 0 && ::bind(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0;
  }
  ~NotifySocket() {
    if (fd_ >= 0) ::close(fd_);
  }
  bool good() const { return bound_; }
  const std::string& path() const { return path_; }
  // Everything sent so far, one string a datagram.
  void Drain() {
    char buf[512];
    for (ssize_t n; (n = ::recv(fd_, buf, sizeof(buf), 0)) > 0;) {
      heard_.emplace_back(buf, static_cast<std::size_t>(n));
    }
  }
  int Count(const std::string& word) const {
    int n = 0;
    for (const auto& m : heard_) n += m.find(word) != std::string::npos;
    return n;
  }
  const std::vector<std::string>& heard() const { return heard_; }

 private:
  std::string path_;
  int fd_ = -1;
  bool bound_ = false;
  std::vector<std::string> heard_;
};

// The bridges run their own device-paced loops instead of ServiceApp::Run(), and the
// launcher's export-systemd makes each a Type=notify unit with WatchdogSec=: each must say
// READY=1 once running against its device, feed the watchdog with every heartbeat, and say
// STOPPING=1 on SIGTERM (systemd would otherwise time out the start, or kill a healthy bridge).
TEST(SimLive, EveryBridgeSpeaksSystemdsNotifyProtocol) {
  ASSERT_TRUE(testing::InNetns());
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const std::string config_path = path("config.pbtxt");
  std::unique_ptr<Child> sim = StartWalkingTwin(dir, config_path);
  if (HasFatalFailure()) return;
  struct Bridge {
    std::string name;
    std::vector<std::string> argv;
    std::unique_ptr<NotifySocket> socket;
    std::unique_ptr<Child> child;
  };
  std::vector<Bridge> bridges;
  // A long silence timeout: a loaded machine must not make the ATI bridge restart the stream.
  bridges.push_back({"ati",
                     {FTCAL_ATI_BRIDGE, "--config", config_path, "--silence-timeout", "1.0"},
                     nullptr,
                     nullptr});
  bridges.push_back(
      {"dynamixel", {FTCAL_DYNAMIXEL_BRIDGE, "--config", config_path}, nullptr, nullptr});
  bridges.push_back({"mocap", {FTCAL_MOCAP_BRIDGE, "--config", config_path}, nullptr, nullptr});
  for (Bridge& b : bridges) {
    b.socket = std::make_unique<NotifySocket>(path(b.name + ".notify"));
    ASSERT_TRUE(b.socket->good()) << b.socket->path();
    ::setenv("NOTIFY_SOCKET", b.socket->path().c_str(), 1);
    ::setenv("WATCHDOG_USEC", "3000000", 1);
    b.child = std::make_unique<Child>(b.argv, path(b.name + ".out"), path(b.name + ".err"));
    ::unsetenv("NOTIFY_SOCKET");
    ::unsetenv("WATCHDOG_USEC");
  }
  SleepS(4.0);
  for (Bridge& b : bridges) b.socket->Drain();
  for (Bridge& b : bridges) {
    SCOPED_TRACE(b.name);
    EXPECT_EQ(b.socket->Count("READY=1"), 1) << testing::ReadFile(path(b.name + ".err"));
    EXPECT_GE(b.socket->Count("WATCHDOG=1"), 2) << "one per heartbeat for ~3 s";
    EXPECT_EQ(b.socket->Count("STOPPING=1"), 0);
  }
  for (Bridge& b : bridges)
    Terminate(*b.child, "ftcal-" + b.name + "-bridge", path(b.name + ".err"));
  for (Bridge& b : bridges) {
    SCOPED_TRACE(b.name);
    b.socket->Drain();
    EXPECT_EQ(b.socket->Count("STOPPING=1"), 1);
    EXPECT_EQ(b.socket->Count("READY=1"), 1);
  }
  Terminate(*sim, "ftcal-sim live", path("sim.err"));
  if (!HasFailure()) testing::RemoveTree(dir);
}

// /proc/PID/stat's scheduling fields for a process's main thread: {rt_priority, policy}
// (fields 40 and 41; 1 is SCHED_FIFO). Empty when the process is gone.
std::pair<std::string, std::string> SchedulingOf(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string line;
  if (!std::getline(stat, line)) return {};
  std::istringstream rest(line.substr(line.rfind(')') + 2));
  std::vector<std::string> fields;  // fields[0] is field 3
  for (std::string f; rest >> f;) fields.push_back(f);
  if (fields.size() <= 38) return {};
  return {fields[37], fields[38]};
}

// Every bridge takes --realtime (ServiceApp's scheduling flags) and runs its device loop
// SCHED_FIFO at the priority asked once its device is open, as the kernel itself reports;
// without the privilege it says so and runs on as an ordinary process.
TEST(SimLive, EveryBridgeRunsItsDeviceLoopRealtimeWhenAsked) {
  ASSERT_TRUE(testing::InNetns());
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const std::string config_path = path("config.pbtxt");
  std::unique_ptr<Child> sim = StartWalkingTwin(dir, config_path);
  if (HasFatalFailure()) return;
  const std::vector<std::string> rt = {"--realtime", "--realtime-priority", "12"};
  std::vector<std::pair<std::string, std::unique_ptr<Child>>> bridges;
  for (const auto& [name, exe] :
       std::vector<std::pair<std::string, std::string>>{{"ati", FTCAL_ATI_BRIDGE},
                                                        {"dynamixel", FTCAL_DYNAMIXEL_BRIDGE},
                                                        {"mocap", FTCAL_MOCAP_BRIDGE}}) {
    std::vector<std::string> argv = {exe, "--config", config_path};
    argv.insert(argv.end(), rt.begin(), rt.end());
    bridges.emplace_back(name,
                         std::make_unique<Child>(argv, path(name + ".out"), path(name + ".err")));
  }
  const bool privileged = ::geteuid() == 0;
  for (auto& [name, child] : bridges) {
    SCOPED_TRACE(name);
    const std::string err = path(name + ".err");
    // The flags are applied once the device is open: the log line says when.
    const std::string said =
        privileged ? "--realtime: SCHED_FIFO priority 12" : "SCHED_FIFO refused";
    bool logged = false;
    for (int i = 0; i < 100 && !logged; ++i) {
      logged = testing::ReadFile(err).find(said) != std::string::npos ||
               testing::ReadFile(path(name + ".out")).find(said) != std::string::npos;
      if (!logged) SleepS(0.1);
    }
    EXPECT_TRUE(logged) << "no '" << said << "' in its log\n" << testing::ReadFile(err);
    const auto [priority, policy] = SchedulingOf(child->pid());
    if (privileged) {
      EXPECT_EQ(policy, "1") << "SCHED_FIFO";
      EXPECT_EQ(priority, "12");
    } else {
      EXPECT_EQ(policy, "0") << "SCHED_OTHER";
    }
  }
  for (auto& [name, child] : bridges)
    Terminate(*child, "ftcal-" + name + "-bridge", path(name + ".err"));
  Terminate(*sim, "ftcal-sim live", path("sim.err"));
  if (!HasFailure()) testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
