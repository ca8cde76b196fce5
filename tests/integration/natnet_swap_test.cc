// Swapping the motion capture changes nothing downstream (issue 16). The same twin session
// (scenario "stand", the same seed) runs twice as real processes over LCM inside this network
// namespace (scripts/netns-exec runs the binary): once ftcal-sim live serves QTM and
// ftcal-mocap-bridge reads it, once it serves OptiTrack Motive (NatNet 4.1, multicast, Y-up,
// a pivot frame away from the chassis) and ftcal-natnet-bridge reads it. Both sessions, recorded
// by lcm-logger, go through ftcal-pose-segmenter --replay. Every MOCAP_BODY of the same twin
// frame must be the same from either bridge to f32 rounding, and the steady poses the segmenter
// keeps in both runs must be the same twin poses: the same shaft angles, attitude and wrenches.
// (The calibrations are compared by experiment_live_test, which runs the whole live experiment
// through each bridge: minutes of real time, where this test takes seconds.)
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <regex>
#include <thread>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/geometry.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "ftcal/steady_pose_t.hpp"

namespace ftcal {
namespace {

using testing::Child;
using testing::Terminate;
using Clock = std::chrono::steady_clock;

constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=8388608";
constexpr std::uint64_t kSeed = 5;
// Over four standing poses (0.6 s move + 5 s dwell each): three whole ones, of which a marker
// dropout of the twin's may cost one (the segmenter keeps a pose only with every marker seen).
constexpr double kRunS = 24.0;

using testing::SleepS;

std::string ConfigText(const std::string& device, bool optitrack) {
  std::string text = testing::ReadFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  text = std::regex_replace(text, std::regex("device: \"[^\"]*\""), "device: \"" + device + "\"");
  text = std::regex_replace(text, std::regex("reply_timeout_s: [0-9.]+"), "reply_timeout_s: 0.05");
  if (optitrack) {
    text = std::regex_replace(text, std::regex("system: QUALISYS"), "system: OPTITRACK");
    // Motive's pivot at the markers' centroid, turned from the chassis' axes: the bridge must
    // bring the pose back to the chassis frame.
    text = std::regex_replace(text, std::regex("    silence_s: 0.5\n"),
                              "    silence_s: 0.5\n    x_pivot_chassis { translation_m { x: 0.01 "
                              "y: -0.02 z: -0.06 } rpy_deg { x: 0 y: 0 z: 30 } }\n");
  }
  return text;
}

struct Session {
  std::vector<steady_pose_t> poses;
  std::map<int64_t, mocap_body_t> mocap;  // by frame number (tick + 1 in both emulations)
  int64_t mocap_messages = 0;
  int64_t mocap_tracked = 0;
  service_status_t segmenter;  // its last status: the counters say why a run was not a pose
};

std::string Counters(const service_status_t& s) {
  std::string out;
  for (int i = 0; i < s.num_counters; ++i) {
    out += " " + s.counter_name[i] + "=" + std::to_string(s.counter_value[i]);
  }
  return out;
}

// One live session with the given mocap, then the segmenter over its recording.
Session RunSession(bool natnet) {
  Session out;
  const std::string dir = testing::MakeTempDir();
  auto path = [&](const std::string& name) { return dir + "/" + name; };
  const std::string link = path("tty");
  const std::string config_path = path("config.pbtxt");
  std::ofstream(config_path) << ConfigText(link, natnet);

  std::vector<std::string> sim_argv = {FTCAL_SIM,     "live",
                                       "--config",    config_path,
                                       "--pty-link",  link,
                                       "--truth-dir", dir,
                                       "--ready",     path("ready"),
                                       "--scenario",  "stand",
                                       "--seed",      std::to_string(kSeed),
                                       "--ati-rate",  "500"};
  if (natnet) {
    for (const char* a :
         {"--mocap", "natnet", "--natnet-version", "4.1", "--natnet-transport", "multicast"}) {
      sim_argv.push_back(a);
    }
  }
  Child sim(sim_argv, path("sim.out"), path("sim.err"));
  const auto deadline = Clock::now() + std::chrono::seconds(30);
  while (::access(path("ready").c_str(), F_OK) != 0) {
    EXPECT_FALSE(sim.Wait(0.02).has_value())
        << "ftcal-sim ended: " << testing::ReadFile(path("sim.err"));
    if (!sim.running() || Clock::now() > deadline) return out;
  }
  Child logger({FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", path("run.lcmlog")}, path("logger.out"),
               path("logger.err"));
  SleepS(0.3);
  const std::string url = "udpm://239.255.76.67:7667?ttl=0";
  Child ati(
      {FTCAL_ATI_BRIDGE, "--config", config_path, "--lcm-url", url, "--silence-timeout", "1.0"},
      path("ati.out"), path("ati.err"));
  Child dxl({FTCAL_DYNAMIXEL_BRIDGE, "--config", config_path, "--lcm-url", url}, path("dxl.out"),
            path("dxl.err"));
  Child mocap({natnet ? FTCAL_NATNET_BRIDGE : FTCAL_MOCAP_BRIDGE, "--config", config_path,
               "--lcm-url", url},
              path("mocap.out"), path("mocap.err"));
  // The operator's STANDING markers: the segmenter looks for poses between them, and the
  // stop makes the pose in progress one.
  lcm::LCM lcm(url);
  auto marker = [&](bool start) {
    experiment_marker_t m{};
    m.utime = std::chrono::duration_cast<std::chrono::microseconds>(
                  std::chrono::system_clock::now().time_since_epoch())
                  .count();
    m.session_id = "swap";
    m.phase = experiment_marker_t::STANDING;
    m.start = start;
    lcm.publish("EXPERIMENT", &m);
  };
  marker(true);
  SleepS(kRunS);
  marker(false);
  SleepS(0.2);
  sim.Signal(SIGTERM);
  SleepS(0.3);
  Terminate(ati, "ftcal-ati-bridge", path("ati.err"));
  Terminate(dxl, "ftcal-dynamixel-bridge", path("dxl.err"));
  Terminate(mocap, natnet ? "ftcal-natnet-bridge" : "ftcal-mocap-bridge", path("mocap.err"));
  Terminate(sim, "ftcal-sim live", path("sim.err"));
  SleepS(0.5);
  logger.Signal(SIGINT);
  EXPECT_TRUE(logger.Wait(10).has_value());
  std::cout << testing::ReadFile(path("sim.out"));

  Child seg({FTCAL_POSE_SEGMENTER, "--config", config_path, "--replay", path("run.lcmlog"), "--out",
             path("seg.lcmlog")},
            path("seg.out"), path("seg.err"));
  const auto status = seg.Wait(120);
  std::cout << (natnet ? "natnet" : "qtm") << " segmenter: " << testing::ReadFile(path("seg.err"));
  EXPECT_TRUE(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << "ftcal-pose-segmenter: " << testing::ReadFile(path("seg.err"));
  {
    lcm::LogFile log(path("run.lcmlog"), "r");
    while (const lcm::LogEvent* e = log.readNextEvent()) {
      if (e->channel != "MOCAP_BODY") continue;
      mocap_body_t m;
      if (m.decode(e->data, 0, e->datalen) < 0) continue;
      ++out.mocap_messages;
      out.mocap_tracked += m.tracked;
      out.mocap[m.frame_number] = m;
    }
  }
  lcm::LogFile log(path("seg.lcmlog"), "r");
  EXPECT_TRUE(log.good());
  while (log.good()) {
    const lcm::LogEvent* e = log.readNextEvent();
    if (e == nullptr) break;
    if (e->channel == "FTCAL_STATUS") {
      service_status_t st;
      if (st.decode(e->data, 0, e->datalen) >= 0 && st.name == "ftcal-pose-segmenter")
        out.segmenter = st;
    }
    if (e->channel != "STEADY_POSE") continue;
    steady_pose_t p;
    if (p.decode(e->data, 0, e->datalen) >= 0) out.poses.push_back(p);
  }
  if (!::testing::Test::HasFailure()) testing::RemoveTree(dir);
  return out;
}

double MaxAngleDiff(const steady_pose_t& a, const steady_pose_t& b) {
  double worst = 0;
  for (int k = 0; k < 6; ++k) worst = std::max(worst, std::abs(a.angle_rad[k] - b.angle_rad[k]));
  return worst;
}

TEST(NatNetSwap, TheSegmenterKeepsTheSamePosesWhicheverMocapBridge) {
  testing::AheadOfTheMachine();
  ASSERT_TRUE(testing::InNetns());
  ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) not found at configure time";
  const Session qtm = RunSession(false);
  ASSERT_FALSE(::testing::Test::HasFatalFailure());
  const Session natnet = RunSession(true);
  std::cout << "qtm: " << qtm.mocap_messages << " MOCAP_BODY (" << qtm.mocap_tracked
            << " tracked), " << qtm.poses.size()
            << " steady poses; natnet: " << natnet.mocap_messages << " MOCAP_BODY ("
            << natnet.mocap_tracked << " tracked), " << natnet.poses.size()
            << " steady poses\nqtm segmenter:" << Counters(qtm.segmenter)
            << "\nnatnet segmenter:" << Counters(natnet.segmenter) << "\n";
  // 1. Message by message: the same twin frame (same frame number: both emulations number
  // tick + 1 and neither skips) gives the same MOCAP_BODY from either bridge, to f32 rounding
  // (QTM sends a rotation matrix and millimetres; Motive a Y-up quaternion of a pivot frame
  // 6 cm and 30 deg away from the chassis, and metres).
  int64_t pairs = 0;
  for (const auto& [frame, a] : qtm.mocap) {
    const auto it = natnet.mocap.find(frame);
    if (it == natnet.mocap.end()) continue;
    const mocap_body_t& b = it->second;
    ++pairs;
    const std::string where = "frame " + std::to_string(frame);
    EXPECT_EQ(a.device_utime, b.device_utime) << where;
    ASSERT_EQ(bool(a.tracked), bool(b.tracked)) << where;
    if (a.tracked) {
      const Mat3 Ra =
          QuaternionToRotation(Eigen::Vector4d(a.q_gc[0], a.q_gc[1], a.q_gc[2], a.q_gc[3]));
      const Mat3 Rb =
          QuaternionToRotation(Eigen::Vector4d(b.q_gc[0], b.q_gc[1], b.q_gc[2], b.q_gc[3]));
      EXPECT_LT(LogSO3(Ra.transpose() * Rb).norm(), 2e-6) << where;
      const Mat3 Wa =
          QuaternionToRotation(Eigen::Vector4d(a.q_wc[0], a.q_wc[1], a.q_wc[2], a.q_wc[3]));
      const Mat3 Wb =
          QuaternionToRotation(Eigen::Vector4d(b.q_wc[0], b.q_wc[1], b.q_wc[2], b.q_wc[3]));
      EXPECT_LT(LogSO3(Wa.transpose() * Wb).norm(), 2e-6) << where;
      EXPECT_NEAR(a.yaw_rad, b.yaw_rad, 2e-6) << where;
      for (int i = 0; i < 3; ++i) EXPECT_NEAR(a.position_m[i], b.position_m[i], 2e-6) << where;
      EXPECT_NEAR(a.residual_m, b.residual_m, 1e-9) << where;
    }
    ASSERT_EQ(a.num_markers, b.num_markers) << where;
    for (int i = 0; i < a.num_markers; ++i) {
      ASSERT_EQ(bool(a.marker_tracked[i]), bool(b.marker_tracked[i])) << where << " marker " << i;
      for (int j = 0; j < 3 && a.marker_tracked[i]; ++j) {
        EXPECT_NEAR(a.marker_m[i][j], b.marker_m[i][j], 2e-6) << where << " marker " << i;
      }
    }
    if (::testing::Test::HasFailure()) break;  // one frame's story is enough
  }
  std::cout << "MOCAP_BODY of the same frame from both bridges: " << pairs << " pairs compared\n";
  EXPECT_GT(pairs, 1500);

  // 2. Through the segmenter: every pose it keeps in both runs is the same pose. How many
  // runs become poses depends on the machine's load as much as on the mocap (the segmenter's
  // counters above say why one was not: short, a marker dropout, stale inputs), so the
  // comparison is over the poses found in both, and there must be one at least.
  ASSERT_GE(qtm.poses.size(), 1u);
  ASSERT_GE(natnet.poses.size(), 1u);
  int matched = 0;
  for (const steady_pose_t& a : qtm.poses) {
    const steady_pose_t* best = nullptr;
    for (const steady_pose_t& b : natnet.poses) {
      if (best == nullptr || MaxAngleDiff(a, b) < MaxAngleDiff(a, *best)) best = &b;
    }
    // One encoder count: the same twin pose (standing poses differ by degrees).
    if (best == nullptr || MaxAngleDiff(a, *best) > 2.0 * M_PI / 4096.0) continue;
    ++matched;
    const steady_pose_t& b = *best;
    const std::string where = "qtm pose " + std::to_string(a.pose_index) + " / natnet pose " +
                              std::to_string(b.pose_index);
    const Mat3 Ra =
        QuaternionToRotation(Eigen::Vector4d(a.q_wc[0], a.q_wc[1], a.q_wc[2], a.q_wc[3]));
    const Mat3 Rb =
        QuaternionToRotation(Eigen::Vector4d(b.q_wc[0], b.q_wc[1], b.q_wc[2], b.q_wc[3]));
    // Not to f32 rounding as the messages above: the two runs' steady windows start and end
    // on different samples (the machine's load shifts them), and the twin's chassis still
    // settles a little within a pose, so the medians are of slightly different sets.
    const double attitude = LogSO3(Ra.transpose() * Rb).norm();
    EXPECT_LT(attitude, 1e-3) << where;
    EXPECT_EQ(bool(a.markers_ok), bool(b.markers_ok)) << where;
    // The wrenches come from the same seeded ATI stream in both runs: the medians agree to
    // the spread of a steady window's edges.
    double worst = 0;
    for (int k = 0; k < 6; ++k) {
      for (int i = 0; i < 6; ++i)
        worst = std::max(worst, std::abs(a.wrench[k][i] - b.wrench[k][i]));
    }
    EXPECT_LT(worst, 0.05) << where;
    std::cout << where << ": attitude differs by " << attitude << " rad, wrenches by " << worst
              << " at most\n";
  }
  EXPECT_GE(matched, 1);
}

}  // namespace
}  // namespace ftcal
