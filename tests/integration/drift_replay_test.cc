// ftcal-drift over a log (issue #40) as a lab runs it: ftcal-sim log writes a walk whose offsets
// step on one leg while they creep on all, with the drifted truth over time beside it
// (<log>.drift.csv); ftcal-drift --replay tracks them. Both are real processes. The truth to
// meet is what the twin wrote, read back here: the DRIFT series (decoded through the wire guard)
// and --out-calibration must agree with it within the bounds; the demo's drift session
// (standing poses and tripod stances after the offsets drifted) must agree with its drifted
// truth as ftcal-calibrator --reestimate-offsets does (offset_drift_test).
#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/messages.h"
#include "common/wire_guard.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/drift_t.hpp"
#include "ftcal/legs.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::ReadFile;

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
constexpr double kForceBoundN = 0.1;  // the issue's, for a walk
constexpr double kTorqueBoundNm = 0.005;
constexpr double kTwoCyclesS = 25.0;  // of the 0.08 Hz gait

struct Result {
  int exit_code = -1;
  std::string err;
};

class DriftReplayTest : public ::testing::Test {
 protected:
  void SetUp() override { dir_ = testing::MakeTempDir(); }
  void TearDown() override {
    if (std::getenv("FTCAL_TEST_KEEP") == nullptr) testing::RemoveTree(dir_);
  }
  Result Run(const std::vector<std::string>& argv, const std::string& tag) {
    Child child(argv, dir_ + "/" + tag + ".out", dir_ + "/" + tag + ".err");
    const auto status = child.Wait(100);
    Result r;
    if (status && WIFEXITED(*status)) r.exit_code = WEXITSTATUS(*status);
    r.err = ReadFile(dir_ + "/" + tag + ".err");
    return r;
  }
  std::string dir_;
};

// The twin's drifted truth file: per leg, (utime, change) rows in time order.
std::map<std::string, std::vector<std::pair<int64_t, Vec6>>> ReadTruthCsv(const std::string& path) {
  std::map<std::string, std::vector<std::pair<int64_t, Vec6>>> out;
  std::ifstream in(path);
  std::string line;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    std::stringstream ss(line);
    std::string cell;
    std::vector<std::string> cells;
    while (std::getline(ss, cell, ',')) cells.push_back(cell);
    if (cells.size() != 15) continue;
    Vec6 d;
    for (int i = 0; i < 6; ++i) d[i] = std::stod(cells[3 + i]);
    out[cells[2]].emplace_back(std::stoll(cells[1]), d);
  }
  return out;
}

// The truth at `utime`: the last row at or before it (the file has rows at both sides of a step).
Vec6 TruthAt(const std::vector<std::pair<int64_t, Vec6>>& rows, int64_t utime) {
  Vec6 d = Vec6::Zero();
  for (const auto& [t, v] : rows) {
    if (t > utime) break;
    d = v;
  }
  return d;
}

std::vector<drift_t> ReadDrift(const std::string& path) {
  std::vector<drift_t> out;
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return out;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel != "DRIFT") continue;
    drift_t m;
    const auto refused = wire::Decode(e->data, e->datalen, &m);
    EXPECT_FALSE(refused) << refused->detail;
    if (!refused) out.push_back(m);
  }
  return out;
}

TEST_F(DriftReplayTest, AStepWhileWalkingIsTrackedAndFlaggedAndWrittenToTheCalibration) {
  const std::string log = dir_ + "/walk.lcmlog";
  // MR knocks something at 30 s; every leg creeps by 1 N / 0.03 N*m over 10 minutes.
  ASSERT_EQ(Run({FTCAL_SIM, "log", "--config", kConfig, "--out", log, "--seed", "3", "--scenarios",
                 "walk", "--walk-s", "90", "--drift-step", "MR:30:2,-2,2,0.05,-0.05,0.05",
                 "--drift-ramp", "all:0:600:1,-1,1,0.03,-0.03,0.03"},
                "sim")
                .exit_code,
            0);
  const auto truth = ReadTruthCsv(dir_ + "/walk.drift.csv");
  ASSERT_EQ(truth.size(), static_cast<size_t>(kNumLegs));
  const Result r = Run({FTCAL_DRIFT, "--config", kConfig, "--replay", log, "--out",
                        dir_ + "/drift.lcmlog", "--calibration", dir_ + "/walk.truth.pbtxt",
                        "--out-calibration", dir_ + "/tracked.pbtxt", "--csv", dir_ + "/drift.csv"},
                       "drift");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.err.find("offset drift beyond the calibration: MR fx"), std::string::npos) << r.err;

  const std::vector<drift_t> drift = ReadDrift(dir_ + "/drift.lcmlog");
  ASSERT_GE(drift.size(), 85u);  // once a second of the log, and a last one at its end
  const int64_t t0 = truth.at("HL").front().first;
  int checked = 0;
  for (const drift_t& m : drift) {
    const double t = 1e-6 * static_cast<double>(m.utime - t0);
    if (t < 30.0 + kTwoCyclesS) continue;
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 d = TruthAt(truth.at(std::string(kLegNames[k])), m.utime);
      for (int i = 0; i < 6; ++i) {
        EXPECT_NEAR(m.offset_change[k][i], d[i], i < 3 ? kForceBoundN : kTorqueBoundNm)
            << kLegNames[k] << " component " << i << " at " << t << " s";
      }
    }
    ++checked;
  }
  EXPECT_GT(checked, 30);
  // The step is beyond the truth calibration's sigma (none: the warn_min floor), the creep of
  // at most 0.15 N not: WARN on MR's six components only.
  const drift_t& last = drift.back();
  EXPECT_EQ(last.status, int{drift_t::WARN});
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_EQ(last.warn_mask[k], k == 4 ? 63 : 0) << kLegNames[k];
    EXPECT_GE(last.windows[k], 5) << kLegNames[k];
  }
  // The balance with the tracked offsets is back at the undrifted walk's (its attitude noise:
  // ~0.3 N); untracked it carries the step.
  const drift_t& late = drift[drift.size() - 3];
  ASSERT_GT(late.balance_samples, 50);
  EXPECT_LT(late.balance_force_rms_n[1], 0.5);
  EXPECT_GT(late.balance_force_rms_n[0], 2.0);

  // --out-calibration: the truth's offsets plus the change at the log's end, version + 1.
  const calibration::Calibration base = ReadCalibrationFile(dir_ + "/walk.truth.pbtxt");
  const calibration::Calibration tracked = ReadCalibrationFile(dir_ + "/tracked.pbtxt");
  const config::Config config = LoadConfigFile(kConfig);
  const RobotCalibration b = CalibrationFromProto(base, config.robot());
  const RobotCalibration a = CalibrationFromProto(tracked, config.robot());
  EXPECT_EQ(tracked.version(), base.version() + 1);
  EXPECT_EQ(tracked.offset_reestimation().rank(), 36u);
  EXPECT_GT(tracked.offset_reestimation().unloaded_leg_samples(), 30u);
  for (int k = 0; k < kNumLegs; ++k) {
    const Vec6 d = truth.at(std::string(kLegNames[k])).back().second;
    for (int i = 0; i < 6; ++i) {
      EXPECT_NEAR(a.leg[k].offset[i] - b.leg[k].offset[i], d[i],
                  i < 3 ? kForceBoundN : kTorqueBoundNm)
          << kLegNames[k] << " component " << i;
    }
    EXPECT_EQ(a.leg[k].weight_n, b.leg[k].weight_n);  // only the offsets change
  }
  EXPECT_NE(ReadFile(dir_ + "/drift.csv").find("utime,leg,status,d_fx_n"), std::string::npos);
}

// The demo's drift session: standing poses, then tripod stances with the offsets drifted (up to
// 3 N, 0.1 N*m) from the first frame. The lifted tripods are the windows; the bounds are the
// offline re-estimation's (offset_drift_test).
TEST_F(DriftReplayTest, TheDemosDriftSessionAgreesWithTheDriftedTruth) {
  const std::string log = dir_ + "/drift.lcmlog";
  ASSERT_EQ(Run({FTCAL_SIM,
                 "log",
                 "--config",
                 kConfig,
                 "--out",
                 log,
                 "--truth",
                 dir_ + "/truth.pbtxt",
                 "--seed",
                 "7",
                 "--com",
                 "leg-aware",
                 "--scenarios",
                 "stand,tripod",
                 "--poses",
                 "20",
                 "--tripod-stances",
                 "12",
                 "--drift-at-s",
                 "0"},
                "sim")
                .exit_code,
            0);
  const Result r =
      Run({FTCAL_DRIFT, "--config", kConfig, "--replay", log, "--out", dir_ + "/out.lcmlog",
           "--calibration", dir_ + "/truth.pbtxt", "--out-calibration", dir_ + "/tracked.pbtxt"},
          "drift");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const config::Config config = LoadConfigFile(kConfig);
  const RobotCalibration tracked =
      CalibrationFromProto(ReadCalibrationFile(dir_ + "/tracked.pbtxt"), config.robot());
  const RobotCalibration drifted =
      CalibrationFromProto(ReadCalibrationFile(dir_ + "/truth.drifted.pbtxt"), config.robot());
  const RobotCalibration before =
      CalibrationFromProto(ReadCalibrationFile(dir_ + "/truth.pbtxt"), config.robot());
  for (int k = 0; k < kNumLegs; ++k) {
    // The drift is real (so agreeing is not agreeing with the start)...
    EXPECT_GT((drifted.leg[k].offset - before.leg[k].offset).head<3>().cwiseAbs().maxCoeff(), 0.1);
    for (int i = 0; i < 6; ++i) {
      // ...and tracked within issue #3's bounds, as the offline re-estimation holds it.
      EXPECT_NEAR(tracked.leg[k].offset[i], drifted.leg[k].offset[i], i < 3 ? 0.02 : 0.001)
          << kLegNames[k] << " component " << i;
    }
  }
}

// --apply over a log (the same stage as live, its CALIBRATION into --out): a walk without
// drift publishes nothing (the tracked changes stay within the floor); a step on MR at 30 s and
// one on FL at 42 s, while every leg creeps by 0.15 N in the 90 s (not significant), publish
// MR's and FL's offsets only, after the first step, the calibrations at least
// drift.apply_min_interval_s (20 s) of the log apart (FL's waits for it), each numbered on, the
// last at the drifted truth.
std::vector<CalibrationMessage> ReadCalibrations(const std::string& path) {
  std::vector<CalibrationMessage> out;
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return out;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel != "CALIBRATION") continue;
    calibration_t m;
    EXPECT_FALSE(wire::Decode(e->data, e->datalen, &m).has_value());
    out.push_back(FromLcm(m));
  }
  return out;
}

TEST_F(DriftReplayTest, ApplyPublishesOnlySignificantChangesAtMostOncePerInterval) {
  std::string config_text = ReadFile(kConfig) + "\ndrift { apply_min_interval_s: 20 }\n";
  const std::string config = dir_ + "/config.pbtxt";
  std::ofstream(config) << config_text;
  const std::string calm = dir_ + "/calm.lcmlog";
  ASSERT_EQ(Run({FTCAL_SIM, "log", "--config", kConfig, "--out", calm, "--seed", "5", "--scenarios",
                 "walk", "--walk-s", "60"},
                "sim-calm")
                .exit_code,
            0);
  Result r =
      Run({FTCAL_DRIFT, "--config", config, "--replay", calm, "--out", dir_ + "/calm-out.lcmlog",
           "--calibration", dir_ + "/calm.truth.pbtxt", "--apply"},
          "drift-calm");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(ReadCalibrations(dir_ + "/calm-out.lcmlog").empty()) << r.err;

  const std::string log = dir_ + "/walk.lcmlog";
  ASSERT_EQ(
      Run({FTCAL_SIM, "log", "--config", kConfig, "--out", log, "--seed", "3", "--scenarios",
           "walk", "--walk-s", "90", "--drift-step", "MR:30:2,-2,2,0.05,-0.05,0.05", "--drift-step",
           "FL:42:-1.5,1,1.5,0.04,0.03,-0.04", "--drift-ramp", "all:0:600:1,-1,1,0.03,-0.03,0.03"},
          "sim")
          .exit_code,
      0);
  r = Run({FTCAL_DRIFT, "--config", config, "--replay", log, "--out", dir_ + "/out.lcmlog",
           "--calibration", dir_ + "/walk.truth.pbtxt", "--apply"},
          "drift");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const std::vector<CalibrationMessage> cals = ReadCalibrations(dir_ + "/out.lcmlog");
  ASSERT_GE(cals.size(), 2u) << r.err;
  const auto truth = ReadTruthCsv(dir_ + "/walk.drift.csv");
  const int64_t t0 = truth.at("HL").front().first;
  const config::Config cfg = LoadConfigFile(config);
  const calibration::Calibration base = ReadCalibrationFile(dir_ + "/walk.truth.pbtxt");
  const RobotCalibration b = CalibrationFromProto(base, cfg.robot());
  const int mr = *LegIndex("MR"), fl = *LegIndex("FL");
  for (size_t c = 0; c < cals.size(); ++c) {
    EXPECT_EQ(cals[c].version, static_cast<int64_t>(base.version() + 1 + c));
    EXPECT_GT(cals[c].utime, t0 + 30'000'000) << "calibration " << c << " before the step";
    if (c > 0) {
      EXPECT_GE(cals[c].utime - cals[c - 1].utime, 20'000'000) << "calibration " << c;
    }
    const RobotCalibration a = CalibrationFromProto(cals[c].proto, cfg.robot());
    for (int k = 0; k < kNumLegs; ++k) {
      if (k != mr && k != fl) {
        EXPECT_EQ(a.leg[k].offset, b.leg[k].offset) << kLegNames[k];
      }
    }
  }
  const RobotCalibration last = CalibrationFromProto(cals.back().proto, cfg.robot());
  for (const int k : {mr, fl}) {
    const Vec6 d = TruthAt(truth.at(std::string(kLegNames[k])), cals.back().utime);
    for (int i = 0; i < 6; ++i) {
      EXPECT_NEAR(last.leg[k].offset[i] - b.leg[k].offset[i], d[i],
                  i < 3 ? kForceBoundN : kTorqueBoundNm)
          << kLegNames[k] << " component " << i;
    }
  }
  for (const CalibrationMessage& c : cals) {
    std::printf("version %lld at %.1f s of the log: %s\n", static_cast<long long>(c.version),
                1e-6 * static_cast<double>(c.utime - t0),
                c.proto.warning(c.proto.warning_size() - 1).c_str());
  }
}

TEST_F(DriftReplayTest, ABadCalibrationIsRefusedNamingIt) {
  const std::string cal = dir_ + "/bad.pbtxt";
  std::ofstream(cal) << "robot_name: \"bigant\"\nleg { name: \"HL\" }\n";
  const std::string log = dir_ + "/empty.lcmlog";
  ASSERT_EQ(Run({FTCAL_SIM, "log", "--config", kConfig, "--out", log, "--scenarios", "walk",
                 "--walk-s", "1"},
                "sim")
                .exit_code,
            0);
  const Result r = Run({FTCAL_DRIFT, "--config", kConfig, "--replay", log, "--out",
                        dir_ + "/out.lcmlog", "--calibration", cal},
                       "bad");
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_NE(r.err.find("--calibration " + cal), std::string::npos) << r.err;
}

}  // namespace
}  // namespace ftcal
