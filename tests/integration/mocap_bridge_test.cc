// ftcal-mocap-bridge against the twin's QTM RT server emulator.
//
// In-process cases drive the two classes over real TCP on loopback (the emulator in a thread,
// the bridge's class in the test thread, its output through a callback); the last case runs the
// real processes (ftcal-emulate-qtm serving the BigAntTwin, ftcal-mocap-bridge) over LCM
// multicast inside a private network namespace (scripts/netns-exec runs this whole binary), and
// compares what arrived on MOCAP_BODY with the truth file the emulator wrote.
//
// The truth is what generated the data: the poses the source produced (checked within f32
// rounding) and the frames the emulator put on the wire (checked exactly).
#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <thread>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "bridge_run.h"
#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/geometry.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "mocap_bridge.h"
#include "qtm_emulator.h"

namespace ftcal {
namespace {

using Clock = std::chrono::steady_clock;
constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

double SecondsSince(Clock::time_point t) {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

Mat3 RotZ(double a) { return Eigen::AngleAxisd(a, Vec3::UnitZ()).toRotationMatrix(); }

// Synthetic chassis motion with a known heading per tick, and four markers on the body; marker
// 2 is not seen for ticks 10-19 (a dropout of the source itself).
constexpr double kYaw0 = 0.3, kYawRate = 0.004;
sim::QtmPose SyntheticPose(int64_t k) {
  sim::QtmPose p;
  const double t = 0.01 * static_cast<double>(k);
  p.R_GC = RotationFromRollPitchYaw(0.05 * std::sin(t), 0.03 * std::cos(t), kYaw0 + kYawRate * k);
  p.p_GoCo_G_m = Vec3(1.0 + 0.001 * k, -2.0, 0.25);
  p.residual_m = 0.0004;
  const Vec3 points_C[4] = {
      {0.2, 0.1, 0.05}, {0.2, -0.1, 0.05}, {-0.2, 0.1, 0.05}, {-0.2, -0.1, 0.05}};
  for (const Vec3& b : points_C) p.markers_G_m.push_back(p.R_GC * b + p.p_GoCo_G_m);
  if (k >= 10 && k < 20) p.markers_G_m[2].setConstant(kNaN);
  return p;
}

sim::QtmEmulatorOptions EmulatorOptions(double rate_hz) {
  sim::QtmEmulatorOptions o;
  o.port = 0;  // any free port
  o.rate_hz = rate_hz;
  o.labels = sim::DefaultQtmLabels(4);
  return o;
}

MocapBridgeOptions BridgeOptions(uint16_t port) {
  MocapBridgeOptions o;
  o.address = "127.0.0.1";
  o.port = port;
  return o;
}

// One emulator run with a bridge attached.
struct PairRun {
  std::vector<sim::QtmSentFrame> sent;
  std::vector<mocap_body_t> published;
  std::vector<std::string> health;  // reasons seen, in order, without repeats
  sim::QtmEmulatorCounters emulator;
  std::unique_ptr<ServiceStats> stats;
  int64_t Counter(const std::string& name) const {
    auto it = stats->counters().find(name);
    return it == stats->counters().end() ? -1 : it->second;
  }
  int64_t Kind(const std::string& kind) const {
    auto it = stats->kinds().find(kind);
    return it == stats->kinds().end() ? 0 : it->second;
  }
};

PairRun RunWithBridge(sim::QtmEmulatorOptions eo, int64_t ticks, MocapBridgeOptions bo = {}) {
  PairRun run;
  sim::QtmEmulator emulator(std::move(eo), [](int64_t k) { return SyntheticPose(k); });
  emulator.SetObserver([&run](const sim::QtmSentFrame& s) { run.sent.push_back(s); });
  const uint16_t port = emulator.port();
  std::thread server([&] { emulator.Run(ticks); });

  run.stats = std::make_unique<ServiceStats>(testing::QuietLogger("mocap_bridge_test"));
  if (bo.address.empty()) bo = BridgeOptions(port);
  bo.port = port;
  MocapBridge bridge(
      bo, *run.stats, [&run](const mocap_body_t& m) { run.published.push_back(m); },
      [] { return int64_t{0}; });
  std::atomic<bool> server_done{false};
  std::thread watcher;  // joins the server and flags it, so the bridge loop never blocks
  watcher = std::thread([&] {
    server.join();
    server_done = true;
  });
  try {
    testing::StepUntilServed(bridge, server_done, &run.health);
  } catch (...) {
    emulator.RequestStop();
    watcher.join();
    throw;
  }
  watcher.join();
  run.emulator = emulator.counters();
  return run;
}

void ExpectMatchesWire(const mocap_body_t& m, const sim::QtmSentFrame& s,
                       const std::string& where) {
  EXPECT_EQ(m.frame_number, s.frame_number) << where;
  EXPECT_EQ(m.device_utime, s.timestamp_us) << where;
  EXPECT_EQ(m.body, "chassis") << where;
  ASSERT_EQ(m.tracked, s.body.tracked()) << where;
  if (m.tracked) {
    const Mat3 R = s.body.R_GB;  // the f32 values on the wire
    const Mat3 R_from_q =
        QuaternionToRotation(Eigen::Vector4d(m.q_gc[0], m.q_gc[1], m.q_gc[2], m.q_gc[3]));
    EXPECT_LT((R_from_q - R).cwiseAbs().maxCoeff(), 1e-6) << where;
    const double yaw = std::atan2(R(1, 0), R(0, 0));
    EXPECT_NEAR(m.yaw_rad, yaw, 1e-12) << where;
    const Mat3 R_WC =
        QuaternionToRotation(Eigen::Vector4d(m.q_wc[0], m.q_wc[1], m.q_wc[2], m.q_wc[3]));
    EXPECT_LT((R_WC - RotZ(-yaw) * R).cwiseAbs().maxCoeff(), 1e-6) << where;
    // Heading removed: W's x axis is C's x projected on the floor.
    EXPECT_NEAR(R_WC(1, 0), 0.0, 1e-6) << where;
    for (int i = 0; i < 3; ++i) EXPECT_EQ(m.position_m[i], s.body.p_GoBo_G_mm(i) / 1000.0) << where;
    EXPECT_EQ(m.residual_m, s.body.residual_mm / 1000.0) << where;
  } else {
    for (int i = 0; i < 4; ++i)
      EXPECT_TRUE(std::isnan(m.q_gc[i]) && std::isnan(m.q_wc[i])) << where;
    for (int i = 0; i < 3; ++i) EXPECT_TRUE(std::isnan(m.position_m[i])) << where;
    EXPECT_TRUE(std::isnan(m.yaw_rad)) << where;
  }
  ASSERT_EQ(m.num_markers, static_cast<int>(s.markers.size())) << where;
  for (size_t i = 0; i < s.markers.size(); ++i) {
    ASSERT_EQ(bool(m.marker_tracked[i]), s.markers[i].tracked()) << where << " marker " << i;
    for (int a = 0; a < 3; ++a) {
      if (m.marker_tracked[i]) {
        EXPECT_EQ(m.marker_m[i][a], s.markers[i].p_GoM_G_mm(a) / 1000.0) << where;
      } else {
        EXPECT_TRUE(std::isnan(m.marker_m[i][a])) << where;
      }
    }
  }
}

std::map<int64_t, const sim::QtmSentFrame*> ByFrame(const std::vector<sim::QtmSentFrame>& sent) {
  std::map<int64_t, const sim::QtmSentFrame*> out;
  for (const auto& s : sent) out[s.frame_number] = &s;
  return out;
}

TEST(MocapBridgeTest, PublishesEveryFrameAsSentAndAsGenerated) {
  PairRun run = RunWithBridge(EmulatorOptions(200), 240);
  ASSERT_GE(run.sent.size(), 150u) << "the bridge streamed too late";
  ASSERT_EQ(run.published.size(), run.sent.size());
  for (size_t i = 0; i < run.sent.size(); ++i) {
    const auto& s = run.sent[i];
    const auto& m = run.published[i];
    const std::string where = "frame " + std::to_string(s.frame_number);
    ExpectMatchesWire(m, s, where);
    // Against the generating poses (f32 rounding: ~1e-7 relative).
    const sim::QtmPose truth = SyntheticPose(s.tick);
    EXPECT_NEAR(m.yaw_rad, kYaw0 + kYawRate * s.tick, 2e-6) << where;
    EXPECT_LT((QuaternionToRotation(Eigen::Vector4d(m.q_wc[0], m.q_wc[1], m.q_wc[2], m.q_wc[3])) -
               RemoveHeading(truth.R_GC))
                  .cwiseAbs()
                  .maxCoeff(),
              2e-6)
        << where;
    for (int a = 0; a < 3; ++a) EXPECT_NEAR(m.position_m[a], truth.p_GoCo_G_m(a), 1e-6) << where;
    EXPECT_NEAR(m.residual_m, 0.0004, 1e-9) << where;
    EXPECT_EQ(bool(m.marker_tracked[2]), !(s.tick >= 10 && s.tick < 20)) << where;
    // Frame numbers and timestamps of an undisturbed stream: consecutive, 1/rate apart.
    EXPECT_EQ(s.frame_number, s.tick + 1);
    EXPECT_EQ(m.device_utime, s.tick * 5000) << where;
  }
  EXPECT_EQ(run.Counter("published"), static_cast<int64_t>(run.sent.size()));
  EXPECT_EQ(run.Counter("frame_gaps"), 0);
  EXPECT_EQ(run.Counter("connects"), 1);
  EXPECT_EQ(run.Counter("parameter_reads"), 1);
  EXPECT_EQ(run.stats->errors(), 0);
  EXPECT_EQ(run.stats->drops(), 0);
  // Streaming and healthy once frames flowed.
  EXPECT_NE(std::find(run.health.begin(), run.health.end(), ""), run.health.end());
}

TEST(MocapBridgeTest, CountsEveryFaultAndPublishesNothingCorrupt) {
  auto eo = EmulatorOptions(200);
  eo.faults.seed = 7;
  eo.faults.gap_probability = 0.03;
  eo.faults.max_gap_frames = 3;
  eo.faults.corrupt_probability = 0.03;
  eo.faults.marker_dropout_probability = 0.01;
  eo.faults.marker_dropout_ticks = 7;
  eo.faults.untracked = {{100, 30}};
  eo.faults.settings_changed = {200};
  eo.reorder_bodies_on_change = true;  // the chassis is body 2, then body 1 after the event
  PairRun run = RunWithBridge(eo, 400);
  ASSERT_GE(run.sent.size(), 300u);
  const auto sent = ByFrame(run.sent);

  // Published: exactly the sent frames that were not corrupt, less those that arrived while
  // the parameters were being re-read after the settings event (counted as such).
  std::set<int64_t> expected, published;
  int64_t corrupt = 0, untracked_sent = 0, skipped = 0;
  for (size_t i = 0; i < run.sent.size(); ++i) {
    const auto& s = run.sent[i];
    if (s.corrupt) {
      ++corrupt;
    } else {
      expected.insert(s.frame_number);
      untracked_sent += !s.body.tracked();
    }
    if (i > 0) skipped += s.frame_number - run.sent[i - 1].frame_number - 1;
  }
  ASSERT_GT(corrupt, 0) << "seed gave no corrupt frame";
  ASSERT_GT(skipped, 0) << "seed gave no gap";
  ASSERT_GT(untracked_sent, 0);
  for (const auto& m : run.published) {
    ASSERT_TRUE(published.insert(m.frame_number).second) << "frame published twice";
    ASSERT_TRUE(sent.count(m.frame_number)) << "published frame never sent";
    const auto& s = *sent.at(m.frame_number);
    EXPECT_FALSE(s.corrupt) << "corrupt frame " << m.frame_number << " published";
    ExpectMatchesWire(m, s, "frame " + std::to_string(m.frame_number));
  }
  std::vector<int64_t> missing;
  std::set_difference(expected.begin(), expected.end(), published.begin(), published.end(),
                      std::back_inserter(missing));
  EXPECT_EQ(static_cast<int64_t>(missing.size()),
            run.Kind("QTM frame while parameters are unknown"));
  EXPECT_LE(missing.size(), 20u) << "a parameter re-read on loopback takes a frame or two";

  EXPECT_EQ(run.Counter("decode_errors"), corrupt);
  EXPECT_EQ(run.Kind("undecodable QTM data packet"), corrupt);
  EXPECT_EQ(run.Counter("published"), static_cast<int64_t>(run.published.size()));
  int64_t untracked_published = 0;
  for (const auto& m : run.published) untracked_published += !m.tracked;
  EXPECT_EQ(run.Counter("untracked"), untracked_published);
  EXPECT_EQ(untracked_published, untracked_sent);  // no untracked frame fell in the re-read
  // Gaps as the bridge sees them: every number between two decoded frames that it did not
  // decode, i.e. the emulator's skips plus the corrupt and re-read frames inside the span.
  const int64_t first = *published.begin(), last = *published.rbegin();
  int64_t lost = 0;
  for (const auto& s : run.sent) {
    if (s.frame_number > first && s.frame_number < last && !published.count(s.frame_number)) ++lost;
  }
  for (size_t i = 1; i < run.sent.size(); ++i) {
    if (run.sent[i - 1].frame_number >= first && run.sent[i].frame_number <= last) {
      lost += run.sent[i].frame_number - run.sent[i - 1].frame_number - 1;
    }
  }
  EXPECT_EQ(run.Counter("frames_lost"), lost);
  EXPECT_GE(run.Counter("frame_gaps"), run.emulator.gaps > 0 ? 1 : 0);
  EXPECT_EQ(run.Counter("events"), 1);
  EXPECT_EQ(run.Counter("parameter_reads"), 2);
  EXPECT_EQ(run.Counter("connects"), 1);
}

TEST(MocapBridgeTest, RecoversFromNoMoreDataAServerShutdownAndSilence) {
  auto eo = EmulatorOptions(200);
  eo.faults.no_more_data = {{100, 60}};  // 0.3 s not capturing; numbering restarts after
  eo.faults.disconnected = {{300, 60}};  // QTM down 0.3 s, connections refused
  eo.faults.silent = {{480, 120}};       // 0.6 s without a packet, connection kept
  eo.reorder_bodies_on_change = true;    // QTM comes back with the bodies in another order
  PairRun run = RunWithBridge(eo, 700);
  EXPECT_EQ(run.emulator.disconnects, 1);
  EXPECT_EQ(run.Counter("no_more_data"), 1);
  EXPECT_EQ(run.Counter("frame_restarts"), 1);
  EXPECT_EQ(run.Counter("connects"), 2);
  EXPECT_EQ(run.Counter("disconnects"), 1);
  // Redone at the new measurement (capture started) and on the new connection.
  EXPECT_EQ(run.Counter("parameter_reads"), 3);
  EXPECT_EQ(run.Counter("published"), static_cast<int64_t>(run.published.size()));
  auto saw = [&](const std::string& needle) {
    return std::any_of(run.health.begin(), run.health.end(),
                       [&](const std::string& r) { return r.find(needle) != std::string::npos; });
  };
  EXPECT_TRUE(saw("No More Data")) << "DEGRADED while QTM was not capturing";
  EXPECT_TRUE(saw("disconnected")) << "DEGRADED while QTM was down";
  EXPECT_TRUE(saw("no frame from QTM")) << "DEGRADED while QTM was silent";
  EXPECT_EQ(run.Counter("timeouts"), 1);    // the silence (0.6 s: DEGRADED, no reconnect)
  EXPECT_EQ(run.Counter("frame_gaps"), 2);  // after the shutdown and after the silence
  EXPECT_GE(run.Counter("frames_lost"), 60 + 120);
  EXPECT_EQ(run.health.back(), "") << "healthy again at the end";

  // Every frame the bridge published is one that was sent, and the stream resumed within
  // 1 s (200 ticks) of QTM accepting connections again at tick 360.
  const std::vector<sim::QtmSentFrame> second_half(  // after the restart: numbers unique
      run.sent.begin() + static_cast<long>(run.sent.size() / 2), run.sent.end());
  const auto sent = ByFrame(second_half);
  int64_t first_tick_after = -1;
  for (const auto& s : run.sent) {
    if (s.tick >= 360) {
      first_tick_after = s.tick;
      break;
    }
  }
  ASSERT_GE(first_tick_after, 360) << "nothing sent after the shutdown";
  EXPECT_LT(first_tick_after, 560);
  const mocap_body_t& last = run.published.back();
  ASSERT_TRUE(sent.count(last.frame_number));
  EXPECT_EQ(sent.at(last.frame_number)->tick, 699);
  ExpectMatchesWire(last, *sent.at(last.frame_number), "last frame");
  // Every frame after the reconnect is the chassis, although it is now listed first.
  size_t restart = 0;
  for (size_t i = 1; i < run.published.size(); ++i) {
    if (run.published[i].frame_number < run.published[i - 1].frame_number) restart = i;
  }
  int matched = 0;
  for (size_t i = restart; i < run.published.size(); ++i) {
    const auto& m = run.published[i];
    auto it = sent.find(m.frame_number);
    if (it == sent.end() || it->second->tick < 360) continue;
    ExpectMatchesWire(m, *it->second, "frame " + std::to_string(m.frame_number));
    ++matched;
  }
  EXPECT_GE(matched, 100);
}

// §3.10: QTM not capturing sends No More Data, then nothing until the next measurement. The
// bridge once reconnected every silence_reconnect_s meanwhile; it keeps the connection and
// picks the stream up at the capture-started event.
TEST(MocapBridgeTest, NotCapturingKeepsTheConnectionAndResumesAtCaptureStarted) {
  auto eo = EmulatorOptions(200);
  eo.faults.no_more_data = {{100, 300}};  // 1.5 s not capturing
  MocapBridgeOptions bo;
  bo.address = "127.0.0.1";
  bo.silence_reconnect_s = 0.5;  // shorter than the pause
  PairRun run = RunWithBridge(eo, 600, bo);
  EXPECT_EQ(run.Counter("no_more_data"), 1);
  EXPECT_EQ(run.Counter("connects"), 1) << "reconnected while QTM was not capturing";
  EXPECT_EQ(run.Counter("disconnects"), 0);
  EXPECT_EQ(run.Counter("timeouts"), 0);
  EXPECT_EQ(run.Counter("parameter_reads"), 2) << "the new measurement's parameters";
  EXPECT_EQ(run.Counter("frame_restarts"), 1);
  ASSERT_FALSE(run.published.empty());
  // The new measurement's frames were published: numbering restarted at tick 400.
  const auto sent = ByFrame(run.sent);
  const mocap_body_t& last = run.published.back();
  ASSERT_TRUE(sent.count(last.frame_number));
  EXPECT_EQ(sent.at(last.frame_number)->tick, 599);
  EXPECT_EQ(run.health.back(), "") << "healthy again at the end";
}

TEST(MocapBridgeTest, RefusedVersionIsAConfigurationErrorNotAFallback) {
  auto bo = BridgeOptions(0);
  bo.protocol_version = "1.29";  // the emulator serves 1.21-1.28, like QTM's SDK range
  EXPECT_THROW(
      {
        try {
          RunWithBridge(EmulatorOptions(100), 300, bo);
        } catch (const MocapConfigError& e) {
          EXPECT_NE(std::string(e.what()).find("refused protocol version 1.29"), std::string::npos)
              << e.what();
          throw;
        }
      },
      MocapConfigError);

  config::Mocap mocap;
  mocap.set_server_address("127.0.0.1");
  EXPECT_EQ(MocapBridgeOptionsFromConfig(mocap).protocol_version, "1.25");
  EXPECT_EQ(MocapBridgeOptionsFromConfig(mocap).port, 22223);
  for (const char* bad : {"1.20", "1.1", "2.0", "1.2x", "", "1."}) {
    mocap.set_protocol_version(bad);
    EXPECT_THROW(MocapBridgeOptionsFromConfig(mocap), MocapConfigError) << bad;
  }
  mocap.set_protocol_version("1.21");
  EXPECT_NO_THROW(MocapBridgeOptionsFromConfig(mocap));
  mocap.set_server_address("");
  EXPECT_THROW(MocapBridgeOptionsFromConfig(mocap), MocapConfigError);
}

TEST(MocapBridgeTest, ABodyMissingFromTheParametersIsReportedAndNothingPublished) {
  auto bo = BridgeOptions(0);
  bo.body_name = "not_the_chassis";
  PairRun run = RunWithBridge(EmulatorOptions(100), 100, bo);
  EXPECT_TRUE(run.published.empty());
  EXPECT_GE(run.Kind("qtm body missing"), 1);
  ASSERT_FALSE(run.health.empty());
  EXPECT_NE(run.health.back().find("not_the_chassis"), std::string::npos) << run.health.back();
}

// A bare client of the emulator, reading packets with the codec's deframer.
class RawClient {
 public:
  explicit RawClient(uint16_t port) {
    fd_ = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ok_ = ::connect(fd_, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0;
  }
  ~RawClient() { ::close(fd_); }
  bool ok() const { return ok_; }
  void Send(const std::string& command) {
    const auto bytes = qtm::EncodeCommand(command);
    ASSERT_EQ(::send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(bytes.size()));
  }
  // The next packet within 2 s; nullopt on timeout or close.
  std::optional<qtm::Packet> Next() {
    const auto t0 = Clock::now();
    while (SecondsSince(t0) < 2.0) {
      if (auto p = deframer_.Next()) return p;
      pollfd pfd{fd_, POLLIN, 0};
      if (::poll(&pfd, 1, 50) <= 0) continue;
      uint8_t buf[4096];
      const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) return std::nullopt;
      deframer_.Feed(buf, static_cast<size_t>(n));
    }
    return std::nullopt;
  }
  std::string NextText(int32_t* type) {
    auto p = Next();
    if (!p) return "<nothing>";
    *type = p->type;
    return qtm::DecodeText(*p);
  }

 private:
  int fd_ = -1;
  bool ok_ = false;
  qtm::Deframer deframer_;
};

TEST(QtmEmulatorTest, AnswersTheDocumentedHandshakeAndRefusesPastMaxClients) {
  auto eo = EmulatorOptions(100);
  eo.max_clients = 1;
  sim::QtmEmulator emulator(eo, [](int64_t k) { return SyntheticPose(k); });
  std::thread server([&] { emulator.Run(300); });
  {
    RawClient a(emulator.port());
    ASSERT_TRUE(a.ok());
    int32_t type = -1;
    EXPECT_TRUE(qtm::IsWelcome(a.NextText(&type)));
    EXPECT_EQ(type, 1);
    a.Send("Version 1.20");  // below the attribute-style 6D layout
    EXPECT_EQ(a.NextText(&type), "Version NOT supported");
    a.Send("Version 1.28");
    EXPECT_EQ(a.NextText(&type), "Version set to 1.28");
    a.Send("GetParameters All");
    const std::string xml = a.NextText(&type);
    EXPECT_EQ(type, 2);
    const qtm::Parameters params = qtm::ParseParameters(xml);
    EXPECT_EQ(params.body_names, (std::vector<std::string>{"wand", "chassis"}));
    EXPECT_EQ(params.labels_3d, sim::DefaultQtmLabels(4));
    ASSERT_TRUE(params.frequency_hz.has_value());
    EXPECT_EQ(*params.frequency_hz, 100.0);
    EXPECT_NE(xml.find("<QTM_Parameters_Ver_1.28>"), std::string::npos);
    a.Send("Bogus command");
    EXPECT_EQ(a.NextText(&type), "Parse Error");
    EXPECT_EQ(type, 0);

    RawClient b(emulator.port());  // the second of at most one
    ASSERT_TRUE(b.ok());
    EXPECT_EQ(b.NextText(&type), "Connection refused. Max number of clients reached.");
    EXPECT_EQ(type, 0);
    EXPECT_FALSE(b.Next().has_value()) << "closed after the refusal";

    a.Send("StreamFrames FrequencyDivisor:2 3D 6D");
    auto frame_packet = a.Next();
    ASSERT_TRUE(frame_packet.has_value());
    const qtm::DataFrame f = qtm::DecodeData(*frame_packet);
    EXPECT_TRUE(f.has_markers && !f.markers_have_residuals);
    EXPECT_TRUE(f.has_bodies && !f.bodies_have_residuals);
    EXPECT_EQ(f.bodies.size(), 2u);
    EXPECT_EQ((f.frame_number - 1) % 2, 0) << "every second frame";
    auto next_packet = a.Next();
    ASSERT_TRUE(next_packet.has_value());
    EXPECT_EQ(qtm::DecodeData(*next_packet).frame_number, f.frame_number + 2);
  }
  emulator.RequestStop();
  server.join();
  EXPECT_EQ(emulator.counters().refused_clients, 1);
  EXPECT_EQ(emulator.counters().versions_refused, 1);
}

// ---- the real processes over LCM ----

struct TruthRow {
  int64_t tick, frame_number, timestamp_us;
  bool corrupt, tracked;
  Vec3 p_mm;
  Mat3 R;
  std::vector<Vec3> markers_mm;
};

std::map<int64_t, TruthRow> ReadTruth(const std::string& path) {
  std::map<int64_t, TruthRow> rows;
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    // Integers first; then f32 values written with 9 significant digits, which give the
    // float back exactly when read as a float (not as a double).
    std::vector<double> v;
    std::istringstream cells(line);
    for (std::string cell; std::getline(cells, cell, ',');) {
      if (v.size() < 5) {
        v.push_back(static_cast<double>(std::stoll(cell)));
      } else {
        v.push_back(cell == "nan" ? kNaN : static_cast<double>(std::stof(cell)));
      }
    }
    if (v.size() < 18) throw std::runtime_error("short truth row: " + line);
    TruthRow r;
    r.tick = static_cast<int64_t>(v[0]);
    r.frame_number = static_cast<int64_t>(v[1]);
    r.timestamp_us = static_cast<int64_t>(v[2]);
    r.corrupt = v[3] != 0;
    r.tracked = v[4] != 0;
    r.p_mm = Vec3(v[5], v[6], v[7]);
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) r.R(i, j) = v[8 + 3 * j + i];
    }
    for (size_t i = 18; i + 2 < v.size(); i += 3)
      r.markers_mm.emplace_back(v[i], v[i + 1], v[i + 2]);
    rows[r.frame_number] = r;
  }
  return rows;
}

struct Heard {
  double t_s;  // since the test's start
  mocap_body_t msg;
};

class Listener {
 public:
  // LCM keeps 30 messages a subscription by default and drops the rest: a listener kept off
  // the CPU for 0.3 s by a loaded machine lost frames the bridge had published (884 vs 869).
  explicit Listener(Clock::time_point t0) : lcm_(kUrl), t0_(t0) {
    lcm_.subscribe("MOCAP_BODY", &Listener::OnBody, this)->setQueueCapacity(100000);
    lcm_.subscribe("FTCAL_STATUS", &Listener::OnStatus, this)->setQueueCapacity(10000);
  }
  bool good() { return lcm_.good(); }
  void Pump(double seconds) {
    const auto until = Clock::now() + std::chrono::duration<double>(seconds);
    while (Clock::now() < until) lcm_.handleTimeout(20);
  }
  // Seconds since t0 of the first heartbeat of `pid` (its device loop began), pumping up to
  // `timeout_s` for it; -1 when none came.
  double FirstBeatS(pid_t pid, double timeout_s) {
    const auto until = Clock::now() + std::chrono::duration<double>(timeout_s);
    while (true) {
      for (size_t i = 0; i < statuses.size(); ++i) {
        if (statuses[i].pid == pid) return status_t_s[i];
      }
      if (Clock::now() >= until) return -1;
      lcm_.handleTimeout(20);
    }
  }
  std::vector<Heard> bodies;
  std::vector<service_status_t> statuses;
  std::vector<double> status_t_s;  // when each of statuses was heard, s since t0

 private:
  void OnBody(const lcm::ReceiveBuffer*, const std::string&, const mocap_body_t* m) {
    bodies.push_back({std::chrono::duration<double>(Clock::now() - t0_).count(), *m});
  }
  void OnStatus(const lcm::ReceiveBuffer*, const std::string&, const service_status_t* s) {
    if (s->name != "ftcal-mocap-bridge") return;
    statuses.push_back(*s);
    status_t_s.push_back(std::chrono::duration<double>(Clock::now() - t0_).count());
  }
  lcm::LCM lcm_;
  Clock::time_point t0_;
};

int64_t StatusCounter(const service_status_t& s, const std::string& name) {
  for (int i = 0; i < s.num_counters; ++i) {
    if (s.counter_name[i] == name) return s.counter_value[i];
  }
  return -1;
}

TEST(MocapBridgeProcessTest, BridgeOverLcmMatchesTheTwinsTruthAndResumesAfterAKill) {
  ASSERT_TRUE(testing::InNetns());
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const auto t0 = Clock::now();
  Listener listener(t0);
  ASSERT_TRUE(listener.good());

  // 14 s of the twin walking at 100 Hz with faults; the bridge runs from the default config
  // (127.0.0.1:22223: this namespace's own loopback).
  testing::Child emulator(
      {FTCAL_EMULATE_QTM, "--scenario", "walk", "--duration", "14", "--truth", path("truth.csv"),
       "--seed", "5", "--untracked", "2:0.5", "--gap-probability", "0.01", "--corrupt-probability",
       "0.01", "--settings-changed", "9", "--reorder-bodies"},
      path("emulator.out"), path("emulator.err"));
  listener.Pump(0.5);
  auto bridge = std::make_unique<testing::Child>(
      std::vector<std::string>{FTCAL_MOCAP_BRIDGE, "--lcm-url", kUrl}, path("bridge1.out"),
      path("bridge1.err"));
  const pid_t pid1 = bridge->pid();
  // Counted from its loop's start, not from the exec: under a sanitizer on a busy machine a
  // process can take seconds to get there.
  ASSERT_GE(listener.FirstBeatS(pid1, 20), 0) << "the first bridge never started";
  listener.Pump(4.0);
  bridge->Signal(SIGKILL);  // mid-run, no goodbye
  ASSERT_TRUE(bridge->Wait(2).has_value());
  const double killed_s = SecondsSince(t0);
  listener.Pump(0.5);
  const double restarted_s = SecondsSince(t0);
  bridge = std::make_unique<testing::Child>(
      std::vector<std::string>{FTCAL_MOCAP_BRIDGE, "--lcm-url", kUrl}, path("bridge2.out"),
      path("bridge2.err"));
  const pid_t pid2 = bridge->pid();
  const double started2_s = listener.FirstBeatS(pid2, 20);
  ASSERT_GE(started2_s, 0) << "the second bridge never started";
  while (emulator.running() && SecondsSince(t0) < 40) {
    listener.Pump(0.2);
    emulator.Wait(0);
  }
  ASSERT_FALSE(emulator.running()) << "emulator did not end";
  listener.Pump(0.3);
  bridge->Signal(SIGTERM);
  const auto rc = bridge->Wait(2);
  ASSERT_TRUE(rc.has_value()) << "bridge still running 2 s after SIGTERM";
  EXPECT_EQ(testing::DescribeWaitStatus(*rc), "exit 0") << testing::ReadFile(path("bridge2.err"));
  listener.Pump(0.3);

  const auto truth = ReadTruth(path("truth.csv"));
  ASSERT_GT(truth.size(), 1000u) << testing::ReadFile(path("emulator.err"));
  ASSERT_FALSE(listener.bodies.empty());

  // Every published frame is one the emulator sent, uncorrupted, with its values.
  int64_t untracked = 0, first2 = -1, corrupt_seen_by_2 = 0;
  double first2_s = -1;
  std::set<int64_t> heard_frames;
  for (const Heard& h : listener.bodies) {
    const mocap_body_t& m = h.msg;
    const std::string where = "frame " + std::to_string(m.frame_number);
    ASSERT_TRUE(truth.count(m.frame_number)) << where << " was never sent";
    ASSERT_TRUE(heard_frames.insert(m.frame_number).second) << where << " published twice";
    const TruthRow& t = truth.at(m.frame_number);
    ASSERT_FALSE(t.corrupt) << where << " was sent corrupt and still published";
    EXPECT_EQ(m.device_utime, t.timestamp_us) << where;
    ASSERT_EQ(m.tracked, t.tracked) << where;
    if (m.tracked) {
      const Mat3 R_q =
          QuaternionToRotation(Eigen::Vector4d(m.q_gc[0], m.q_gc[1], m.q_gc[2], m.q_gc[3]));
      EXPECT_LT((R_q - t.R).cwiseAbs().maxCoeff(), 1e-6) << where;
      const Mat3 R_w =
          QuaternionToRotation(Eigen::Vector4d(m.q_wc[0], m.q_wc[1], m.q_wc[2], m.q_wc[3]));
      EXPECT_LT((R_w - RotZ(-m.yaw_rad) * t.R).cwiseAbs().maxCoeff(), 1e-6) << where;
      for (int i = 0; i < 3; ++i) EXPECT_EQ(m.position_m[i], t.p_mm(i) / 1000.0) << where;
    } else {
      ++untracked;
      EXPECT_TRUE(std::isnan(m.position_m[0]) && std::isnan(m.q_wc[0])) << where;
    }
    ASSERT_EQ(m.num_markers, static_cast<int>(t.markers_mm.size())) << where;
    for (int i = 0; i < m.num_markers; ++i) {
      ASSERT_EQ(bool(m.marker_tracked[i]), !std::isnan(t.markers_mm[i](0))) << where;
      if (m.marker_tracked[i]) {
        EXPECT_EQ(m.marker_m[i][0], t.markers_mm[i](0) / 1000.0) << where;
      }
    }
    if (h.t_s > restarted_s && first2 < 0) {
      first2 = m.frame_number;
      first2_s = h.t_s;
    }
  }
  EXPECT_GE(untracked, 40) << "0.5 s untracked at 100 Hz, less a gap or two";
  // The restarted bridge is back within 1 s of its loop's start, and the kill left a visible
  // gap in frame numbers.
  ASSERT_GT(first2, 0) << "nothing heard from the restarted bridge";
  EXPECT_LT(first2_s - started2_s, 1.0) << "exec at " << restarted_s << " s";
  int64_t last1 = -1;
  for (const Heard& h : listener.bodies) {
    if (h.t_s < killed_s) last1 = h.msg.frame_number;
  }
  EXPECT_GE(first2 - last1, 40) << "about 0.5 s at 100 Hz between the two bridges";
  for (const auto& [frame, t] : truth) {
    if (frame > first2 && t.corrupt) ++corrupt_seen_by_2;
  }

  // The heartbeats: both bridges RUNNING while streaming, and the last one's counters agree
  // with what was heard and with the truth.
  std::vector<service_status_t> beats2;
  bool saw1 = false;
  for (const auto& s : listener.statuses) {
    saw1 |= s.pid == pid1;
    if (s.pid == pid2) beats2.push_back(s);
  }
  EXPECT_TRUE(saw1);
  ASSERT_GE(beats2.size(), 3u);
  EXPECT_EQ(beats2.back().state, int8_t{service_status_t::STOPPING});
  EXPECT_TRUE(std::any_of(beats2.begin(), beats2.end(), [](const service_status_t& s) {
    return s.state == service_status_t::RUNNING;
  }));
  int64_t heard2 = 0;
  for (const Heard& h : listener.bodies)
    heard2 += h.msg.frame_number >= first2 && h.t_s > restarted_s;
  EXPECT_EQ(StatusCounter(beats2.back(), "published"), heard2);
  EXPECT_EQ(beats2.back().msgs_out, heard2);
  // (+1: the very first frame sent to the new bridge may itself have been a corrupt one.)
  EXPECT_GE(StatusCounter(beats2.back(), "decode_errors"), corrupt_seen_by_2);
  EXPECT_LE(StatusCounter(beats2.back(), "decode_errors"), corrupt_seen_by_2 + 1);
  EXPECT_GE(corrupt_seen_by_2, 3) << "1% of ~900 frames";
  EXPECT_EQ(StatusCounter(beats2.back(), "events"), 1);
  EXPECT_EQ(StatusCounter(beats2.back(), "parameter_reads"), 2);
  if (!HasFailure()) testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
