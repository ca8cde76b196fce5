// ftcal-ati-bridge under full load: six emulated Net F/T boxes streaming 7000 records/s each on
// loopback (ftcal-emulate-ati) into one bridge (or one per leg, --bridges 6), for --duration
// seconds. Prints per leg what was sent, received, lost and published, the bridge's CPU time
// (wait4 rusage) and its receipt-to-publish latency p50/p99, measured in the bridge from the
// kernel's receive timestamp (SO_TIMESTAMPNS) and from the clock when recvmmsg returned, as its
// final heartbeat reports them. Must run inside scripts/netns-exec (ctest does).
//
//   scripts/netns-exec build/tests/bench/ati_bridge_bench --duration 5
#include <signal.h>
#include <fcntl.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <lcm/lcm-cpp.hpp>

#include "ftcal/ft_sample_t.hpp"
#include "ftcal/service_status_t.hpp"

extern char** environ;

namespace {

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
const std::vector<std::string> kLegs = {"HL", "ML", "FL", "HR", "MR", "FR"};

pid_t Spawn(const std::vector<std::string>& argv, const std::string& err_path) {
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 2, err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC,
                                   0644);
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  pid_t pid = -1;
  if (posix_spawn(&pid, args[0], &actions, nullptr, args.data(), environ) != 0) {
    std::fprintf(stderr, "cannot start %s\n", args[0]);
    std::exit(1);
  }
  posix_spawn_file_actions_destroy(&actions);
  return pid;
}

struct Ended {
  int status = 0;
  double cpu_s = 0;
};

Ended Stop(pid_t pid) {
  ::kill(pid, SIGTERM);
  Ended e;
  rusage ru{};
  if (::wait4(pid, &e.status, 0, &ru) == pid) {
    e.cpu_s = ru.ru_utime.tv_sec + ru.ru_utime.tv_usec * 1e-6 + ru.ru_stime.tv_sec +
              ru.ru_stime.tv_usec * 1e-6;
  }
  return e;
}

std::string ReadFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

class Listener {
 public:
  Listener() : lcm_(kUrl) {
    lcm_.subscribe("FT_.*", &Listener::OnSample, this);
    lcm_.subscribe("FTCAL_STATUS", &Listener::OnStatus, this);
    thread_ = std::thread([this] {
      while (!stop_) lcm_.handleTimeout(50);
    });
  }
  ~Listener() {
    stop_ = true;
    thread_.join();
  }
  void OnSample(const lcm::ReceiveBuffer*, const std::string& channel) {
    std::lock_guard<std::mutex> lock(mu_);
    ++heard_[channel.substr(3)];
  }
  void OnStatus(const lcm::ReceiveBuffer* rbuf, const std::string&) {
    ftcal::service_status_t s;
    if (s.decode(rbuf->data, 0, static_cast<int>(rbuf->data_size)) < 0) return;
    std::lock_guard<std::mutex> lock(mu_);
    last_status_[s.pid] = s;
  }
  std::map<std::string, long long> heard() {
    std::lock_guard<std::mutex> lock(mu_);
    return heard_;
  }
  std::map<long long, ftcal::service_status_t> statuses() {
    std::lock_guard<std::mutex> lock(mu_);
    return last_status_;
  }

 private:
  lcm::LCM lcm_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
  std::mutex mu_;
  std::map<std::string, long long> heard_;
  std::map<long long, ftcal::service_status_t> last_status_;
};

long long CounterOf(const ftcal::service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  return -1;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App cli("ftcal-ati-bridge benchmark: six Net F/T boxes at full rate on loopback",
               "ati_bridge_bench");
  double duration_s = 60;
  int bridges = 1;
  int rate_hz = 7000;
  cli.add_option("--duration", duration_s, "seconds of streaming")->capture_default_str();
  cli.add_option("--bridges", bridges, "1: one bridge for all six legs; 6: one per leg")
      ->check(CLI::IsMember({1, 6}))
      ->capture_default_str();
  cli.add_option("--rate", rate_hz, "records/s per box")->capture_default_str();
  CLI11_PARSE(cli, argc, argv);
  const char* netns = std::getenv("FTCAL_NETNS");
  if (netns == nullptr || std::string(netns) != "1") {
    std::fprintf(stderr, "run me through scripts/netns-exec: I send UDP multicast\n");
    return 2;
  }

  char dir_template[] = "/tmp/ati-bench-XXXXXX";
  const std::string dir = ::mkdtemp(dir_template);
  const std::string ready = dir + "/ready";
  // The boxes stop sending after --duration and the bridge is stopped a second later, so that
  // every record sent has had time to arrive: received/sent is then the real loss.
  const pid_t emulator = Spawn({FTCAL_EMULATE_ATI, "--rate", std::to_string(rate_hz),
                                "--duration", std::to_string(duration_s), "--ready", ready},
                               dir + "/emulator.err");
  for (int i = 0; i < 600 && ::access(ready.c_str(), F_OK) != 0; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  if (::access(ready.c_str(), F_OK) != 0) {
    std::fprintf(stderr, "emulator not ready: %s\n", ReadFile(dir + "/emulator.err").c_str());
    return 1;
  }
  Listener listener;
  std::this_thread::sleep_for(std::chrono::milliseconds(200));

  std::vector<pid_t> bridge_pids;
  if (bridges == 1) {
    bridge_pids.push_back(Spawn({FTCAL_ATI_BRIDGE, "--lcm-url", kUrl, "--log-level", "warn"},
                                dir + "/bridge.err"));
  } else {
    for (const auto& leg : kLegs) {
      bridge_pids.push_back(Spawn(
          {FTCAL_ATI_BRIDGE, "--lcm-url", kUrl, "--log-level", "warn", "--legs", leg},
          dir + "/bridge-" + leg + ".err"));
    }
  }
  std::this_thread::sleep_for(std::chrono::duration<double>(duration_s + 1.0));
  std::vector<Ended> ended;
  for (pid_t pid : bridge_pids) ended.push_back(Stop(pid));
  const Ended emu = Stop(emulator);
  std::this_thread::sleep_for(std::chrono::milliseconds(300));

  // The emulator's per-box summary: "ftcal-emulate-ati: HL records N datagrams M ...".
  std::map<std::string, long long> sent;
  std::istringstream lines(ReadFile(dir + "/emulator.err"));
  for (std::string line; std::getline(lines, line);) {
    std::istringstream words(line);
    std::string tag, leg, k1, k2;
    long long records = 0, datagrams = 0;
    if (words >> tag >> leg >> k1 >> records >> k2 >> datagrams && k2 == "datagrams") {
      sent[leg] = datagrams;
    }
  }
  const auto heard = listener.heard();
  const auto statuses = listener.statuses();

  std::printf("ati_bridge_bench: %d boxes x %d records/s for %.1f s on loopback, %d bridge "
              "process(es)\n", 6, rate_hz, duration_s, bridges);
  std::printf("%-4s %10s %10s %10s %8s %10s %10s\n", "leg", "sent", "received", "published",
              "lost", "heard_lcm", "recv/sent");
  long long total_sent = 0, total_received = 0, total_lost = 0;
  for (std::size_t i = 0; i < kLegs.size(); ++i) {
    const std::string& leg = kLegs[i];
    const pid_t pid = bridge_pids[bridges == 1 ? 0 : i];
    const auto it = statuses.find(pid);
    long long received = -1, published = -1, lost = -1;
    if (it != statuses.end()) {
      received = CounterOf(it->second, leg + ".received");
      published = CounterOf(it->second, leg + ".published");
      lost = CounterOf(it->second, leg + ".lost");
    }
    const long long s = sent.count(leg) ? sent.at(leg) : -1;
    const long long h = heard.count(leg) ? heard.at(leg) : 0;
    total_sent += s;
    total_received += received;
    total_lost += lost;
    std::printf("%-4s %10lld %10lld %10lld %8lld %10lld %10.6f\n", leg.c_str(), s, received,
                published, lost, h, s > 0 ? double(received) / double(s) : 0.0);
  }
  std::printf("total: sent %lld received %lld lost %lld (heard_lcm: what this program's own "
              "LCM listener kept up with, for information)\n", total_sent, total_received,
              total_lost);
  for (std::size_t i = 0; i < bridge_pids.size(); ++i) {
    const auto it = statuses.find(bridge_pids[i]);
    std::printf("bridge %zu: CPU %.2f s = %.1f%% of one core", i, ended[i].cpu_s,
                100.0 * ended[i].cpu_s / duration_s);
    if (it != statuses.end()) {
      std::printf("; latency receipt->published p50 %lld us p99 %lld us (user clock at "
                  "recvmmsg), p50 %lld us p99 %lld us (kernel SO_TIMESTAMPNS)",
                  CounterOf(it->second, "latency_p50_us"), CounterOf(it->second, "latency_p99_us"),
                  CounterOf(it->second, "kernel_latency_p50_us"),
                  CounterOf(it->second, "kernel_latency_p99_us"));
    } else {
      std::printf("; no final heartbeat heard");
    }
    std::printf("\n");
  }
  std::printf("emulator: CPU %.2f s\n", emu.cpu_s);
  return 0;
}
