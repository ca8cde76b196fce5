// ftcal-natnet-bridge against the twin's Motive (NatNet) emulator, for bitstreams 3.1 and 4.1
// over unicast and multicast. The whole binary runs inside scripts/netns-exec (a private
// network namespace with loopback multicast): the emulator serves on 127.0.0.1:1510/1511 in a
// thread, the bridge's class runs in the test thread, its output through a callback.
//
// The truth is what generated the data: the emulator's source poses, in ftcal's z-up frame,
// which the emulator turned into Motive's Y-up axes and the rigid body's pivot frame; the
// bridge must undo both to within f32 rounding. Its sample_utime is compared with the instant the
// emulator stamped as mid-exposure on the host clock.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <map>
#include <regex>
#include <set>
#include <thread>

#include <gtest/gtest.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "bridge_run.h"
#include "child_process.h"
#include "ftcal/geometry.h"
#include "natnet_bridge.h"
#include "natnet_emulator.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

int64_t WallUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Synthetic chassis motion with a known heading per tick and four markers on the body; marker
// 2 is not seen for ticks 10-19.
constexpr double kYaw0 = 0.3, kYawRate = 0.004;
const Vec3 kPointsC[4] = {
    {0.2, 0.1, 0.05}, {0.2, -0.1, 0.05}, {-0.2, 0.1, 0.05}, {-0.2, -0.1, 0.05}};
sim::NatNetPose SyntheticPose(int64_t k) {
  sim::NatNetPose p;
  const double t = 0.01 * static_cast<double>(k);
  p.R_GC = RotationFromRollPitchYaw(0.05 * std::sin(t), 0.03 * std::cos(t), kYaw0 + kYawRate * k);
  p.p_GoCo_G_m = Vec3(1.0 + 0.001 * k, -2.0, 0.25);
  p.residual_m = 0.0004;
  for (const Vec3& b : kPointsC) p.markers_G_m.push_back(p.R_GC * b + p.p_GoCo_G_m);
  if (k >= 10 && k < 20) p.markers_G_m[2].setConstant(kNaN);
  return p;
}

// The pivot Motive would have made: at the markers' centroid, axes turned from the chassis'.
Pose3 PivotChassis() {
  return Pose3(RotationFromRollPitchYaw(0.0, 0.0, 0.5), Vec3(0.0, 0.0, -0.05));
}

sim::NatNetEmulatorOptions EmulatorOptions(natnet::Version v, bool multicast) {
  sim::NatNetEmulatorOptions o;
  o.version = v;
  o.multicast = multicast;
  o.rate_hz = 200;
  o.R_PC = PivotChassis().R;
  o.p_PoCo_P_m = PivotChassis().p;
  o.body_points_C_m.assign(std::begin(kPointsC), std::end(kPointsC));
  return o;
}

NatNetBridgeOptions BridgeOptions(bool multicast, std::optional<natnet::Version> bitstream = {}) {
  NatNetBridgeOptions o;
  o.address = "127.0.0.1";
  o.multicast = multicast;
  o.bitstream = bitstream;
  o.X_PC = PivotChassis();
  return o;
}

struct PairRun {
  std::vector<sim::NatNetSentFrame> sent;
  std::vector<mocap_body_t> published;
  std::vector<std::string> health;
  sim::NatNetEmulatorCounters emulator;
  std::unique_ptr<ServiceStats> stats;
  natnet::Version version;
  int64_t Counter(const std::string& name) const {
    auto it = stats->counters().find(name);
    return it == stats->counters().end() ? -1 : it->second;
  }
  bool SawHealth(const std::string& part) const {
    return std::any_of(health.begin(), health.end(),
                       [&](const std::string& h) { return h.find(part) != std::string::npos; });
  }
};

PairRun RunWithBridge(sim::NatNetEmulatorOptions eo, int64_t ticks, NatNetBridgeOptions bo) {
  PairRun run;
  sim::NatNetEmulator emulator(std::move(eo), [](int64_t k) { return SyntheticPose(k); });
  emulator.SetObserver([&run](const sim::NatNetSentFrame& s) { run.sent.push_back(s); });
  bo.command_port = emulator.command_port();
  bo.data_port = emulator.data_port();
  run.stats = std::make_unique<ServiceStats>(testing::QuietLogger("natnet_bridge_test"));
  NatNetBridge bridge(
      bo, *run.stats, [&run](const mocap_body_t& m) { run.published.push_back(m); }, WallUtime);
  bridge.Open();
  std::atomic<bool> done{false};
  std::thread server([&] {
    emulator.Run(ticks);
    done = true;
  });
  try {
    testing::StepUntilServed(bridge, done, &run.health);
  } catch (...) {
    emulator.RequestStop();
    server.join();
    throw;
  }
  server.join();
  run.emulator = emulator.counters();
  run.version = bridge.version();
  return run;
}

// The published message against the pose that generated it.
void ExpectMatchesTruth(const mocap_body_t& m, const sim::NatNetSentFrame& s,
                        const std::string& where) {
  EXPECT_EQ(m.frame_number, s.frame_number) << where;
  EXPECT_EQ(m.body, "chassis") << where;
  EXPECT_EQ(m.device_utime, std::llround(s.timestamp_s * 1e6)) << where;
  ASSERT_EQ(bool(m.tracked), s.tracked) << where;
  if (m.tracked) {
    const Mat3 R_GC =
        QuaternionToRotation(Eigen::Vector4d(m.q_gc[0], m.q_gc[1], m.q_gc[2], m.q_gc[3]));
    EXPECT_LT((R_GC - s.R_GC).cwiseAbs().maxCoeff(), 2e-6) << where;
    const double yaw = std::atan2(s.R_GC(1, 0), s.R_GC(0, 0));
    EXPECT_NEAR(m.yaw_rad, yaw, 2e-6) << where;
    const Mat3 R_WC =
        QuaternionToRotation(Eigen::Vector4d(m.q_wc[0], m.q_wc[1], m.q_wc[2], m.q_wc[3]));
    EXPECT_LT((R_WC - RemoveHeading(s.R_GC)).cwiseAbs().maxCoeff(), 2e-6) << where;
    for (int a = 0; a < 3; ++a) EXPECT_NEAR(m.position_m[a], s.p_GoCo_G_m(a), 2e-6) << where;
    EXPECT_NEAR(m.residual_m, 0.0004, 1e-9) << where;
  } else {
    for (int i = 0; i < 4; ++i)
      EXPECT_TRUE(std::isnan(m.q_gc[i]) && std::isnan(m.q_wc[i])) << where;
    for (int i = 0; i < 3; ++i) EXPECT_TRUE(std::isnan(m.position_m[i])) << where;
    EXPECT_TRUE(std::isnan(m.yaw_rad)) << where;
  }
  ASSERT_EQ(m.num_markers, static_cast<int>(s.markers_G_m.size())) << where;
  for (size_t i = 0; i < s.markers_G_m.size(); ++i) {
    const bool seen = s.tracked && s.markers_G_m[i].allFinite();
    ASSERT_EQ(bool(m.marker_tracked[i]), seen) << where << " marker " << i;
    for (int a = 0; a < 3; ++a) {
      if (seen) {
        EXPECT_NEAR(m.marker_m[i][a], s.markers_G_m[i](a), 2e-6) << where;
      } else {
        EXPECT_TRUE(std::isnan(m.marker_m[i][a])) << where;
      }
    }
  }
}

struct Transport {
  natnet::Version version;
  bool multicast;
};
std::string Name(const Transport& t) {
  return "NatNet " + t.version.ToString() + (t.multicast ? " multicast" : " unicast");
}

class NatNetBridgeTransportTest : public ::testing::TestWithParam<Transport> {};

TEST_P(NatNetBridgeTransportTest, PublishesEveryFrameAsGeneratedWithTheExposureTime) {
  const Transport t = GetParam();
  auto eo = EmulatorOptions(t.version, t.multicast);
  eo.faults.untracked.push_back({100, 20});
  PairRun run = RunWithBridge(eo, 300, BridgeOptions(t.multicast));
  EXPECT_EQ(run.version, t.version) << Name(t);
  ASSERT_GE(run.sent.size(), 200u) << Name(t) << ": the bridge streamed too late";
  std::map<int32_t, const sim::NatNetSentFrame*> by_frame;
  for (const auto& s : run.sent) by_frame[s.frame_number] = &s;
  // Multicast frames flow before the handshake ends: those are dropped, nothing after.
  ASSERT_GE(run.published.size() + 20, run.sent.size()) << Name(t);
  std::vector<double> residual_us;
  int untracked = 0;
  for (const auto& m : run.published) {
    const auto it = by_frame.find(static_cast<int32_t>(m.frame_number));
    ASSERT_NE(it, by_frame.end()) << Name(t) << ": frame " << m.frame_number << " was never sent";
    ExpectMatchesTruth(m, *it->second, Name(t) + " frame " + std::to_string(m.frame_number));
    residual_us.push_back(static_cast<double>(m.sample_utime - it->second->exposure_utime));
    untracked += !m.tracked;
  }
  EXPECT_EQ(untracked, 20) << Name(t);
  EXPECT_EQ(run.Counter("untracked"), 20) << Name(t);
  EXPECT_EQ(run.Counter("published"), static_cast<int64_t>(run.published.size()));
  EXPECT_EQ(run.Counter("decode_errors"), 0) << Name(t);
  EXPECT_EQ(run.Counter("frame_gaps"), 0) << Name(t);
  EXPECT_EQ(run.Counter("connects"), 1) << Name(t);
  EXPECT_EQ(run.Counter("server_lost"), 0) << Name(t);
  EXPECT_EQ(run.stats->errors(), 0) << Name(t) << ": " << run.stats->last_error();
  if (!t.multicast) {
    // Motive streams to a unicast client from its NAT_CONNECT on: a frame may come before the
    // descriptions do, and is dropped (by name, nothing else is).
    const auto& kinds = run.stats->kinds();
    const auto early = kinds.find("natnet frame while descriptions are unknown");
    EXPECT_EQ(run.stats->drops(), early == kinds.end() ? 0 : early->second) << Name(t);
    EXPECT_LE(run.stats->drops(), 2) << Name(t);
    EXPECT_GE(run.Counter("keepalives"), 1) << Name(t);
  }
  EXPECT_NE(std::find(run.health.begin(), run.health.end(), ""), run.health.end()) << Name(t);
  // The time stamp: the mid-exposure instant on the host clock, from Motive's ticks and the
  // minimum-transit offset. Its residual is the smallest loopback transit plus scheduling.
  std::sort(residual_us.begin(), residual_us.end());
  const double median = residual_us[residual_us.size() / 2];
  const double p95 = residual_us[residual_us.size() * 95 / 100];
  std::printf(
      "[ residual ] %s: utime - exposure median %.0f us, p95 %.0f us, min %.0f, max %.0f "
      "(system latency 2000 us removed)\n",
      Name(t).c_str(), median, p95, residual_us.front(), residual_us.back());
  EXPECT_LT(std::abs(median), 1000.0) << Name(t);
}

INSTANTIATE_TEST_SUITE_P(VersionsAndTransports, NatNetBridgeTransportTest,
                         ::testing::Values(Transport{{3, 1}, false}, Transport{{4, 1}, false},
                                           Transport{{3, 1}, true}, Transport{{4, 1}, true}),
                         [](const ::testing::TestParamInfo<Transport>& info) {
                           return "v" + std::to_string(info.param.version.major) +
                                  std::to_string(info.param.version.minor) +
                                  (info.param.multicast ? "_multicast" : "_unicast");
                         });

TEST(NatNetBridgeTest, UnicastClientAsksForItsBitstream) {
  // Motive speaks 4.1; the bridge asks for 3.1 in NAT_CONNECT and reads 3.1 frames.
  auto eo = EmulatorOptions({4, 1}, false);
  PairRun run = RunWithBridge(eo, 200, BridgeOptions(false, natnet::Version{3, 1}));
  EXPECT_EQ(run.version, (natnet::Version{3, 1}));
  EXPECT_GE(run.published.size(), 150u);
  EXPECT_EQ(run.Counter("decode_errors"), 0);
}

TEST(NatNetBridgeTest, WithoutMidExposureTheCameraDataTimeIsUsed) {
  // USB cameras and playback send mid-exposure 0 (§5.3): the stamp falls back to the camera
  // data's arrival, which the emulator puts half the system latency before transmit.
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.mid_exposure_zero = true;
  PairRun run = RunWithBridge(eo, 150, BridgeOptions(false));
  std::map<int32_t, const sim::NatNetSentFrame*> by_frame;
  for (const auto& s : run.sent) by_frame[s.frame_number] = &s;
  std::vector<double> residual_us;
  for (const auto& m : run.published) {
    residual_us.push_back(
        double(m.sample_utime - by_frame.at(int32_t(m.frame_number))->exposure_utime));
  }
  ASSERT_GE(residual_us.size(), 100u);
  std::sort(residual_us.begin(), residual_us.end());
  EXPECT_LT(std::abs(residual_us[residual_us.size() / 2]), 500.0);
  EXPECT_EQ(run.Counter("clock_fallbacks"), 0);
  EXPECT_NEAR(run.Counter("system_latency_us"), 1000, 2);
}

TEST(NatNetBridgeTest, ZUpMotiveGivesTheSamePoses) {
  auto eo = EmulatorOptions({4, 1}, false);
  eo.z_up = true;
  auto bo = BridgeOptions(false);
  bo.up_axis = MotiveFrames::UpAxis::kZ;
  PairRun run = RunWithBridge(eo, 150, bo);
  ASSERT_GE(run.published.size(), 100u);
  std::map<int32_t, const sim::NatNetSentFrame*> by_frame;
  for (const auto& s : run.sent) by_frame[s.frame_number] = &s;
  for (const auto& m : run.published) {
    ExpectMatchesTruth(m, *by_frame.at(static_cast<int32_t>(m.frame_number)), "z-up");
  }
}

TEST(NatNetBridgeTest, WrongUpAxisIsVisibleNotSilent) {
  // The control: the same Y-up stream read as Z-up gives poses far from the truth, so the
  // conversion above is what makes them agree.
  auto eo = EmulatorOptions({4, 1}, false);
  auto bo = BridgeOptions(false);
  bo.up_axis = MotiveFrames::UpAxis::kZ;
  PairRun run = RunWithBridge(eo, 100, bo);
  ASSERT_GE(run.published.size(), 50u);
  const auto& m = run.published.back();
  const auto& s = *std::find_if(run.sent.begin(), run.sent.end(),
                                [&](const auto& x) { return x.frame_number == m.frame_number; });
  EXPECT_GT(std::abs(m.position_m[2] - s.p_GoCo_G_m(2)), 0.1);
}

TEST(NatNetBridgeTest, CountsEveryFaultAndPublishesNothingCorrupt) {
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.seed = 7;
  eo.faults.gap_probability = 0.03;
  eo.faults.duplicate_probability = 0.03;
  eo.faults.corrupt_probability = 0.03;
  eo.faults.edit_mode.push_back({150, 30});
  eo.faults.model_changes = {200, 260};
  PairRun run = RunWithBridge(eo, 340, BridgeOptions(false));
  const auto& e = run.emulator;
  ASSERT_GT(e.frames_corrupt, 0);
  ASSERT_GT(e.frames_duplicated, 0);
  ASSERT_GT(e.gaps, 0);
  // Loopback loses nothing: every fault the emulator made is counted by the bridge, each copy
  // of a corrupt frame as undecodable (a duplicated corrupt frame is never seen as a duplicate).
  int64_t corrupt_copies = 0, clean_duplicates = 0;
  for (const auto& s : run.sent) {
    corrupt_copies += s.corrupt ? (s.duplicated ? 2 : 1) : 0;
    clean_duplicates += s.duplicated && !s.corrupt;
  }
  EXPECT_EQ(run.Counter("decode_errors"), corrupt_copies);
  EXPECT_EQ(run.Counter("duplicates"), clean_duplicates);
  EXPECT_GE(run.Counter("frame_gaps"), e.gaps);  // a corrupt frame between two makes a gap too
  EXPECT_EQ(run.Counter("model_changes"), 2);
  EXPECT_EQ(run.Counter("edit_mode_frames"),
            30 - std::count_if(run.sent.begin(), run.sent.end(),
                               [](const auto& s) { return s.edit_mode && s.corrupt; }));
  EXPECT_TRUE(run.SawHealth("edit mode"));
  // Nothing corrupt, duplicated or in edit mode was published; after each model change (the
  // body renumbered and moved in the list) the body is found again by name.
  std::map<int32_t, const sim::NatNetSentFrame*> by_frame;
  for (const auto& s : run.sent) by_frame[s.frame_number] = &s;
  std::set<int64_t> seen;
  int64_t after_changes = 0;
  for (const auto& m : run.published) {
    const auto& s = *by_frame.at(static_cast<int32_t>(m.frame_number));
    EXPECT_FALSE(s.corrupt) << m.frame_number;
    EXPECT_FALSE(s.edit_mode) << m.frame_number;
    EXPECT_TRUE(seen.insert(m.frame_number).second) << "frame " << m.frame_number << " twice";
    ExpectMatchesTruth(m, s, "frame " + std::to_string(m.frame_number));
    after_changes += s.tick > 265;
  }
  EXPECT_GT(after_changes, 50);
}

TEST(NatNetBridgeTest, WaitsWhileMotiveIsUpButNotStreaming) {
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.silent.push_back({100, 400});  // 2 s without frames, commands answered
  PairRun run = RunWithBridge(eo, 700, BridgeOptions(false));
  EXPECT_GE(run.Counter("probes"), 1);
  EXPECT_GE(run.Counter("not_streaming"), 1);
  EXPECT_EQ(run.Counter("server_lost"), 0);
  EXPECT_EQ(run.Counter("connects"), 1);  // never started over
  EXPECT_TRUE(run.SawHealth("up but sends no frames"));
  const int64_t after = std::count_if(run.published.begin(), run.published.end(),
                                      [](const auto& m) { return m.frame_number > 500; });
  EXPECT_GT(after, 150);
}

TEST(NatNetBridgeTest, ReconnectsAfterMotiveRestarts) {
  auto eo = EmulatorOptions({3, 1}, false);
  eo.faults.down.push_back({100, 300});  // 1.5 s gone; back with new frame numbers and body id
  PairRun run = RunWithBridge(eo, 700, BridgeOptions(false));
  EXPECT_EQ(run.emulator.restarts, 1);
  EXPECT_GE(run.Counter("server_lost"), 1);
  EXPECT_GE(run.Counter("connects"), 2);
  EXPECT_TRUE(run.SawHealth("no SERVERINFO"));
  // After the restart: frame numbers from 1 again, poses right under the new body id.
  std::vector<const sim::NatNetSentFrame*> restarted;
  for (const auto& s : run.sent) {
    if (s.tick >= 400) restarted.push_back(&s);
  }
  int matched = 0;
  for (const auto& m : run.published) {
    for (const auto* s : restarted) {
      if (s->frame_number == m.frame_number &&
          m.sample_utime > restarted.front()->exposure_utime - 1000) {
        ExpectMatchesTruth(m, *s, "after restart, frame " + std::to_string(m.frame_number));
        ++matched;
      }
    }
  }
  EXPECT_GT(matched, 150);
}

// What the bridge should count of a unicast client's stream, from the frames as the emulator
// sent them (in sending order; loopback delivers every datagram, in order).
struct StreamTruth {
  int64_t lost = 0;        // numbers never sent between the first and the last frame sent
  int64_t late = 0;        // frames sent after a higher-numbered one
  int64_t duplicates = 0;  // second copies
};
StreamTruth TruthOf(const std::vector<sim::NatNetSentFrame>& sent) {
  StreamTruth t;
  std::set<int32_t> numbers;
  for (const auto& s : sent) {
    numbers.insert(s.frame_number);
    t.late += s.late;
    t.duplicates += s.duplicated;
  }
  if (sent.empty()) return t;
  const int32_t first = sent.front().frame_number;
  const int32_t last = *numbers.rbegin();
  for (int32_t n = first; n <= last; ++n) t.lost += !numbers.count(n);
  return t;
}

TEST(NatNetBridgeTest, LateFramesAreDroppedNotTakenForARestartAndAreNotLost) {
  // UDP reordering (docs/natnet-protocol.md §6): a late frame is dropped and counted as
  // reordered; it is not a Motive restart (no clock resync, no new descriptions), and the
  // frame numbers it fills in are not lost.
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.seed = 5;
  eo.faults.reorder_probability = 0.04;
  eo.faults.duplicate_probability = 0.03;
  eo.faults.gap_probability = 0.02;
  PairRun run = RunWithBridge(eo, 600, BridgeOptions(false));
  const StreamTruth truth = TruthOf(run.sent);
  ASSERT_GT(truth.late, 5);
  ASSERT_GT(truth.duplicates, 5);
  ASSERT_GT(truth.lost, 5);
  EXPECT_EQ(run.Counter("frame_restarts"), 0);
  EXPECT_EQ(run.Counter("clock_resyncs"), 0);
  EXPECT_EQ(run.emulator.descriptions_sent, 1);
  EXPECT_EQ(run.Counter("reordered"), truth.late);
  EXPECT_EQ(run.Counter("duplicates"), truth.duplicates);
  EXPECT_EQ(run.Counter("frames_lost"), truth.lost);
  EXPECT_EQ(run.Counter("decode_errors"), 0);
  // Every frame that came in order was published once, in order, as generated; no late one.
  std::map<int32_t, const sim::NatNetSentFrame*> by_frame;
  int64_t in_order = 0;
  for (const auto& s : run.sent) {
    by_frame[s.frame_number] = &s;
    in_order += !s.late;
  }
  int64_t previous = -1;
  for (const auto& m : run.published) {
    const auto& s = *by_frame.at(static_cast<int32_t>(m.frame_number));
    EXPECT_FALSE(s.late) << "late frame " << m.frame_number << " published";
    EXPECT_GT(m.frame_number, previous);
    previous = m.frame_number;
    ExpectMatchesTruth(m, s, "frame " + std::to_string(m.frame_number));
  }
  // Only what came before the descriptions is missing (as in the fault-free run).
  EXPECT_LE(in_order - static_cast<int64_t>(run.published.size()), 2);
}

TEST(NatNetBridgeTest, FramesSkippedWhileMotiveIsPausedAreNotLost) {
  // Paused (up, answering, no frames) for 1.5 s while its frame numbers run on: the numbers
  // skipped then are counted as paused; only the gaps of the stream itself are lost.
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.seed = 3;
  eo.faults.gap_probability = 0.03;
  eo.faults.silent.push_back({150, 300});
  PairRun run = RunWithBridge(eo, 700, BridgeOptions(false));
  int64_t lost = 0, paused = 0, pauses = 0;
  for (size_t i = 1; i < run.sent.size(); ++i) {
    const auto& a = run.sent[i - 1];
    const auto& b = run.sent[i];
    const int64_t skipped = b.frame_number - a.frame_number - 1;
    if (b.tick - a.tick == 1) {
      lost += skipped;
    } else {
      paused += skipped;
      ++pauses;
    }
  }
  ASSERT_EQ(pauses, 1);
  ASSERT_GE(paused, 300);
  ASSERT_GT(lost, 3);
  EXPECT_EQ(run.Counter("frames_lost"), lost);
  EXPECT_EQ(run.Counter("frames_paused"), paused);
  EXPECT_EQ(run.Counter("frame_restarts"), 0);
  EXPECT_EQ(run.Counter("server_lost"), 0);
  EXPECT_GE(run.Counter("not_streaming"), 1);
  const int64_t after = std::count_if(run.published.begin(), run.published.end(),
                                      [](const auto& m) { return m.frame_number > 460; });
  EXPECT_GT(after, 200);
}

TEST(NatNetBridgeTest, UnicastClientRejoinsARestartedMotiveWithin100Ms) {
  // A restarted Motive streams to no unicast client until one connects again (§2.5): the bridge
  // must ask again promptly, not wait out a reply timeout. Motive is gone for 0.7 s, longer
  // than the bridge's silence_s (0.5 s), so it returns while the bridge probes.
  auto eo = EmulatorOptions({4, 1}, false);
  eo.faults.down.push_back({200, 140});
  PairRun run = RunWithBridge(eo, 600, BridgeOptions(false));
  ASSERT_EQ(run.emulator.restarts, 1);
  ASSERT_GT(run.emulator.restart_utime, 0);
  // The first frame the restarted Motive sent (to a client that connected again) and the first
  // the bridge published after the restart, against the instant Motive came back.
  const auto first_sent =
      std::find_if(run.sent.begin(), run.sent.end(), [](const auto& s) { return s.tick >= 340; });
  ASSERT_NE(first_sent, run.sent.end());
  const double transmit_ms =
      1e-3 * double(first_sent->exposure_utime + 2000 - run.emulator.restart_utime);
  std::printf("[ rejoin   ] first frame %.1f ms after Motive came back\n", transmit_ms);
  EXPECT_LT(transmit_ms, 100.0);
  size_t restart_at = 0;
  for (size_t i = 1; i < run.published.size() && restart_at == 0; ++i) {
    if (run.published[i].frame_number < run.published[i - 1].frame_number) restart_at = i;
  }
  ASSERT_GT(restart_at, 0u) << "nothing published after the restart";
  const auto& m = run.published[restart_at];
  // utime: the frame's receipt, when it was published.
  const double published_ms = 1e-3 * double(m.utime - run.emulator.restart_utime);
  std::printf("[ rejoin   ] first frame published %.1f ms after Motive came back\n", published_ms);
  EXPECT_LT(published_ms, 100.0);
  // Its pose under the renumbered body is right.
  const auto s = std::find_if(first_sent, run.sent.end(),
                              [&](const auto& x) { return x.frame_number == m.frame_number; });
  ASSERT_NE(s, run.sent.end());
  ExpectMatchesTruth(m, *s, "first after the restart");
  EXPECT_EQ(run.Counter("frame_restarts"), 1);  // frame 1 again, after a silence
  EXPECT_EQ(run.Counter("frames_lost"), 0);
}

TEST(NatNetBridgeTest, AShortMotiveRestartIsTakenForOneFromItsFrames) {
  // Gone for 0.3 s, less than silence_s: no probe, no reconnect; the multicast frames resume
  // with numbers from 1 again, which a late frame could not be. One restart: the clock resynced,
  // the descriptions read again, the renumbered body found by name.
  auto eo = EmulatorOptions({4, 1}, true);
  eo.faults.down.push_back({200, 60});
  PairRun run = RunWithBridge(eo, 500, BridgeOptions(true));
  ASSERT_EQ(run.emulator.restarts, 1);
  EXPECT_EQ(run.Counter("frame_restarts"), 1);
  EXPECT_EQ(run.Counter("clock_resyncs"), 1);
  EXPECT_EQ(run.Counter("server_lost"), 0);
  EXPECT_EQ(run.Counter("reordered"), 0);
  EXPECT_EQ(run.Counter("frames_lost"), 0);
  std::map<int32_t, const sim::NatNetSentFrame*> after;
  for (const auto& s : run.sent) {
    if (s.tick >= 260) after[s.frame_number] = &s;
  }
  size_t restart_at = 0;
  for (size_t i = 1; i < run.published.size() && restart_at == 0; ++i) {
    if (run.published[i].frame_number < run.published[i - 1].frame_number) restart_at = i;
  }
  ASSERT_GT(restart_at, 0u);
  for (size_t i = restart_at; i < run.published.size(); ++i) {
    const auto& m = run.published[i];
    ExpectMatchesTruth(m, *after.at(static_cast<int32_t>(m.frame_number)),
                       "after the restart, frame " + std::to_string(m.frame_number));
  }
  EXPECT_GT(run.published.size() - restart_at, 200u);
}

TEST(NatNetBridgeTest, UnicastKeepAliveHoldsTheSession) {
  auto eo = EmulatorOptions({4, 1}, false);
  eo.client_timeout_s = 1.5;
  PairRun run = RunWithBridge(eo, 800, BridgeOptions(false));  // 4 s
  EXPECT_EQ(run.emulator.clients_expired, 0);
  EXPECT_GE(run.emulator.keepalives, 3);
  EXPECT_EQ(run.Counter("connects"), 1);
  EXPECT_GE(run.published.size(), 750u);
}

TEST(NatNetBridgeTest, BodyMissingIsReportedByName) {
  auto eo = EmulatorOptions({4, 1}, false);
  auto bo = BridgeOptions(false);
  bo.body_name = "robot";
  PairRun run = RunWithBridge(eo, 100, bo);
  EXPECT_TRUE(run.published.empty());
  EXPECT_TRUE(run.SawHealth("rigid body 'robot'"));
  EXPECT_TRUE(run.SawHealth("[wand, chassis]"));
}

#ifdef FTCAL_NATNET_BRIDGE
TEST(NatNetBridgeProcessTest, RefusesAConfigThatRunsTheQualisysBridge) {
  ASSERT_TRUE(testing::InNetns());
  // The embedded default config selects QUALISYS: the NatNet bridge must not also publish.
  const std::string dir = testing::MakeTempDir();
  const std::string url = "udpm://239.255.76.67:7667?ttl=0";
  lcm::LCM lcm(url);
  ASSERT_TRUE(lcm.good());
  testing::StatusWatch watch(lcm);  // subscribed before the bridge starts: nothing is missed
  testing::Child child({FTCAL_NATNET_BRIDGE, "--lcm-url", url}, dir + "/out", dir + "/err");
  const auto status = child.Wait(10);
  ASSERT_TRUE(status.has_value());
  // 3: a bridge's own check of its config section (docs/exit-codes.md).
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 3)
      << testing::DescribeWaitStatus(*status);
  EXPECT_NE(testing::ReadFile(dir + "/err").find("mocap.system"), std::string::npos)
      << testing::ReadFile(dir + "/err");
  // Its last heartbeat, sent before it exited, says so too.
  const auto failed = watch.Await(
      child.pid(), [](const service_status_t& s) { return s.state == service_status_t::FAILED; },
      5);
  ASSERT_TRUE(failed.has_value()) << "no FAILED heartbeat";
  EXPECT_NE(failed->last_error.find("mocap.system"), std::string::npos) << failed->last_error;
  testing::RemoveTree(dir);
}

// A socket the host refuses is the host's network, not the config: exit 4 (docs/exit-codes.md),
// with the port named in the line and in the last heartbeat.
TEST(NatNetBridgeProcessTest, ADataPortHeldByAnotherProgramEndsWithExit4NamingThePort) {
  ASSERT_TRUE(testing::InNetns());
  // Held without SO_REUSEADDR: the bridge's bind to the same port is refused (EADDRINUSE).
  const int holder = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  ASSERT_GE(holder, 0);
  sockaddr_in any{};
  any.sin_family = AF_INET;
  any.sin_addr.s_addr = htonl(INADDR_ANY);
  ASSERT_EQ(::bind(holder, reinterpret_cast<sockaddr*>(&any), sizeof any), 0);
  socklen_t len = sizeof any;
  ASSERT_EQ(::getsockname(holder, reinterpret_cast<sockaddr*>(&any), &len), 0);
  const int port = ntohs(any.sin_port);

  const std::string dir = testing::MakeTempDir();
  std::string config = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  config = std::regex_replace(config, std::regex("system: QUALISYS"), "system: OPTITRACK");
  config = std::regex_replace(config, std::regex("data_port: 1511"),
                              "data_port: " + std::to_string(port));
  std::ofstream(dir + "/config.pbtxt") << config;
  const std::string url = "udpm://239.255.76.67:7667?ttl=0";
  lcm::LCM lcm(url);
  ASSERT_TRUE(lcm.good());
  testing::StatusWatch watch(lcm);
  testing::Child child({FTCAL_NATNET_BRIDGE, "--config", dir + "/config.pbtxt", "--lcm-url", url},
                       dir + "/out", dir + "/err");
  const auto status = child.Wait(10);
  ASSERT_TRUE(status.has_value());
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 4)
      << testing::DescribeWaitStatus(*status) << "\n"
      << testing::ReadFile(dir + "/err");
  const std::string named = "binding the data socket to port " + std::to_string(port);
  EXPECT_NE(testing::ReadFile(dir + "/err").find(named), std::string::npos)
      << testing::ReadFile(dir + "/err");
  const auto failed = watch.Await(
      child.pid(), [](const service_status_t& s) { return s.state == service_status_t::FAILED; },
      5);
  ASSERT_TRUE(failed.has_value()) << "no FAILED heartbeat";
  EXPECT_NE(failed->last_error.find(named), std::string::npos) << failed->last_error;
  ::close(holder);
  testing::RemoveTree(dir);
}
#endif

}  // namespace
}  // namespace ftcal
