// Issue #5, end to end on the twin, with the real executables:
//   ftcal-sim log (hanging series + all 729 standing poses)  -> session.lcmlog, truth.pbtxt
//   ftcal-sim log --scenarios walk (same seed: the same twin) -> walk.lcmlog
//   ftcal-calibrator --log session.lcmlog                    -> cal.pbtxt
//   ftcal-corrector --replay walk.lcmlog, three times: with cal.pbtxt, with the truth file and
//   with the naive tare (the baseline libcal defines: offsets = the upright hanging reading near
//   theta = 0 as cal.pbtxt records it, no leg gravity model, nominal mounting, CoM at B).
// Checked against independent truth:
//   - the twin regenerated in this process with the same seed and options reproduces the walk
//     log's transducer readings to the last bit (so its ground wrenches are the truth of that
//     log), and both sim runs wrote the same truth file;
//   - cal.pbtxt meets the method issue's recovery bounds against the truth;
//   - over the standing poses the calibration leaves a total-wrench residual within 1.2x the one
//     the true parameters leave;
//   - on the walk, the corrected per-leg and total wrenches sit at the noise floor (the error the
//     TRUE parameters leave through the same corrector: reading, attitude and servo noise plus the
//     corrector's hold of the last servo state) and the naive tare is clearly worse.
// Twin: the default one (CoM fixed at C, the report's assumption) with ftcal's exact hanging
// rotations and hanging gravity prior switched on (config/sim.pbtxt otherwise): the report's
// first-order rotations bias the leg weights by up to ~0.02 N (recovery_test), beyond the
// 0.015 N bound, and without the prior the common yaw of the mounting rotations is loose by
// ~0.17°; leg-aware CoM is off because this twin's CoM does not move.
// The logs are large (~1 GB): everything goes to a temporary directory removed at the end
// (FTCAL_TEST_KEEP=1 keeps it). All tests share one run of the pipeline, so the binary runs as
// one ctest test (pipeline_e2e_test.cmake), not one process per TEST.
#include <sys/wait.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <google/protobuf/text_format.h>
#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "child_process.h"
#include "common/messages.h"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/standing.h"
#include "sim/log_writer.h"
#include "twin_calibration.h"
#include "twin_log.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;
using namespace testing_twin;  // NOLINT
using twin_log::ReadChannel;
using twin_log::ReadFtRecords;
using twin_log::ReadLegWrenches;
using twin_log::ReadWrenchSums;

constexpr uint64_t kSeed = 1;
constexpr int kAllPoses = 729;
const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";

// Recovery bounds (method issue #3).
constexpr double kWeightBoundN = 0.015;
constexpr double kForceOffsetBoundN = 0.02;
constexpr double kTorqueOffsetBoundNm = 0.001;
constexpr double kComCurveBoundM = 0.2e-3;
constexpr double kRotationBoundDeg = 0.15;
constexpr double kPTildePrimeBoundM = 0.5e-3;
constexpr double kResidualRatioBound = 1.2;
// Walking: the estimated calibration's rms errors within this factor of the floor (the same as
// the standing residual's bound: the calibration adds its own estimation error, which the
// recovery bounds keep small beside the per-sample noise).
constexpr double kFloorRatioBound = 1.2;
// The naive tare must be worse than the floor by at least this factor (per-leg mean force and
// torque rms, total force and torque rms). Not tuned: the naive model misses the mounting tilt
// (1-3 deg of a ~13 N load: 0.2-0.7 N), the leg gravity as the leg swings (a ~6 N leg whose CoM
// moves by centimetres: ~0.1 N*m) and the 1 cm from B to the CoM (~0.1 N*m per leg), each far
// above a floor of ~0.1 N / ~0.01 N*m.
constexpr double kNaiveMarginFactor = 2.0;

double Seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

// rms of the per-axis errors of a set of 3-vectors.
struct Rms3 {
  double sum_sq = 0.0;
  int64_t n = 0;
  void Add(const Vec3& e) {
    sum_sq += e.squaredNorm();
    n += 3;
  }
  double Value() const { return n ? std::sqrt(sum_sq / static_cast<double>(n)) : NAN; }
};

// Corrected walking wrenches of one calibration against the twin's true ground wrenches.
struct WalkErrors {
  std::array<Rms3, kNumLegs> leg_force, leg_torque;
  Rms3 total_force, total_torque;
  int64_t leg_samples = 0, frames_with_total = 0, flagged = 0, outputs = 0;
  double MeanLegForce() const {
    double s = 0;
    for (const Rms3& r : leg_force) s += r.Value();
    return s / kNumLegs;
  }
  double MeanLegTorque() const {
    double s = 0;
    for (const Rms3& r : leg_torque) s += r.Value();
    return s / kNumLegs;
  }
};

struct Pipeline {
  std::string dir;
  bool keep = false;
  config::Config config;
  std::unique_ptr<BigAntTwin> twin;
  std::vector<TwinFrame> walk;      // the regenerated walk, frame i = rdt_sequence i + 1
  std::vector<StandingPose> poses;  // the regenerated steady standing poses
  std::string walk_log, truth_path, walk_truth_path, cal_path, truth_cal_path, naive_cal_path;
  std::string ftcal_config_path;
  calibration::Calibration cal;
  std::map<std::string, std::string> wrench_logs;  // "estimated", "truth", "naive"
  bool ok = false;
};
Pipeline* px = nullptr;

// Runs a program to completion; fails (fatally for the caller) with its stderr otherwise.
void RunProgram(const std::vector<std::string>& argv, const std::string& tag, double timeout_s) {
  const auto started = std::chrono::steady_clock::now();
  const std::string out = px->dir + "/" + tag + ".out", err = px->dir + "/" + tag + ".err";
  Child child(argv, out, err);
  const auto status = child.Wait(timeout_s);
  ASSERT_TRUE(status.has_value()) << tag << " did not finish in " << timeout_s << " s";
  ASSERT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << tag << ": " << DescribeWaitStatus(*status) << "\n"
      << ReadFile(err);
  std::printf("pipeline_e2e: %s took %.1f s\n", tag.c_str(), Seconds(started));
}

// The naive-tare baseline as a calibration file the corrector can use (see the header).
calibration::Calibration NaiveCalibration(const calibration::Calibration& cal) {
  calibration::Calibration naive;
  naive.set_robot_name(cal.robot_name());
  naive.set_g0_m_s2(cal.g0_m_s2());
  naive.set_total_mass_kg(cal.total_mass_kg());
  naive.set_version(cal.version() + 1000);
  for (const calibration::LegCalibration& leg : cal.leg()) {
    if (leg.naive_offset_size() != 6) {
      throw std::runtime_error("cal.pbtxt: leg " + leg.name() + " has " +
                               std::to_string(leg.naive_offset_size()) + " naive_offset entries");
    }
    calibration::LegCalibration* l = naive.add_leg();
    l->set_name(leg.name());
    l->mutable_force_offset_n()->set_x(leg.naive_offset(0));
    l->mutable_force_offset_n()->set_y(leg.naive_offset(1));
    l->mutable_force_offset_n()->set_z(leg.naive_offset(2));
    l->mutable_torque_offset_nm()->set_x(leg.naive_offset(3));
    l->mutable_torque_offset_nm()->set_y(leg.naive_offset(4));
    l->mutable_torque_offset_nm()->set_z(leg.naive_offset(5));
    l->mutable_leg_weight_n()->set_value(0.0);  // no leg gravity model
    for (calibration::SinusoidFit* s :
         {l->mutable_com()->mutable_x(), l->mutable_com()->mutable_z()}) {
      s->set_a_m(0.0);
      s->set_c_rad(0.0);
      s->set_d_m(0.0);
    }
    l->mutable_com()->mutable_y_m()->set_value(0.0);
    calibration::Mounting* m = l->mutable_mounting();  // nominal: R~ = I, p~' = 0 (CoM at B)
    for (double q : {1.0, 0.0, 0.0, 0.0}) m->add_quaternion_wxyz(q);
    m->mutable_p_tilde_prime_m()->set_x(0.0);
    m->mutable_p_tilde_prime_m()->set_y(0.0);
    m->mutable_p_tilde_prime_m()->set_z(0.0);
  }
  return naive;
}

class PipelineE2e : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    px = new Pipeline;
    px->dir = testing::MakeTempDir();
    const char* keep = std::getenv("FTCAL_TEST_KEEP");
    px->keep = keep && *keep && std::string(keep) != "0";
    px->config = LoadConfigFile(kConfig);
    Build();
    if (::testing::Test::HasFatalFailure()) return;
    px->ok = true;
  }

  static void Build() {
    const auto started = std::chrono::steady_clock::now();
    const std::string& d = px->dir;
    config::Config ftcal_config = px->config;
    // ftcal's method (README, scripts/demo): exact hanging rotations and the hanging gravity
    // prior, which pins the common yaw the standing poses alone leave ~0.17° loose.
    ftcal_config.mutable_calibrator()->set_exact_hanging_rotations(true);
    ftcal_config.mutable_calibrator()->set_hanging_gravity_prior(true);
    std::string text;
    ASSERT_TRUE(google::protobuf::TextFormat::PrintToString(ftcal_config, &text));
    px->ftcal_config_path = d + "/sim-exact.pbtxt";
    WriteFileAtomic(px->ftcal_config_path, text);

    const std::string session = d + "/session.lcmlog";
    px->walk_log = d + "/walk.lcmlog";
    px->truth_path = d + "/truth.pbtxt";
    px->walk_truth_path = d + "/walk.truth.pbtxt";
    px->cal_path = d + "/cal.pbtxt";
    const std::string seed = std::to_string(kSeed);
    // The truth: the same twin in this process (the seed and the options ftcal-sim log uses by
    // default), generated on a thread while the programs run: the walk from t = 0 for
    // ftcal-sim log's default --walk-s, as `--scenarios walk` runs it (WriteExperiment starts
    // the first scenario at twin time 0), and the steady standing poses.
    TwinOptions options;
    options.seed = kSeed;
    px->twin = std::make_unique<BigAntTwin>(px->config, options);
    std::thread truth_thread([] {
      px->twin->TripodWalk(ExperimentPlan().walk_s, RunOptions{},
                           [](const TwinFrame& f) { px->walk.push_back(f); });
      px->poses = px->twin->MakeSteadyPoses(kAllPoses);
    });
    // Joined on every path out, also when an ASSERT returns early.
    struct Joiner {
      std::thread& t;
      ~Joiner() {
        if (t.joinable()) t.join();
      }
    } joiner{truth_thread};
    // The walk's log is independent of the calibration: write it while the calibrator works.
    Child walk_sim({FTCAL_SIM, "log", "--config", kConfig, "--out", px->walk_log, "--truth",
                    px->walk_truth_path, "--seed", seed, "--scenarios", "walk"},
                   d + "/sim_walk.out", d + "/sim_walk.err");
    RunProgram({FTCAL_SIM, "log", "--config", kConfig, "--out", session, "--truth", px->truth_path,
                "--seed", seed, "--scenarios", "hang,stand"},
               "sim_session", 300);
    if (HasFatalFailure()) return;
    RunProgram({FTCAL_CALIBRATOR, "--config", px->ftcal_config_path, "--log", session, "--out",
                px->cal_path},
               "calibrator", 300);
    if (!px->keep) std::remove(session.c_str());
    if (HasFatalFailure()) return;
    const auto walk_status = walk_sim.Wait(300);
    ASSERT_TRUE(walk_status && WIFEXITED(*walk_status) && WEXITSTATUS(*walk_status) == 0)
        << "sim_walk: " << ReadFile(d + "/sim_walk.err");

    px->cal = ReadCalibrationFile(px->cal_path);
    calibration::Calibration truth = ReadCalibrationFile(px->truth_path);
    truth.set_version(px->cal.version() + 2000);
    px->truth_cal_path = d + "/truth-for-corrector.pbtxt";
    WriteCalibrationFile(truth, px->truth_cal_path);
    px->naive_cal_path = d + "/naive.pbtxt";
    WriteCalibrationFile(NaiveCalibration(px->cal), px->naive_cal_path);

    // Three correctors over the walk, two at a time (two cores).
    const std::vector<std::pair<std::string, std::string>> runs = {
        {"estimated", px->cal_path}, {"truth", px->truth_cal_path}, {"naive", px->naive_cal_path}};
    for (const auto& [name, cal] : runs) px->wrench_logs[name] = d + "/wrench-" + name + ".lcmlog";
    auto argv = [&](const std::string& name, const std::string& cal) {
      return std::vector<std::string>{FTCAL_CORRECTOR, "--config", px->ftcal_config_path,
                                      "--calibration", cal,        "--replay",
                                      px->walk_log,    "--out",    px->wrench_logs[name]};
    };
    {
      Child a(argv(runs[0].first, runs[0].second), d + "/corrector-estimated.out",
              d + "/corrector-estimated.err");
      RunProgram(argv(runs[1].first, runs[1].second), "corrector-truth", 300);
      const auto status = a.Wait(300);
      ASSERT_TRUE(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
          << "corrector-estimated: " << ReadFile(d + "/corrector-estimated.err");
    }
    RunProgram(argv(runs[2].first, runs[2].second), "corrector-naive", 300);
    if (HasFatalFailure()) return;

    truth_thread.join();
    std::printf("pipeline_e2e: pipeline and twin ready in %.1f s (%zu walking frames)\n",
                Seconds(started), px->walk.size());
  }

  static void TearDownTestSuite() {
    if (px->keep) {
      std::printf("pipeline_e2e: kept %s\n", px->dir.c_str());
    } else {
      testing::RemoveTree(px->dir);
    }
    delete px;
    px = nullptr;
  }

  void SetUp() override { ASSERT_TRUE(px && px->ok) << "the pipeline did not run (see above)"; }

  // Errors of one corrector run against the regenerated twin's true ground wrenches (W axes,
  // about C: contact_wrench_t's frame; the twin's CoM is C).
  static WalkErrors Compare(const std::string& name) {
    const auto& ch = px->config.channels();
    // (leg, utime) of every FT sample -> its frame, from the walk log itself (rdt_sequence).
    std::array<std::map<int64_t, int64_t>, kNumLegs> frame_of;
    for (int k = 0; k < kNumLegs; ++k) {
      for (const FtRecord& r :
           ReadFtRecords(px->walk_log, ch.ft_prefix() + std::string(kLegNames[k]), k)) {
        frame_of[k][r.in.utime] = r.rdt_sequence - 1;
      }
    }
    WalkErrors e;
    for (const LegWrench& m : ReadLegWrenches(px->wrench_logs.at(name), ch.contact_wrench())) {
      ++e.outputs;
      const int k = m.leg;
      EXPECT_TRUE(k >= 0 && k < kNumLegs) << name;
      if (k < 0 || k >= kNumLegs) continue;
      const auto it = frame_of[k].find(m.utime);
      EXPECT_NE(it, frame_of[k].end())
          << name << ": no FT sample of leg " << k << " at " << m.utime;
      if (it == frame_of[k].end()) continue;
      const int64_t i = it->second;
      // The first frame comes before any servo state or mocap frame: flagged, not compared.
      if (m.flags != 0) {
        ++e.flagged;
        continue;
      }
      const TwinFrame& f = px->walk[static_cast<size_t>(i)];
      const Pose3 X_W_C(f.R_WC, Vec3::Zero());
      const Vec6 truth = TransformWrench(X_W_C, f.ground_w_C[k]);
      Vec6 got;
      for (int a = 0; a < 6; ++a) got[a] = m.wrench_W[a];
      e.leg_force[k].Add(got.head<3>() - truth.head<3>());
      e.leg_torque[k].Add(got.tail<3>() - truth.tail<3>());
      ++e.leg_samples;
    }
    // The first sum whose six legs all carry frame i's samples (each leg's sample nearest the
    // sum's instant, as the corrector takes them, is of frame i): its total is frame i's.
    int64_t last_total_frame = -1;
    for (const WrenchSum& s : ReadWrenchSums(px->wrench_logs.at(name), ch.contact_wrench_sum())) {
      if (s.flags != 0) continue;  // stale or saturated inputs: flagged, not compared
      int64_t i = -1;
      bool one_frame = true;
      for (int k = 0; k < kNumLegs && one_frame; ++k) {
        if (frame_of[k].empty()) {
          one_frame = false;
          break;
        }
        auto it = frame_of[k].lower_bound(s.utime);
        if (it == frame_of[k].end() ||
            (it != frame_of[k].begin() && s.utime - std::prev(it)->first <= it->first - s.utime)) {
          --it;
        }
        const int64_t j = it->second;
        if (i < 0) i = j;
        one_frame = j == i;
      }
      if (!one_frame || i == last_total_frame) continue;
      last_total_frame = i;
      const TwinFrame& f = px->walk[static_cast<size_t>(i)];
      const Pose3 X_W_C(f.R_WC, Vec3::Zero());
      Vec6 total_truth = Vec6::Zero();
      for (int l = 0; l < kNumLegs; ++l) total_truth += TransformWrench(X_W_C, f.ground_w_C[l]);
      Vec6 total;
      for (int a = 0; a < 6; ++a) total[a] = s.total_W[a];
      e.total_force.Add(total.head<3>() - total_truth.head<3>());
      e.total_torque.Add(total.tail<3>() - total_truth.tail<3>());
      ++e.frames_with_total;
    }
    return e;
  }
};

TEST_F(PipelineE2e, TheRegeneratedTwinIsTheLogsTwinToTheLastBit) {
  // Both sim runs (same seed) wrote the same truth, and it is the regenerated twin's.
  EXPECT_EQ(ReadFile(px->truth_path), ReadFile(px->walk_truth_path));
  const RobotCalibration file_truth =
      CalibrationFromProto(ReadCalibrationFile(px->truth_path), px->config.robot());
  const RobotCalibration& truth = px->twin->Truth();
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_EQ(file_truth.leg[k].offset, truth.leg[k].offset) << "leg " << k;
    EXPECT_EQ(file_truth.leg[k].weight_n, truth.leg[k].weight_n) << "leg " << k;
    EXPECT_LT((file_truth.leg[k].R_tilde - truth.leg[k].R_tilde).norm(), 1e-12) << "leg " << k;
    EXPECT_LT((file_truth.leg[k].p_tilde_prime - truth.leg[k].p_tilde_prime).norm(), 1e-15)
        << "leg " << k;
  }
  // Every transducer sample of the walk log equals the regenerated reading, bit for bit.
  const auto& ch = px->config.channels();
  int64_t compared = 0, differ = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    size_t records = 0;
    for (const ft_batch_t& m :
         ReadChannel<ft_batch_t>(px->walk_log, ch.ft_prefix() + std::string(kLegNames[k]))) {
      for (size_t r = 0; r < static_cast<size_t>(m.n); ++r, ++records) {
        const TwinFrame& f = px->walk[static_cast<size_t>(m.rdt_sequence[r] - 1)];
        for (size_t a = 0; a < 6; ++a) {
          const double expected = f.reading[k][static_cast<int>(a)];
          if (std::memcmp(&m.wrench[r][a], &expected, sizeof(double)) != 0 ||
              m.counts[r][a] != f.counts[k][a]) {
            if (++differ <= 5) {
              ADD_FAILURE() << "leg " << k << " sample " << m.rdt_sequence[r] << " axis " << a
                            << ": log " << m.wrench[r][a] << " regenerated " << expected;
            }
          }
          ++compared;
        }
      }
    }
    ASSERT_EQ(records, px->walk.size()) << "leg " << k;
  }
  EXPECT_EQ(differ, 0);
  std::printf("pipeline_e2e: %lld walk readings compared with the regenerated twin, %lld differ\n",
              static_cast<long long>(compared), static_cast<long long>(differ));
}

TEST_F(PipelineE2e, CalibrationFromTheLogMeetsTheRecoveryBounds) {
  const RobotCalibration est = CalibrationFromProto(px->cal, px->config.robot());
  const RobotCalibration& truth = px->twin->Truth();
  EXPECT_EQ(px->cal.model(), calibration::FULL) << "the twin has every mounting error";
  double weight = 0, force = 0, torque = 0, com = 0, rot = 0, pp = 0;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& e = est.leg[k];
    const LegCalibration& t = truth.leg[k];
    const double leg_rot = RotationErrorDeg(e.R_tilde, t.R_tilde).norm();
    const double leg_pp = (e.p_tilde_prime - t.p_tilde_prime).norm();
    std::printf(
        "pipeline_e2e: leg %s: weight %+.5f N, force offset max %.5f N, torque offset max "
        "%.6f N*m, CoM curve %.4f mm, rotation %.4f deg, p~' %.4f mm\n",
        std::string(kLegNames[k]).c_str(), e.weight_n - t.weight_n,
        (e.offset.head<3>() - t.offset.head<3>()).cwiseAbs().maxCoeff(),
        (e.offset.tail<3>() - t.offset.tail<3>()).cwiseAbs().maxCoeff(),
        MaxCurveDistance(e.com, t.com) * 1e3, leg_rot, leg_pp * 1e3);
    weight = std::max(weight, std::abs(e.weight_n - t.weight_n));
    force = std::max(force, (e.offset.head<3>() - t.offset.head<3>()).cwiseAbs().maxCoeff());
    torque = std::max(torque, (e.offset.tail<3>() - t.offset.tail<3>()).cwiseAbs().maxCoeff());
    com = std::max(com, MaxCurveDistance(e.com, t.com));
    rot = std::max(rot, leg_rot);
    pp = std::max(pp, leg_pp);
  }
  std::printf(
      "pipeline_e2e: cal.pbtxt vs truth, largest errors: leg weight %.5f N (bound %.3f), "
      "force offsets %.5f N (%.2f), torque offsets %.6f N*m (%.3f), CoM curve %.4f mm "
      "(%.1f), mounting rotations %.4f deg (%.2f), p~' %.4f mm (%.1f)\n",
      weight, kWeightBoundN, force, kForceOffsetBoundN, torque, kTorqueOffsetBoundNm, com * 1e3,
      kComCurveBoundM * 1e3, rot, kRotationBoundDeg, pp * 1e3, kPTildePrimeBoundM * 1e3);
  EXPECT_LE(weight, kWeightBoundN);
  EXPECT_LE(force, kForceOffsetBoundN);
  EXPECT_LE(torque, kTorqueOffsetBoundNm);
  EXPECT_LE(com, kComCurveBoundM);
  EXPECT_LE(rot, kRotationBoundDeg);
  EXPECT_LE(pp, kPTildePrimeBoundM);
}

TEST_F(PipelineE2e, StandingResidualWithinTheBoundOfTheTrueParameters) {
  // The same residual for both parameter sets, on the twin's own steady poses (medians of the
  // steady parts; the calibrator segmented the log itself, so its poses differ slightly).
  const std::vector<StandingPose>& poses = px->poses;
  ASSERT_GT(poses.size(), 600u);
  const RobotCalibration est = CalibrationFromProto(px->cal, px->config.robot());
  const Vec6 k = StandingOptionsFromConfig(px->config.calibrator()).k_weights;
  auto rms = [&](const RobotCalibration& cal) {
    return std::sqrt(WeightedRss(TotalWrenchResiduals(cal, poses, false), k) /
                     static_cast<double>(poses.size()));
  };
  const double truth_rms = rms(px->twin->Truth()), est_rms = rms(est);
  std::printf(
      "pipeline_e2e: %zu standing poses, K-weighted rms total-wrench residual: true "
      "parameters %.5f, cal.pbtxt %.5f (ratio %.3f, bound %.1f)\n",
      poses.size(), truth_rms, est_rms, est_rms / truth_rms, kResidualRatioBound);
  EXPECT_LE(est_rms, kResidualRatioBound * truth_rms);
}

TEST_F(PipelineE2e, WalkingWrenchesSitAtTheNoiseFloorAndTheNaiveTareIsWorse) {
  std::map<std::string, WalkErrors> by;
  for (const char* name : {"truth", "estimated", "naive"}) by[name] = Compare(name);
  const int64_t expected_outputs = static_cast<int64_t>(px->walk.size()) * kNumLegs;
  for (const auto& [name, e] : by) {
    EXPECT_EQ(e.outputs, expected_outputs) << name << ": one output per transducer sample";
    // Only the first frame (before any servo state or mocap frame) may be flagged.
    EXPECT_LE(e.flagged, kNumLegs) << name;
    // A total for every frame but the first (flagged) and the last: a sum at the pace leg's
    // last instant waits for a sample at or after it from the legs whose transducers stamp
    // earlier, and the log ends first.
    EXPECT_GE(e.frames_with_total, static_cast<int64_t>(px->walk.size()) - 2) << name;
    std::printf(
        "pipeline_e2e: walk, %-9s %lld leg samples, %lld frame totals; rms error per leg "
        "force [N] / torque [N*m]:",
        name.c_str(), static_cast<long long>(e.leg_samples),
        static_cast<long long>(e.frames_with_total));
    for (int k = 0; k < kNumLegs; ++k) {
      std::printf(" %s %.4f/%.5f", std::string(kLegNames[k]).c_str(), e.leg_force[k].Value(),
                  e.leg_torque[k].Value());
    }
    std::printf("; mean %.4f N / %.5f N*m; total %.4f N / %.5f N*m\n", e.MeanLegForce(),
                e.MeanLegTorque(), e.total_force.Value(), e.total_torque.Value());
  }
  const WalkErrors& floor = by["truth"];
  const WalkErrors& est = by["estimated"];
  const WalkErrors& naive = by["naive"];
  // The floor is noise, not zero: an error this small would mean the truth leaked into the
  // readings' path (reading noise alone is 0.05 N per axis).
  EXPECT_GT(floor.MeanLegForce(), 0.03);
  std::printf(
      "pipeline_e2e: walk, ratio to the floor (estimated | naive): mean leg force %.3f | "
      "%.2f, mean leg torque %.3f | %.2f, total force %.3f | %.2f, total torque %.3f | "
      "%.2f (bound %.1f | at least %.1f)\n",
      est.MeanLegForce() / floor.MeanLegForce(), naive.MeanLegForce() / floor.MeanLegForce(),
      est.MeanLegTorque() / floor.MeanLegTorque(), naive.MeanLegTorque() / floor.MeanLegTorque(),
      est.total_force.Value() / floor.total_force.Value(),
      naive.total_force.Value() / floor.total_force.Value(),
      est.total_torque.Value() / floor.total_torque.Value(),
      naive.total_torque.Value() / floor.total_torque.Value(), kFloorRatioBound,
      kNaiveMarginFactor);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_LE(est.leg_force[k].Value(), kFloorRatioBound * floor.leg_force[k].Value())
        << kLegNames[k];
    EXPECT_LE(est.leg_torque[k].Value(), kFloorRatioBound * floor.leg_torque[k].Value())
        << kLegNames[k];
  }
  EXPECT_LE(est.total_force.Value(), kFloorRatioBound * floor.total_force.Value());
  EXPECT_LE(est.total_torque.Value(), kFloorRatioBound * floor.total_torque.Value());
  EXPECT_GE(naive.MeanLegForce(), kNaiveMarginFactor * floor.MeanLegForce());
  EXPECT_GE(naive.MeanLegTorque(), kNaiveMarginFactor * floor.MeanLegTorque());
  EXPECT_GE(naive.total_force.Value(), kNaiveMarginFactor * floor.total_force.Value());
  EXPECT_GE(naive.total_torque.Value(), kNaiveMarginFactor * floor.total_torque.Value());
}

}  // namespace
}  // namespace ftcal
