// ftcal-calibrator as a real process over logs the test writes from the BigAnt twin (four short
// hanging series and 60 standing poses, with EXPERIMENT markers as the sequencer sends them):
// the calibration is checked against the twin's truth, provenance against the log's own
// SHA-256, the report against the files it names; damaged or incomplete logs and a config for
// other channels must be refused with exit 2, a message naming the problem, and no output.
#include <sys/wait.h>
#include <sys/stat.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <sstream>
#include <memory>
#include <regex>
#include <set>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/spdlog.h>

#include "calibrator/calibrator.h"
#include "child_process.h"
#include "common/bus.h"
#include "common/lcm_bus.h"
#include "common/log_replay_bus.h"
#include "common/service_stats.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/digest_cache.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "ftcal_pre_batch/ft_sample_t.hpp"
#include "ftcal_pre_fixed6/servo_state_t.hpp"
#include "ftcal_pre_sample_time/mocap_body_t.hpp"
#include "ftcal_pre_sample_time/servo_state_t.hpp"
#include "sim/twin.h"
#include "twin_log.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::ReadFile;
// The log writers the multi-process tests share.
using twin_log::AppendFrame;
using twin_log::Encode;
using twin_log::Event;
using twin_log::Utime;
using twin_log::WriteLog;

constexpr int kPoses = 60;
// A short walk after the poses (1.6 gait cycles): the report's walking figure.
constexpr double kWalkS = 20.0;
const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";

experiment_marker_t Marker(int64_t utime, int8_t phase, bool start, const Vec3& gravity_b) {
  experiment_marker_t m{};
  m.utime = utime;
  m.session_id = "calibrator-test";
  m.phase = phase;
  m.start = start;
  for (int i = 0; i < 3; ++i) m.gravity_b[i] = gravity_b[i];
  m.note = "calibrator_test";
  return m;
}

struct Fixture {
  std::string dir;
  config::Config config;
  std::unique_ptr<BigAntTwin> twin;
  std::string log, log_no_markers, log_no_z_neg, log_truncated, truth, config_other;
  std::string config_signed;  // the same, but EXPERIMENT markers must be signed
  int64_t markers = 0;        // the EXPERIMENT markers in `log`, all unsigned
  std::vector<Event> events;  // the whole session, for the live test
};
Fixture* fx = nullptr;

class CalibratorTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    fx = new Fixture;
    fx->dir = testing::MakeTempDir();
    fx->config = LoadConfigFile(kConfig);
    TwinOptions opt;
    opt.seed = 11;
    opt.marker_dropout_rate_hz = 0.0;
    // Short enough for a fast test, long enough for the method: three 6 s leg cycles per
    // series (two are the minimum for the cycle-spread sigmas) and poses that settle within
    // 1.2 s and stay steady for about 2 s (the segmenter needs 1.5 s).
    opt.hang_cycles = 3;
    opt.hang_cycle_s = 6.0;
    opt.pose_dwell_s = 3.6;
    opt.settle_cutoff_s = 1.2;
    fx->twin = std::make_unique<BigAntTwin>(fx->config, opt);
    const auto& ch = fx->config.channels();

    // Event lists: all, without markers, without the HANG_Z_NEG markers.
    std::vector<Event> all, no_markers, no_z_neg;
    // Every list has every frame; only the markers differ.
    const auto frames = [&](const TwinFrame& f) {
      AppendFrame(f, fx->config, &all);
      AppendFrame(f, fx->config, &no_markers);
      AppendFrame(f, fx->config, &no_z_neg);
    };
    auto marker = [&](double t_s, int8_t phase, bool start, const Vec3& g, bool in_no_z_neg) {
      const Event e = Encode(Utime(t_s), ch.experiment(), Marker(Utime(t_s), phase, start, g));
      all.push_back(e);
      if (in_no_z_neg) no_z_neg.push_back(e);
    };
    double t = 0.0;
    for (int s = 0; s < kNumHangSeries; ++s) {
      const auto series = static_cast<HangSeries>(s);
      const int8_t phase = static_cast<int8_t>(experiment_marker_t::HANG_X_POS + s);
      const Vec3 g = fx->twin->StatedGravityB(series);
      const bool keep = series != HangSeries::kZNeg;
      marker(t, phase, true, g, keep);
      RunOptions run;
      run.t0_s = t + 0.01;
      t = fx->twin->Hanging(series, run, frames);
      marker(t + 0.005, phase, false, g, keep);
      t += 1.0;
    }
    marker(t, experiment_marker_t::STANDING, true, Vec3::Zero(), true);
    RunOptions run;
    run.t0_s = t + 0.01;
    t = fx->twin->Standing(kPoses, run, frames);
    marker(t + 0.005, experiment_marker_t::STANDING, false, Vec3::Zero(), true);
    t += 1.0;
    marker(t, experiment_marker_t::WALKING, true, Vec3::Zero(), true);
    RunOptions walk;
    walk.t0_s = t + 0.01;
    t = fx->twin->TripodWalk(kWalkS, walk, frames);
    marker(t + 0.005, experiment_marker_t::WALKING, false, Vec3::Zero(), true);

    fx->log = fx->dir + "/session.lcmlog";
    fx->log_no_markers = fx->dir + "/no_markers.lcmlog";
    fx->log_no_z_neg = fx->dir + "/no_z_neg.lcmlog";
    fx->log_truncated = fx->dir + "/truncated.lcmlog";
    WriteLog(fx->log, all);
    fx->events = all;
    WriteLog(fx->log_no_markers, no_markers);
    WriteLog(fx->log_no_z_neg, no_z_neg);
    // Cut in the middle of an event, 70% in: the standing poses' stop marker is lost too, but
    // the refusal must come from the damaged tail, not from what happens to be missing.
    const std::string bytes = ReadFile(fx->log);
    std::ofstream(fx->log_truncated, std::ios::binary)
        .write(bytes.data(), static_cast<std::streamsize>(bytes.size() * 7 / 10 + 13));
    fx->truth = fx->dir + "/truth.pbtxt";
    fx->twin->WriteTruthFile(fx->truth);
    // The same robot with the transducers on other channels: the log's FT_* are not its legs.
    std::string cfg = ReadFile(kConfig);
    cfg.replace(cfg.find("channels {}"), 11, "channels { ft_prefix: \"ATI_\" }");
    fx->config_other = fx->dir + "/other.pbtxt";
    std::ofstream(fx->config_other) << cfg;
    // The same robot with signatures required, as config/bigant.pbtxt's auth has them.
    std::string signed_cfg = ReadFile(kConfig);
    const std::string unsigned_ok = "allow_unsigned: true";
    signed_cfg.replace(signed_cfg.find(unsigned_ok), unsigned_ok.size(), "allow_unsigned: false");
    fx->config_signed = fx->dir + "/signed.pbtxt";
    std::ofstream(fx->config_signed) << signed_cfg;
    fx->markers = std::count_if(all.begin(), all.end(),
                                [&](const Event& e) { return e.channel == ch.experiment(); });
  }
  static void TearDownTestSuite() {
    // FTCAL_TEST_KEEP=1 keeps the logs, calibration and report for a look.
    if (std::getenv("FTCAL_TEST_KEEP") == nullptr) testing::RemoveTree(fx->dir);
    delete fx;
    fx = nullptr;
  }

  struct Result {
    int exit_code = -1;
    std::string out, err;
  };
  static Result Run(const std::vector<std::string>& extra, const std::string& tag) {
    std::vector<std::string> argv = {FTCAL_CALIBRATOR};
    argv.insert(argv.end(), extra.begin(), extra.end());
    Child child(argv, fx->dir + "/" + tag + ".out", fx->dir + "/" + tag + ".err");
    const auto status = child.Wait(120);
    Result r;
    if (status && WIFEXITED(*status)) r.exit_code = WEXITSTATUS(*status);
    r.out = ReadFile(fx->dir + "/" + tag + ".out");
    r.err = ReadFile(fx->dir + "/" + tag + ".err");
    return r;
  }

  // The segmenter's poses log of the session (made once): its STEADY_POSE events carry their
  // scatter. Empty when the segmenter failed (a failure of this test's own).
  static std::string PosesLog() {
    const std::string poses = fx->dir + "/poses.lcmlog";
    if (std::filesystem::exists(poses)) return poses;
    Child seg({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--replay", fx->log, "--out", poses},
              fx->dir + "/seg.out", fx->dir + "/seg.err");
    const auto status = seg.Wait(120);
    if (!(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)) {
      ADD_FAILURE() << "ftcal-pose-segmenter failed: " << ReadFile(fx->dir + "/seg.err");
      return "";
    }
    return poses;
  }

  // Reads `path` into `collector` as the calibrator does (its replay bus, to the end).
  static void ReadInto(CalibrationCollector& collector, const std::string& path) {
    ServiceStats stats(spdlog::default_logger());
    LogReplayBus bus(path, fx->dir + "/replay-scratch.lcmlog", stats);
    collector.Attach(bus);
    bus.Run([] {}, 1'000'000);
    ASSERT_TRUE(bus.finished());
    ASSERT_EQ(stats.errors(), 0) << stats.last_error();
  }

  // Reads `path` into `collector` with the span index `index` (may be null) as the calibrator
  // does; the bytes it skipped.
  static int64_t ReadIndexed(CalibrationCollector& collector, const std::string& path,
                             const logindex::LogIndex* index) {
    ServiceStats stats(spdlog::default_logger());
    LogReplayBus bus(path, fx->dir + "/replay-scratch.lcmlog", stats);
    collector.SetSpanIndex(index);
    collector.Attach(bus);
    bus.Run([] {}, 1'000'000);
    collector.SetSpanIndex(nullptr);
    collector.Flush();
    EXPECT_TRUE(bus.finished());
    EXPECT_EQ(stats.errors(), 0) << stats.last_error();
    return bus.skipped_bytes();
  }

  // A refusal: exit 2, `what` in the message, neither the calibration nor its residuals.
  static void ExpectRefused(const std::vector<std::string>& args, const std::string& tag,
                            const std::string& what) {
    const std::string out = fx->dir + "/" + tag + ".pbtxt";
    std::vector<std::string> argv = args;
    argv.insert(argv.end(), {"--config", kConfig, "--out", out});
    Result r = Run(argv, tag);
    EXPECT_EQ(r.exit_code, 2) << r.err;
    EXPECT_NE(r.err.find(what), std::string::npos) << "expected '" << what << "' in:\n" << r.err;
    EXPECT_FALSE(std::filesystem::exists(out));
    EXPECT_FALSE(std::filesystem::exists(ResidualsPathFor(out)));
  }
};

// Two legs' servo ids swapped in the Dynamixel bridge's config: the bridge names each servo's
// leg by its id, so SERVO_STATE says "ML" for the servo that turns HL and the other way round.
// The calibrator's standing data says so and the calibration is refused, naming both legs,
// unless --accept-leg-map-mismatch.
TEST_F(CalibratorTest, RefusesALogWithTwoServoIdsSwapped) {
  std::vector<Event> events = fx->events;
  int swapped_states = 0;
  for (Event& e : events) {
    if (e.channel != "SERVO_STATE") continue;
    servo_state_t m;
    ASSERT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
              static_cast<int>(e.data.size()));
    ASSERT_EQ(m.leg[0], "HL");
    ASSERT_EQ(m.leg[1], "ML");
    std::swap(m.leg[0], m.leg[1]);
    e = Encode(e.utime, e.channel, m);
    ++swapped_states;
  }
  ASSERT_GT(swapped_states, 0);
  const std::string log = fx->dir + "/swapped_servos.lcmlog";
  WriteLog(log, events);
  const std::string out = fx->dir + "/swapped.pbtxt";
  const Result r = Run({"--log", log, "--config", kConfig, "--out", out}, "swapped");
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_NE(r.err.find("data of legs HL, ML contradicts their configured position"),
            std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("HL's transducer follows ML's shaft"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("--accept-leg-map-mismatch"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(out));
  const Result anyway =
      Run({"--log", log, "--config", kConfig, "--out", out, "--accept-leg-map-mismatch"},
          "swapped_accepted");
  ASSERT_EQ(anyway.exit_code, 0) << anyway.err;
  const calibration::Calibration cal = ReadCalibrationFile(out);
  EXPECT_FALSE(cal.leg_map_check().consistent());
  EXPECT_TRUE(cal.leg_map_check().accepted_mismatch());
}

// The recording lost a tenth of one transducer's records in a hanging series (a receive
// buffer overflowing): the calibration is refused, naming the series, the channel and the
// count, unless --allow-gaps; then the file counts exactly the records taken out. A bridge
// restart inside the standing phase (the numbers start again from 1) and two records swapped
// in arrival are not gaps.
TEST_F(CalibratorTest, RefusesAPhaseThatLostRecordsUnlessAllowedAndCountsThemExactly) {
  const auto& ch = fx->config.channels();
  std::vector<Event> events;
  int phase = -1;
  int64_t hl_seen = 0, dropped = 0, kept = 0, ml_standing = 0, ml_total_standing = 0;
  bool last_dropped = false;
  for (const Event& e : fx->events) {
    if (e.channel == ch.experiment()) {
      experiment_marker_t m;
      ASSERT_GT(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())), 0);
      phase = m.start ? m.phase : -1;
    }
    if (phase == experiment_marker_t::STANDING && e.channel == ch.ft_prefix() + "ML") {
      ++ml_total_standing;
    }
  }
  ASSERT_GT(ml_total_standing, 100);
  int64_t mr_in_z_pos = 0;
  std::optional<Event> held;  // an FT_MR record of HANG_Z_POS held back one record
  phase = -1;
  for (const Event& e : fx->events) {
    if (e.channel == ch.experiment()) {
      experiment_marker_t m;
      m.decode(e.data.data(), 0, static_cast<int>(e.data.size()));
      phase = m.start ? m.phase : -1;
    }
    if (phase == experiment_marker_t::HANG_X_POS && e.channel == "FT_HL") {
      last_dropped = ++hl_seen % 10 == 0;
      if (last_dropped) {
        ++dropped;
        continue;
      }
      ++kept;
    }
    if (phase == experiment_marker_t::STANDING && e.channel == "FT_ML" &&
        ++ml_standing > ml_total_standing / 2) {
      ft_batch_t m;
      ASSERT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                static_cast<int>(e.data.size()));
      ASSERT_EQ(m.n, 1);                                        // the twin's: a record a message
      m.rdt_sequence[0] = ml_standing - ml_total_standing / 2;  // a new RDT stream: 1, 2, ...
      events.push_back(Encode(e.utime, e.channel, m));
      continue;
    }
    if (phase == experiment_marker_t::HANG_Z_POS && e.channel == "FT_MR" && ++mr_in_z_pos == 500) {
      held = e;
      continue;
    }
    events.push_back(e);
    if (held && e.channel == "FT_MR") {
      events.push_back(*held);
      held.reset();
    }
  }
  ASSERT_GT(dropped, 20);
  // A record dropped last in the phase has no later number in it to show the gap.
  const int64_t lost = dropped - (last_dropped ? 1 : 0);
  const std::string log = fx->dir + "/gaps.lcmlog";
  WriteLog(log, events);
  ExpectRefused({"--log", log}, "gaps",
                "HANG_X_POS (session 'calibrator-test') FT_HL: " + std::to_string(lost) + " of " +
                    std::to_string(kept + lost) + " records lost");
  {
    const Result r =
        Run({"--log", log, "--config", kConfig, "--out", fx->dir + "/gaps.pbtxt"}, "gaps_message");
    EXPECT_NE(r.err.find("--allow-gaps"), std::string::npos) << r.err;
  }
  const std::string out = fx->dir + "/gaps-allowed.pbtxt";
  const Result r =
      Run({"--log", log, "--config", kConfig, "--out", out, "--allow-gaps"}, "gaps_allowed");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const calibration::Calibration cal = ReadCalibrationFile(out);
  bool warned = false;
  for (const std::string& w : cal.warning())
    warned = warned || w.find("--allow-gaps") != std::string::npos;
  EXPECT_TRUE(warned);
  // Four series, STANDING, WALKING: six phases of six channels.
  ASSERT_EQ(cal.recording_gaps_size(), 36);
  for (const calibration::RecordingGaps& g : cal.recording_gaps()) {
    SCOPED_TRACE(g.phase() + " " + g.channel());
    if (g.phase() == "HANG_X_POS" && g.channel() == "FT_HL") {
      EXPECT_EQ(g.lost(), static_cast<uint64_t>(lost));
      EXPECT_EQ(g.received(), static_cast<uint64_t>(kept));
      EXPECT_NEAR(g.lost_share(), static_cast<double>(lost) / (kept + lost), 1e-12);
    } else {
      EXPECT_EQ(g.lost(), 0u) << "the twin published every record";
    }
    EXPECT_EQ(g.restarts(), g.phase() == "STANDING" && g.channel() == "FT_ML" ? 1u : 0u);
    EXPECT_EQ(g.used(), g.phase() != "WALKING");
    EXPECT_GT(g.received(), 0u);
  }
}

// The segmenter's poses log carries each pose's within-pose scatter. Read before the session,
// it spares the calibrator segmenting the STANDING phase again; the calibrator reads it first
// whichever order the --logs are given in (it has no transducer sample at its start), and
// says so. Both orders give the same calibration, number for number, and its noise floor is
// the one the calibrator finds by segmenting the session itself.
TEST_F(CalibratorTest, APosesLogReadFirstSparesSegmentingAgainAndChangesNoNumber) {
  const std::string poses = PosesLog();
  ASSERT_FALSE(poses.empty());
  const std::string after = fx->dir + "/cal-poses-after.pbtxt";
  const std::string before = fx->dir + "/cal-poses-before.pbtxt";
  const Result ra =
      Run({"--log", fx->log, "--log", poses, "--config", kConfig, "--out", after}, "poses_after");
  const Result rb =
      Run({"--log", poses, "--log", fx->log, "--config", kConfig, "--out", before}, "poses_before");
  // The session alone: the calibrator's own segmentation gives every pose and its scatter.
  const std::string own = fx->dir + "/cal-own-poses.pbtxt";
  const Result ro = Run({"--log", fx->log, "--config", kConfig, "--out", own}, "own_poses");
  ASSERT_EQ(ra.exit_code, 0) << ra.err;
  ASSERT_EQ(rb.exit_code, 0) << rb.err;
  ASSERT_EQ(ro.exit_code, 0) << ro.err;
  for (const Result* r : {&rb, &ra}) {
    EXPECT_NE(r->err.find("carry their within-pose scatter: not segmented again"),
              std::string::npos)
        << r->err;
    EXPECT_EQ(r->err.find("steady poses segmented"), std::string::npos) << r->err;
  }
  EXPECT_NE(ra.err.find("reading " + poses + " before " + fx->log), std::string::npos) << ra.err;
  EXPECT_EQ(rb.err.find("reading " + poses + " before"), std::string::npos) << rb.err;
  EXPECT_NE(ro.err.find("steady poses segmented"), std::string::npos) << ro.err;

  calibration::Calibration a = ReadCalibrationFile(after), b = ReadCalibrationFile(before);
  EXPECT_GE(b.standing_poses(), kPoses * 9 / 10);
  // The scatter came from the messages: the noise floor is there, from every pose.
  ASSERT_TRUE(b.has_noise_floor());
  EXPECT_EQ(b.noise_floor().poses_with_scatter(), b.standing_poses());
  EXPECT_EQ(a.noise_floor().DebugString(), b.noise_floor().DebugString());
  // ...and it is the scatter the calibrator finds itself over the same samples: the message
  // carries the segmenter's numbers, not something of its own (the medians' attitude crosses
  // the message as a quaternion, hence a tolerance rather than equality).
  const calibration::Calibration o = ReadCalibrationFile(own);
  EXPECT_EQ(o.standing_poses(), b.standing_poses());
  EXPECT_EQ(o.noise_floor().poses_with_scatter(), b.noise_floor().poses_with_scatter());
  ASSERT_EQ(o.noise_floor().floor_rms_size(), 6);
  ASSERT_EQ(b.noise_floor().floor_rms_size(), 6);
  for (int i = 0; i < 6; ++i) {
    EXPECT_GT(b.noise_floor().floor_rms(i), 0.0) << i;
    EXPECT_NEAR(b.noise_floor().floor_rms(i), o.noise_floor().floor_rms(i),
                1e-9 * o.noise_floor().floor_rms(i))
        << i;
  }
  // Everything but the provenance (input order, command line, time) is the same.
  a.clear_provenance();
  b.clear_provenance();
  EXPECT_EQ(a.DebugString(), b.DebugString());
  EXPECT_EQ(ReadFile(ResidualsPathFor(after)), ReadFile(ResidualsPathFor(before)));
}

// The digest cache: a second run on an unchanged log takes its SHA-256 from the cache (and
// says so) instead of hashing it again, and the provenance is the file's hash either way.
TEST_F(CalibratorTest, ASecondRunTakesTheLogsDigestFromTheCache) {
  const std::string cache = fx->dir + "/digest-cache";
  std::optional<testing::ScopedEnv> cache_env(std::in_place, "FTCAL_CACHE_DIR", cache);
  // The cache stores a log whose ctime is 2 s old (a write in the same clock tick as the hash
  // would not change its key): the fixture's log may be younger.
  struct stat st {};
  ASSERT_EQ(::stat(fx->log.c_str(), &st), 0);
  while (std::time(nullptr) < st.st_ctim.tv_sec + 3) ::usleep(100'000);
  const std::string first = fx->dir + "/cal-cache-1.pbtxt", second = fx->dir + "/cal-cache-2.pbtxt";
  const Result r1 = Run({"--log", fx->log, "--config", kConfig, "--out", first}, "cache1");
  const Result r2 = Run({"--log", fx->log, "--config", kConfig, "--out", second}, "cache2");
  cache_env.reset();
  ASSERT_EQ(r1.exit_code, 0) << r1.err;
  ASSERT_EQ(r2.exit_code, 0) << r2.err;
  EXPECT_EQ(r1.err.find("from the digest cache"), std::string::npos) << r1.err;
  EXPECT_NE(r2.err.find(fx->log + ": SHA-256 from the digest cache in " + cache), std::string::npos)
      << r2.err;
  const std::string sha = Sha256File(fx->log);
  EXPECT_EQ(ReadCalibrationFile(first).provenance().input(0).sha256(), sha);
  EXPECT_EQ(ReadCalibrationFile(second).provenance().input(0).sha256(), sha);
}

// The span index in the digest cache: the first run reads the session whole and leaves the
// index beside the digest; the second skips the STANDING span (and says so) and writes the
// same calibration, residuals and walk, number for number.
TEST_F(CalibratorTest, ASecondRunSkipsTheStandingSpanAndWritesTheSameCalibration) {
  const std::string poses = PosesLog();
  ASSERT_FALSE(poses.empty());
  const std::string cache = fx->dir + "/span-cache";
  std::optional<testing::ScopedEnv> cache_env(std::in_place, "FTCAL_CACHE_DIR", cache);
  struct stat st {};
  ASSERT_EQ(::stat(fx->log.c_str(), &st), 0);
  while (std::time(nullptr) < st.st_ctim.tv_sec + 3) ::usleep(100'000);  // settled: see above
  const std::string first = fx->dir + "/cal-span-1.pbtxt", second = fx->dir + "/cal-span-2.pbtxt";
  const std::vector<std::string> logs = {"--log", poses, "--log", fx->log, "--config", kConfig};
  auto args = [&](const std::string& out) {
    std::vector<std::string> a = logs;
    a.insert(a.end(), {"--out", out});
    return a;
  };
  const Result r1 = Run(args(first), "span1");
  const Result r2 = Run(args(second), "span2");
  cache_env.reset();
  ASSERT_EQ(r1.exit_code, 0) << r1.err;
  ASSERT_EQ(r2.exit_code, 0) << r2.err;
  const std::string skipped = "not read: their records were counted when this log was read before";
  EXPECT_EQ(r1.err.find(skipped), std::string::npos) << r1.err;
  EXPECT_NE(r2.err.find(skipped), std::string::npos) << r2.err;
  calibration::Calibration a = ReadCalibrationFile(first), b = ReadCalibrationFile(second);
  EXPECT_EQ(a.recording_gaps_size(), b.recording_gaps_size());
  a.clear_provenance();
  b.clear_provenance();
  EXPECT_EQ(a.DebugString(), b.DebugString());
  EXPECT_EQ(ReadFile(ResidualsPathFor(first)), ReadFile(ResidualsPathFor(second)));
  EXPECT_EQ(ReadFile(WalkingPathFor(first)), ReadFile(WalkingPathFor(second)));
}

// A Net F/T in buffered mode sends several records a datagram, and the bridge publishes them
// as one ft_batch_t. The session with each leg's records regrouped 7 to a message (sent when
// its last record was, receipt = that record's time; a message ends early where the records'
// rdt_sequence jumps, as a datagram holds consecutive records, and at a marker, as the twin's
// log has no records between its phases) calibrates to the same calibration, number for number: the
// reader is indifferent to how the records were batched.
TEST_F(CalibratorTest, RecordsBatchedSevenToAMessageCalibrateTheSame) {
  constexpr int kPerMessage = 7;
  const auto& ch = fx->config.channels();
  std::map<std::string, int64_t> left;  // per FT channel: records still to come
  for (const Event& e : fx->events) {
    if (e.channel.rfind(ch.ft_prefix(), 0) == 0) ++left[e.channel];
  }
  ASSERT_EQ(left.size(), static_cast<size_t>(kNumLegs));
  std::map<std::string, ft_batch_t> open;   // per FT channel: the message being filled
  std::map<std::string, Event> open_event;  // per FT channel: the last record's event
  std::vector<Event> events;
  int64_t records_in = 0, records_out = 0, messages_out = 0;
  auto close = [&](const std::string& channel) {
    ft_batch_t& b = open[channel];
    if (b.n == 0) return;
    records_out += b.n;
    ++messages_out;
    events.push_back(Encode(open_event[channel].utime, channel, b));
    b = ft_batch_t{};
  };
  for (const Event& e : fx->events) {
    // The twin's log has no records between its phases: a datagram the box sent before a
    // marker went out before it.
    if (e.channel == ch.experiment()) {
      for (int k = 0; k < kNumLegs; ++k) close(ch.ft_prefix() + std::string(kLegNames[k]));
    }
    if (e.channel.rfind(ch.ft_prefix(), 0) != 0) {
      events.push_back(e);
      continue;
    }
    ft_batch_t one;
    ASSERT_EQ(one.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
              static_cast<int>(e.data.size()));
    ASSERT_EQ(one.n, 1) << "the twin's log: a record a message";
    ASSERT_EQ(one.sample_utime[0], one.receipt_utime);
    ++records_in;
    if (open[e.channel].n > 0 && one.rdt_sequence[0] != open[e.channel].rdt_sequence.back() + 1) {
      close(e.channel);
    }
    ft_batch_t& b = open[e.channel];
    open_event[e.channel] = e;
    if (b.n == 0) {
      b = ft_batch_t{};
      b.leg = one.leg;
    }
    ++b.n;
    b.receipt_utime = one.receipt_utime;
    b.sample_utime.push_back(one.sample_utime[0]);
    b.rdt_sequence.push_back(one.rdt_sequence[0]);
    b.ft_sequence.push_back(one.ft_sequence[0]);
    b.status.push_back(one.status[0]);
    b.counts.push_back(one.counts[0]);
    b.wrench.push_back(one.wrench[0]);
    b.gap.push_back(one.gap[0]);
    b.flags.push_back(one.flags[0]);
    const bool last = --left[e.channel] == 0;
    if (b.n == kPerMessage || last) close(e.channel);
  }
  for (const auto& [channel, b] : open) EXPECT_EQ(b.n, 0) << channel << ": records left over";
  ASSERT_EQ(records_out, records_in);
  // Mostly 7 a message: a short one only where a phase ends.
  ASSERT_LE(messages_out, records_in / kPerMessage + 20 * kNumLegs);
  const std::string batched = fx->dir + "/batched.lcmlog";
  WriteLog(batched, events);
  {  // What the log holds: every record once, in order, 7 a message.
    for (int k = 0; k < kNumLegs; ++k) {
      const std::string channel = ch.ft_prefix() + std::string(kLegNames[k]);
      const std::vector<FtRecord> a = twin_log::ReadFtRecords(fx->log, channel, k);
      const std::vector<FtRecord> b = twin_log::ReadFtRecords(batched, channel, k);
      ASSERT_EQ(a.size(), b.size()) << channel;
      for (size_t i = 0; i < a.size(); ++i) {
        ASSERT_EQ(a[i].in.utime, b[i].in.utime) << channel << " " << i;
        ASSERT_EQ(a[i].rdt_sequence, b[i].rdt_sequence) << channel << " " << i;
        ASSERT_EQ(a[i].in.wrench, b[i].in.wrench) << channel << " " << i;
      }
      const auto messages = twin_log::ReadChannel<ft_batch_t>(batched, channel);
      EXPECT_LT(messages.size(), a.size() / kPerMessage + 20) << channel;
    }
  }
  {  // Collected in this process first, to say where a difference begins.
    CalibrationCollector one(fx->config), seven(fx->config);
    EXPECT_EQ(ReadIndexed(one, fx->log, nullptr), 0);
    EXPECT_EQ(ReadIndexed(seven, batched, nullptr), 0);
    ASSERT_EQ(one.phase_gaps().size(), seven.phase_gaps().size());
    for (size_t p = 0; p < one.phase_gaps().size(); ++p) {
      const PhaseGaps &a = one.phase_gaps()[p], &b = seven.phase_gaps()[p];
      SCOPED_TRACE(PhaseName(a.phase));
      EXPECT_EQ(a.phase, b.phase);
      EXPECT_EQ(a.received, b.received);
      EXPECT_EQ(a.lost, b.lost);
      EXPECT_EQ(a.restarts, b.restarts);
    }
    const std::vector<HangingRecording>& ha = one.HangingRecordings();
    const std::vector<HangingRecording>& hb = seven.HangingRecordings();
    ASSERT_EQ(ha.size(), hb.size());
    for (size_t s = 0; s < ha.size(); ++s) {
      for (int k = 0; k < kNumLegs; ++k) {
        EXPECT_EQ(ha[s].legs[k].t_s.size(), hb[s].legs[k].t_s.size())
            << "hanging series " << s << ", leg " << kLegNames[k] << ": aligned samples";
        EXPECT_TRUE(ha[s].legs[k].t_s == hb[s].legs[k].t_s &&
                    ha[s].legs[k].wrench == hb[s].legs[k].wrench &&
                    ha[s].legs[k].angle_rad == hb[s].legs[k].angle_rad)
            << "hanging series " << s << ", leg " << kLegNames[k];
      }
    }
    EXPECT_EQ(one.segmented_pose_count(), seven.segmented_pose_count());
    EXPECT_EQ(one.walking_samples().size(), seven.walking_samples().size());
  }

  const std::string one_out = fx->dir + "/cal-one-a-message.pbtxt";
  const std::string batched_out = fx->dir + "/cal-batched.pbtxt";
  const Result r1 = Run({"--log", fx->log, "--config", kConfig, "--out", one_out}, "one_a_message");
  const Result r7 = Run({"--log", batched, "--config", kConfig, "--out", batched_out}, "batched");
  ASSERT_EQ(r1.exit_code, 0) << r1.err;
  ASSERT_EQ(r7.exit_code, 0) << r7.err;
  calibration::Calibration a = ReadCalibrationFile(one_out), b = ReadCalibrationFile(batched_out);
  ASSERT_EQ(a.leg_size(), kNumLegs);
  EXPECT_EQ(a.recording_gaps_size(), b.recording_gaps_size());
  // Everything but the provenance (the input's name and digest, command line, time).
  a.clear_provenance();
  b.clear_provenance();
  EXPECT_EQ(a.DebugString(), b.DebugString());
  EXPECT_EQ(ReadFile(ResidualsPathFor(one_out)), ReadFile(ResidualsPathFor(batched_out)));
}

// A session recorded before the batched FT message (ft_sample_t, one record a message), before
// the fixed-size arrays (servo_state_t with its num_servos) and before the mapped sample times
// (servo_state_t and mocap_body_t without sample_utime; every other servo message of one
// version, every other of the next), written here with those versions' own generated encoders:
// the calibrator refuses it, naming the command that converts it; converted by
// ftcal-log-upgrade, it calibrates to the current log's calibration, number for number (the
// fixture's log carries sample_utime = utime, what every reader aligned by before).
TEST_F(CalibratorTest, AnOlderLogIsRefusedNamingTheUpgradeAndUpgradedCalibratesTheSame) {
  const auto& ch = fx->config.channels();
  std::vector<Event> events;
  int64_t ft = 0, servo = 0, mocap = 0;
  for (const Event& e : fx->events) {
    if (e.channel.rfind(ch.ft_prefix(), 0) == 0) {
      ft_batch_t b;
      ASSERT_EQ(b.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                static_cast<int>(e.data.size()));
      for (size_t i = 0; i < static_cast<size_t>(b.n); ++i, ++ft) {
        ftcal_pre_batch::ft_sample_t old{};
        old.utime = b.sample_utime[i];
        old.leg = b.leg;
        old.rdt_sequence = b.rdt_sequence[i];
        old.ft_sequence = b.ft_sequence[i];
        old.status = b.status[i];
        for (size_t j = 0; j < 6; ++j) {
          old.counts[j] = b.counts[i][j];
          old.wrench[j] = b.wrench[i][j];
        }
        old.gap = b.gap[i];
        old.flags = b.flags[i];
        events.push_back(Encode(e.utime, e.channel, old));
      }
    } else if (e.channel == ch.servo_state()) {
      servo_state_t s;
      ASSERT_EQ(s.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                static_cast<int>(e.data.size()));
      ASSERT_EQ(s.sample_utime, s.utime);
      if (servo++ % 2 == 1) {
        ftcal_pre_sample_time::servo_state_t old{};
        old.utime = s.utime;
        for (int k = 0; k < kNumLegs; ++k) {
          old.leg[k] = s.leg[k];
          old.id[k] = s.id[k];
          old.angle_rad[k] = s.angle_rad[k];
          old.velocity_rad_s[k] = s.velocity_rad_s[k];
          old.current_a[k] = s.current_a[k];
          old.hardware_error[k] = s.hardware_error[k];
          old.device_tick_ms[k] = s.device_tick_ms[k];
          old.flags[k] = s.flags[k];
        }
        events.push_back(Encode(e.utime, e.channel, old));
        continue;
      }
      ftcal_pre_fixed6::servo_state_t old{};
      old.utime = s.utime;
      old.num_servos = kNumLegs;
      for (int k = 0; k < kNumLegs; ++k) {
        old.leg.push_back(s.leg[k]);
        old.id.push_back(s.id[k]);
        old.angle_rad.push_back(s.angle_rad[k]);
        old.velocity_rad_s.push_back(s.velocity_rad_s[k]);
        old.current_a.push_back(s.current_a[k]);
        old.hardware_error.push_back(s.hardware_error[k]);
        old.device_tick_ms.push_back(s.device_tick_ms[k]);
        old.flags.push_back(s.flags[k]);
      }
      events.push_back(Encode(e.utime, e.channel, old));
    } else if (e.channel == ch.mocap_body()) {
      mocap_body_t m;
      ASSERT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                static_cast<int>(e.data.size()));
      ASSERT_EQ(m.sample_utime, m.utime);
      ftcal_pre_sample_time::mocap_body_t old{};
      old.utime = m.utime;
      old.frame_number = m.frame_number;
      old.device_utime = m.device_utime;
      old.body = m.body;
      old.tracked = m.tracked;
      for (int i = 0; i < 4; ++i) {
        old.q_wc[i] = m.q_wc[i];
        old.q_gc[i] = m.q_gc[i];
      }
      for (int i = 0; i < 3; ++i) old.position_m[i] = m.position_m[i];
      old.yaw_rad = m.yaw_rad;
      old.residual_m = m.residual_m;
      old.num_markers = m.num_markers;
      old.marker_m = m.marker_m;
      old.marker_tracked = m.marker_tracked;
      events.push_back(Encode(e.utime, e.channel, old));
      ++mocap;
    } else {
      events.push_back(e);
    }
  }
  ASSERT_GT(ft, 0);
  ASSERT_GT(servo, 1);
  ASSERT_GT(mocap, 0);
  const std::string old_log = fx->dir + "/older.lcmlog", new_log = fx->dir + "/upgraded.lcmlog";
  WriteLog(old_log, events);

  const Result refused =
      Run({"--log", old_log, "--config", kConfig, "--out", fx->dir + "/cal-older.pbtxt"}, "older");
  EXPECT_EQ(refused.exit_code, 2) << refused.err;
  EXPECT_NE(refused.err.find("ftcal-log-upgrade"), std::string::npos) << refused.err;

  Child upgrade({FTCAL_LOG_UPGRADE, old_log, new_log}, fx->dir + "/upgrade.out",
                fx->dir + "/upgrade.err");
  const auto status = upgrade.Wait(120);
  ASSERT_TRUE(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << ReadFile(fx->dir + "/upgrade.err");

  const std::string current_out = fx->dir + "/cal-current.pbtxt";
  const std::string upgraded_out = fx->dir + "/cal-upgraded.pbtxt";
  const Result r1 = Run({"--log", fx->log, "--config", kConfig, "--out", current_out}, "current");
  const Result r2 = Run({"--log", new_log, "--config", kConfig, "--out", upgraded_out}, "upgraded");
  ASSERT_EQ(r1.exit_code, 0) << r1.err;
  ASSERT_EQ(r2.exit_code, 0) << r2.err;
  calibration::Calibration a = ReadCalibrationFile(current_out);
  calibration::Calibration b = ReadCalibrationFile(upgraded_out);
  ASSERT_EQ(a.leg_size(), kNumLegs);
  a.clear_provenance();
  b.clear_provenance();
  EXPECT_EQ(a.DebugString(), b.DebugString());
  EXPECT_EQ(ReadFile(ResidualsPathFor(current_out)), ReadFile(ResidualsPathFor(upgraded_out)));
}

// A writer hands its log's digest over: the segmenter takes the poses log's SHA-256 as it
// writes it, so the first calibration that reads the log takes the digest from the cache
// (and says so), and the provenance is still the file's own hash. The session log, written
// by this test and not by one of ftcal's writers, is hashed.
TEST_F(CalibratorTest, TheFirstRunTakesThePosesLogsDigestFromTheSegmenterThatWroteIt) {
  const std::string cache = fx->dir + "/writer-cache";
  std::optional<testing::ScopedEnv> cache_env(std::in_place, "FTCAL_CACHE_DIR", cache);
  const std::string poses = fx->dir + "/poses-handed.lcmlog";
  Child seg({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--replay", fx->log, "--out", poses},
            fx->dir + "/seg-handed.out", fx->dir + "/seg-handed.err");
  const auto status = seg.Wait(120);
  const std::string out = fx->dir + "/cal-handed.pbtxt";
  const Result r =
      Run({"--log", poses, "--log", fx->log, "--config", kConfig, "--out", out}, "handed");
  cache_env.reset();
  ASSERT_TRUE(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << ReadFile(fx->dir + "/seg-handed.err");
  const std::string poses_sha = Sha256File(poses);
  const std::string seg_log =
      ReadFile(fx->dir + "/seg-handed.err") + ReadFile(fx->dir + "/seg-handed.out");
  EXPECT_NE(seg_log.find("SHA-256 " + poses_sha + " handed to the digest cache"), std::string::npos)
      << seg_log;
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.err.find(poses + ": SHA-256 from the digest cache in " + cache), std::string::npos)
      << r.err;
  EXPECT_EQ(r.err.find(fx->log + ": SHA-256 from the digest cache"), std::string::npos) << r.err;
  // Nor did the segmenter index the session: the first calibration hashes it, reading it whole.
  EXPECT_NE(seg_log.find(fx->log + ": no span index for the calibrator: its digest is not in "
                                   "the cache"),
            std::string::npos)
      << seg_log;
  const auto cal = ReadCalibrationFile(out);
  ASSERT_EQ(cal.provenance().input_size(), 2);
  for (const auto& input : cal.provenance().input()) {
    EXPECT_EQ(input.sha256(), Sha256File(input.path())) << input.path();
  }
}

// The segmenter's replay leaves the session's span index beside its digest (here stored by the
// test, as the session's writer would hand it over): the first calibration after it skips the
// STANDING span and writes what a calibrator that reads everything writes, number for number.
// The index is the one a calibrator makes when it reads the session whole, byte for byte.
TEST_F(CalibratorTest, TheSegmentersReplayIndexesTheSessionForTheFirstCalibration) {
  struct stat st {};
  ASSERT_EQ(::stat(fx->log.c_str(), &st), 0);
  while (std::time(nullptr) < st.st_ctim.tv_sec + 3) ::usleep(100'000);  // settled: see above
  const std::optional<FileKey> key = FileKeyOf(fx->log);
  ASSERT_TRUE(key);
  const std::string sha = Sha256File(fx->log);
  const std::string cache = fx->dir + "/segmenter-index-cache",
                    by_calibrator = fx->dir + "/calibrator-index-cache";
  for (const std::string& dir : {cache, by_calibrator}) {
    ASSERT_TRUE(DigestCache(dir).Store(fx->log, *key, sha)) << dir;
  }

  std::optional<testing::ScopedEnv> cache_env(std::in_place, "FTCAL_CACHE_DIR", cache);
  const std::string poses = fx->dir + "/poses-indexing.lcmlog";
  Child seg({FTCAL_POSE_SEGMENTER, "--config", kConfig, "--replay", fx->log, "--out", poses},
            fx->dir + "/seg-indexing.out", fx->dir + "/seg-indexing.err");
  const auto status = seg.Wait(120);
  ASSERT_TRUE(status && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << ReadFile(fx->dir + "/seg-indexing.err");
  const std::string seg_log = ReadFile(fx->dir + "/seg-indexing.err");
  EXPECT_TRUE(std::regex_search(
      seg_log, std::regex("span index for the calibrator in the digest cache: [1-9][0-9]* spans")))
      << seg_log;
  const std::optional<std::string> index = DigestCache(cache).LookupNote("spans", fx->log);
  ASSERT_TRUE(index) << seg_log;

  const std::string first = fx->dir + "/cal-seg-index.pbtxt";
  const Result r =
      Run({"--log", poses, "--log", fx->log, "--config", kConfig, "--out", first}, "seg-index");
  cache_env.reset();
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_NE(r.err.find("STANDING (session"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("not read: their records were counted when this log was read before"),
            std::string::npos)
      << r.err;

  // What a calibrator writes reading everything (no cache: both logs hashed and read whole).
  const std::string whole = fx->dir + "/cal-whole.pbtxt";
  std::optional<testing::ScopedEnv> no_cache(std::in_place, "FTCAL_CACHE_DIR", "");
  const Result w =
      Run({"--log", poses, "--log", fx->log, "--config", kConfig, "--out", whole}, "whole");
  no_cache.reset();
  ASSERT_EQ(w.exit_code, 0) << w.err;
  EXPECT_EQ(w.err.find("not read:"), std::string::npos) << w.err;
  calibration::Calibration a = ReadCalibrationFile(first), b = ReadCalibrationFile(whole);
  EXPECT_EQ(a.provenance().input(1).sha256(), sha);
  a.clear_provenance();
  b.clear_provenance();
  EXPECT_EQ(a.DebugString(), b.DebugString());
  EXPECT_EQ(ReadFile(ResidualsPathFor(first)), ReadFile(ResidualsPathFor(whole)));
  EXPECT_EQ(ReadFile(WalkingPathFor(first)), ReadFile(WalkingPathFor(whole)));

  // The index a calibrator stores reading the session whole is the segmenter's.
  std::optional<testing::ScopedEnv> other(std::in_place, "FTCAL_CACHE_DIR", by_calibrator);
  const Result c = Run({"--log", poses, "--log", fx->log, "--config", kConfig, "--out",
                        fx->dir + "/cal-own-index.pbtxt"},
                       "own-index");
  other.reset();
  ASSERT_EQ(c.exit_code, 0) << c.err;
  const std::optional<std::string> own = DigestCache(by_calibrator).LookupNote("spans", fx->log);
  ASSERT_TRUE(own) << c.err;
  EXPECT_EQ(*index, *own);
}

// The walk follows the STANDING phase. Over a span not segmented again the transducer records
// are only counted and the servo states and mocap frames decoded only at its end (the last
// ones, all the aligner keeps): the walk is then aligned sample for sample as when the
// collector segments that span itself, shaft angles and attitudes included.
TEST_F(CalibratorTest, AStandingSpanNotSegmentedAgainLeavesTheAlignerAsSegmentingItWould) {
  const std::string poses = PosesLog();
  ASSERT_FALSE(poses.empty());
  CalibrationCollector own(fx->config), skipping(fx->config);
  skipping.SetSkipSegmentingLoggedSessions(true);
  ReadInto(own, fx->log);
  ReadInto(skipping, poses);
  ReadInto(skipping, fx->log);
  own.Flush();
  skipping.Flush();
  EXPECT_GT(own.segmented_pose_count(), 0u);
  EXPECT_EQ(skipping.segmented_pose_count(), 0u);
  const std::vector<SyncSample>& a = own.walking_samples();
  const std::vector<SyncSample>& b = skipping.walking_samples();
  ASSERT_GT(a.size(), 100u);
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    SCOPED_TRACE("walking sample " + std::to_string(i));
    ASSERT_EQ(a[i].utime, b[i].utime);
    ASSERT_EQ(a[i].angle_rad, b[i].angle_rad);
    ASSERT_EQ(a[i].wrench, b[i].wrench);
    ASSERT_EQ(a[i].R_WC, b[i].R_WC);
    ASSERT_EQ(a[i].attitude_ok, b[i].attitude_ok);
  }
  // The records of the span are counted all the same.
  ASSERT_EQ(own.phase_gaps().size(), skipping.phase_gaps().size());
  for (size_t p = 0; p < own.phase_gaps().size(); ++p) {
    EXPECT_EQ(own.phase_gaps()[p].received, skipping.phase_gaps()[p].received) << p;
    EXPECT_EQ(own.phase_gaps()[p].lost, skipping.phase_gaps()[p].lost) << p;
  }
}

// The span index. Reading a session whole after its poses log, the collector notes the span of
// the STANDING phase where it only counted records and kept servo states and mocap frames: from
// after the last event that did more (here a channel first seen inside the phase) to the first
// of the messages the phase's end keeps. Given that index, another collector skips the span
// and collects exactly what the whole reading did: every phase's counts (the span has records
// lost, two out of order and a restarted RDT stream) and the walk after it, aligned sample for
// sample from the servo states and mocap frames kept. An index whose counts do not match the
// reading's is not used.
TEST_F(CalibratorTest, ASpanIndexSkipsWhatItCountedAndChangesNothingCollected) {
  const std::string poses = PosesLog();
  ASSERT_FALSE(poses.empty());
  const auto& ch = fx->config.channels();
  std::vector<Event> events;
  std::vector<int64_t> offset{0};  // of each event written, and the end
  int phase = -1;
  int64_t hl = 0, ml = 0, mr = 0, note_offset = -1, stop_offset = -1;
  std::optional<Event> held;
  auto push = [&](const Event& e) {
    events.push_back(e);
    offset.push_back(offset.back() + 28 + static_cast<int64_t>(e.channel.size() + e.data.size()));
  };
  for (const Event& e : fx->events) {
    if (e.channel == ch.experiment()) {
      experiment_marker_t m;
      ASSERT_GT(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())), 0);
      if (m.phase == experiment_marker_t::STANDING && !m.start) stop_offset = offset.back();
      phase = m.start ? m.phase : -1;
    }
    if (phase == experiment_marker_t::STANDING) {
      if (e.channel == ch.ft_prefix() + "HL" && ++hl % 7 == 0) continue;  // lost
      if (e.channel == ch.ft_prefix() + "ML" && ++ml > 2000) {            // a new RDT stream
        ft_batch_t m;
        ASSERT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                  static_cast<int>(e.data.size()));
        ASSERT_EQ(m.n, 1);  // the twin's: a record a message
        m.rdt_sequence[0] = ml - 2000;
        push(Encode(e.utime, e.channel, m));
        continue;
      }
      if (e.channel == ch.ft_prefix() + "MR" && ++mr == 1500) {  // one record late
        held = e;
        continue;
      }
      if (note_offset < 0 && hl == 300) {  // a channel never seen before: not only counted
        note_offset = offset.back();
        push(Event{e.utime, "OPERATOR_NOTE", {1, 2, 3}});
      }
    }
    push(e);
    if (held && e.channel == ch.ft_prefix() + "MR") {
      push(*held);
      held.reset();
    }
  }
  ASSERT_GT(note_offset, 0);
  ASSERT_GT(stop_offset, note_offset);
  ASSERT_GT(ml, 2100);
  const std::string log = fx->dir + "/span-index.lcmlog";
  WriteLog(log, events);

  // Reads the poses log, then `log` with `index`: the bytes skipped.
  auto read = [&](CalibrationCollector& c, const logindex::LogIndex* index) {
    c.SetSkipSegmentingLoggedSessions(true);
    ReadInto(c, poses);
    return ReadIndexed(c, log, index);
  };
  CalibrationCollector whole(fx->config);
  EXPECT_EQ(read(whole, nullptr), 0);
  const logindex::LogIndex index = whole.TakeSpanIndex();
  ASSERT_EQ(index.span_size(), 1) << index.DebugString();
  const logindex::SkippableSpan& span = index.span(0);
  EXPECT_EQ(index.rules(), whole.SpanIndexRules());
  EXPECT_EQ(span.session(), "calibrator-test");
  // It begins at the event after the new channel's, and ends before the stop marker with a
  // servo state or mocap frame (the first the end keeps).
  EXPECT_EQ(span.from_offset(), *std::upper_bound(offset.begin(), offset.end(), note_offset));
  EXPECT_LT(span.to_offset(), stop_offset);
  const auto at_to = std::find(offset.begin(), offset.end(), span.to_offset());
  ASSERT_NE(at_to, offset.end()) << "not an event's start";
  const std::string& first_kept = events[static_cast<size_t>(at_to - offset.begin())].channel;
  EXPECT_TRUE(first_kept == ch.servo_state() || first_kept == ch.mocap_body()) << first_kept;
  EXPECT_EQ(span.events(),
            (at_to - offset.begin()) -
                (std::find(offset.begin(), offset.end(), span.from_offset()) - offset.begin()));

  CalibrationCollector skipping(fx->config);
  EXPECT_EQ(read(skipping, &index), span.to_offset() - span.from_offset());
  EXPECT_EQ(skipping.counters().span_events_skipped, span.events());
  EXPECT_EQ(skipping.TakeSpanIndex().span_size(), 0) << "a reading with skips notes nothing";

  logindex::LogIndex other = index;
  other.mutable_span(0)->mutable_at_from(3)->set_received(span.at_from(3).received() + 1);
  CalibrationCollector declined(fx->config);
  EXPECT_EQ(read(declined, &other), 0);
  EXPECT_EQ(declined.counters().span_events_skipped, 0);

  for (const CalibrationCollector* c : {&skipping, &declined}) {
    ASSERT_EQ(c->phase_gaps().size(), whole.phase_gaps().size());
    for (size_t p = 0; p < whole.phase_gaps().size(); ++p) {
      const PhaseGaps &a = whole.phase_gaps()[p], &b = c->phase_gaps()[p];
      SCOPED_TRACE(PhaseName(a.phase));
      EXPECT_EQ(a.phase, b.phase);
      EXPECT_EQ(a.received, b.received);
      EXPECT_EQ(a.lost, b.lost);
      EXPECT_EQ(a.restarts, b.restarts);
      if (a.phase == experiment_marker_t::STANDING) {
        EXPECT_EQ(a.lost[0], hl / 7 - (hl % 7 == 0 ? 1 : 0)) << "HL: every 7th record";
        EXPECT_EQ(a.restarts[1], 1) << "ML's new stream";
        EXPECT_EQ(a.lost[4], 0) << "MR's late record fills its gap";
      }
    }
    const std::vector<SyncSample>&wa = whole.walking_samples(), &wb = c->walking_samples();
    ASSERT_GT(wa.size(), 100u);
    ASSERT_EQ(wa.size(), wb.size());
    for (size_t i = 0; i < wa.size(); ++i) {
      ASSERT_EQ(wa[i].utime, wb[i].utime) << i;
      ASSERT_EQ(wa[i].angle_rad, wb[i].angle_rad) << i;
      ASSERT_EQ(wa[i].wrench, wb[i].wrench) << i;
      ASSERT_EQ(wa[i].R_WC, wb[i].R_WC) << i;
    }
    EXPECT_EQ(c->StandingPoses().size(), whole.StandingPoses().size());
    EXPECT_EQ(c->unloaded_samples().size(), whole.unloaded_samples().size());
    EXPECT_EQ(c->tare().has_value(), whole.tare().has_value());
    if (c->tare() && whole.tare()) {
      EXPECT_EQ((*c->tare())[2], (*whole.tare())[2]);
    }
  }
}

// Offline calibration does not collect tripod stances (only offset re-estimation takes them):
// a TRIPOD phase is then only counted, to the same counts as a reading that segments it, its
// span noted under its phase and skipped another time; a reading that wants the stances reads
// it. Here the fixture's walk, a tripod gait, is marked TRIPOD.
TEST_F(CalibratorTest, ATripodPhaseNotCollectedIsCountedTheSameAndSkippedAnotherTime) {
  const auto& ch = fx->config.channels();
  std::vector<Event> events;
  for (const Event& e : fx->events) {
    experiment_marker_t m;
    if (e.channel == ch.experiment() &&
        m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0 &&
        m.phase == experiment_marker_t::WALKING) {
      m.phase = experiment_marker_t::TRIPOD;
      events.push_back(Encode(e.utime, e.channel, m));
      continue;
    }
    events.push_back(e);
  }
  const std::string log = fx->dir + "/tripod.lcmlog";
  WriteLog(log, events);
  auto read = [&](CalibrationCollector& c, bool collect, const logindex::LogIndex* index) {
    c.SetCollectTripodStances(collect);
    return ReadIndexed(c, log, index);
  };
  CalibrationCollector segmenting(fx->config), counting(fx->config);
  EXPECT_EQ(read(segmenting, true, nullptr), 0);
  EXPECT_EQ(read(counting, false, nullptr), 0);
  EXPECT_EQ(segmenting.TakeSpanIndex().span_size(), 0) << "a segmented phase is not skippable";
  // No poses log was read first, so STANDING was segmented: the one span is the tripod's.
  const logindex::LogIndex index = counting.TakeSpanIndex();
  ASSERT_EQ(index.span_size(), 1) << index.DebugString();
  const logindex::SkippableSpan& span = index.span(0);
  EXPECT_EQ(span.phase(), int{experiment_marker_t::TRIPOD});
  CalibrationCollector skipping(fx->config), collecting(fx->config);
  EXPECT_EQ(read(skipping, false, &index), span.to_offset() - span.from_offset());
  EXPECT_EQ(skipping.counters().span_events_skipped, span.events());
  EXPECT_EQ(read(collecting, true, &index), 0) << "its stances wanted: the tripod is read";
  bool tripod_seen = false;
  for (const CalibrationCollector* c : {&counting, &skipping, &collecting}) {
    ASSERT_EQ(c->phase_gaps().size(), segmenting.phase_gaps().size());
    for (size_t p = 0; p < segmenting.phase_gaps().size(); ++p) {
      const PhaseGaps &a = segmenting.phase_gaps()[p], &b = c->phase_gaps()[p];
      SCOPED_TRACE(PhaseName(a.phase));
      tripod_seen = tripod_seen || a.phase == experiment_marker_t::TRIPOD;
      EXPECT_EQ(a.phase, b.phase);
      EXPECT_EQ(a.received, b.received);
      EXPECT_EQ(a.lost, b.lost);
      EXPECT_EQ(a.restarts, b.restarts);
    }
    EXPECT_EQ(c->StandingPoses().size(), segmenting.StandingPoses().size());
  }
  EXPECT_TRUE(tripod_seen);
  EXPECT_TRUE(counting.unloaded_samples().empty());
  EXPECT_TRUE(skipping.unloaded_samples().empty());
  EXPECT_EQ(collecting.unloaded_samples().size(), segmenting.unloaded_samples().size());
}

// Offline, Calibrate() starts on its own thread when the session's STANDING phase starts and
// is not segmented again (its poses were read before): its result is the calibration the
// calibrator computes after reading, and a change to its inputs afterwards discards it (here:
// the poses log read again adds its poses).
TEST_F(CalibratorTest, AnEarlyCalibrationIsTheLateOneAndIsDiscardedWhenItsInputsChange) {
  const std::string poses = PosesLog();
  ASSERT_FALSE(poses.empty());
  CalibratorOptions options;
  options.config_path = kConfig;
  {
    CalibrationCollector collector(fx->config);
    collector.SetSkipSegmentingLoggedSessions(true);
    EarlyCalibration early(collector, fx->config, options);
    EXPECT_FALSE(early.started());
    ReadInto(collector, poses);
    EXPECT_FALSE(early.started());  // no hanging series yet
    ReadInto(collector, fx->log);
    collector.Flush();
    EXPECT_TRUE(early.started());
    CalibrationRun taken = RunCalibration(collector, fx->config, options, &early);
    CalibrationRun computed = RunCalibration(collector, fx->config, options);
    taken.proto.clear_provenance();
    computed.proto.clear_provenance();
    EXPECT_GT(taken.proto.leg_size(), 0);
    EXPECT_EQ(taken.proto.DebugString(), computed.proto.DebugString());
  }
  {
    CalibrationCollector collector(fx->config);
    collector.SetSkipSegmentingLoggedSessions(true);
    EarlyCalibration early(collector, fx->config, options);
    ReadInto(collector, poses);
    ReadInto(collector, fx->log);
    ASSERT_TRUE(early.started());
    ReadInto(collector, poses);
    collector.Flush();
    EXPECT_FALSE(early.Take().has_value());
  }
}

// --profile report: the report's procedure (first-order hanging rotations, fixed CoM, no prior),
// four candidates; the file says so.
TEST_F(CalibratorTest, ReportProfileFromTheCommandLine) {
  const std::string out = fx->dir + "/cal-report.pbtxt";
  const Result r =
      Run({"--log", fx->log, "--config", kConfig, "--out", out, "--profile", "report"}, "report");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const calibration::Calibration cal = ReadCalibrationFile(out);
  EXPECT_EQ(cal.solver().profile(), "REPORT");
  EXPECT_FALSE(cal.solver().exact_hanging_rotations());
  EXPECT_FALSE(cal.solver().hanging_gravity_prior());
  EXPECT_FALSE(cal.solver().leg_aware_com());
  EXPECT_EQ(cal.model_selection_size(), 4);
  EXPECT_NE(r.out.find("profile REPORT"), std::string::npos) << r.out;
}

TEST_F(CalibratorTest, CalibratesTheTwinsLogCloseToTruthWithProvenanceAndReport) {
  const std::string out = fx->dir + "/cal.pbtxt";
  const std::string report = fx->dir + "/report";
  const Result r = Run({"--log", fx->log, "--config", kConfig, "--out", out, "--report", report,
                        "--truth", fx->truth},
                       "ok");
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const calibration::Calibration cal = ReadCalibrationFile(out);
  const calibration::Calibration truth = ReadCalibrationFile(fx->truth);
  ASSERT_EQ(cal.leg_size(), kNumLegs);
  double worst_weight = 0.0, worst_force = 0.0, worst_torque = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& e = cal.leg(k);
    const auto& t = truth.leg(k);
    SCOPED_TRACE(e.name());
    worst_weight =
        std::max(worst_weight, std::abs(e.leg_weight_n().value() - t.leg_weight_n().value()));
    for (const auto& [a, b] : {std::pair{e.force_offset_n().x(), t.force_offset_n().x()},
                               {e.force_offset_n().y(), t.force_offset_n().y()},
                               {e.force_offset_n().z(), t.force_offset_n().z()}}) {
      worst_force = std::max(worst_force, std::abs(a - b));
    }
    for (const auto& [a, b] : {std::pair{e.torque_offset_nm().x(), t.torque_offset_nm().x()},
                               {e.torque_offset_nm().y(), t.torque_offset_nm().y()},
                               {e.torque_offset_nm().z(), t.torque_offset_nm().z()}}) {
      worst_torque = std::max(worst_torque, std::abs(a - b));
    }
    EXPECT_EQ(e.name(), t.name());
    // Noise 0.05 N per sample over thousands of samples: seed 11 lands within 0.012 N
    // (weights), 0.005 N and 0.0002 N m (offsets); the bounds leave 4-10x room for the short
    // series (3 cycles) and are still far below the errors a wrong series or sign would give.
    EXPECT_NEAR(e.leg_weight_n().value(), t.leg_weight_n().value(), 0.05);
    EXPECT_NEAR(e.force_offset_n().x(), t.force_offset_n().x(), 0.05);
    EXPECT_NEAR(e.force_offset_n().y(), t.force_offset_n().y(), 0.05);
    EXPECT_NEAR(e.force_offset_n().z(), t.force_offset_n().z(), 0.05);
    EXPECT_NEAR(e.torque_offset_nm().x(), t.torque_offset_nm().x(), 0.002);
    EXPECT_NEAR(e.torque_offset_nm().y(), t.torque_offset_nm().y(), 0.002);
    EXPECT_NEAR(e.torque_offset_nm().z(), t.torque_offset_nm().z(), 0.002);
  }
  std::printf(
      "calibrator vs twin truth: |d mg| <= %.4f N, |d f_o| <= %.4f N, |d tau_o| <= "
      "%.5f N m\n%s",
      worst_weight, worst_force, worst_torque, r.out.c_str());
  EXPECT_GE(cal.standing_poses(), kPoses * 9 / 10);
  ASSERT_EQ(cal.provenance().input_size(), 1);
  EXPECT_EQ(cal.provenance().input(0).sha256(), Sha256File(fx->log));
  EXPECT_EQ(cal.provenance().input(0).bytes(), std::filesystem::file_size(fx->log));
  EXPECT_EQ(cal.provenance().config_sha256(), Sha256File(kConfig));
  EXPECT_FALSE(cal.provenance().software_version().empty());
  // The summary table is printed, with the selected model's name.
  EXPECT_NE(r.out.find(calibration::StandingModel_Name(cal.model())), std::string::npos) << r.out;
  // The default: eight candidates (four mounting models x fixed / leg-aware robot CoM), the
  // margin it won by, the mass check and the journal's RMSE, naive tare against calibrated.
  EXPECT_EQ(cal.model_selection_size(), 8);
  EXPECT_EQ(cal.solver().profile(), "FTCAL");
  EXPECT_NE(r.out.find("selected by a BIC margin of"), std::string::npos) << r.out;
  ASSERT_TRUE(cal.has_mass_check());
  EXPECT_TRUE(cal.mass_check().consistent());
  EXPECT_NE(r.out.find("Total mass: configured"), std::string::npos) << r.out;
  ASSERT_GE(cal.result_rmse_size(), 2);  // standing poses and the walk (+ legs with --truth)
  for (const auto& row : cal.result_rmse()) {
    EXPECT_GT(row.count(), 0u) << row.samples() << " " << row.wrench();
    EXPECT_LT(row.force_calibrated_n(), row.force_naive_n())
        << row.samples() << " " << row.wrench();
    EXPECT_LT(row.torque_calibrated_nm(), row.torque_naive_nm())
        << row.samples() << " " << row.wrench();
  }
  EXPECT_NE(r.out.find("Ground-contact RMSE"), std::string::npos) << r.out;

  // Residuals: one row per pose and variant.
  const std::string csv = ReadFile(ResidualsPathFor(out));
  const auto rows = std::count(csv.begin(), csv.end(), '\n');
  EXPECT_EQ(rows, 1 + 3 * static_cast<long>(cal.standing_poses()));

  // The report and every image it names.
  const std::string html = ReadFile(report + "/index.html");
  ASSERT_FALSE(html.empty());
  std::set<std::string> images;
  const std::regex img("src=\"([^\"]+\\.png)\"");
  for (auto it = std::sregex_iterator(html.begin(), html.end(), img); it != std::sregex_iterator();
       ++it) {
    images.insert((*it)[1]);
  }
  EXPECT_GE(images.size(), 4u);
  for (const std::string& name : images) {
    const std::string path = report + "/" + name;
    ASSERT_TRUE(std::filesystem::exists(path)) << path;
    EXPECT_GT(std::filesystem::file_size(path), 1000u) << path;
  }
  // With --truth, the true values are beside the estimates.
  EXPECT_NE(html.find("truth"), std::string::npos);
  // The correlation of the estimates: the report's strongest pair of HL is the file's.
  ASSERT_TRUE(cal.has_correlation());
  {
    const auto& c = cal.correlation();
    const int n = c.parameter_size();
    ASSERT_EQ(c.value_size(), n * n);
    auto of_hl = [&](int i) { return c.parameter(i).rfind("HL ", 0) == 0; };
    int bi = -1, bj = -1;
    for (int i = 0; i < n; ++i) {
      for (int j = i + 1; j < n; ++j) {
        if (!of_hl(i) && !of_hl(j)) continue;
        if (bi < 0 || std::abs(c.value(n * i + j)) > std::abs(c.value(n * bi + bj))) {
          bi = i;
          bj = j;
        }
      }
    }
    ASSERT_GE(bi, 0);
    auto esc = [](std::string t) {
      for (size_t at = t.find('\''); at != std::string::npos; at = t.find('\'', at)) {
        t.replace(at, 1, "&#x27;");
      }
      return t;
    };
    char rho[16];
    std::snprintf(rho, sizeof rho, "%+.3f", c.value(n * bi + bj));
    const std::string row = "<tr><td>HL</td><td>" + esc(c.parameter(bi)) + "</td><td>" +
                            esc(c.parameter(bj)) + "</td><td>" + rho + "</td></tr>";
    EXPECT_NE(html.find(row), std::string::npos) << row;
    EXPECT_NE(html.find("correlation.png"), std::string::npos);
  }
  // The leg map check, with the config right: consistent, in the file and the report.
  ASSERT_TRUE(cal.has_leg_map_check());
  EXPECT_TRUE(cal.leg_map_check().consistent());
  EXPECT_NE(html.find("Leg map check"), std::string::npos);

  // The walk corrected three ways, one sample per 0.04 s. Against the twin: with the true
  // parameters the six ground wrenches sum to (0, 0, G, 0, 0, 0) about the CoM (the twin's
  // quasi-static walk) within the reading and attitude noise; the calibration corrects like the
  // true parameters up to its own small error, the naive tare many times worse.
  EXPECT_NE(html.find("walking.png"), std::string::npos);
  std::map<std::string, std::vector<std::vector<double>>> walk;
  {
    std::istringstream lines(ReadFile(WalkingPathFor(out)));
    std::string line;
    ASSERT_TRUE(std::getline(lines, line));
    EXPECT_EQ(line.rfind("t_s,variant,HL_fx_n,", 0), 0u) << line;
    while (std::getline(lines, line)) {
      std::istringstream fields(line);
      std::string t, variant, v;
      std::getline(fields, t, ',');
      std::getline(fields, variant, ',');
      std::vector<double> row;
      while (std::getline(fields, v, ',')) row.push_back(std::stod(v));
      ASSERT_EQ(row.size(), 42u) << line;
      walk[variant].push_back(row);
    }
  }
  ASSERT_EQ(walk.size(), 3u);
  const auto& full = walk["full calibration"];
  const auto& naive = walk["naive tare"];
  const auto& true_params = walk["truth"];
  EXPECT_NEAR(static_cast<double>(full.size()), kWalkS / 0.04, 3.0);
  ASSERT_EQ(naive.size(), full.size());
  ASSERT_EQ(true_params.size(), full.size());
  const double G = fx->config.robot().total_mass_kg() * fx->config.robot().g0_m_s2();
  double total_f2 = 0.0, total_t2 = 0.0, full_f2 = 0.0, naive_f2 = 0.0;
  for (size_t i = 0; i < full.size(); ++i) {
    for (int c = 0; c < 3; ++c) {
      const double target = c == 2 ? G : 0.0;
      total_f2 += std::pow(true_params[i][36 + c] - target, 2);
      total_t2 += std::pow(true_params[i][39 + c], 2);
    }
    for (int k = 0; k < kNumLegs; ++k) {
      for (int c = 0; c < 3; ++c) {
        full_f2 += std::pow(full[i][6 * k + c] - true_params[i][6 * k + c], 2);
        naive_f2 += std::pow(naive[i][6 * k + c] - true_params[i][6 * k + c], 2);
      }
    }
  }
  const double n = static_cast<double>(full.size());
  const double total_f = std::sqrt(total_f2 / (3 * n)), total_t = std::sqrt(total_t2 / (3 * n));
  const double full_f = std::sqrt(full_f2 / (18 * n)), naive_f = std::sqrt(naive_f2 / (18 * n));
  std::printf(
      "walk (%zu samples): true parameters' total vs (0,0,G,0,0,0) rms %.4f N / %.5f N m; "
      "leg force rms vs the true parameters' correction: calibration %.5f N, naive %.4f N\n",
      full.size(), total_f, total_t, full_f, naive_f);
  // Noise: 6 readings x 0.05 N, and 0.2 deg of mocap attitude tilting G = 80 N (0.28 N).
  EXPECT_LT(total_f, 0.3);
  EXPECT_LT(total_t, 0.05);
  EXPECT_LT(full_f, 0.05);
  EXPECT_GT(naive_f, 5.0 * full_f);

  // scripts/report on its own refuses a residuals file that is not the calibrator's, naming
  // the line, and writes nothing.
  const std::string bad_csv = fx->dir + "/bad.csv";
  std::ofstream(bad_csv) << csv.substr(0, csv.find('\n') + 1) << "0,naive tare,1,2,x,4,5,6\n";
  const std::string bad_dir = fx->dir + "/bad_report";
  ::setenv("FTCAL_PYTHON_DIR", FTCAL_PYTHON_DIR, 1);  // this build's schemas
  Child report_child({std::string(FTCAL_SOURCE_DIR) + "/scripts/report", out, bad_csv, bad_dir},
                     fx->dir + "/bad_report.out", fx->dir + "/bad_report.err");
  const auto status = report_child.Wait(60);
  ASSERT_TRUE(status.has_value());
  EXPECT_TRUE(WIFEXITED(*status) && WEXITSTATUS(*status) == 2);
  EXPECT_NE(ReadFile(fx->dir + "/bad_report.err").find("bad.csv:2: a value is not a number"),
            std::string::npos)
      << ReadFile(fx->dir + "/bad_report.err");
  EXPECT_FALSE(std::filesystem::exists(bad_dir + "/index.html"));
}

TEST_F(CalibratorTest, RefusesALogWithoutMarkers) {
  ExpectRefused({"--log", fx->log_no_markers}, "no_markers", "no EXPERIMENT markers");
}

TEST_F(CalibratorTest, RefusesUnsignedMarkersNamingTheirCountAndWhatToDo) {
  // The twin's markers are unsigned; a config that requires signed ones refuses every one. The
  // refusal must say so, not that the log has no markers.
  ASSERT_GT(fx->markers, 0);
  const std::string out = fx->dir + "/unsigned.pbtxt";
  const Result r = Run({"--log", fx->log, "--config", fx->config_signed, "--out", out}, "unsigned");
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_NE(r.err.find(std::to_string(fx->markers) + " on channel 'EXPERIMENT' were refused as "
                                                     "unsigned"),
            std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("auth.allow_unsigned"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("--signing-key"), std::string::npos) << r.err;
  EXPECT_EQ(r.err.find("no EXPERIMENT markers (channel"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(out));
}

TEST_F(CalibratorTest, RefusesALogMissingASeries) {
  ExpectRefused({"--log", fx->log_no_z_neg}, "no_z_neg", "missing hanging series: HANG_Z_NEG");
}

TEST_F(CalibratorTest, RefusesAMissingLog) {
  ExpectRefused({"--log", fx->log, "--log", fx->dir + "/absent.lcmlog"}, "absent",
                "input log '" + fx->dir + "/absent.lcmlog' does not exist");
}

TEST_F(CalibratorTest, RefusesAnOutputDirectoryThatDoesNotExistBeforeReading) {
  const std::string out = fx->dir + "/no-such-dir/cal.pbtxt";
  const Result r = Run({"--log", fx->log, "--config", kConfig, "--out", out}, "no_out_dir");
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_NE(r.err.find("directory '" + fx->dir + "/no-such-dir' does not exist"), std::string::npos)
      << r.err;
  // Refused before the log was read: no progress line.
  EXPECT_EQ(r.err.find("events"), std::string::npos) << r.err;
  EXPECT_FALSE(std::filesystem::exists(fx->dir + "/no-such-dir"));
}

TEST_F(CalibratorTest, RefusesATruncatedLog) {
  ExpectRefused({"--log", fx->log_truncated}, "truncated", "damaged or truncated");
}

TEST_F(CalibratorTest, RefusesAConfigWhoseLegsAreNotTheLogsChannels) {
  const std::string out = fx->dir + "/other.pbtxt.out";
  const Result r = Run({"--log", fx->log, "--config", fx->config_other, "--out", out}, "other");
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_NE(r.err.find("config legs with no channel in the log: ATI_FL"), std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("FT_HL"), std::string::npos) << r.err;  // what the log has instead
  EXPECT_FALSE(std::filesystem::exists(out));
}

// Live mode on an in-process LCM (memq://, no network): the same session published event by
// event; one calibration when STANDING stops, published as calibration_t whose bytes are the
// file's proto and whose hash is theirs.
TEST_F(CalibratorTest, LiveCalibratesWhenStandingStopsPublishesAndWrites) {
  ServiceStats stats(spdlog::default_logger());
  LcmBus bus("memq://", stats);
  std::vector<calibration_t> published;
  bus.Subscribe<calibration_t>(
      fx->config.channels().calibration(),
      [&](const MessageInfo&, const calibration_t& m) { published.push_back(m); });
  const std::string out = fx->dir + "/live.pbtxt";
  int calibrated = 0;
  CalibratorOptions options;
  options.config_path = kConfig;
  LiveCalibrator live(fx->config, bus, out, options, [&](const CalibrationRun&) { ++calibrated; });
  auto drain = [&] {
    while (bus.HandleOnce(0) > 0) {
    }
  };
  for (size_t i = 0; i < fx->events.size(); ++i) {
    const Event& e = fx->events[i];
    bus.PublishRaw(e.channel, e.data.data(), static_cast<int>(e.data.size()));
    if (i % 512 == 0) drain();
  }
  drain();
  drain();  // the calibration published from inside the STANDING stop handler
  EXPECT_EQ(live.refused(), 0) << live.last_refusal();
  EXPECT_EQ(calibrated, 1);
  ASSERT_EQ(published.size(), 1u);
  const calibration_t& m = published[0];
  EXPECT_EQ(m.version, 1);
  const std::string bytes(m.data.begin(), m.data.end());
  EXPECT_EQ(m.content_sha256, Sha256Hex(bytes));
  calibration::Calibration from_bus;
  ASSERT_TRUE(from_bus.ParseFromString(bytes));
  const calibration::Calibration from_file = ReadCalibrationFile(out);
  EXPECT_EQ(from_file.SerializeAsString(), bytes);
  EXPECT_EQ(from_bus.version(), 1u);
  const calibration::Calibration truth = ReadCalibrationFile(fx->truth);
  ASSERT_EQ(from_bus.leg_size(), kNumLegs);
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_NEAR(from_bus.leg(k).leg_weight_n().value(), truth.leg(k).leg_weight_n().value(), 0.05);
  }
  EXPECT_TRUE(std::filesystem::exists(ResidualsPathFor(out)));
}

}  // namespace
}  // namespace ftcal
