// The calibration experiment run live end to end (issue 11): scripts/experiment on the twin
// (ftcal-sim live --scenario commanded --control: the servos follow the goals, the operator's
// FIFO hangs, lifts and sets the robot down), the three bridges, lcm-logger, the segmenter, the
// live calibrator, the corrector and the sequencer with config/sim.pbtxt's plan "experiment"
// (tare, four hanging series, 46 standing poses), all real processes over real LCM inside this
// test's private network namespace (ctest runs it through scripts/netns-exec).
//
// Checked here, independently of the script's own verdict:
//   - the live calibration recovers the twin's true parameters (truth.pbtxt, written by the
//     twin at start) within bounds for this short experiment (p~' within its own sigma);
//   - it equals the offline calibration of the lcm-logger recording parameter by parameter:
//     the two collect the same messages with the same collector code and solve the same
//     problem, so what differs is only what the solver's floating point makes of it.
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <iostream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "child_process.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/geometry.h"

namespace ftcal {
namespace {

using testing::Child;

// The leg CoM curve's largest distance between two calibrations over a cycle, m.
double ComCurveDistance(const LegComModel& a, const LegComModel& b) {
  double worst = 0.0;
  for (int i = 0; i < 400; ++i) {
    const double phase = i / 400.0;
    worst = std::max(worst, (a.At(phase) - b.At(phase)).norm());
  }
  return worst;
}

double RotationDeg(const Mat3& a, const Mat3& b) {
  const double c = std::clamp(((a.transpose() * b).trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / M_PI;
}

struct Errors {
  double weight_n = 0, force_n = 0, torque_nm = 0, com_m = 0, rotation_deg = 0, p_tilde_m = 0;
};

Errors Compare(const RobotCalibration& a, const RobotCalibration& b) {
  Errors e;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& x = a.leg[k];
    const LegCalibration& y = b.leg[k];
    e.weight_n = std::max(e.weight_n, std::abs(x.weight_n - y.weight_n));
    e.force_n = std::max(e.force_n, (x.offset.head<3>() - y.offset.head<3>()).cwiseAbs().maxCoeff());
    e.torque_nm = std::max(e.torque_nm, (x.offset.tail<3>() - y.offset.tail<3>()).cwiseAbs().maxCoeff());
    e.com_m = std::max(e.com_m, ComCurveDistance(x.com, y.com));
    e.rotation_deg = std::max(e.rotation_deg, RotationDeg(x.R_tilde, y.R_tilde));
    e.p_tilde_m = std::max(e.p_tilde_m, (x.p_tilde_prime - y.p_tilde_prime).norm());
  }
  return e;
}

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

TEST(ExperimentLive, TheShortPlanCalibratesLiveAsTheTruthAndAsTheRecording) {
  const char* netns = std::getenv("FTCAL_NETNS");
  ASSERT_TRUE(netns != nullptr && std::string(netns) == "1")
      << "this test sends UDP multicast: run it through scripts/netns-exec (ctest does)";
  const std::string dir = testing::MakeTempDir();
  const std::string out = dir + "/experiment";
  Child run({"/usr/bin/env", std::string("FTCAL_BUILD_DIR=") + FTCAL_BUILD_DIR,
             "FTCAL_EXPERIMENT_SEED=3", std::string(FTCAL_SOURCE_DIR) + "/scripts/experiment", out},
            dir + "/experiment.out", dir + "/experiment.err");
  const auto status = run.Wait(1100);
  ASSERT_TRUE(status.has_value()) << "scripts/experiment did not end\n"
                                  << testing::ReadFile(dir + "/experiment.out");
  const std::string said =
      testing::ReadFile(dir + "/experiment.out") + testing::ReadFile(dir + "/experiment.err");
  std::cout << said;
  // 0: its own comparisons passed; 1: they did not (checked below regardless); anything else:
  // the experiment did not run to its end.
  ASSERT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) <= 1)
      << testing::DescribeWaitStatus(*status) << "\n" << said << "\n"
      << testing::ReadFile(out + "/logs/sequencer.err");

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
  Print("live vs truth", vs_truth);
  EXPECT_LE(vs_truth.weight_n, 3 * 0.015);
  EXPECT_LE(vs_truth.force_n, 3 * 0.02);
  EXPECT_LE(vs_truth.torque_nm, 3 * 0.001);
  EXPECT_LE(vs_truth.com_m, 3 * 0.2e-3);
  EXPECT_LE(vs_truth.rotation_deg, 3 * 0.15);
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& e = live_proto.leg(k).mounting().p_tilde_prime_m();
    const Vec3 sigma(e.sigma_x(), e.sigma_y(), e.sigma_z());
    const Vec3 err = live.leg[k].p_tilde_prime - truth.leg[k].p_tilde_prime;
    for (int i = 0; i < 3; ++i) {
      ASSERT_GT(sigma[i], 0.0) << "leg " << k << ": the calibration states no sigma for p~'";
      EXPECT_LE(std::abs(err[i]), 4 * sigma[i])
          << "leg " << live_proto.leg(k).name() << " p~' component " << i << ": " << err[i] * 1e3
          << " mm off, sigma " << sigma[i] * 1e3 << " mm";
    }
    EXPECT_LE(err.head<2>().norm(), 3 * 0.5e-3) << "leg " << live_proto.leg(k).name();
  }

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
      std::cout << "collected differently: live '" << live_counts[i] << "', offline '"
                << offline_counts[i] << "'\n";
    }
  }
  const Errors vs_offline = Compare(live, offline);
  Print("live vs offline", vs_offline);
  EXPECT_LE(vs_offline.weight_n, tol * 0.015);
  EXPECT_LE(vs_offline.force_n, tol * 0.02);
  EXPECT_LE(vs_offline.torque_nm, tol * 0.001);
  EXPECT_LE(vs_offline.com_m, tol * 0.2e-3);
  EXPECT_LE(vs_offline.rotation_deg, tol * 0.15);
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& e = live_proto.leg(k).mounting().p_tilde_prime_m();
    const Vec3 sigma(e.sigma_x(), e.sigma_y(), e.sigma_z());
    const Vec3 d = live.leg[k].p_tilde_prime - offline.leg[k].p_tilde_prime;
    for (int i = 0; i < 3; ++i) {
      EXPECT_LE(std::abs(d[i]), 0.1 * sigma[i])
          << "leg " << live_proto.leg(k).name() << " p~' component " << i;
    }
  }

  if (!::testing::Test::HasFailure()) testing::RemoveTree(dir);
}

}  // namespace
}  // namespace ftcal
