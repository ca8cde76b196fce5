// The whole chain live against the same chain replayed (issue #5): inside this network namespace
// (scripts/netns-exec runs the binary) lcm-logplayer plays a short twin session sped up while
// ftcal-pose-segmenter, ftcal-calibrator (live) and ftcal-corrector run on LCM and lcm-logger
// records; then the same input goes through --replay / --log. The recorded STEADY_POSEs, the
// calibration and the CONTACT_WRENCHes must be what the replays give. And ftcal-corrector
// SIGKILLed mid-play and started again corrupts nothing and, once its inputs are back, gives the
// replay's outputs.
//
// "Same inputs" for a CONTACT_WRENCH is read off the message itself: its input ages (ft_age_s
// per leg, servo_age_s, mocap_age_s) are utime minus the stamps of the inputs it used, computed
// the same way live and on replay, so equal ages mean the same input samples. A live output whose
// inputs differ from the replay's for the same (utime, leg) (a datagram reordered or lost on the
// way, or a restarted process) is counted, never silently compared as different numbers.
#include <signal.h>
#include <sys/wait.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <memory>
#include <thread>
#include <utility>
#include <vector>

#include <google/protobuf/util/field_comparator.h>
#include <google/protobuf/util/message_differencer.h>
#include <gtest/gtest.h>

#include <spdlog/spdlog.h>

#include "calibrator/calibrator.h"
#include "child_process.h"
#include "test_helpers.h"
#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/service_stats.h"
#include <lcm/lcm-cpp.hpp>

#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "pose_segmenter/pose_segmenter_stage.h"
#include "twin_log.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;
using namespace twin_log;

// The largest receive buffer the kernel allows (net.core.rmem_max, 4 MiB here): at 6x, with
// the machine busy, LCM's default 200 KiB overflows now and then and the recorder loses datagrams.
constexpr char kUrl[] = "udpm://239.255.76.67:7667?ttl=0&recv_buf_size=4194304";
const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
const std::string kSession = "pipeline-live-test";
// 30 poses is the config's min_poses; two more in case the segmenter drops a short one.
constexpr int kPoses = 32;
constexpr double kWalkS = 20.0;  // after STANDING: the corrector's data once calibrated
constexpr char kSpeed[] = "4";   // lcm-logplayer -s: about 190 s of robot time in ~48 s

struct Fixture {
  std::string dir;
  config::Config config;
  std::unique_ptr<BigAntTwin> twin;
  std::vector<Event> events;
  size_t standing_stop = 0;  // index of the STANDING stop marker in events
  std::string log;
  std::string truth;
};
Fixture* fx = nullptr;

class PipelineLiveTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    fx = new Fixture;
    fx->dir = testing::MakeTempDir();
    fx->config = LoadConfigFile(kConfig);
    TwinOptions opt;
    opt.seed = 31;
    opt.marker_dropout_rate_hz = 0.0;
    // As short as the method allows (calibrator_test's reasoning): three leg cycles per series
    // (two are the minimum, and the sampled phase may end just short of the second), poses
    // steady for about 1.9 s after settling (the segmenter needs 1.5 s).
    opt.hang_cycles = 3;
    opt.hang_cycle_s = 4.0;
    opt.pose_dwell_s = 3.0;
    opt.settle_cutoff_s = 1.0;
    fx->twin = std::make_unique<BigAntTwin>(fx->config, opt);
    fx->standing_stop = AppendSession(*fx->twin, fx->config, kSession, kPoses, kWalkS, &fx->events);
    fx->log = fx->dir + "/in.lcmlog";
    WriteLog(fx->log, fx->events);
    fx->truth = fx->dir + "/truth.pbtxt";
    fx->twin->WriteTruthFile(fx->truth);
  }
  static void TearDownTestSuite() {
    if (std::getenv("FTCAL_TEST_KEEP") == nullptr) testing::RemoveTree(fx->dir);
    delete fx;
    fx = nullptr;
  }

  void SetUp() override {
    ASSERT_TRUE(testing::InNetns());
    testing::AheadOfTheMachine();
    ASSERT_STRNE(FTCAL_LCM_LOGGER, "") << "lcm-logger (liblcm-bin) not found at configure time";
    ASSERT_STRNE(FTCAL_LCM_LOGPLAYER, "")
        << "lcm-logplayer (liblcm-bin) not found at configure time";
  }

  static std::string Path(const std::string& name) { return fx->dir + "/" + name; }

  // Runs a program to completion (exit 0 required); its stderr goes to <tag>.err.
  static void RunToEnd(const std::vector<std::string>& argv, const std::string& tag) {
    Child child(argv, Path(tag + ".out"), Path(tag + ".err"));
    const auto status = child.Wait(120);
    ASSERT_TRUE(status.has_value()) << tag << " did not finish";
    ASSERT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
        << tag << ": " << DescribeWaitStatus(*status) << "\n"
        << ReadFile(Path(tag + ".err"));
  }

  static void StopWithSigint(Child& child, const std::string& tag) {
    child.Signal(SIGINT);
    const auto rc = child.Wait(20);
    ASSERT_TRUE(rc.has_value()) << tag << " did not stop on SIGINT";
    EXPECT_TRUE(WIFEXITED(*rc) && WEXITSTATUS(*rc) == 0)
        << tag << ": " << DescribeWaitStatus(*rc) << "\n"
        << ReadFile(Path(tag + ".err"));
  }
};

// The inputs a stage handled, from the summary it logs at exit ("... in N out M ...").
int64_t InputsHandled(const std::string& err_path) {
  const std::string err = ReadFile(err_path);
  const std::regex summary("\\] in ([0-9]+) out ");
  std::smatch m;
  EXPECT_TRUE(std::regex_search(err, m, summary)) << err_path;
  return m.empty() ? -1 : std::stoll(m[1]);
}

// The outputs a stage published, from the same summary.
int64_t OutputsPublished(const std::string& err_path) {
  const std::string err = ReadFile(err_path);
  const std::regex summary("\\] in [0-9]+ out ([0-9]+) ");
  std::smatch m;
  EXPECT_TRUE(std::regex_search(err, m, summary)) << err_path;
  return m.empty() ? -1 : std::stoll(m[1]);
}

// The calibrator's account of what it collected: the "<series> complete: N samples per leg, M
// attitude samples" and "calibrating: ..." lines, without their time stamps.
std::string HangingSummary(const std::string& err_path) {
  std::string out, line;
  std::istringstream in(ReadFile(err_path));
  while (std::getline(in, line)) {
    const auto at = line.find("] [info] ");
    if (at == std::string::npos) continue;
    if (line.find(" complete: ") != std::string::npos ||
        line.find("calibrating: ") != std::string::npos) {
      out += line.substr(at) + "\n";
    }
  }
  return out;
}

// Everything of a calibration but where and when it was made (provenance) and its version
// number: doubles within `fraction` relative (or 1e-12 absolute, for values that are zero).
void ExpectSameCalibration(const calibration::Calibration& a, const calibration::Calibration& b,
                           double fraction) {
  using google::protobuf::util::DefaultFieldComparator;
  using google::protobuf::util::MessageDifferencer;
  DefaultFieldComparator comparator;
  comparator.set_float_comparison(DefaultFieldComparator::APPROXIMATE);
  comparator.SetDefaultFractionAndMargin(fraction, 1e-12);
  comparator.set_treat_nan_as_equal(true);
  MessageDifferencer differencer;
  differencer.set_field_comparator(&comparator);
  const auto* d = calibration::Calibration::descriptor();
  differencer.IgnoreField(d->FindFieldByName("provenance"));
  differencer.IgnoreField(d->FindFieldByName("version"));
  std::string report;
  differencer.ReportDifferencesToString(&report);
  EXPECT_TRUE(differencer.Compare(a, b)) << report;
}

TEST_F(PipelineLiveTest, LiveChainGivesTheReplaysPosesCalibrationAndWrenches) {
  const auto& ch = fx->config.channels();
  // ---- live ----
  const std::string recorded = Path("live.lcmlog"), live_cal = Path("live_cal.pbtxt");
  Child logger({FTCAL_LCM_LOGGER, "--lcm-url", kUrl, "-f", recorded}, Path("logger.out"),
               Path("logger.err"));
  Child seg({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--lcm-url", kUrl}, Path("seg.out"),
            Path("seg.err"));
  Child cal({FTCAL_CALIBRATOR, "--config", kConfig, "--lcm-url", kUrl, "--out", live_cal},
            Path("cal.out"), Path("cal.err"));
  Child cor({FTCAL_CORRECTOR, "--config", kConfig, "--lcm-url", kUrl}, Path("cor.out"),
            Path("cor.err"));
  {
    // Every stage subscribed (its first heartbeat), and the logger (which sends none) too.
    lcm::LCM ear(kUrl);
    const auto heard = testing::AwaitHeartbeats(ear, {seg.pid(), cal.pid(), cor.pid()}, 30);
    ASSERT_EQ(heard.size(), 3u) << "a stage sent no heartbeat in 30 s";
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
  }
  const auto started = std::chrono::steady_clock::now();
  Child player({FTCAL_LCM_LOGPLAYER, "-s", kSpeed, "-l", kUrl, fx->log}, Path("player.out"),
               Path("player.err"));
  const auto played = player.Wait(90);
  ASSERT_TRUE(played && WIFEXITED(*played) && WEXITSTATUS(*played) == 0)
      << ReadFile(Path("player.err"));
  const double play_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  std::this_thread::sleep_for(std::chrono::milliseconds(700));  // the last outputs
  StopWithSigint(seg, "seg");
  StopWithSigint(cal, "cal");
  StopWithSigint(cor, "cor");
  logger.Signal(SIGINT);
  ASSERT_TRUE(logger.Wait(10));
  std::printf("played %zu events at %sx in %.1f s\n", fx->events.size(), kSpeed, play_s);

  // ---- replay ----
  const std::string seg_ref = Path("seg_ref.lcmlog"), ref_cal = Path("ref_cal.pbtxt");
  RunToEnd({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--replay", fx->log, "--out", seg_ref},
           "seg_ref");
  // The calibrator reads the poses the segmenter published, as the live one heard them.
  RunToEnd(
      {FTCAL_CALIBRATOR, "--config", kConfig, "--log", fx->log, "--log", seg_ref, "--out", ref_cal},
      "cal_ref");

  // UDP multicast may lose a datagram when the machine is busy (lcm-logplayer does not wait):
  // each stage logs how many inputs it handled ("in N out M"); a live stage that handled fewer
  // than its replay lost some, and its outputs near the loss are counted, not compared.
  const int64_t seg_lost = InputsHandled(Path("seg_ref.err")) - InputsHandled(Path("seg.err"));
  // And the recorder may lose what the segmenter published: its SYNC_SAMPLE and STEADY_POSE
  // (the "out" count) against what lcm-logger wrote.
  const int64_t recorder_lost =
      OutputsPublished(Path("seg.err")) -
      static_cast<int64_t>(ReadChannel<sync_sample_t>(recorded, ch.sync_sample()).size() +
                           ReadChannel<steady_pose_t>(recorded, ch.steady_pose()).size());
  std::printf("datagrams lost live: %lld by the segmenter, %lld of its outputs by the recorder\n",
              static_cast<long long>(seg_lost), static_cast<long long>(recorder_lost));
  EXPECT_GE(recorder_lost, 0);
  const bool poses_exact = seg_lost == 0 && recorder_lost == 0;
  EXPECT_GE(seg_lost, 0);

  // STEADY_POSE: the same poses, everything but the publish time bit for bit.
  const auto live_poses = ReadChannel<steady_pose_t>(recorded, ch.steady_pose());
  const auto ref_poses = ReadChannel<steady_pose_t>(seg_ref, ch.steady_pose());
  ASSERT_GE(ref_poses.size(), 30u);
  auto same_pose = [](const steady_pose_t& a, const steady_pose_t& b) {
    return a.session_id == b.session_id && a.start_utime == b.start_utime &&
           a.end_utime == b.end_utime && a.num_samples == b.num_samples &&
           Flat(a.wrench) == Flat(b.wrench) && Flat(a.angle_rad) == Flat(b.angle_rad) &&
           a.markers_ok == b.markers_ok && std::equal(a.q_wc, a.q_wc + 4, b.q_wc);
  };
  size_t matched = 0;
  for (const auto& p : live_poses) {
    for (const auto& r : ref_poses) matched += same_pose(p, r);
  }
  std::printf("STEADY_POSE: %zu live, %zu replayed, %zu the same\n", live_poses.size(),
              ref_poses.size(), matched);
  if (poses_exact) {
    ASSERT_EQ(live_poses.size(), ref_poses.size()) << ReadFile(Path("seg.err"));
    for (size_t i = 0; i < ref_poses.size(); ++i) {
      EXPECT_TRUE(same_pose(live_poses[i], ref_poses[i])) << "pose " << i;
      EXPECT_EQ(live_poses[i].pose_index, ref_poses[i].pose_index);
    }
  } else {
    // A pose whose samples were lost is shorter or gone: at most a few.
    EXPECT_GE(matched + 3, ref_poses.size());
  }

  // Calibration: one published live, its bytes the file's, its numbers the offline run's.
  const auto published = ReadChannel<calibration_t>(recorded, ch.calibration());
  ASSERT_EQ(published.size(), 1u) << ReadFile(Path("cal.err"));
  const calibration_t& cal_msg = published[0];
  EXPECT_EQ(cal_msg.version, 1);
  const std::string bytes(cal_msg.data.begin(), cal_msg.data.end());
  EXPECT_EQ(cal_msg.content_sha256, Sha256Hex(bytes));
  calibration::Calibration from_bus;
  ASSERT_TRUE(from_bus.ParseFromString(bytes));
  const calibration::Calibration from_file = ReadCalibrationFile(live_cal);
  EXPECT_EQ(from_file.SerializeAsString(), bytes);
  // The live calibrator's heartbeat: about 1 Hz while it ran, then STOPPING with its counters.
  // The recorder may lose datagrams on a busy machine (counted above as recorder_lost): at least
  // half the beats must be there, and the last must be STOPPING when it lost nothing.
  {
    std::vector<service_status_t> beats;
    for (const auto& m : ReadChannel<service_status_t>(recorded, ch.status())) {
      if (m.name == "ftcal-calibrator") beats.push_back(m);
    }
    ASSERT_GE(beats.size(), static_cast<size_t>(play_s / 2)) << "played " << play_s << " s";
    EXPECT_EQ(int{beats.front().state}, int{service_status_t::RUNNING});
    if (recorder_lost == 0) {
      EXPECT_EQ(int{beats.back().state}, int{service_status_t::STOPPING});
    }
    int64_t calibrations = 0, refused = 0;
    for (const service_status_t& b : beats) {
      for (int i = 0; i < b.num_counters; ++i) {
        if (b.counter_name[i] == "calibrations")
          calibrations = std::max(calibrations, b.counter_value[i]);
        if (b.counter_name[i] == "refused") refused = std::max(refused, b.counter_value[i]);
      }
    }
    EXPECT_EQ(calibrations, 1);
    EXPECT_EQ(refused, 0);
    EXPECT_GT(beats.back().msgs_out, 0);  // CALIBRATION
  }
  const calibration::Calibration reference = ReadCalibrationFile(ref_cal);
  EXPECT_EQ(reference.standing_poses(), ref_poses.size());
  // The same inputs (the same poses, every hanging sample): the same numbers.
  if (seg_lost == 0 && HangingSummary(Path("cal.err")) == HangingSummary(Path("cal_ref.err"))) {
    ExpectSameCalibration(from_bus, reference, 1e-6);
  } else {
    std::printf(
        "calibration not compared at 1e-6: the live calibrator's inputs differ "
        "(datagrams lost):\n%s--- replay:\n%s",
        HangingSummary(Path("cal.err")).c_str(), HangingSummary(Path("cal_ref.err")).c_str());
  }
  // And a calibration at all: the leg weights near the truth (calibrator_test's bound).
  const calibration::Calibration truth = ReadCalibrationFile(fx->truth);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_NEAR(reference.leg(k).leg_weight_n().value(), truth.leg(k).leg_weight_n().value(), 0.05);
  }

  // CONTACT_WRENCH: the corrector replayed over the input with the published calibration where
  // the STANDING stop marker is (the live corrector got it a little later: it published nothing
  // before, so every live output has a replayed counterpart).
  std::vector<Event> with_cal = fx->events;
  const int64_t stop_utime = with_cal[fx->standing_stop].utime;
  with_cal.insert(with_cal.begin() + static_cast<std::ptrdiff_t>(fx->standing_stop) + 1,
                  Encode(stop_utime, ch.calibration(), cal_msg));
  const std::string cor_in = Path("cor_ref_in.lcmlog"), cor_ref = Path("cor_ref.lcmlog");
  WriteLog(cor_in, with_cal);
  RunToEnd({FTCAL_CORRECTOR, "--config", kConfig, "--replay", cor_in, "--out", cor_ref}, "cor_ref");
  const auto live_w = ReadLegWrenches(recorded, ch.contact_wrench());
  const auto ref_w = ReadLegWrenches(cor_ref, ch.contact_wrench());
  const WrenchComparison c = CompareWrenches(live_w, ref_w);
  std::printf(
      "CONTACT_WRENCH: %zu live, %zu replayed; %zu with the same inputs (max |diff| %.3g), "
      "%zu with reordered/lost inputs, %zu without a replayed counterpart\n",
      c.outputs, ref_w.size(), c.same_inputs, c.worst, c.inputs_differ, c.missing_ref);
  EXPECT_EQ(c.missing_ref, 0u);
  EXPECT_EQ(c.duplicate, 0u);
  EXPECT_LE(c.worst, 1e-6);
  // The walk after the calibration, 100 Hz x 6 legs, minus the time Calibrate() took live.
  EXPECT_GT(c.outputs, static_cast<size_t>(kWalkS * 100 * kNumLegs / 3))
      << ReadFile(Path("cor.err"));
  // Reordering or loss is the exception on loopback, not the rule (even on a busy machine).
  EXPECT_LE(c.inputs_differ, c.outputs / 20)
      << "first at utime " << (c.differ_utimes.empty() ? 0 : c.differ_utimes[0]);
  // CONTACT_WRENCH_SUM: the replay's sums are the sums of its leg-samples, one per six; the live
  // sums carry the published calibration (the recorder may lose a leg-sample, so the live sums
  // are not checked against the recorded legs).
  const double weight = CalibrationFromProto(from_bus, fx->config.robot()).TotalWeightN();
  const SumCheck ref_sums =
      CheckSums(cor_ref, ch.contact_wrench(), ch.contact_wrench_sum(), weight);
  EXPECT_EQ(ref_sums.worst, 0.0);
  EXPECT_LT(ref_sums.worst_age, 1e-6);
  EXPECT_GE(ref_sums.sums * kNumLegs + kNumLegs, ref_w.size());
  const auto live_sums = ReadWrenchSums(recorded, ch.contact_wrench_sum());
  EXPECT_GT(live_sums.size(), live_w.size() / kNumLegs / 2);
  for (const auto& s : live_sums) EXPECT_EQ(s.calibration_version, cal_msg.version);
}

// UDP loses a datagram now and then on a busy machine, so the live test above can compare the
// calibration at 1e-6 only when none was lost. Here the same live objects (PoseSegmenterStage and
// LiveCalibrator on one bus, the segmenter's last pose arriving after the stop marker as it does
// live) run on LCM's in-process memq://, which loses nothing: the calibration published must be
// the offline one.
TEST_F(PipelineLiveTest, LiveCalibratorOnALosslessBusGivesTheOfflineCalibration) {
  const auto& ch = fx->config.channels();
  ServiceStats stats(spdlog::default_logger());
  LcmBus bus("memq://", stats);
  PoseSegmenterStage segmenter(fx->config, bus);
  std::vector<calibration_t> published;
  bus.Subscribe<calibration_t>(ch.calibration(), [&](const MessageInfo&, const calibration_t& m) {
    published.push_back(m);
  });
  CalibratorOptions options;
  options.config_path = kConfig;
  LiveCalibrator live(fx->config, bus, Path("memq_cal.pbtxt"), options, nullptr);
  auto drain = [&] {
    while (bus.HandleOnce(0) > 0) {
    }
  };
  for (size_t i = 0; i <= fx->standing_stop; ++i) {
    const Event& e = fx->events[i];
    bus.PublishRaw(e.channel, e.data.data(), static_cast<int>(e.data.size()));
    if (i % 512 == 0) drain();
  }
  drain();
  drain();
  EXPECT_EQ(live.refused(), 0) << live.last_refusal();
  ASSERT_EQ(published.size(), 1u);
  calibration::Calibration from_bus;
  ASSERT_TRUE(
      from_bus.ParseFromString(std::string(published[0].data.begin(), published[0].data.end())));

  const std::string seg_ref = Path("memq_seg_ref.lcmlog"), ref_cal = Path("memq_ref_cal.pbtxt");
  RunToEnd({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--replay", fx->log, "--out", seg_ref},
           "memq_seg_ref");
  RunToEnd(
      {FTCAL_CALIBRATOR, "--config", kConfig, "--log", fx->log, "--log", seg_ref, "--out", ref_cal},
      "memq_cal_ref");
  const calibration::Calibration reference = ReadCalibrationFile(ref_cal);
  EXPECT_EQ(from_bus.standing_poses(), reference.standing_poses());
  EXPECT_GE(reference.standing_poses(), 30u);
  ExpectSameCalibration(from_bus, reference, 1e-6);
}

// SIGKILL in the middle of lcm-logplayer's play, then a new corrector: every recorded output
// decodes; before the kill and once the new process has heard a servo state and a mocap frame,
// the outputs are the replay's for the same inputs; only the first frame after the restart
// differs (its inputs were not heard), and the only outputs missing are those of the samples
// played while no corrector ran.
// The test's own ear on the bus: the CONTACT_WRENCH leg-samples and who sent a heartbeat,
// heard in this thread while it waits (ahead of the machine, with room for every message).
class WrenchEar {
 public:
  explicit WrenchEar(const std::string& channel) : lcm_(kUrl) {
    lcm_.subscribe(channel, &WrenchEar::OnWrench, this)->setQueueCapacity(1'000'000);
    lcm_.subscribe("FTCAL_STATUS", &WrenchEar::OnStatus, this)->setQueueCapacity(10'000);
    lcm_.subscribe("FT_.*", &WrenchEar::OnFt, this)->setQueueCapacity(1'000'000);
  }
  // Until the transducers' stream (the player's) reaches sample time `utime`.
  bool AwaitFtUtime(int64_t utime, double timeout_s) {
    return PumpUntil([&] { return last_ft_ >= utime; }, timeout_s);
  }
  int64_t last_utime() const { return last_; }
  bool AwaitBeat(pid_t pid, double timeout_s) {
    return PumpUntil([&] { return beats_.count(pid) > 0; }, timeout_s);
  }
  // Until the leg-samples heard span `span_us` of sample time.
  bool AwaitSpanUs(int64_t span_us, double timeout_s) {
    return PumpUntil([&] { return !heard_.empty() && last_ - first_ >= span_us; }, timeout_s);
  }
  bool AwaitUtime(int64_t utime, double timeout_s) {
    return PumpUntil([&] { return !heard_.empty() && last_ >= utime; }, timeout_s);
  }
  const std::vector<LegWrench>& wrenches() const { return heard_; }

 private:
  template <class Pred>
  bool PumpUntil(Pred done, double timeout_s) {
    const auto deadline =
        std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (!done()) {
      if (std::chrono::steady_clock::now() >= deadline) return false;
      lcm_.handleTimeout(20);
    }
    return true;
  }
  void OnWrench(const lcm::ReceiveBuffer*, const std::string&, const contact_wrench_t* m) {
    for (const LegWrench& w : FromLcm(*m)) {
      if (heard_.empty()) first_ = last_ = w.utime;
      first_ = std::min(first_, w.utime);
      last_ = std::max(last_, w.utime);
      heard_.push_back(w);
    }
  }
  void OnFt(const lcm::ReceiveBuffer*, const std::string&, const ft_batch_t* m) {
    for (int64_t t : m->sample_utime) last_ft_ = std::max(last_ft_, t);
  }
  void OnStatus(const lcm::ReceiveBuffer*, const std::string&, const service_status_t* s) {
    beats_.insert(s->pid);
  }
  lcm::LCM lcm_;
  std::vector<LegWrench> heard_;
  int64_t first_ = 0, last_ = 0, last_ft_ = 0;
  std::set<pid_t> beats_;
};

TEST_F(PipelineLiveTest, CorrectorKilledAndRestartedCorruptsNothing) {
  const auto& ch = fx->config.channels();
  // The walk part of the session only: the corrector starts with the truth calibration.
  std::vector<Event> walk(fx->events.begin() + static_cast<std::ptrdiff_t>(fx->standing_stop) + 1,
                          fx->events.end());
  walk.resize(walk.size() / 2);  // 15 s of robot time
  const std::string in = Path("walk.lcmlog");
  WriteLog(in, walk);
  const std::string ref = Path("kill_ref.lcmlog");
  RunToEnd({FTCAL_CORRECTOR, "--config", kConfig, "--calibration", fx->truth, "--replay", in,
            "--out", ref},
           "kill_ref");

  // Every step waits for what it needs to have happened, not for a time: a corrector killed
  // before it published, or restarted too late to publish, proves nothing (both happened on a
  // loaded machine with fixed sleeps).
  WrenchEar ear(ch.contact_wrench());
  const std::vector<std::string> argv = {FTCAL_CORRECTOR, "--config",  kConfig, "--calibration",
                                         fx->truth,       "--lcm-url", kUrl};
  auto first = std::make_unique<Child>(argv, Path("kcor1.out"), Path("kcor1.err"));
  ASSERT_TRUE(ear.AwaitBeat(first->pid(), 30)) << "no heartbeat\n" << ReadFile(Path("kcor1.err"));
  Child player({FTCAL_LCM_LOGPLAYER, "-s", "3", "-l", kUrl, in}, Path("kplayer.out"),
               Path("kplayer.err"));
  // Half a second of robot time corrected by the first process, then it dies mid-stream.
  ASSERT_TRUE(ear.AwaitSpanUs(500'000, 30)) << ReadFile(Path("kcor1.err"));
  first->Signal(SIGKILL);
  const auto killed = first->Wait(5);
  ASSERT_TRUE(killed && WIFSIGNALED(*killed) && WTERMSIG(*killed) == SIGKILL);
  // A gap no restart could hide: 0.3 s of the stream go by with no corrector.
  ASSERT_TRUE(ear.AwaitFtUtime(ear.last_utime() + 300'000, 30));
  Child second(argv, Path("kcor2.out"), Path("kcor2.err"));
  ASSERT_TRUE(ear.AwaitBeat(second.pid(), 30)) << "no heartbeat\n" << ReadFile(Path("kcor2.err"));
  const auto played = player.Wait(60);
  ASSERT_TRUE(played && WIFEXITED(*played) && WEXITSTATUS(*played) == 0)
      << ReadFile(Path("kplayer.err"));
  // Until the last sample's correction is heard (or 10 s: a lost last datagram is counted below).
  int64_t last_ft = 0;
  for (const LegWrench& w : ReadLegWrenches(ref, ch.contact_wrench())) {
    last_ft = std::max(last_ft, w.utime);
  }
  ear.AwaitUtime(last_ft, 10);
  StopWithSigint(second, "kcor2");

  const auto live_w = ear.wrenches();
  const auto ref_w = ReadLegWrenches(ref, ch.contact_wrench());
  size_t ft_events = 0;
  for (const Event& e : walk) ft_events += e.channel.rfind(ch.ft_prefix(), 0) == 0;
  ASSERT_EQ(ref_w.size(), ft_events);
  const WrenchComparison c = CompareWrenches(live_w, ref_w);
  EXPECT_EQ(c.missing_ref, 0u);
  EXPECT_EQ(c.duplicate, 0u);
  EXPECT_LE(c.worst, 1e-6);
  // The two processes' outputs: a gap (killed .. subscribed again) in the sample times.
  std::vector<int64_t> times;
  for (const auto& m : live_w) times.push_back(m.utime);
  ASSERT_FALSE(times.empty());
  std::sort(times.begin(), times.end());
  int64_t gap_from = 0, gap_to = 0;
  for (size_t i = 1; i < times.size(); ++i) {
    if (times[i] - times[i - 1] > gap_to - gap_from) {
      gap_from = times[i - 1];
      gap_to = times[i];
    }
  }
  std::printf(
      "killed and restarted: %zu live outputs of %zu, gap %.2f s of robot time, %zu with "
      "other inputs (max |diff| %.3g over %zu)\n",
      live_w.size(), ref_w.size(), 1e-6 * static_cast<double>(gap_to - gap_from), c.inputs_differ,
      c.worst, c.same_inputs);
  EXPECT_GE(gap_to - gap_from, 200'000) << "no gap: was the corrector killed at all?";
  // Inputs differ in the restarted process's first frames (legs not heard yet, legs corrected
  // before its first servo state and mocap frame came) and wherever a datagram was lost on the
  // way: the exception.
  size_t after_restart = 0;
  for (int64_t t : c.differ_utimes) after_restart += t >= gap_to && t - gap_to <= 30'000;
  EXPECT_GE(after_restart, 1u) << "the restarted process cannot know the legs it has not heard";
  EXPECT_LE(c.inputs_differ, c.outputs / 20);
  // Both processes published: for a while before and after the kill.
  EXPECT_LT(times.front(), gap_from - 300'000);
  EXPECT_GT(times.back(), gap_to + 300'000);
}

}  // namespace
}  // namespace ftcal
