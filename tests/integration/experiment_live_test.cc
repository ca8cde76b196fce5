// The calibration experiment run live end to end (issue 11), and the motion capture swapped
// under it (issue 16), through scripts/experiment: the twin (ftcal-sim live --scenario
// commanded --control), the ATI, Dynamixel and mocap bridges, ftcal-record, the segmenter, the
// live calibrator, the corrector and the sequencer, all real processes over real LCM, each run in
// a network namespace of its own (scripts/netns-exec inside this test's).
//
// Main tier: the plan "quick" of config/sim.pbtxt (tare, four hanging series, 41 standing poses
// in four minutes of motion) through QTM, alone; and a run whose ATI bridge is killed as the plan
// starts ends at once, naming it.
// Long tier: the plan "experiment" (46 poses, slower hanging series) twice at once, the same twin
// session (seed 3) each time, once through the twin's QTM server and ftcal-mocap-bridge, once
// through its OptiTrack Motive server (NatNet 4.1 multicast, a pivot frame away from the
// chassis) and ftcal-natnet-bridge.
//
// Checked here, independently of the script's own verdict, for each run:
//   - the live calibration recovers the twin's true parameters (truth.pbtxt, written by the
//     twin at start) within bounds for this short experiment (p~' within its own sigma);
//   - it equals the offline calibration of the recording: the two collect the same
//     messages with the same collector code and solve the same problem.
// And across the two runs of the long tier (the swap changes nothing downstream):
//   - both kept enough standing poses to calibrate; which ones each kept is printed (a marker
//     dropout at a steady window's edge falls in one run and not the other: scheduling);
//   - the two calibrations agree, parameter by parameter, within the accuracy each run is held
//     to against the truth, and p~' within four combined sigmas.
// Neither reruns itself: a run that stops early (a bridge that reports itself DEGRADED stops the
// sequencer, as it must) fails the test with the sequencer's log.
#include <dirent.h>
#include <signal.h>
#include <sys/wait.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "test_helpers.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/geometry.h"
#include "ftcal/steady_pose_t.hpp"
#include "calibration_errors.h"

namespace ftcal {
namespace {

using testing::Child;

using namespace calibration_errors;  // NOLINT: calibration_errors.h

void Print(const char* what, const Errors& e) {
  std::cout << what << ": leg weight " << e.weight_n << " N, force offsets " << e.force_n
            << " N, torque offsets " << e.torque_nm << " N*m, leg CoM " << e.com_m * 1e3
            << " mm, mounting rotations " << e.rotation_deg << " deg, p~' " << e.p_tilde_m * 1e3
            << " mm\n";
}

// The calibrator's "HANG_X_POS complete: N samples per leg, ..." lines: what it collected.
std::vector<std::string> Collected(const std::string& log_path) {
  std::vector<std::string> lines;
  std::istringstream in(testing::ReadFile(log_path));
  const std::regex re("(HANG_[A-Z_]+ complete: [0-9]+ samples per leg)");
  for (std::string line; std::getline(in, line);) {
    std::smatch m;
    if (std::regex_search(line, m, re)) lines.push_back(m[1]);
  }
  return lines;
}

// One scripts/experiment run in a network namespace of its own.
struct ExperimentRun {
  std::string name;   // "qtm", "natnet"
  std::string mocap;  // FTCAL_EXPERIMENT_MOCAP
  std::string out;
  std::unique_ptr<Child> child;
  std::string plan = "experiment";  // FTCAL_EXPERIMENT_PLAN
};

void Start(ExperimentRun& run, const std::string& dir) {
  run.out = dir + "/" + run.name;
  run.child = std::make_unique<Child>(
      std::vector<std::string>{std::string(FTCAL_SOURCE_DIR) + "/scripts/netns-exec",
                               "/usr/bin/env", std::string("FTCAL_BUILD_DIR=") + FTCAL_BUILD_DIR,
                               "FTCAL_EXPERIMENT_SEED=3", "FTCAL_EXPERIMENT_MOCAP=" + run.mocap,
                               "FTCAL_EXPERIMENT_PLAN=" + run.plan,
                               std::string(FTCAL_SOURCE_DIR) + "/scripts/experiment", run.out},
      dir + "/" + run.name + ".out", dir + "/" + run.name + ".err");
}

// The run's own checks: against the truth (the whole experiment's recovery bounds times
// `truth_scale`, p~' within four of its sigmas, each horizontal one within
// `max_horizontal_sigma_m`), and live against offline.
void CheckRun(const ExperimentRun& run, double truth_scale = 3,
              double max_horizontal_sigma_m = 1e-3) {
  const std::string& out = run.out;
  const config::Config config = LoadConfigFile(out + "/config.pbtxt");
  const calibration::Calibration live_proto = ReadCalibrationFile(out + "/calibration.pbtxt");
  const calibration::Calibration offline_proto =
      ReadCalibrationFile(out + "/calibration-offline.pbtxt");
  const RobotCalibration live = CalibrationFromProto(live_proto, config.robot());
  const RobotCalibration offline = CalibrationFromProto(offline_proto, config.robot());
  const RobotCalibration truth =
      CalibrationFromProto(ReadCalibrationFile(out + "/truth.pbtxt"), config.robot());
  // Against the truth. The whole experiment's recovery bounds (scripts/compare_calibration.py:
  // 0.015 N, 0.02 N, 0.001 N*m, 0.2 mm, 0.15 deg, 0.5 mm) times three: this plan has three
  // hanging cycles a series instead of ten and ~40 steady poses instead of 729. p~' is held to
  // its own sigma instead: with ~40 poses its vertical component is known to 2-5 mm only (the
  // feet move little in z), so each component within four of the sigma the calibration states.
  const Errors vs_truth = Compare(live, truth);
  Print((run.name + ": live vs truth").c_str(), vs_truth);
  ExpectWithinBounds(vs_truth, truth_scale, run.name + ": live vs truth");
  ExpectPTildeWithinSigmas(live_proto, live, truth, 4, max_horizontal_sigma_m);

  // Against the offline calibration of the recording: the same poses, the same model. The two
  // run the same collector and solver, so with the same messages they agree to the solver's
  // rounding (1e-6 of the bounds). They can differ by messages: on a loaded machine the
  // recorder's socket or the live calibrator's overflows (both are sized to the kernel's
  // net.core.rmem_max), or two publishers' datagrams reach the two sockets in another order at
  // a marker. Then the counts that differ are printed (the explanation) and the two must agree
  // to a tenth of the bounds used against the truth, p~' to a tenth of its stated sigma.
  EXPECT_EQ(live_proto.standing_poses(), offline_proto.standing_poses());
  EXPECT_EQ(live_proto.model(), offline_proto.model());
  const std::vector<std::string> live_counts = Collected(out + "/logs/calibrator.err");
  const std::vector<std::string> offline_counts = Collected(out + "/logs/calibrator-offline.err");
  ASSERT_EQ(live_counts.size(), 4u) << testing::ReadFile(out + "/logs/calibrator.err");
  // Equal hanging counts do not mean equal data: a standing sample one receiver missed moves a
  // pose's median (seen in a clean-clone run: the same hanging counts, rotations 2.1e-4 deg and
  // p~' 1.5 um apart). No count here covers every standing sample, so the two always get the
  // tolerance of a difference in messages.
  const bool same = live_counts == offline_counts;
  const double tol = 0.3;
  for (std::size_t i = 0; !same && i < live_counts.size() && i < offline_counts.size(); ++i) {
    if (live_counts[i] != offline_counts[i]) {
      std::cout << run.name << ": collected differently: live '" << live_counts[i] << "', offline '"
                << offline_counts[i] << "'\n";
    }
  }
  const Errors vs_offline = Compare(live, offline);
  Print((run.name + ": live vs offline").c_str(), vs_offline);
  ExpectWithinBounds(vs_offline, tol, run.name + ": live vs offline");
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& e = live_proto.leg(k).mounting().p_tilde_prime_m();
    const Vec3 sigma(e.sigma_x(), e.sigma_y(), e.sigma_z());
    const Vec3 d = live.leg[k].p_tilde_prime - offline.leg[k].p_tilde_prime;
    for (int i = 0; i < 3; ++i) {
      EXPECT_LE(std::abs(d[i]), 0.1 * sigma[i])
          << "leg " << live_proto.leg(k).name() << " p~' component " << i;
    }
  }
}

// The grid poses the segmenter kept (STEADY_POSE in the recording), each as its shaft angles
// rounded to a tenth of a radian: the grid's angles (0, +-36 deg) are 0.63 rad apart, a pose's
// median within a few encoder counts of its goal.
std::multiset<std::vector<int>> KeptPoses(const std::string& log_path) {
  std::multiset<std::vector<int>> poses;
  lcm::LogFile log(log_path, "r");
  EXPECT_TRUE(log.good()) << log_path;
  while (log.good()) {
    const lcm::LogEvent* e = log.readNextEvent();
    if (e == nullptr) break;
    if (e->channel != "STEADY_POSE") continue;
    steady_pose_t p;
    if (p.decode(e->data, 0, e->datalen) < 0) continue;
    std::vector<int> key;
    for (int k = 0; k < 6; ++k) key.push_back(static_cast<int>(std::lround(p.angle_rad[k] * 10)));
    poses.insert(key);
  }
  return poses;
}

// |a - b| within `k` of the two stated sigmas combined, for one estimated number.
void ExpectAgrees(double a, double sa, double b, double sb, double k, const std::string& what) {
  ASSERT_TRUE(sa > 0 && sb > 0) << what << ": no sigma stated (" << sa << ", " << sb << ")";
  const double s = std::hypot(sa, sb);
  EXPECT_LE(std::abs(a - b), k * s)
      << what << ": " << a << " vs " << b << ", " << std::abs(a - b) / s
      << " combined sigmas apart (sigmas " << sa << ", " << sb << ")";
}
void ExpectAgrees(const calibration::Vec3Estimate& a, const calibration::Vec3Estimate& b, double k,
                  const std::string& what) {
  ExpectAgrees(a.x(), a.sigma_x(), b.x(), b.sigma_x(), k, what + ".x");
  ExpectAgrees(a.y(), a.sigma_y(), b.y(), b.sigma_y(), k, what + ".y");
  ExpectAgrees(a.z(), a.sigma_z(), b.z(), b.sigma_z(), k, what + ".z");
}

// The processes running with `arg` among their arguments (a run's config path picks out its
// group): /proc's command lines, NUL-separated.
std::vector<pid_t> ProcessesWithArg(const std::string& arg) {
  std::vector<pid_t> found;
  DIR* proc = ::opendir("/proc");
  if (proc == nullptr) return found;
  while (const dirent* e = ::readdir(proc)) {
    const pid_t pid = static_cast<pid_t>(std::atoi(e->d_name));
    if (pid <= 0) continue;
    const std::string cmdline = testing::ReadFile("/proc/" + std::string(e->d_name) + "/cmdline");
    std::istringstream in(cmdline);
    for (std::string a; std::getline(in, a, '\0');) {
      if (a == arg) {
        found.push_back(pid);
        break;
      }
    }
  }
  ::closedir(proc);
  return found;
}

// A bridge that dies as the plan starts ends the experiment at once, by name. The sequencer
// stops by itself when a bridge it has heard goes stale, but one it has not heard yet is only
// "not there yet": it asked again at every prompt, and scripts/experiment, its operator, waited
// for the next prompt (18 minutes, once, until a test gave up). Now the script exits 2 within
// seconds, says which process exited with the end of its log, and leaves no process behind.
TEST(ExperimentLive, ABridgeThatDiesAsThePlanStartsEndsTheExperimentNamingIt) {
  ASSERT_TRUE(testing::InNetns());
  testing::AheadOfTheMachine();
  const std::string dir = testing::MakeTempDir();
  ExperimentRun run{"bridge-dies", "qualisys", "", nullptr};
  Start(run, dir);
  const std::string said_path = dir + "/" + run.name + ".out";
  // Until the script starts the sequencer, which has then heard nothing yet.
  const std::string step3 = "== 3/4";
  for (int i = 0; i < 3000 && testing::ReadFile(said_path).find(step3) == std::string::npos; ++i) {
    ASSERT_TRUE(run.child->running())
        << testing::ReadFile(said_path) << testing::ReadFile(dir + "/" + run.name + ".err");
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  ASSERT_NE(testing::ReadFile(said_path).find(step3), std::string::npos);
  const std::string config = run.out + "/config.pbtxt";
  pid_t ati = 0;
  for (pid_t pid : ProcessesWithArg(config)) {
    if (testing::ReadFile("/proc/" + std::to_string(pid) + "/comm").rfind("ftcal-ati-bri", 0) ==
        0) {
      ati = pid;
    }
  }
  ASSERT_GT(ati, 0) << "no ftcal-ati-bridge running with --config " << config;
  const auto killed_at = std::chrono::steady_clock::now();
  ASSERT_EQ(::kill(ati, SIGKILL), 0);
  const auto status = run.child->Wait(60);
  const double took_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - killed_at).count();
  const std::string err = testing::ReadFile(dir + "/" + run.name + ".err");
  if (!status) {
    run.child->Signal(SIGTERM);  // the script's own exit trap stops the group
    run.child->Wait(30);
    for (pid_t pid : ProcessesWithArg(config)) ::kill(pid, SIGKILL);  // should that not have
  }
  ASSERT_TRUE(status.has_value()) << "scripts/experiment still ran 60 s after its ATI bridge died\n"
                                  << err;
  std::printf("[ figure ] ATI bridge killed -> scripts/experiment ended: %.2f s\n", took_s);
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 2)
      << testing::DescribeWaitStatus(*status) << "\n"
      << err;
  EXPECT_LT(took_s, 10.0);
  EXPECT_NE(err.find("ati exited while the plan ran"), std::string::npos) << err;
  EXPECT_NE(err.find("the experiment stopped because ati exited"), std::string::npos) << err;
  // The rest of the group went with it (the script's exit stops every process it started).
  std::vector<pid_t> left;
  for (int i = 0; i < 50; ++i) {
    left = ProcessesWithArg(config);
    if (left.empty()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_TRUE(left.empty()) << left.size() << " processes of the group still run";
  for (pid_t pid : left) ::kill(pid, SIGKILL);  // not into the next test
}

// The main tier's live experiment: the plan "quick" (the same phases as "experiment" in about
// four minutes of motion) through QTM, alone on the machine. The long tier's test below runs the
// whole plan through both motion captures at once; natnet_swap_test checks the swap in the main
// tier.
TEST(ExperimentLive, TheQuickPlanCalibratesLiveAsTheTruth) {
  ASSERT_TRUE(testing::InNetns());
  testing::AheadOfTheMachine();
  const std::string dir = testing::MakeTempDir();
  ExperimentRun run{"quick", "qualisys", "", nullptr, "quick"};
  Start(run, dir);
  const std::optional<int> status = run.child->Wait(900);
  std::cout << testing::ReadFile(dir + "/quick.out") << testing::ReadFile(dir + "/quick.err");
  if (!status) {
    run.child->Signal(SIGTERM);
    run.child->Wait(30);
    FAIL() << "scripts/experiment did not end in 900 s";
  }
  // 0: its own comparisons passed; 1: they did not (checked below regardless); anything else:
  // the experiment did not run to its end.
  ASSERT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) <= 1)
      << testing::DescribeWaitStatus(*status) << "\n"
      << testing::ReadFile(run.out + "/logs/sequencer.err");
  // 41 poses of 2.5 s instead of 46 of 3 s and 4 s hanging cycles instead of 6 s: the same
  // bounds against the truth, p~' known to 1.5 mm horizontally instead of 1 (1.0-1.3 mm seen
  // beside two busy loops; the two-host test allows the same for its lost poses).
  CheckRun(run, 3, 1.5e-3);
  EXPECT_GE(KeptPoses(run.out + "/session.lcmlog").size(), 30u);
  if (!::testing::Test::HasFailure()) testing::RemoveTree(dir);
}

TEST(ExperimentLive, TheShortPlanCalibratesLiveAsTheTruthThroughQtmAndThroughNatNetAlike) {
  ASSERT_TRUE(testing::InNetns());
  testing::AheadOfTheMachine();
  const std::string dir = testing::MakeTempDir();
  // Both at once: each is mostly waiting (5 s dwells, slow hanging turns), and the two
  // sessions are the same twin seed, so the swap is the only difference between them.
  ExperimentRun runs[2] = {{"qtm", "qualisys", "", nullptr}, {"natnet", "optitrack", "", nullptr}};
  for (ExperimentRun& r : runs) Start(r, dir);
  std::optional<int> statuses[2];
  for (int i = 0; i < 2; ++i) statuses[i] = runs[i].child->Wait(1100);
  bool ran = true;
  for (int i = 0; i < 2; ++i) {
    ExperimentRun& r = runs[i];
    const std::optional<int>& status = statuses[i];
    SCOPED_TRACE(r.name);
    const std::string said = testing::ReadFile(dir + "/" + r.name + ".out") +
                             testing::ReadFile(dir + "/" + r.name + ".err");
    std::cout << "==== " << r.name << " (FTCAL_EXPERIMENT_MOCAP=" << r.mocap << ")\n" << said;
    if (!status) {
      ADD_FAILURE() << "scripts/experiment did not end";
      r.child->Signal(SIGTERM);
      r.child->Wait(30);
      ran = false;
      continue;
    }
    // 0: its own comparisons passed; 1: they did not (checked below regardless); anything
    // else: the experiment did not run to its end.
    EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) <= 1)
        << testing::DescribeWaitStatus(*status) << "\n"
        << testing::ReadFile(r.out + "/logs/sequencer.err");
    ran = ran && WIFEXITED(*status) && WEXITSTATUS(*status) <= 1;
  }
  ASSERT_TRUE(ran);
  for (const ExperimentRun& r : runs) {
    SCOPED_TRACE(r.name);
    CheckRun(r);
  }

  // The swap: the same poses kept, the same calibration within its uncertainty.
  const auto qtm_poses = KeptPoses(runs[0].out + "/session.lcmlog");
  const auto natnet_poses = KeptPoses(runs[1].out + "/session.lcmlog");
  std::cout << "steady poses kept: qtm " << qtm_poses.size() << ", natnet " << natnet_poses.size()
            << "\n";
  // The calibrator needs calibrator.min_poses (30) of the plan's 46.
  EXPECT_GE(qtm_poses.size(), 30u);
  EXPECT_GE(natnet_poses.size(), 30u);
  // The segmenter leaves out a pose when the twin drops a chassis marker during its steady
  // window (require_all_markers), or when a bridge's data stalls in it. The twin follows real
  // time here, so a dropout near a window's edge falls inside it in one run and outside in the
  // other by a few milliseconds of scheduling, and on a loaded machine one run's stall is not
  // the other's: seen 37 against 36 on a quiet machine, then 5 and 10 poses kept by one run only
  // (of 34-38). Which poses are kept is scheduling here, not the bridge, so it is printed, not
  // bounded: the swap is judged by the calibrations below. (natnet_swap_test, on a scenario
  // keyed to the frame count instead of the clock, requires the very same poses.)
  std::vector<std::vector<int>> only_one;
  std::set_symmetric_difference(qtm_poses.begin(), qtm_poses.end(), natnet_poses.begin(),
                                natnet_poses.end(), std::back_inserter(only_one));
  for (const auto& pose : only_one) {
    std::cout << "kept in one run only:";
    for (int a : pose) std::cout << " " << a / 10.0;
    std::cout << " rad\n";
  }
  std::cout << "poses kept by one run only: " << only_one.size() << "\n";

  const config::Config config = LoadConfigFile(runs[0].out + "/config.pbtxt");
  const calibration::Calibration a = ReadCalibrationFile(runs[0].out + "/calibration.pbtxt");
  const calibration::Calibration b = ReadCalibrationFile(runs[1].out + "/calibration.pbtxt");
  EXPECT_EQ(a.model(), b.model()) << "the two chose different mounting models";
  ASSERT_EQ(a.leg_size(), kNumLegs);
  ASSERT_EQ(b.leg_size(), kNumLegs);
  // The swap changes the calibration by less than the accuracy each run is held to against
  // the truth (CheckRun). Not by the stated sigmas: those are the noise's share, and the two
  // runs differ by more than noise: other samples at the hanging series' ends, other poses
  // (above), and each bridge's own latency against the transducers (seen: one force offset
  // 0.005 N apart, 6 combined sigmas, against a bound of 0.06 N). p~' alone is held to its
  // sigmas, as against the truth, where its vertical component is known to a few mm only.
  const RobotCalibration qtm = CalibrationFromProto(a, config.robot());
  const RobotCalibration natnet = CalibrationFromProto(b, config.robot());
  const Errors apart = Compare(qtm, natnet);
  Print("qtm vs natnet", apart);
  ExpectWithinBounds(apart, 3, "qtm vs natnet");
  for (int i = 0; i < kNumLegs; ++i) {
    ExpectAgrees(a.leg(i).mounting().p_tilde_prime_m(), b.leg(i).mounting().p_tilde_prime_m(), 4.0,
                 "leg " + a.leg(i).name() + " p~'");
  }

  if (!::testing::Test::HasFailure()) testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
