// Bad logs into ftcal-pose-segmenter --replay, ftcal-corrector --replay and ftcal-calibrator
// --log (issue #5): an event whose payload is damaged (its type fingerprint flipped), an event
// whose sync word is broken, a message of the wrong type on an FT channel, and logs or
// calibrations from another robot. Each must give a clear error or be skipped with a count,
// and the stages' outputs for the intact events must be those of the clean log; the calibrator
// must refuse rather than calibrate on what is left.
//
// LCM's log format has no checksum: a flipped bit inside a number decodes to another number and
// no reader can tell. What can be detected is a broken type fingerprint or length (undecodable)
// and a broken event header (unreadable bytes): those are what this test damages.
#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <regex>
#include <set>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "child_process.h"
#include "common/messages.h"
#include "ftcal/calibration_io.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/service_status_t.hpp"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "twin_log.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::DescribeWaitStatus;
using testing::ReadFile;
using namespace twin_log;

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
const std::string kSession = "bad-logs-test";
constexpr int kStagePoses = 3;
constexpr int kCalibrationPoses = 32;

// Size of an event in LCM's log format: sync word, event number, timestamp, channel length,
// data length, channel, data.
size_t EventBytes(const Event& e) { return 28 + e.channel.size() + e.data.size(); }

// Byte offset of event `index` in a log written by WriteLog.
size_t EventOffset(const std::vector<Event>& events, size_t index) {
  size_t at = 0;
  for (size_t i = 0; i < index; ++i) at += EventBytes(events[i]);
  return at;
}

void PatchFile(const std::string& from, const std::string& to, size_t offset,
               const std::vector<uint8_t>& xor_mask) {
  std::string bytes = ReadFile(from);
  ASSERT_LE(offset + xor_mask.size(), bytes.size());
  for (size_t i = 0; i < xor_mask.size(); ++i) bytes[offset + i] ^= static_cast<char>(xor_mask[i]);
  std::ofstream(to, std::ios::binary)
      .write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
}

calibration_t CalibrationMessage(const calibration::Calibration& proto, int64_t utime,
                                 int64_t version) {
  return ToLcm(proto, version, utime);
}

// The error names the bytes skipped: up to the end of the damaged event at `at`. LCM 1.3.1's
// reader also refuses the event before it (not followed by a sync word), so the span may start
// one event earlier: that intact event is reported lost, not silently dropped (see the report
// of issue #5: LogReplayBus could parse events itself and keep it).
void ExpectSkippedSpan(const std::string& error, size_t at, const Event& damaged) {
  const std::regex span("skipped ([0-9]+) unreadable bytes at offset ([0-9]+)");
  std::smatch m;
  ASSERT_TRUE(std::regex_search(error, m, span)) << error;
  const size_t bytes = std::stoull(m[1]), from = std::stoull(m[2]);
  EXPECT_EQ(from + bytes, at + EventBytes(damaged)) << error;
  EXPECT_LE(from, at) << error;
  EXPECT_GE(from + 600, at) << error << " (more than the event before it)";
}

struct Fixture {
  std::string dir;
  config::Config config;
  // Stages: three standing poses with the truth calibration at the start.
  std::unique_ptr<BigAntTwin> twin;
  std::vector<TwinFrame> frames;
  std::vector<Event> stage_events;
  size_t damaged_frame = 0;  // a frame in pose 1's settling (no steady pose near it) ...
  size_t damaged_index = 0;  // ... and its first event, FT_HL
  std::string stage_log;
  // Calibrator: a whole session (hanging series, standing poses).
  std::unique_ptr<BigAntTwin> session_twin;
  std::vector<Event> session_events;
  std::string session_log;
};
Fixture* fx = nullptr;

class BadLogsTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    fx = new Fixture;
    fx->dir = testing::MakeTempDir();
    fx->config = LoadConfigFile(kConfig);
    const auto& ch = fx->config.channels();

    TwinOptions opt;
    opt.seed = 41;
    opt.marker_dropout_rate_hz = 0.0;
    fx->twin = std::make_unique<BigAntTwin>(fx->config, opt);
    fx->twin->Standing(kStagePoses, {}, [](const TwinFrame& f) { fx->frames.push_back(f); });
    std::vector<Event>& ev = fx->stage_events;
    ev.push_back(Encode(kT0 - 2000, ch.experiment(),
                        Marker(kT0 - 2000, kSession, experiment_marker_t::STANDING, true)));
    ev.push_back(Encode(kT0 - 1000, ch.calibration(),
                        CalibrationMessage(fx->twin->TruthProto(), kT0 - 1000, 1)));
    // One second into pose 1's motion and settling: more than a derivative window (0.41 s)
    // away from the end of pose 0's steady run and from the start of pose 1's.
    size_t& damaged_frame = fx->damaged_frame;
    while (fx->frames[damaged_frame].segment != 1) ++damaged_frame;
    damaged_frame += 100;
    EXPECT_FALSE(fx->frames[damaged_frame].steady);
    for (size_t i = 0; i < fx->frames.size(); ++i) {
      if (i == damaged_frame) fx->damaged_index = ev.size();  // its first event is FT_HL
      AppendFrame(fx->frames[i], fx->config, &ev);
    }
    EXPECT_EQ(ev[fx->damaged_index].channel, ch.ft_prefix() + "HL");
    const int64_t end = Utime(fx->frames.back().t_s) + 1000;
    ev.push_back(
        Encode(end, ch.experiment(), Marker(end, kSession, experiment_marker_t::STANDING, false)));
    fx->stage_log = fx->dir + "/stage.lcmlog";
    WriteLog(fx->stage_log, ev);

    TwinOptions sopt = opt;
    sopt.hang_cycles = 3;
    sopt.hang_cycle_s = 4.0;
    sopt.pose_dwell_s = 3.0;
    sopt.settle_cutoff_s = 1.0;
    fx->session_twin = std::make_unique<BigAntTwin>(fx->config, sopt);
    AppendSession(*fx->session_twin, fx->config, kSession, kCalibrationPoses, 0.0,
                  &fx->session_events);
    fx->session_log = fx->dir + "/session.lcmlog";
    WriteLog(fx->session_log, fx->session_events);
  }
  static void TearDownTestSuite() {
    if (std::getenv("FTCAL_TEST_KEEP") == nullptr) testing::RemoveTree(fx->dir);
    delete fx;
    fx = nullptr;
  }

  static std::string Path(const std::string& name) { return fx->dir + "/" + name; }

  struct Result {
    int exit_code = -1;
    std::string err;
  };
  static Result Run(const std::vector<std::string>& argv, const std::string& tag) {
    Child child(argv, Path(tag + ".out"), Path(tag + ".err"));
    const auto status = child.Wait(120);
    Result r;
    EXPECT_TRUE(status.has_value()) << tag << " did not finish";
    if (status && WIFEXITED(*status)) r.exit_code = WEXITSTATUS(*status);
    r.err = ReadFile(Path(tag + ".err"));
    return r;
  }

  // A stage over a log to completion (exit 0); returns the output log.
  static std::string Replay(const std::string& exe, const std::string& in, const std::string& tag,
                            const std::string& config = kConfig) {
    const std::string out = Path(tag + ".lcmlog");
    // The segmenter's SYNC_SAMPLE too: the tests here compare them.
    std::vector<std::string> argv = {exe, "--config", config, "--replay", in, "--out", out};
    if (exe == FTCAL_POSE_SEGMENTER) argv.push_back("--sync-samples");
    const Result r = Run(argv, tag);
    EXPECT_EQ(r.exit_code, 0) << tag << ": " << r.err;
    return out;
  }

  static service_status_t FinalStatus(const std::string& out) {
    const auto status = ReadChannel<service_status_t>(out, fx->config.channels().status());
    EXPECT_EQ(status.size(), 1u) << out;
    return status.empty() ? service_status_t{} : status.back();
  }
  static std::map<std::string, int64_t> Counters(const service_status_t& s) {
    std::map<std::string, int64_t> c;
    for (int i = 0; i < s.num_counters; ++i) c[s.counter_name[i]] = s.counter_value[i];
    return c;
  }

  // The calibrator must refuse `log`: exit 2, every word of `what` in its message, no file.
  static void ExpectCalibratorRefuses(const std::string& log, const std::string& tag,
                                      const std::vector<std::string>& what,
                                      const std::string& config = kConfig) {
    const std::string out = Path(tag + ".pbtxt");
    const Result r = Run({FTCAL_CALIBRATOR, "--config", config, "--log", log, "--out", out}, tag);
    EXPECT_EQ(r.exit_code, 2) << r.err;
    for (const std::string& w : what) {
      EXPECT_NE(r.err.find(w), std::string::npos) << "expected '" << w << "' in:\n" << r.err;
    }
    EXPECT_FALSE(std::filesystem::exists(out));
  }
};

std::vector<std::vector<uint8_t>> RawChannel(const std::string& path, const std::string& channel) {
  std::vector<std::vector<uint8_t>> out;
  for (const Event& e : ReadLog(path)) {
    if (e.channel == channel) out.push_back(e.data);
  }
  return out;
}

// The segmenter's outputs over a log with frame `lost`'s FT_HL sample lost (and with it, the
// damaged bytes may take the frame's mocap frame): every SYNC_SAMPLE of the clean run, byte for
// byte, but three: frame `lost`'s is missing (HL, the pace leg, has no reading there:
// libcal/include/ftcal/aligner.h), and the frames before and after it have their own readings
// and angles, their attitude from the nearest mocap frame left. The same STEADY_POSEs (but
// publish time).
void ExpectSegmenterLostOnlyThatFrame(const std::string& clean, const std::string& dirty,
                                      size_t lost) {
  const auto& ch = fx->config.channels();
  const auto a = ReadChannel<sync_sample_t>(clean, ch.sync_sample());
  const auto b = ReadChannel<sync_sample_t>(dirty, ch.sync_sample());
  const auto a_raw = RawChannel(clean, ch.sync_sample());
  const auto b_raw = RawChannel(dirty, ch.sync_sample());
  ASSERT_EQ(a.size(), fx->frames.size());
  ASSERT_EQ(b_raw.size(), a_raw.size() - 1);
  const int64_t lost_utime = Utime(fx->frames[lost].t_s);
  const int64_t next_utime = Utime(fx->frames[lost + 1].t_s);
  const int64_t previous_utime = Utime(fx->frames[lost - 1].t_s);
  size_t j = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    if (a[i].utime == lost_utime) continue;
    ASSERT_LT(j, b_raw.size());
    if (a[i].utime == next_utime || a[i].utime == previous_utime) {
      ASSERT_EQ(b[j].utime, a[i].utime);
      const size_t frame = a[i].utime == next_utime ? lost + 1 : lost - 1;
      for (int c = 0; c < 6; ++c) {
        for (int k = 0; k < kNumLegs; ++k) {
          EXPECT_EQ(b[j].wrench[k][c], fx->frames[frame].reading[k][c]);
        }
      }
      EXPECT_EQ(Flat(b[j].angle_rad), Flat(a[i].angle_rad));  // interpolated to the same sync time
    } else {
      ASSERT_EQ(a_raw[i], b_raw[j]) << "SYNC_SAMPLE at " << a[i].utime;
    }
    ++j;
  }
  const auto pa = ReadChannel<steady_pose_t>(clean, ch.steady_pose());
  const auto pb = ReadChannel<steady_pose_t>(dirty, ch.steady_pose());
  ASSERT_EQ(pa.size(), static_cast<size_t>(kStagePoses));
  ASSERT_EQ(pb.size(), pa.size());
  for (size_t i = 0; i < pa.size(); ++i) {
    EXPECT_EQ(pb[i].start_utime, pa[i].start_utime);
    EXPECT_EQ(pb[i].end_utime, pa[i].end_utime);
    EXPECT_EQ(pb[i].num_samples, pa[i].num_samples);
    EXPECT_EQ(Flat(pb[i].wrench), Flat(pa[i].wrench));
    EXPECT_EQ(Flat(pb[i].angle_rad), Flat(pa[i].angle_rad));
  }
}

// The corrector's outputs over a log with frame `lost`'s FT_HL sample lost: exactly that
// leg-sample's output missing, every other one with the clean run's inputs with its numbers
// exactly (a leg-sample depends on its own sample, the servo state and the attitude only). The
// sums are at the pace leg's (HL's) sample instants, each of the six samples of its frame: the
// lost frame has no sum, every other one is the clean run's (its totals too, but in the two
// frames whose attitude the damaged bytes may have taken).
void ExpectCorrectorLostOnlyThatSample(const std::string& clean, const std::string& dirty,
                                       size_t lost) {
  const auto& ch = fx->config.channels();
  const auto a = ReadLegWrenches(clean, ch.contact_wrench());
  const auto b = ReadLegWrenches(dirty, ch.contact_wrench());
  ASSERT_EQ(a.size(), fx->frames.size() * kNumLegs);
  ASSERT_EQ(b.size(), a.size() - 1);
  const int64_t lost_utime = Utime(fx->frames[lost].t_s);
  const WrenchIndex b_index = IndexWrenches(b);
  EXPECT_EQ(b_index.count({lost_utime, 0}), 0u);
  const WrenchComparison c = CompareWrenches(b, a);
  EXPECT_EQ(c.missing_ref, 0u);
  EXPECT_EQ(c.duplicate, 0u);
  // Other inputs (an attitude lost with the damaged bytes) only in that frame and the next.
  const int64_t next_utime = Utime(fx->frames[lost + 1].t_s);
  EXPECT_LE(c.inputs_differ, static_cast<size_t>(2 * kNumLegs));
  for (int64_t t : c.differ_utimes) EXPECT_TRUE(t == lost_utime || t == next_utime) << t;
  EXPECT_EQ(c.same_inputs + c.inputs_differ, b.size());
  EXPECT_EQ(c.worst, 0.0);

  const auto sa = ReadWrenchSums(clean, ch.contact_wrench_sum());
  const auto sb = ReadWrenchSums(dirty, ch.contact_wrench_sum());
  ASSERT_EQ(sa.size(), fx->frames.size());
  ASSERT_EQ(sb.size(), sa.size() - 1);
  for (size_t i = 0; i < sb.size(); ++i) {
    const WrenchSum& ref = sa[i < lost ? i : i + 1];
    EXPECT_EQ(sb[i].utime, ref.utime) << "sum " << i;
    EXPECT_NE(sb[i].utime, lost_utime);
    EXPECT_EQ(sb[i].oldest_ft_age_s, ref.oldest_ft_age_s) << "sum " << i;
    if (sb[i].utime != next_utime) {
      for (int j = 0; j < 6; ++j)
        EXPECT_TRUE(SameOrBothNan(sb[i].total_W[j], ref.total_W[j])) << "sum " << i;
    }
  }
  const double weight = fx->twin->Truth().TotalWeightN();
  const SumCheck check = CheckSums(dirty, ch.contact_wrench(), ch.contact_wrench_sum(), weight);
  EXPECT_EQ(check.sums, sb.size());
  EXPECT_EQ(check.worst, 0.0);
  EXPECT_LT(check.worst_age, 1e-6);
}

TEST_F(BadLogsTest, CorruptPayloadIsCountedAndOnlyThatEventIsLost) {
  const auto& ch = fx->config.channels();
  // Flip the first byte of the damaged event's fingerprint (the payload's first 8 bytes).
  const Event& e = fx->stage_events[fx->damaged_index];
  const size_t payload = EventOffset(fx->stage_events, fx->damaged_index) + 28 + e.channel.size();
  const std::string log = Path("payload.lcmlog");
  PatchFile(fx->stage_log, log, payload, {0xff});
  for (const char* exe : {FTCAL_POSE_SEGMENTER, FTCAL_CORRECTOR}) {
    const std::string tag = std::string(exe).substr(std::string(exe).rfind('/') + 1);
    SCOPED_TRACE(tag);
    const std::string clean = Replay(exe, fx->stage_log, tag + "_clean");
    const std::string dirty = Replay(exe, log, tag + "_payload");
    // One drop more than the clean run, no error more (the corrector's clean run has one: no
    // calibration before the log's first CALIBRATION).
    const service_status_t s = FinalStatus(dirty), s0 = FinalStatus(clean);
    EXPECT_EQ(s.drops, s0.drops + 1);
    EXPECT_EQ(s.errors, s0.errors);
    // The kind is logged (once per kind); the heartbeat carries the count.
    const std::string err = ReadFile(dirty.substr(0, dirty.size() - 7) + ".err");
    EXPECT_NE(err.find("undecodable ft_batch_t on FT_HL"), std::string::npos) << err;
    if (exe == std::string(FTCAL_POSE_SEGMENTER)) {
      ExpectSegmenterLostOnlyThatFrame(clean, dirty, fx->damaged_frame);
    } else {
      ExpectCorrectorLostOnlyThatSample(clean, dirty, fx->damaged_frame);
    }
  }
  (void)ch;
}

TEST_F(BadLogsTest, BrokenSyncWordIsAnErrorWithTheSpanAndOnlyThatEventIsLost) {
  const Event& e = fx->stage_events[fx->damaged_index];
  const size_t at = EventOffset(fx->stage_events, fx->damaged_index);
  const std::string log = Path("sync.lcmlog");
  PatchFile(fx->stage_log, log, at, {0x00, 0xff, 0x00, 0x00});
  for (const char* exe : {FTCAL_POSE_SEGMENTER, FTCAL_CORRECTOR}) {
    const std::string tag = std::string(exe).substr(std::string(exe).rfind('/') + 1);
    SCOPED_TRACE(tag);
    const std::string clean = Replay(exe, fx->stage_log, tag + "_clean_s");
    const std::string dirty = Replay(exe, log, tag + "_sync");
    const service_status_t s = FinalStatus(dirty), s0 = FinalStatus(clean);
    EXPECT_EQ(s.errors, s0.errors + 1);
    EXPECT_EQ(s.drops, s0.drops);
    ExpectSkippedSpan(s.last_error, at, e);
    if (exe == std::string(FTCAL_POSE_SEGMENTER)) {
      ExpectSegmenterLostOnlyThatFrame(clean, dirty, fx->damaged_frame);
    } else {
      ExpectCorrectorLostOnlyThatSample(clean, dirty, fx->damaged_frame);
    }
  }
}

TEST_F(BadLogsTest, WrongTypeOnAnFtChannelIsCountedNotDecoded) {
  const auto& ch = fx->config.channels();
  // A servo state on FT_HL just before the damaged frame's own sample.
  std::vector<Event> ev = fx->stage_events;
  const Event& servo = ev[fx->damaged_index + kNumLegs];
  ASSERT_EQ(servo.channel, ch.servo_state());
  const Event wrong{ev[fx->damaged_index].utime, ch.ft_prefix() + "HL", servo.data};
  ev.insert(ev.begin() + static_cast<std::ptrdiff_t>(fx->damaged_index), wrong);
  const std::string log = Path("wrong_type.lcmlog");
  WriteLog(log, ev);
  for (const char* exe : {FTCAL_POSE_SEGMENTER, FTCAL_CORRECTOR}) {
    const std::string tag = std::string(exe).substr(std::string(exe).rfind('/') + 1);
    SCOPED_TRACE(tag);
    const std::string clean = Replay(exe, fx->stage_log, tag + "_clean_w");
    const std::string dirty = Replay(exe, log, tag + "_wrong");
    // One drop more than the clean run, no error more (the corrector's clean run has one: no
    // calibration before the log's first CALIBRATION).
    const service_status_t s = FinalStatus(dirty), s0 = FinalStatus(clean);
    EXPECT_EQ(s.drops, s0.drops + 1);
    EXPECT_EQ(s.errors, s0.errors);
    // The kind is logged (once per kind); the heartbeat carries the count.
    const std::string err = ReadFile(dirty.substr(0, dirty.size() - 7) + ".err");
    EXPECT_NE(err.find("undecodable ft_batch_t on FT_HL"), std::string::npos) << err;
    for (const std::string& channel :
         {ch.sync_sample(), ch.contact_wrench(), ch.contact_wrench_sum()}) {
      EXPECT_EQ(RawChannel(clean, channel), RawChannel(dirty, channel)) << channel;
    }
    const auto pa = ReadChannel<steady_pose_t>(clean, ch.steady_pose());
    const auto pb = ReadChannel<steady_pose_t>(dirty, ch.steady_pose());
    ASSERT_EQ(pa.size(), pb.size());
    for (size_t i = 0; i < pa.size(); ++i) EXPECT_EQ(Flat(pa[i].wrench), Flat(pb[i].wrench));
  }
}

// A calibration made for another robot (a leg renamed) on CALIBRATION: refused and counted, no
// wrench published with it; the corrector says why.
TEST_F(BadLogsTest, CorrectorRefusesACalibrationForOtherLegs) {
  const auto& ch = fx->config.channels();
  calibration::Calibration other = fx->twin->TruthProto();
  other.mutable_leg(0)->set_name("XL");
  std::vector<Event> ev = fx->stage_events;
  ASSERT_EQ(ev[1].channel, ch.calibration());
  ev[1] = Encode(ev[1].utime, ch.calibration(), CalibrationMessage(other, ev[1].utime, 1));
  const std::string log = Path("other_legs.lcmlog");
  WriteLog(log, ev);
  const std::string out = Replay(FTCAL_CORRECTOR, log, "corrector_other_legs");
  EXPECT_TRUE(ReadLegWrenches(out, ch.contact_wrench()).empty());
  EXPECT_TRUE(ReadWrenchSums(out, ch.contact_wrench_sum()).empty());
  const service_status_t s = FinalStatus(out);
  auto c = Counters(s);
  EXPECT_EQ(c["calibrations_refused"], 1);
  EXPECT_EQ(c["corrected"], 0);
  EXPECT_NE(s.last_error.find("refused calibration"), std::string::npos) << s.last_error;
  EXPECT_NE(s.last_error.find("XL"), std::string::npos) << s.last_error;
}

TEST_F(BadLogsTest, CalibratorRefusesACorruptPayload) {
  // An FT_HL event in the middle of the session (inside a hanging series).
  const std::vector<Event>& ev = fx->session_events;
  size_t i = ev.size() / 4;
  while (ev[i].channel != fx->config.channels().ft_prefix() + "HL") ++i;
  const size_t payload = EventOffset(ev, i) + 28 + ev[i].channel.size();
  const std::string log = Path("session_payload.lcmlog");
  PatchFile(fx->session_log, log, payload, {0xff});
  ExpectCalibratorRefuses(
      log, "cal_payload",
      {"damaged or truncated", "1 undecodable messages", "undecodable ft_batch_t on FT_HL"});
}

TEST_F(BadLogsTest, CalibratorRefusesABrokenSyncWord) {
  const std::vector<Event>& ev = fx->session_events;
  const size_t i = ev.size() / 3;
  const size_t at = EventOffset(ev, i);
  const std::string log = Path("session_sync.lcmlog");
  PatchFile(fx->session_log, log, at, {0x00, 0xff, 0x00, 0x00});
  ExpectCalibratorRefuses(log, "cal_sync", {"damaged or truncated", "1 unreadable spans"});
  ExpectSkippedSpan(ReadFile(Path("cal_sync.err")), at, ev[i]);
}

TEST_F(BadLogsTest, CalibratorRefusesAWrongTypeOnAnFtChannel) {
  std::vector<Event> ev = fx->session_events;
  const auto& ch = fx->config.channels();
  size_t i = ev.size() / 2;
  while (ev[i].channel != ch.servo_state()) ++i;
  ev.insert(ev.begin() + static_cast<std::ptrdiff_t>(i),
            Event{ev[i].utime, ch.ft_prefix() + "HL", ev[i].data});
  const std::string log = Path("session_wrong_type.lcmlog");
  WriteLog(log, ev);
  ExpectCalibratorRefuses(log, "cal_wrong_type",
                          {"damaged or truncated", "undecodable ft_batch_t on FT_HL"});
}

// A log from a robot whose leg HL is called XL: the config's legs are not the log's.
TEST_F(BadLogsTest, CalibratorRefusesALogWithAnotherRobotsLegs) {
  std::vector<Event> ev = fx->session_events;
  const std::string from = fx->config.channels().ft_prefix() + "HL";
  for (Event& e : ev) {
    if (e.channel == from) e.channel = fx->config.channels().ft_prefix() + "XL";
  }
  const std::string log = Path("session_xl.lcmlog");
  WriteLog(log, ev);
  ExpectCalibratorRefuses(log, "cal_xl",
                          {"channels for legs the config does not have: FT_XL",
                           "config legs with no channel in the log: FT_HL"});
}

// The config of a heavier robot (total_mass_kg 10% up) for this robot's log: refused, naming the
// mass, instead of a calibration that leaves every standing pose 8 N off.
TEST_F(BadLogsTest, CalibratorRefusesAConfigWithAnotherTotalMass) {
  std::string cfg = ReadFile(kConfig);
  const std::string from = "total_mass_kg: 8.18";
  ASSERT_NE(cfg.find(from), std::string::npos);
  cfg.replace(cfg.find(from), from.size(), "total_mass_kg: 9.0");
  const std::string heavy = Path("heavy.pbtxt");
  std::ofstream(heavy) << cfg;
  ExpectCalibratorRefuses(fx->session_log, "cal_heavy",
                          {"differs from the config's weight", "total_mass_kg 9 kg"}, heavy);
  // The right config calibrates the same log.
  const std::string out = Path("cal_ok.pbtxt");
  const Result r = Run(
      {FTCAL_CALIBRATOR, "--config", kConfig, "--log", fx->session_log, "--out", out}, "cal_ok");
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(std::filesystem::exists(out));
}

}  // namespace
}  // namespace ftcal
