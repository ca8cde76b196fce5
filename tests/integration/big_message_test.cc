// Issue 36, finding 4: LCM reassembles a fragmented message before ftcal's wire guard sees it
// (Debian's liblcm 1.3.1 takes up to 256 MiB on any subscribed channel; no URL option bounds it),
// so what bounds a process is its memory limit. The real Dynamixel bridge, run as shipped
// (--realtime: SCHED_FIFO, memory locked) against the bus emulator, is sent what an attacker on
// the LCM group could send to SERVO_CMD, the one channel a bridge subscribes to:
//  - the first fragment of a message announcing 250 MB, and nothing more: before the fix, the
//    locked process made LCM's whole reassembly buffer resident at once (mlockall MCL_FUTURE);
//  - a whole 250 MB message: it must fit within the memory limit the shipped robot config gives
//    the bridge (config/bigant.pbtxt, systemd's MemoryMax=), which was 256 MB before the fix.
// The fragments are written here, by the LCM wire format (docs/architecture.md, "What a message
// may cost"), so that the test decides the pacing: lcm_publish sends them back to back and the
// receiver's socket buffer would drop most of them.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <functional>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "ftcal/config.h"
#include "ftcal/service_status_t.hpp"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr char kGroup[] = "239.255.76.67";
constexpr uint16_t kPort = 7667;
constexpr uint32_t kBigBytes = 250'000'000;
constexpr double kMiB = 1024.0 * 1024.0;

// A kernel-reported figure of /proc/<pid>/status in MiB ("VmRSS", "VmHWM"), or -1.
double ProcStatusMiB(pid_t pid, const std::string& key) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(key + ":", 0) == 0) return std::stod(line.substr(key.size() + 1)) / 1024.0;
  }
  return -1;
}

// One sender of LCM datagrams (its own socket, so its own fragment buffer at the receivers:
// LCM keys incomplete messages by the sender's address).
class RawSender {
 public:
  RawSender() : fd_(::socket(AF_INET, SOCK_DGRAM, 0)) {
    to_.sin_family = AF_INET;
    to_.sin_port = htons(kPort);
    ::inet_pton(AF_INET, kGroup, &to_.sin_addr);
    const unsigned char ttl = 0;
    ::setsockopt(fd_, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl);
  }
  ~RawSender() { ::close(fd_); }
  bool good() const { return fd_ >= 0; }

  // A message of `size` bytes on `channel` in fragments of at most `fragment` bytes (LCM's
  // "LC03" long header, big-endian), fragments [0, count) of it; `between` after each one.
  bool SendFragments(const std::string& channel, uint32_t seqno, uint32_t size, uint32_t fragment,
                     uint32_t count, std::chrono::microseconds between) {
    const uint32_t total = (size + fragment - 1) / fragment;
    if (total > 0xffff) return false;
    std::vector<uint8_t> datagram;
    for (uint32_t no = 0; no < count && no < total; ++no) {
      const uint32_t offset = no * fragment;
      const uint32_t n = std::min(fragment, size - offset);
      datagram.clear();
      Put32(datagram, 0x4c433033);
      Put32(datagram, seqno);
      Put32(datagram, size);
      Put32(datagram, offset);
      Put16(datagram, static_cast<uint16_t>(no));
      Put16(datagram, static_cast<uint16_t>(total));
      if (no == 0)
        datagram.insert(datagram.end(), channel.c_str(), channel.c_str() + channel.size() + 1);
      datagram.resize(datagram.size() + n, static_cast<uint8_t>(0xA5 ^ no));
      if (::sendto(fd_, datagram.data(), datagram.size(), 0,
                   reinterpret_cast<const sockaddr*>(&to_),
                   sizeof to_) != static_cast<ssize_t>(datagram.size())) {
        return false;
      }
      std::this_thread::sleep_for(between);
    }
    return true;
  }

 private:
  static void Put32(std::vector<uint8_t>& b, uint32_t v) {
    for (int s = 24; s >= 0; s -= 8) b.push_back(static_cast<uint8_t>(v >> s));
  }
  static void Put16(std::vector<uint8_t>& b, uint16_t v) {
    b.push_back(static_cast<uint8_t>(v >> 8));
    b.push_back(static_cast<uint8_t>(v));
  }
  int fd_;
  sockaddr_in to_{};
};

// The heartbeat counts a refused input as a drop (named in the log, not in last_error).
bool RefusedOnServoCmd(const service_status_t& s, int64_t drops_before) {
  return s.drops > drops_before;
}

class BigMessageTest : public testing::NetnsDirTest {
 protected:
  void SetUp() override {
    NetnsDirTest::SetUp();
    testing::AheadOfTheMachine();
    std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    const std::string key = "device: \"";
    const size_t at = text.find(key, text.find("dynamixel {"));
    ASSERT_NE(at, std::string::npos);
    text.replace(at + key.size(), text.find('"', at + key.size()) - at - key.size(), Path("tty"));
    std::ofstream(Path("config.pbtxt")) << text;
    emulator_ = std::make_unique<Child>(
        std::vector<std::string>{FTCAL_EMULATE_DYNAMIXEL, "--link", Path("tty"), "--config",
                                 Path("config.pbtxt"), "--scenario", "standing"},
        Path("emu.out"), Path("emu.err"));
    for (int i = 0; i < 1000 && ::access(Path("tty").c_str(), F_OK) != 0; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ASSERT_EQ(::access(Path("tty").c_str(), F_OK), 0) << testing::ReadFile(Path("emu.err"));
  }
  void TearDown() override {
    if (bridge_) testing::Terminate(*bridge_, "the Dynamixel bridge", Path("bridge.err"));
    if (emulator_) testing::Terminate(*emulator_, "the emulator", Path("emu.err"));
    NetnsDirTest::TearDown();
  }
  std::string BridgeLog() {
    return testing::ReadFile(Path("bridge.out")) + testing::ReadFile(Path("bridge.err"));
  }

  std::unique_ptr<Child> emulator_, bridge_;
};

TEST_F(BigMessageTest, A250MBCommandCostsTheLockedBridgeItsSizeOnlyAndFitsItsShippedLimit) {
  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  testing::StatusWatch heartbeats(lcm);
  const config::Config shipped =
      LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/bigant.pbtxt");
  double limit_mib = 0;
  for (const auto& group : shipped.launch().group()) {
    for (const auto& p : group.process()) {
      if (p.command() == "ftcal-dynamixel-bridge") limit_mib = p.restart().memory_max_mb();
    }
  }
  ASSERT_GT(limit_mib, 0) << "config/bigant.pbtxt gives the Dynamixel bridge no memory limit";

  bridge_ = std::make_unique<Child>(
      std::vector<std::string>{FTCAL_DYNAMIXEL_BRIDGE, "--config", Path("config.pbtxt"),
                               "--lcm-url", std::string(kUrl) + "&recv_buf_size=4194304",
                               "--realtime", "--log-level", "info"},
      Path("bridge.out"), Path("bridge.err"));
  const pid_t pid = bridge_->pid();
  auto running = heartbeats.Await(
      pid, [](const service_status_t& s) { return s.state == service_status_t::RUNNING; }, 30);
  ASSERT_TRUE(running) << BridgeLog();
  const bool locked = BridgeLog().find("memory locked") != std::string::npos;
  // As root (CI) the bridge is granted mlockall, and the lone fragment below is the point.
  if (::geteuid() == 0) {
    EXPECT_TRUE(locked) << BridgeLog();
  }
  const double rss0 = ProcStatusMiB(pid, "VmRSS");
  ASSERT_GT(rss0, 0);

  RawSender attacker, marker;
  ASSERT_TRUE(attacker.good() && marker.good());
  // A lone first fragment, then a small garbage message from another sender: once that one is
  // refused, the fragment before it has been taken.
  ASSERT_TRUE(
      attacker.SendFragments("SERVO_CMD", 1, kBigBytes, 60000, 1, std::chrono::microseconds(0)));
  ASSERT_TRUE(marker.SendFragments("SERVO_CMD", 1, 3000, 1400, 3, std::chrono::microseconds(0)));
  auto after_first = heartbeats.Await(
      pid, [&](const service_status_t& s) { return RefusedOnServoCmd(s, running->drops); }, 15);
  ASSERT_TRUE(after_first) << "the small message after the lone fragment was not refused\n"
                           << BridgeLog();
  const double rss_first = ProcStatusMiB(pid, "VmHWM");
  std::cout << "Dynamixel bridge (" << (locked ? "memory locked" : "memory NOT locked") << "): RSS "
            << rss0 << " MiB at start, high-water " << rss_first
            << " MiB after a lone fragment announcing 250 MB\n";
  EXPECT_LT(rss_first - rss0, 16) << "a lone fragment made the announced size resident";

  // The whole message, paced so that the receiver's socket buffer keeps every fragment. UDP
  // gives no back-pressure, and the receiver's pace is the machine's (each fragment's pages
  // faulted in as they are written, on a VM where a fault is dear): a lost fragment loses the
  // message, which then proves nothing about its cost. So it is sent again, slower, with a new
  // sequence number (LCM drops the partial one), until one arrives whole; the attempts are
  // printed. What is asserted is the cost of the message that arrived.
  RawSender whole;
  std::optional<service_status_t> after_whole;
  int attempts = 0;
  for (const int pace_us : {150, 500, 1500}) {
    ++attempts;
    ASSERT_TRUE(whole.SendFragments("SERVO_CMD", 6 + static_cast<uint32_t>(attempts), kBigBytes,
                                    60000, 0xffff, std::chrono::microseconds(pace_us)));
    after_whole = heartbeats.Await(
        pid, [&](const service_status_t& s) { return RefusedOnServoCmd(s, after_first->drops); },
        10);
    if (after_whole) break;
    std::cout << "the 250 MB message paced at " << pace_us
              << " us a fragment did not arrive whole: sent again, slower\n";
  }
  ASSERT_TRUE(after_whole) << "the 250 MB message was not refused after " << attempts
                           << " sends (fragments lost each time?)\n"
                           << BridgeLog();
  std::cout << "the whole message arrived at send " << attempts << "\n";
  const double hwm = ProcStatusMiB(pid, "VmHWM");
  std::cout << "Dynamixel bridge: high-water RSS " << hwm << " MiB after a whole 250 MB message "
            << "(" << kBigBytes / kMiB << " MiB); shipped MemoryMax " << limit_mib << " MiB\n";
  // The message arrived whole (it was refused as a whole) and was held whole, once.
  EXPECT_GT(hwm, kBigBytes / kMiB);
  EXPECT_LT(hwm, limit_mib) << "systemd would kill the bridge: raise its memory_max_mb in "
                               "config/bigant.pbtxt";
  // Still at work: a heartbeat RUNNING after it, and the memory given back.
  EXPECT_TRUE(heartbeats.Await(
      pid, [](const service_status_t& s) { return s.state == service_status_t::RUNNING; }, 5))
      << BridgeLog();
  EXPECT_TRUE(bridge_->running());
  // Given back once LCM's receive path has freed the message: waited for, up to 5 s.
  double rss = ProcStatusMiB(pid, "VmRSS");
  for (int i = 0; i < 100 && rss >= rss0 + 16; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    rss = ProcStatusMiB(pid, "VmRSS");
  }
  EXPECT_LT(rss, rss0 + 16) << "the bridge kept the message's memory after " << attempts
                            << " send(s)";
}

}  // namespace
}  // namespace ftcal
