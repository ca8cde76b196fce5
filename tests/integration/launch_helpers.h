// What the tests of ftcal-launch share (launch_test, two_host_experiment_test): the programs on
// supervisord's PATH, ftcal-launch and supervisorctl run from the test, what the test hears on
// the bus (Ear), what the kernel says about supervisord's children (/proc), and two network
// namespaces "robot" and "workstation" joined by a veth pair for the two-host groups.
//
// The including target defines FTCAL_LAUNCH, FTCAL_EVENTS, FTCAL_SIM, FTCAL_ATI_BRIDGE,
// FTCAL_DYNAMIXEL_BRIDGE, FTCAL_MOCAP_BRIDGE, FTCAL_SEGMENTER, FTCAL_CALIBRATOR,
// FTCAL_CORRECTOR, FTCAL_DRIFT, FTCAL_LCM_LOGGER and FTCAL_RECORD (the programs' paths), as
// launch_test.cmake does.
#pragma once

#include <fcntl.h>
#include <sched.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <chrono>
#include <cstdlib>
#include <ctime>
#include <deque>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/process_state_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "launcher/launch_plan.h"
#include "launcher/supervisor.h"

namespace ftcal::launch_testing {

using Clock = std::chrono::steady_clock;
using launch::RunShell;
using launch::ShellQuote;

// supervisord spawns a replacement at the top of its next loop, after its next wake-up; the
// group's pacer (ftcal-supervisor-events --pace 0.1) makes one every 0.1 s. Without it the
// restart took 0.02-2.05 s here (its 1 s poll timeout, twice when the first reap came early).
// The bound is on Respawn::net_s(): a stall of the whole machine is nobody's restart time.
constexpr double kRestartBoundS = 1.0;

inline double Since(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

inline std::string Dir(const char* path) {
  return std::filesystem::path(path).parent_path().string();
}

// The programs' directories at the front of PATH (each once): supervisord hands its children
// this PATH, so the groups' commands are found by name.
inline void PutOnPath(const std::vector<std::string>& programs) {
  const char* old = std::getenv("PATH");
  std::string path = old ? old : "/usr/bin:/bin";
  for (auto p = programs.rbegin(); p != programs.rend(); ++p) {
    const std::string dir = Dir(p->c_str());
    if ((":" + path + ":").find(":" + dir + ":") == std::string::npos) path = dir + ":" + path;
  }
  ::setenv("PATH", path.c_str(), 1);
}

// Every program the groups run, on the PATH supervisord hands its children.
inline void PutProgramsOnPath() {
  PutOnPath({FTCAL_LAUNCH, FTCAL_EVENTS, FTCAL_SIM, FTCAL_ATI_BRIDGE, FTCAL_DYNAMIXEL_BRIDGE,
             FTCAL_MOCAP_BRIDGE, FTCAL_SEGMENTER, FTCAL_CALIBRATOR, FTCAL_CORRECTOR, FTCAL_DRIFT,
             FTCAL_LCM_LOGGER, FTCAL_RECORD});
}

// What the test itself hears on the bus, read on a thread of its own: the test blocks in
// ftcal-launch and supervisorctl for seconds, and LCM drops what a subscription cannot queue.
class Ear {
 public:
  // Arrival times and counts are kept for the channels matching `channels` (a regex).
  explicit Ear(const std::string& url, const std::string& channels = ".*") : lcm_(url) {
    EXPECT_TRUE(lcm_.good()) << url;
    lcm_.subscribe(channels, &Ear::OnAny, this)->setQueueCapacity(100000);
    lcm_.subscribe("FTCAL_STATUS", &Ear::OnStatus, this)->setQueueCapacity(10000);
    lcm_.subscribe("PROCESS_STATE", &Ear::OnState, this)->setQueueCapacity(10000);
    thread_ = std::thread([this] {
      while (!stop_) lcm_.handleTimeout(20);
    });
  }
  ~Ear() {
    stop_ = true;
    thread_.join();
  }
  void Pump(double seconds) { std::this_thread::sleep_for(std::chrono::duration<double>(seconds)); }
  // Waits until `done` or `timeout_s`; true when done.
  bool PumpUntil(const std::function<bool()>& done, double timeout_s) {
    const auto end = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (Clock::now() < end) {
      if (done()) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return done();
  }
  // Messages per second on each channel matching the prefix over the last `window_s`.
  std::map<std::string, double> Rates(const std::string& prefix, double window_s) const {
    std::lock_guard<std::mutex> lock(mutex_);
    std::map<std::string, double> out;
    const auto from = Clock::now() - std::chrono::duration_cast<Clock::duration>(
                                         std::chrono::duration<double>(window_s));
    for (const auto& [ch, times] : arrivals_) {
      if (ch.rfind(prefix, 0) != 0) continue;
      int n = 0;
      for (auto t : times) n += t >= from;
      out[ch] = n / window_s;
    }
    return out;
  }
  // Waits up to `timeout_s` for a `window_s` in which each of `channels` channels matching
  // `prefix` ran at >= `hz`; true when one came. The best window seen is in `best` (its slowest
  // channel's rate), for the message. A twin starved of CPU for more than 50 ms by the other
  // tests on the machine drops that stall's records as a NetBox would (no burst afterwards), so
  // one snapshot can fall short while the group is healthy; a bridge that cannot keep the rate
  // never gets a full window.
  bool AtRate(const std::string& prefix, std::size_t channels, double hz, double window_s,
              double timeout_s, double* best = nullptr) {
    double best_slowest = 0;
    const bool ok = PumpUntil(
        [&] {
          const auto r = Rates(prefix, window_s);
          if (r.size() != channels) return false;
          double slowest = hz * 10;
          for (const auto& [ch, rate] : r) slowest = std::min(slowest, rate);
          best_slowest = std::max(best_slowest, slowest);
          return slowest >= hz;
        },
        timeout_s);
    if (best) *best = best_slowest;
    return ok;
  }
  // Waits up to `timeout_s` for a `window_s` in which each of `channels` FT channels matching
  // `prefix` brought at least `fraction` of the records its box sent in that window, counted by
  // the box's own rdt_sequence, and at least `min_hz` of them a second (the group runs at all).
  // The bound is what the machine let the twin send, not a fixed rate: beside other work the
  // twin's boxes send fewer records (a stalled NetBox skips, it does not burst), and a pipeline
  // that keeps up still brings every one of them. `best` gets the best window's lowest fraction.
  bool Delivered(const std::string& prefix, std::size_t channels, double fraction, double min_hz,
                 double window_s, double timeout_s, double* best = nullptr) {
    double best_lowest = 0;
    const bool ok = PumpUntil(
        [&] {
          std::lock_guard<std::mutex> lock(mutex_);
          const auto from = Clock::now() - std::chrono::duration_cast<Clock::duration>(
                                               std::chrono::duration<double>(window_s));
          std::size_t n_channels = 0;
          double lowest = 1.0;
          bool enough = true;
          for (const auto& [ch, heard] : ft_heard_) {
            if (ch.rfind(prefix, 0) != 0) continue;
            ++n_channels;
            int64_t n = 0, first = -1, last = -1;
            for (const auto& [t, seq] : heard) {
              if (t < from) continue;
              if (first < 0 || seq < last) first = seq, n = 0;  // a box restart: count anew
              last = seq;
              ++n;
            }
            const double sent = first < 0 ? 0.0 : static_cast<double>(last - first + 1);
            lowest = std::min(lowest, sent > 0 ? n / sent : 0.0);
            enough = enough && n >= min_hz * window_s;
          }
          if (n_channels != channels) return false;
          best_lowest = std::max(best_lowest, lowest);
          return enough && lowest >= fraction;
        },
        timeout_s);
    if (best) *best = best_lowest;
    return ok;
  }
  struct Beat {
    service_status_t status;
    Clock::time_point at;
  };
  std::vector<Beat> beats() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return beats_;
  }
  // The heartbeats from index `from` on, and how many there are: a long test polls these
  // without copying every heartbeat it has heard.
  std::vector<Beat> beats_since(std::size_t from) const {
    std::lock_guard<std::mutex> lock(mutex_);
    return {beats_.begin() + static_cast<std::ptrdiff_t>(std::min(from, beats_.size())),
            beats_.end()};
  }
  std::size_t beat_count() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return beats_.size();
  }
  std::vector<process_state_t> states() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return states_;
  }
  // Messages heard on `channel` since the start.
  int64_t count(const std::string& channel) const {
    std::lock_guard<std::mutex> lock(mutex_);
    const auto it = counts_.find(channel);
    return it == counts_.end() ? 0 : it->second;
  }

 private:
  void OnAny(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto now = Clock::now();
    ft_batch_t ft;
    const bool is_ft = channel.rfind("FT_", 0) == 0 && ft.decode(rbuf->data, 0, rbuf->data_size) ==
                                                           static_cast<int>(rbuf->data_size);
    std::lock_guard<std::mutex> lock(mutex_);
    ++counts_[channel];
    auto& a = arrivals_[channel];
    a.push_back(now);
    while (!a.empty() && a.front() < now - std::chrono::seconds(10)) a.pop_front();
    if (is_ft) {
      auto& h = ft_heard_[channel];
      // One entry per record: a message carries a datagram's n records.
      for (int i = 0; i < ft.n; ++i) h.emplace_back(now, ft.rdt_sequence[i]);
      while (!h.empty() && h.front().first < now - std::chrono::seconds(10)) h.pop_front();
    }
  }
  void OnStatus(const lcm::ReceiveBuffer* rbuf, const std::string&) {
    service_status_t s;
    if (s.decode(rbuf->data, 0, rbuf->data_size) != static_cast<int>(rbuf->data_size)) return;
    std::lock_guard<std::mutex> lock(mutex_);
    beats_.push_back({s, Clock::now()});
  }
  void OnState(const lcm::ReceiveBuffer* rbuf, const std::string&) {
    process_state_t m;
    if (m.decode(rbuf->data, 0, rbuf->data_size) != static_cast<int>(rbuf->data_size)) return;
    std::lock_guard<std::mutex> lock(mutex_);
    states_.push_back(m);
  }
  lcm::LCM lcm_;
  mutable std::mutex mutex_;
  std::map<std::string, std::deque<Clock::time_point>> arrivals_;
  std::map<std::string, std::deque<std::pair<Clock::time_point, int64_t>>> ft_heard_;
  std::map<std::string, int64_t> counts_;
  std::vector<Beat> beats_;
  std::vector<process_state_t> states_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

inline void WriteText(const std::string& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
}

struct Ran {
  int rc;
  std::string out;
  double seconds;
};
inline Ran Launch(const std::vector<std::string>& args, double timeout_s = 120) {
  PutProgramsOnPath();
  std::string line = ShellQuote(FTCAL_LAUNCH);
  for (const auto& a : args) line += " " + ShellQuote(a);
  const auto t0 = Clock::now();
  auto r = RunShell({}, line, "", timeout_s);
  return {r.exit_code, r.output, Since(t0)};
}

inline std::map<std::string, launch::ProgramStatus> SupervisorStatus(
    const std::string& run_dir, const std::vector<std::string>& shell = {}) {
  return launch::ParseStatus(
      RunShell(shell, "supervisorctl -c " + ShellQuote(run_dir + "/supervisord.conf") + " status")
          .output);
}

// Stops whatever supervisord a test started in `run_dir`, even when the test failed half-way.
struct SupervisordGuard {
  std::vector<std::string> run_dirs;
  ~SupervisordGuard() {
    for (const auto& dir : run_dirs) {
      std::ifstream in(dir + "/supervisord.pid");
      pid_t pid = 0;
      if (in >> pid && pid > 0) {
        ::kill(pid, SIGTERM);
        for (int i = 0; i < 100 && ::kill(pid, 0) == 0; ++i) {
          std::this_thread::sleep_for(std::chrono::milliseconds(50));
        }
        if (::kill(pid, 0) == 0) ::kill(pid, SIGKILL);
      }
    }
  }
};

inline pid_t SupervisordPid(const std::string& run_dir) {
  std::ifstream in(run_dir + "/supervisord.pid");
  pid_t pid = 0;
  in >> pid;
  return pid;
}

// A child of `parent` running `program` (argv[0]'s file name) other than `old`, from /proc:
// what the kernel says, not what supervisor or the process report.
inline pid_t ChildRunning(pid_t parent, const std::string& program, pid_t old) {
  for (const auto& entry : std::filesystem::directory_iterator("/proc")) {
    const std::string name = entry.path().filename().string();
    if (name.find_first_not_of("0123456789") != std::string::npos) continue;
    const pid_t pid = std::stoi(name);
    if (pid == old) continue;
    std::ifstream stat(entry.path() / "stat");
    std::string line;
    if (!std::getline(stat, line)) continue;
    const auto close = line.rfind(')');
    if (close == std::string::npos) continue;
    std::istringstream rest(line.substr(close + 2));
    char state;
    pid_t ppid = 0;
    if (!(rest >> state >> ppid) || ppid != parent) continue;
    std::ifstream cmd(entry.path() / "cmdline");
    std::string argv0;
    std::getline(cmd, argv0, '\0');
    if (std::filesystem::path(argv0).filename() == program) return pid;
  }
  return 0;
}

// Seconds on CLOCK_BOOTTIME, the clock of /proc/PID/stat's starttime.
inline double BootS() {
  timespec ts{};
  ::clock_gettime(CLOCK_BOOTTIME, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// When the kernel created `pid` (its fork), in BootS() seconds at the kernel's tick (10 ms);
// -1 when it is gone.
inline double ForkedAtBootS(pid_t pid) {
  std::ifstream stat("/proc/" + std::to_string(pid) + "/stat");
  std::string line;
  if (!std::getline(stat, line)) return -1;
  const auto close = line.rfind(')');
  if (close == std::string::npos) return -1;
  std::istringstream rest(line.substr(close + 2));
  std::string field;
  // After the comm come field 3 (state) .. field 22 (starttime): starttime is the 20th.
  for (int i = 3; i <= 22; ++i) {
    if (!(rest >> field)) return -1;
  }
  return std::stod(field) / static_cast<double>(::sysconf(_SC_CLK_TCK));
}

// One kill -9 and supervisord's answer to it, as the kernel saw it. `forked_s` is from the kill
// to the new child's fork (its /proc start time, so what this test takes to look does not count);
// `stalled_s` is the part of it in which this test was not run at all for more than 0.1 s while
// it watched (a stall of the whole machine: a VM descheduled, memory reclaim), which delays
// supervisord as much as anything and is no one's restart time. A restart that merely came late
// is not hidden by it: the watcher runs every few milliseconds on an otherwise idle process.
struct Respawn {
  pid_t parent = 0;
  std::string program;
  pid_t old = 0;
  pid_t pid = 0;         // the new child, 0 when none came
  double forked_s = -1;  // kill -> the new child's fork
  double seen_s = -1;    // kill -> this test saw it run `program`
  double stalled_s = 0;  // of forked_s, the machine's stalls
  double net_s() const { return forked_s - stalled_s; }
  std::string Describe() const {
    std::ostringstream s;
    s << net_s() << " s (forked " << forked_s << " s after the kill, seen running " << seen_s
      << " s; the machine stalled " << stalled_s << " s of it)";
    return s.str();
  }
};

// Watches /proc, every few milliseconds, until each target's parent has a new child running its
// program, or `timeout_s` after the kill (`kill_boot_s`, BootS() just before it).
inline void WatchRespawns(double kill_boot_s, const std::vector<Respawn*>& targets,
                          double timeout_s) {
  constexpr double kStallS = 0.1;
  std::vector<std::pair<double, double>> stalls;
  double last = BootS();
  auto pending = [&] {
    return std::any_of(targets.begin(), targets.end(), [](const Respawn* r) { return !r->pid; });
  };
  while (pending() && last - kill_boot_s < timeout_s) {
    for (Respawn* r : targets) {
      if (r->pid) continue;
      if (const pid_t pid = ChildRunning(r->parent, r->program, r->old); pid > 0) {
        const double forked = ForkedAtBootS(pid);
        if (forked < 0) continue;  // gone again: the next one counts
        r->pid = pid;
        r->seen_s = BootS() - kill_boot_s;
        r->forked_s = std::max(0.0, forked - kill_boot_s);
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
    const double now = BootS();
    if (now - last > kStallS) stalls.emplace_back(last, now);
    last = now;
  }
  for (Respawn* r : targets) {
    if (!r->pid) continue;
    const double end = kill_boot_s + r->forked_s;
    for (const auto& [from, to] : stalls) {
      r->stalled_s += std::max(0.0, std::min(to, end) - std::max(from, kill_boot_s));
    }
  }
}

// ---- Two hosts: network namespaces "robot" and "workstation" joined by a veth pair ----

inline std::string Sh(const std::string& line) {
  const auto r = RunShell({}, line, "", 30);
  EXPECT_EQ(r.exit_code, 0) << line << ": " << r.output;
  return r.output;
}

// Two namespaces of this test's own, joined by a veth pair with a multicast route on each side:
// LCM at ttl=1 crosses the link and goes no further (nothing else is attached).
struct TwoNamespaces {
  std::string robot, workstation;
  int original = -1;
  TwoNamespaces() {
    const std::string tag = std::to_string(::getpid());
    robot = "ftcal-r" + tag;
    workstation = "ftcal-w" + tag;
    const std::string vr = "ftr" + tag, vw = "ftw" + tag;  // interface names <= 15 chars
    Sh("ip netns add " + robot + " && ip netns add " + workstation);
    Sh("ip link add " + vr + " type veth peer name " + vw);
    Sh("ip link set " + vr + " netns " + robot + " && ip link set " + vw + " netns " + workstation);
    Sh("ip -n " + robot + " addr add 10.77.0.1/30 dev " + vr);
    Sh("ip -n " + workstation + " addr add 10.77.0.2/30 dev " + vw);
    for (const auto& [ns, dev] : {std::pair{robot, vr}, std::pair{workstation, vw}}) {
      Sh("ip -n " + ns + " link set lo up && ip -n " + ns + " link set " + dev +
         " up multicast on && ip -n " + ns + " route add 224.0.0.0/4 dev " + dev);
    }
    original = ::open("/proc/self/ns/net", O_RDONLY | O_CLOEXEC);
  }
  // This process (and what it starts from now on) joins namespace `name`.
  void Enter(const std::string& name) const {
    const int fd = ::open(("/run/netns/" + name).c_str(), O_RDONLY | O_CLOEXEC);
    ASSERT_GE(fd, 0) << name;
    ASSERT_EQ(::setns(fd, CLONE_NEWNET), 0) << name;
    ::close(fd);
  }
  ~TwoNamespaces() {
    if (original >= 0) {
      ::setns(original, CLONE_NEWNET);
      ::close(original);
    }
    RunShell({}, "ip netns del " + robot + "; ip netns del " + workstation, "", 30);
  }
};

// `base` (a config's text) cut before its launch section, its LCM at ttl=1, with a launch
// section of the two namespaces' hosts and `groups` ("  group { ... }" blocks): the robot
// driven through `ip netns exec`, the workstation the host ftcal-launch runs on.
inline std::string TwoHostLaunchConfig(const std::string& base, const TwoNamespaces& ns,
                                       const std::string& robot_run, const std::string& ws_run,
                                       const std::string& groups) {
  std::string text = base.substr(0, base.find("launch {"));
  const std::string url = "lcm_url: \"udpm://239.255.76.67:7667?ttl=0\"";
  EXPECT_NE(text.find(url), std::string::npos) << "the config's lcm_url changed";
  if (text.find(url) != std::string::npos) {
    text.replace(text.find(url), url.size(), "lcm_url: \"udpm://239.255.76.67:7667?ttl=1\"");
  }
  return text + R"(
launch {
  host { name: "robot" address: "10.77.0.1" run_dir: ")" +
         robot_run + R"("
         shell: ["ip", "netns", "exec", ")" +
         ns.robot + R"(", "sh", "-c"] }
  host { name: "workstation" address: "10.77.0.2" run_dir: ")" +
         ws_run + R"(" }
)" + groups +
         "}\n";
}

// The new pid's first heartbeat after `from` (index into ear.beats()), as seconds after t_kill.
inline std::optional<std::pair<int64_t, double>> Restarted(const Ear& ear, std::size_t from,
                                                           const std::string& name, pid_t old_pid,
                                                           Clock::time_point t_kill) {
  for (const auto& b : ear.beats_since(from)) {
    if (b.status.name == name && b.status.pid != old_pid) {
      return std::pair{b.status.pid, std::chrono::duration<double>(b.at - t_kill).count()};
    }
  }
  return std::nullopt;
}

// The row of ftcal-status's process-group table for `process` ("two:ati-bridge"): HOST PROCESS
// SUPERVISOR PID RESTARTS HEARTBEAT ...
inline std::vector<std::string> GroupRow(const std::string& table, const std::string& process) {
  std::istringstream lines(table);
  for (std::string line; std::getline(lines, line);) {
    std::istringstream words(line);
    std::vector<std::string> row;
    for (std::string w; words >> w;) row.push_back(w);
    if (row.size() >= 6 && row[1] == process) return row;
  }
  return {};
}

}  // namespace ftcal::launch_testing
