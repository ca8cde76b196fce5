// ftcal-drift --apply on live LCM (issue #40): lcm-logplayer plays a walk ftcal-sim wrote with
// MR's offsets stepping 2 N / 0.05 N*m at 10 s into ftcal-drift --apply (signing with a key made
// here, the only key the config trusts on CALIBRATION; unsigned refused) and ftcal-corrector,
// both started with the twin's undrifted truth. The test waits for events only: both heartbeats
// before playing, then DRIFT until one covers the log's end. Then:
//  - ftcal-drift published signed calibrations, version + 1 each, none before the step (the
//    small changes of the undrifted legs are not significant), at most one per 5 s of the log
//    (drift.apply_min_interval_s), the last with MR's offsets at the twin's drifted truth and
//    every other leg's untouched;
//  - the corrector took it up (CONTACT_WRENCH_SUM's calibration_version);
//  - the balance residual with the calibration in use (DRIFT's untracked one, and the corrector's
//    CONTACT_WRENCH_SUM) rose with the step and fell back near its value before the step.
#include <sys/stat.h>
#include <sys/wait.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/messages.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/drift_t.hpp"
#include "ftcal/legs.h"
#include "ftcal/signed_envelope_t.hpp"
#include "signed_commander.h"
#include "test_helpers.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::ReadFile;

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0";
constexpr double kStepAtS = 10.0;
constexpr double kWalkS = 50.0;
constexpr double kStep[6] = {2, -2, 2, 0.05, -0.05, 0.05};
constexpr double kForceBoundN = 0.1;  // the issue's, for a walk (drift_replay_test)
constexpr double kTorqueBoundNm = 0.005;

class DriftApplyLiveTest : public testing::NetnsDirTest {};

struct Heard {
  std::vector<drift_t> drift;
  std::vector<contact_wrench_sum_t> sums;
  std::vector<signed_envelope_t> calibrations;
  void OnDrift(const lcm::ReceiveBuffer*, const std::string&, const drift_t* m) {
    drift.push_back(*m);
  }
  void OnSum(const lcm::ReceiveBuffer*, const std::string&, const contact_wrench_sum_t* m) {
    sums.push_back(*m);
  }
  void OnCalibration(const lcm::ReceiveBuffer*, const std::string&, const signed_envelope_t* m) {
    calibrations.push_back(*m);
  }
};

// rms of |residual force| over the corrector's sums made with calibration versions
// v_min..v_max, at instants in [from, to) and not flagged; -1 when there is none.
double SumForceRms(const std::vector<contact_wrench_sum_t>& sums, int64_t v_min, int64_t v_max,
                   int64_t from, int64_t to, int* count) {
  double sq = 0.0;
  int n = 0;
  for (const contact_wrench_sum_t& m : sums) {
    if (m.calibration_version < v_min || m.calibration_version > v_max) continue;
    for (int i = 0; i < m.n; ++i) {
      if (m.utime[i] < from || m.utime[i] >= to || m.flags[i] != 0) continue;
      const std::vector<double>& r = m.residual_w[i];
      sq += r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
      ++n;
    }
  }
  *count = n;
  return n > 0 ? std::sqrt(sq / n) : -1.0;
}

TEST_F(DriftApplyLiveTest, AStepIsAppliedAndTheCorrectorSwitchesBackToBalance) {
  const std::string log = Path("walk.lcmlog");
  char step[128];
  std::snprintf(step, sizeof step, "MR:%g:%g,%g,%g,%g,%g,%g", kStepAtS, kStep[0], kStep[1],
                kStep[2], kStep[3], kStep[4], kStep[5]);
  {
    Child sim({FTCAL_SIM, "log", "--config", kConfig, "--out", log, "--seed", "4", "--scenarios",
               "walk", "--walk-s", std::to_string(kWalkS), "--drift-step", step},
              Path("sim.out"), Path("sim.err"));
    const auto rc = sim.Wait(60);
    ASSERT_TRUE(rc && WIFEXITED(*rc) && WEXITSTATUS(*rc) == 0) << ReadFile(Path("sim.err"));
  }
  // The config: the twin's, with a key made here trusted on CALIBRATION and nothing unsigned
  // taken, and --apply's interval short enough for a 50 s walk.
  const std::string key = Path("drift.key");
  const std::string public_hex = testing::WriteKeyFile(key);
  std::string config_text = ReadFile(kConfig);
  const size_t allow = config_text.find("allow_unsigned: true");
  ASSERT_NE(allow, std::string::npos);
  config_text.replace(allow, 20, "allow_unsigned: false");
  config_text = testing::TrustKey(config_text, "drift", public_hex, {"CALIBRATION"});
  config_text += "\ndrift { apply_min_interval_s: 5 }\n";
  const std::string config = Path("config.pbtxt");
  std::ofstream(config) << config_text;
  for (const char* d : {"state-drift", "state-cor"}) ASSERT_EQ(::mkdir(Path(d).c_str(), 0700), 0);

  lcm::LCM lcm(kUrl);
  ASSERT_TRUE(lcm.good());
  Heard heard;
  lcm.subscribe("DRIFT", &Heard::OnDrift, &heard)->setQueueCapacity(10000);
  lcm.subscribe("CONTACT_WRENCH_SUM", &Heard::OnSum, &heard)->setQueueCapacity(100000);
  lcm.subscribe("CALIBRATION", &Heard::OnCalibration, &heard)->setQueueCapacity(100);

  const std::string truth_path = Path("walk.truth.pbtxt");
  Child drift({FTCAL_DRIFT, "--config", config, "--lcm-url", kUrl, "--calibration", truth_path,
               "--apply", "--signing-key", key, "--state-dir", Path("state-drift")},
              Path("drift.out"), Path("drift.err"));
  Child cor({FTCAL_CORRECTOR, "--config", config, "--lcm-url", kUrl, "--calibration", truth_path,
             "--state-dir", Path("state-cor")},
            Path("cor.out"), Path("cor.err"));
  // Subscribed and in their loops once they are heard.
  ASSERT_EQ(testing::AwaitHeartbeats(lcm, {drift.pid(), cor.pid()}, 30).size(), 2u)
      << ReadFile(Path("drift.err")) << ReadFile(Path("cor.err"));

  // The log's first and last sample times.
  int64_t first_utime = 0, last_utime = 0;
  {
    lcm::LogFile in(log, "r");
    ASSERT_TRUE(in.good());
    while (const lcm::LogEvent* e = in.readNextEvent()) {
      if (first_utime == 0) first_utime = e->timestamp;
      last_utime = e->timestamp;
    }
  }
  const auto at = [&](double s) { return first_utime + static_cast<int64_t>(s * 1e6); };
  const auto started = std::chrono::steady_clock::now();
  Child player({FTCAL_LCM_LOGPLAYER, "-s", "4", "-l", kUrl, log}, Path("player.out"),
               Path("player.err"));
  const auto until = started + std::chrono::seconds(60);
  auto covers_end = [&] {
    return !heard.drift.empty() && heard.drift.back().utime >= last_utime - 100'000;
  };
  while (!covers_end() && std::chrono::steady_clock::now() < until) lcm.handleTimeout(100);
  ASSERT_TRUE(covers_end()) << heard.drift.size() << " DRIFT heard\n"
                            << ReadFile(Path("drift.err"));
  const auto played = player.Wait(30);
  ASSERT_TRUE(played && WIFEXITED(*played) && WEXITSTATUS(*played) == 0)
      << ReadFile(Path("player.err"));
  // The corrector's last sums (it may trail the tracker's DRIFT by a few messages).
  const auto drain_until = std::chrono::steady_clock::now() + std::chrono::seconds(2);
  while (std::chrono::steady_clock::now() < drain_until) lcm.handleTimeout(50);
  std::printf("played and heard in %.1f s\n",
              std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count());
  testing::Terminate(drift, "ftcal-drift", Path("drift.err"));
  testing::Terminate(cor, "ftcal-corrector", Path("cor.err"));

  // What ftcal-drift published: each signed by its key, numbered on from the truth's version,
  // at most one per apply_min_interval_s (5 s) of the log's time, none before the step (the
  // undrifted legs' small changes are not significant), and only MR's offsets changed. A window
  // of MR's in the air across the step sees part of it (the window's mean): the next window
  // brings the rest, so two calibrations are right; the last one holds the drifted truth.
  ASSERT_FALSE(heard.calibrations.empty()) << ReadFile(Path("drift.err"));
  EXPECT_LE(heard.calibrations.size(), 3u);
  const config::Config cfg = LoadConfigFile(config);
  const calibration::Calibration truth_proto = ReadCalibrationFile(truth_path);
  const RobotCalibration truth = CalibrationFromProto(truth_proto, cfg.robot());
  const int64_t v0 = static_cast<int64_t>(truth_proto.version());
  const int mr = *LegIndex("MR");
  CalibrationMessage applied;
  int64_t previous_apply = 0;
  for (size_t c = 0; c < heard.calibrations.size(); ++c) {
    const signed_envelope_t& env = heard.calibrations[c];
    EXPECT_EQ(auth::ToHex(env.signer, sizeof env.signer), public_hex);
    calibration_t cal_msg;
    ASSERT_EQ(cal_msg.decode(env.payload.data(), 0, env.size), env.size);
    applied = FromLcm(cal_msg);
    EXPECT_EQ(applied.version, v0 + 1 + static_cast<int64_t>(c));
    ASSERT_GT(applied.proto.warning_size(), 0);
    const std::string& provenance = applied.proto.warning(applied.proto.warning_size() - 1);
    std::printf("calibration %lld: %s\n", static_cast<long long>(applied.version),
                provenance.c_str());
    EXPECT_NE(provenance.find(" MR from "), std::string::npos) << provenance;
    const size_t at_pos = provenance.find("at utime ");
    ASSERT_NE(at_pos, std::string::npos) << provenance;
    const int64_t apply_utime = std::stoll(provenance.substr(at_pos + 9));
    EXPECT_GT(apply_utime, at(kStepAtS)) << "applied before the step";
    if (previous_apply > 0) {
      EXPECT_GE(apply_utime - previous_apply, 5'000'000);
    }
    previous_apply = apply_utime;
  }
  const RobotCalibration got = CalibrationFromProto(applied.proto, cfg.robot());
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      if (k == mr) {
        EXPECT_NEAR(got.leg[k].offset[i] - truth.leg[k].offset[i], kStep[i],
                    i < 3 ? kForceBoundN : kTorqueBoundNm)
            << "MR component " << i;
      } else {
        EXPECT_EQ(got.leg[k].offset[i], truth.leg[k].offset[i]) << kLegNames[k] << " " << i;
      }
    }
    EXPECT_EQ(got.leg[k].weight_n, truth.leg[k].weight_n);  // only the offsets
  }
  const int64_t version = applied.version;

  // When the last one came into use in the tracker (its first DRIFT); the tracker and the
  // corrector end on it.
  int64_t applied_utime = 0;
  for (const drift_t& m : heard.drift) {
    if (m.calibration_version == version) {
      applied_utime = m.utime;
      break;
    }
  }
  ASSERT_GT(applied_utime, 0);
  EXPECT_EQ(heard.drift.back().calibration_version, version);
  ASSERT_FALSE(heard.sums.empty());
  EXPECT_EQ(heard.sums.back().calibration_version, version);

  // DRIFT's balance with the calibration in use ([0]): before the step, between the step and
  // the last calibration (a message covers the 4 s of log before it: from 4 s after the step),
  // and from 5 s after the last calibration to the end.
  auto balance = [&](int64_t from, int64_t to, int64_t v_min, int64_t v_max) {
    double worst = 0.0, sum = 0.0;
    int n = 0;
    for (const drift_t& m : heard.drift) {
      if (m.utime < from || m.utime >= to) continue;
      if (m.calibration_version < v_min || m.calibration_version > v_max) continue;
      if (m.balance_samples < 20 || !std::isfinite(m.balance_force_rms_n[0])) continue;
      worst = std::max(worst, m.balance_force_rms_n[0]);
      sum += m.balance_force_rms_n[0];
      ++n;
    }
    return std::make_tuple(n, n > 0 ? sum / n : -1.0, worst);
  };
  const auto [n_before, mean_before, worst_before] = balance(at(2), at(kStepAtS), v0, v0);
  const auto [n_stepped, mean_stepped, worst_stepped] =
      balance(at(kStepAtS + 4), applied_utime, v0, version - 1);
  const auto [n_after, mean_after, worst_after] =
      balance(applied_utime + 5'000'000, last_utime + 1, version, version);
  std::printf(
      "DRIFT balance force rms (calibration in use): before the step %.3f N (max %.3f, %d), "
      "stepped %.3f N (max %.3f, %d), applied %.3f N (max %.3f, %d); applied %.1f s after the "
      "step (the last)\n",
      mean_before, worst_before, n_before, mean_stepped, worst_stepped, n_stepped, mean_after,
      worst_after, n_after, 1e-6 * static_cast<double>(applied_utime - at(kStepAtS)));
  ASSERT_GT(n_before, 0);
  ASSERT_GT(n_stepped, 0);
  ASSERT_GT(n_after, 0);
  // The step moves the balance by 2-3 N, a half step (a window across it) by half that; back within
  // 0.2 N of the undrifted walk's once the last calibration is in use.
  EXPECT_GT(mean_stepped, mean_before + 1.0);
  EXPECT_LT(worst_after, mean_before + 0.2);

  // The corrector's own output, the sums' residual force over the same spans.
  int c_before = 0, c_stepped = 0, c_after = 0;
  const double r_before = SumForceRms(heard.sums, v0, v0, at(2), at(kStepAtS), &c_before);
  const double r_stepped =
      SumForceRms(heard.sums, v0, version - 1, at(kStepAtS + 1), applied_utime, &c_stepped);
  const double r_after = SumForceRms(heard.sums, version, version, applied_utime + 5'000'000,
                                     last_utime + 1, &c_after);
  std::printf(
      "CONTACT_WRENCH_SUM residual force rms: before the step %.3f N (%d sums), stepped %.3f N "
      "(%d), applied %.3f N (%d)\n",
      r_before, c_before, r_stepped, c_stepped, r_after, c_after);
  ASSERT_GT(c_before, 100);
  ASSERT_GT(c_stepped, 100);
  ASSERT_GT(c_after, 100);
  EXPECT_GT(r_stepped, r_before + 1.0);
  EXPECT_LT(r_after, r_before + 0.2);
}

}  // namespace
}  // namespace ftcal
