// ftcal-sim log: the twin's experiment as an LCM log. A short experiment (one leg cycle per
// hanging series, a few poses and stances, a short walk) is written, decoded and compared with
// the twin's frames made again independently from the same seed; the log must be the same
// bytes for the same seed, and the program must write its files atomically.
#include <sys/stat.h>
#include <sys/wait.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iterator>
#include <map>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/digest_cache.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/geometry.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "sim/log_writer.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
constexpr uint64_t kSeed = 7;
// The log's clocks: SimLogOptions' default, a lab's; a host stall delays a stamp by this at most.
const SimClocks kClocks = SimClocks::Lab();
const int64_t kStallUs = std::llround(kClocks.stall_max_s * 1e6);

std::string TempDir() {
  char tmpl[] = "/tmp/sim_log_test.XXXXXX";
  const char* dir = ::mkdtemp(tmpl);
  EXPECT_NE(dir, nullptr);
  return dir ? dir : "/tmp";
}

std::string ReadBytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

bool Exists(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0;
}

TwinOptions Options() {
  TwinOptions o;
  o.seed = kSeed;
  o.hang_cycles = 1;
  o.marker_dropout_rate_hz = 0.05;  // a few dropouts in a short log: NaN markers get exercised
  return o;
}

ExperimentPlan Plan() {
  ExperimentPlan p;
  p.poses = 4;
  p.tripod_stances = 2;
  p.walk_s = 8.0;
  p.gap_s = 1.5;
  p.drift_at_s = 100.0;  // during the standing poses
  return p;
}

double WrapToPi(double a) { return std::remainder(a, 2.0 * M_PI); }

struct Decoded {
  std::vector<std::string> channel;
  std::vector<int64_t> timestamp;
  std::array<std::vector<ft_batch_t>, kNumLegs> ft;  // the writer's: one record a message
  std::vector<servo_state_t> servo;
  std::vector<mocap_body_t> mocap;
  std::vector<experiment_marker_t> markers;
  int undecodable = 0;
};

template <class Msg>
bool DecodeExactly(const lcm::LogEvent& e, Msg* m) {
  return m->decode(e.data, 0, e.datalen) == e.datalen;
}

Decoded ReadLog(const std::string& path) {
  Decoded d;
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return d;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    d.channel.push_back(e->channel);
    d.timestamp.push_back(e->timestamp);
    bool ok = false;
    if (e->channel.rfind("FT_", 0) == 0) {
      ft_batch_t m;
      ok = DecodeExactly(*e, &m);
      const auto k = LegIndex(e->channel.substr(3));
      ok = ok && k.has_value();
      if (ok) d.ft[*k].push_back(m);
    } else if (e->channel == "SERVO_STATE") {
      d.servo.emplace_back();
      ok = DecodeExactly(*e, &d.servo.back());
    } else if (e->channel == "MOCAP_BODY") {
      d.mocap.emplace_back();
      ok = DecodeExactly(*e, &d.mocap.back());
    } else if (e->channel == "EXPERIMENT") {
      d.markers.emplace_back();
      ok = DecodeExactly(*e, &d.markers.back());
    }
    if (!ok) ++d.undecodable;
  }
  return d;
}

// The frames and phase boundaries the plan should produce, made by calling the twin directly.
struct Expected {
  std::vector<TwinFrame> frames;
  struct Phase {
    ExperimentPhase phase;
    size_t first, end;  // frame index range
  };
  std::vector<Phase> phases;
};

Expected MakeExpected(const BigAntTwin& twin, const ExperimentPlan& plan) {
  Expected x;
  double t = 0.0;
  auto sink = [&x](const TwinFrame& f) { x.frames.push_back(f); };
  auto add = [&](ExperimentPhase phase, const std::function<double(const RunOptions&)>& run) {
    const size_t first = x.frames.size();
    t = run(RunOptions{t, plan.drift_at_s}) + plan.gap_s;
    x.phases.push_back({phase, first, x.frames.size()});
  };
  add(ExperimentPhase::kTare, [&](const RunOptions& r) { return twin.Tare(r, sink); });
  for (int s = 0; s < kNumHangSeries; ++s) {
    add(static_cast<ExperimentPhase>(1 + s),
        [&](const RunOptions& r) { return twin.Hanging(static_cast<HangSeries>(s), r, sink); });
  }
  add(ExperimentPhase::kStanding,
      [&](const RunOptions& r) { return twin.Standing(plan.poses, r, sink); });
  add(ExperimentPhase::kTripod,
      [&](const RunOptions& r) { return twin.TripodStances(plan.tripod_stances, r, sink); });
  add(ExperimentPhase::kWalking,
      [&](const RunOptions& r) { return twin.TripodWalk(plan.walk_s, r, sink); });
  return x;
}

class SimLogTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new std::string(TempDir());
    config_ = new config::Config(LoadConfigFile(kConfig));
    twin_ = new BigAntTwin(*config_, Options());
    SimLogOptions lo;
    lo.seed = kSeed;
    lo.session_id = "sim-log-test";
    SimLogWriter writer(*config_, *dir_ + "/a.lcmlog", lo);
    end_s_ = WriteExperiment(*twin_, Plan(), &writer);
    handed_ = new std::string(writer.Commit());
    counts_ = writer.counts();
    log_ = new Decoded(ReadLog(*dir_ + "/a.lcmlog"));
    expected_ = new Expected(MakeExpected(*twin_, Plan()));
  }
  static void TearDownTestSuite() {
    std::system(("rm -rf '" + *dir_ + "'").c_str());
    delete expected_;
    delete log_;
    delete twin_;
    delete config_;
    delete dir_;
    delete handed_;
  }
  static int64_t Utime(double t_s) { return kSimLogT0Utime + std::llround(t_s * 1e6); }

  static std::string* dir_;
  static config::Config* config_;
  static BigAntTwin* twin_;
  static Decoded* log_;
  static Expected* expected_;
  static SimLogCounts counts_;
  static double end_s_;
  static std::string* handed_;  // the digest Commit() handed to the digest cache
};
std::string* SimLogTest::handed_ = nullptr;
std::string* SimLogTest::dir_ = nullptr;
config::Config* SimLogTest::config_ = nullptr;
BigAntTwin* SimLogTest::twin_ = nullptr;
Decoded* SimLogTest::log_ = nullptr;
Expected* SimLogTest::expected_ = nullptr;
SimLogCounts SimLogTest::counts_;
double SimLogTest::end_s_ = 0.0;

TEST_F(SimLogTest, EveryEventDecodesAndTimeNeverGoesBack) {
  EXPECT_EQ(log_->undecodable, 0);
  ASSERT_FALSE(log_->timestamp.empty());
  for (size_t i = 1; i < log_->timestamp.size(); ++i) {
    ASSERT_GE(log_->timestamp[i], log_->timestamp[i - 1])
        << "event " << i << " on " << log_->channel[i];
  }
  EXPECT_EQ(static_cast<int64_t>(log_->timestamp.size()), counts_.Total());
}

// The log's SHA-256, taken as it was written, is the file's, and is in the digest cache (the
// suite's, FTCAL_CACHE_DIR) for the calibrator's first run.
TEST_F(SimLogTest, TheDigestHandedToTheCacheIsTheFiles) {
  const DigestCache cache = DigestCache::FromEnvironment();
  if (!cache.enabled()) GTEST_SKIP() << "FTCAL_CACHE_DIR set empty: no digest cache";
  const std::string path = *dir_ + "/a.lcmlog";
  EXPECT_EQ(*handed_, Sha256File(path));
  EXPECT_EQ(cache.Lookup(path), std::optional<std::string>(Sha256File(path)));
}

TEST_F(SimLogTest, OneEventPerDevicePerFrame) {
  const size_t n = expected_->frames.size();
  ASSERT_GT(n, 8000u);  // 4 x 20 s hanging alone
  for (int k = 0; k < kNumLegs; ++k) EXPECT_EQ(log_->ft[k].size(), n) << kLegNames[k];
  EXPECT_EQ(log_->servo.size(), n);
  EXPECT_EQ(log_->mocap.size(), n);
  EXPECT_EQ(log_->markers.size(), 2 * expected_->phases.size());
  EXPECT_NEAR(end_s_, expected_->frames.back().t_s + 0.01, 1e-9);
}

TEST_F(SimLogTest, FtSamplesAreTheTwinReadingsWithDeviceCounters) {
  const auto& frames = expected_->frames;
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& ft = log_->ft[k];
    ASSERT_EQ(ft.size(), frames.size());
    for (size_t i = 0; i < ft.size(); ++i) {
      const ft_batch_t& m = ft[i];
      ASSERT_EQ(m.leg, kLegNames[k]);
      // One record a message (a box in real-time mode), decoded exactly: every array has it.
      ASSERT_EQ(m.n, 1) << kLegNames[k] << " message " << i;
      ASSERT_EQ(m.rdt_sequence[0], static_cast<int64_t>(i) + 1);
      if (i > 0) {
        // The box's own clock (a lab's, SimClocks::Lab(): tens of ppm off) between the samples.
        const double counts =
            7000.0 * (1.0 + 1e-6 * kClocks.ft[k].rate_ppm) * (frames[i].t_s - frames[i - 1].t_s);
        ASSERT_NEAR(
            static_cast<double>((m.ft_sequence[0] - ft[i - 1].ft_sequence[0] + (int64_t{1} << 32)) %
                                (int64_t{1} << 32)),
            counts, 1.0);
      }
      ASSERT_GE(m.ft_sequence[0], 0);
      ASSERT_LT(m.ft_sequence[0], int64_t{1} << 32);
      ASSERT_EQ(m.status[0], 0);
      ASSERT_EQ(m.flags[0], 0);
      ASSERT_EQ(m.gap[0], 0);
      // The receipt: the host time, a device latency after the frame, later in a host stall.
      const int64_t latency = m.receipt_utime - Utime(frames[i].t_s);
      ASSERT_GE(latency, 500) << i;
      ASSERT_LE(latency, 1800 + kStallUs) << i;
      // The sample time: the counter mapped as the ATI bridge maps it, the frame's instant plus
      // the least latency (500-800 us), never after the receipt.
      ASSERT_LE(m.sample_utime[0], m.receipt_utime) << i;
      const int64_t mapped = m.sample_utime[0] - Utime(frames[i].t_s);
      ASSERT_GE(mapped, 300) << kLegNames[k] << " " << i;
      ASSERT_LE(mapped, 1800) << kLegNames[k] << " " << i;
      ASSERT_EQ(m.wrench[0].size(), 6u);
      ASSERT_EQ(m.counts[0].size(), 6u);
      for (int a = 0; a < 6; ++a) {
        ASSERT_EQ(m.wrench[0][a], frames[i].reading[k][a]) << kLegNames[k] << " frame " << i;
        ASSERT_EQ(m.counts[0][a], frames[i].counts[k][a]);
      }
    }
  }
  // The plan's drift time reached the twin: the log carries drifted frames from 100 s on.
  int drifted = 0;
  for (const auto& f : frames) {
    ASSERT_EQ(f.drifted, f.t_s >= 100.0) << f.t_s;
    drifted += f.drifted;
  }
  EXPECT_GT(drifted, 100);
}

TEST_F(SimLogTest, ServoStateIsWhatTheBridgeReports) {
  const auto& frames = expected_->frames;
  const double half_count = M_PI / 4096.0 + 1e-12;
  std::vector<double> latency_us;
  for (size_t i = 0; i < frames.size(); ++i) {
    const servo_state_t& s = log_->servo[i];
    for (int k = 0; k < kNumLegs; ++k) {
      ASSERT_EQ(s.leg[k], kLegNames[k]);
      ASSERT_EQ(s.id[k], static_cast<int32_t>(config_->robot().leg(k).servo().id()));
      ASSERT_GT(s.angle_rad[k], -M_PI - 1e-12);
      ASSERT_LE(s.angle_rad[k], M_PI + 1e-12);
      ASSERT_LE(std::abs(WrapToPi(s.angle_rad[k] - frames[i].angle_rad[k])), half_count)
          << kLegNames[k] << " frame " << i;
      ASSERT_EQ(s.flags[k], 0);
      if (i > 0) {
        ASSERT_GE(s.device_tick_ms[k], log_->servo[i - 1].device_tick_ms[k]);
      }
    }
    latency_us.push_back(static_cast<double>(s.utime - Utime(frames[i].t_s)));
    ASSERT_LE(s.sample_utime, s.utime) << i;
    // The ticks mapped as the Dynamixel bridge maps them: the read's instant plus the least
    // latency (2 ms), within the millisecond the ticks resolve.
    const int64_t mapped = s.sample_utime - Utime(frames[i].t_s);
    ASSERT_GE(mapped, 1500) << i;
    ASSERT_LE(mapped, 3500) << i;
  }
  // The walk turns the legs right round: wrapped angles must appear.
  bool wrapped = false;
  for (const auto& f : frames)
    for (double a : f.angle_rad) wrapped |= std::abs(a) > M_PI + 0.1;
  EXPECT_TRUE(wrapped);
  for (double l : latency_us) {
    ASSERT_GE(l, 2000);
    ASSERT_LE(l, 3500 + kStallUs);
  }
  // Jitter, not a constant delay.
  const auto [lo, hi] = std::minmax_element(latency_us.begin(), latency_us.end());
  EXPECT_GT(*hi - *lo, 1000);
  // Walking: the velocity is the angle's rate (legs turn at least 0.5 rad/s somewhere).
  double max_speed = 0.0;
  for (const auto& s : log_->servo)
    for (double v : s.velocity_rad_s) max_speed = std::max(max_speed, std::abs(v));
  EXPECT_GT(max_speed, 0.5);
}

TEST_F(SimLogTest, MocapCarriesTheTwinAttitudeWithHeadingRemoved) {
  const auto& frames = expected_->frames;
  int untracked_markers = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    // The event's log timestamp is the message's host time, as lcm-logger would record it.
    const mocap_body_t& b = log_->mocap[i];
    const TwinFrame& f = frames[i];
    ASSERT_EQ(b.body, config_->mocap().body_name());
    ASSERT_TRUE(b.tracked);
    ASSERT_EQ(b.frame_number, 1 + std::llround(f.t_s * 100));
    ASSERT_EQ(b.device_utime, std::llround(1e6 * kClocks.mocap.DeviceSeconds(f.t_s)));
    const Eigen::Vector4d q_wc(b.q_wc[0], b.q_wc[1], b.q_wc[2], b.q_wc[3]);
    const Eigen::Vector4d q_gc(b.q_gc[0], b.q_gc[1], b.q_gc[2], b.q_gc[3]);
    ASSERT_LT((QuaternionToRotation(q_gc) - f.R_GC).norm(), 1e-12);
    ASSERT_LT((QuaternionToRotation(q_wc) - RemoveHeading(f.R_GC)).norm(), 1e-12);
    // Heading removed: W's x axis (the body's heading) has no y component.
    const Mat3 R_WC = QuaternionToRotation(q_wc);
    ASSERT_NEAR(R_WC(1, 0), 0.0, 1e-12);
    ASSERT_NEAR(b.yaw_rad, HeadingYaw(f.R_GC), 1e-15);
    for (int a = 0; a < 3; ++a) ASSERT_EQ(b.position_m[a], f.p_GB_m[a]);
    ASSERT_EQ(b.num_markers, kNumChassisMarkers);
    for (int m = 0; m < kNumChassisMarkers; ++m) {
      ASSERT_EQ(static_cast<bool>(b.marker_tracked[m]), f.marker_tracked[m]);
      for (int a = 0; a < 3; ++a) {
        if (f.marker_tracked[m]) {
          ASSERT_EQ(b.marker_m[m][a], f.marker_G_m[m][a]);
        } else {
          ASSERT_TRUE(std::isnan(b.marker_m[m][a]));
        }
      }
      untracked_markers += !f.marker_tracked[m];
    }
    const int64_t latency = b.utime - Utime(f.t_s);
    ASSERT_GE(latency, 4000);
    ASSERT_LE(latency, 5500 + kStallUs);
    ASSERT_LE(b.sample_utime, b.utime);
    const int64_t mapped = b.sample_utime - Utime(f.t_s);
    ASSERT_GE(mapped, 3800) << i;
    ASSERT_LE(mapped, 5500) << i;
  }
  EXPECT_GT(untracked_markers, 0);
}

TEST_F(SimLogTest, MarkersBracketEachPhaseWithStatedGravity) {
  const auto& phases = expected_->phases;
  const auto& frames = expected_->frames;
  ASSERT_EQ(log_->markers.size(), 2 * phases.size());
  const std::vector<ExperimentPhase> order = {
      ExperimentPhase::kTare,     ExperimentPhase::kHangXPos, ExperimentPhase::kHangXNeg,
      ExperimentPhase::kHangZPos, ExperimentPhase::kHangZNeg, ExperimentPhase::kStanding,
      ExperimentPhase::kTripod,   ExperimentPhase::kWalking};
  ASSERT_EQ(phases.size(), order.size());
  for (size_t p = 0; p < phases.size(); ++p) {
    const experiment_marker_t& start = log_->markers[2 * p];
    const experiment_marker_t& stop = log_->markers[2 * p + 1];
    EXPECT_EQ(start.phase, static_cast<int8_t>(order[p])) << p;
    EXPECT_EQ(stop.phase, start.phase);
    EXPECT_TRUE(start.start);
    EXPECT_FALSE(stop.start);
    EXPECT_EQ(start.session_id, "sim-log-test");
    Vec3 g_expected = Vec3::Zero();
    if (p >= 1 && p <= kNumHangSeries) {  // after the TARE phase
      g_expected = twin_->StatedGravityB(static_cast<HangSeries>(p - 1));
      EXPECT_NEAR(g_expected.norm(), 1.0, 1e-12);
    }
    for (int a = 0; a < 3; ++a) {
      EXPECT_EQ(start.gravity_b[a], g_expected[a]) << p;
      EXPECT_EQ(stop.gravity_b[a], g_expected[a]) << p;
    }
    // Every device event of the phase's frames lies between its markers; the phase's frames
    // have its phase code.
    const TwinFrame& first = frames[phases[p].first];
    const TwinFrame& last = frames[phases[p].end - 1];
    EXPECT_EQ(first.phase, order[p]);
    EXPECT_EQ(last.phase, order[p]);
    EXPECT_LT(start.utime, Utime(first.t_s));
    EXPECT_GT(stop.utime, log_->mocap[phases[p].end - 1].utime);
    EXPECT_GT(stop.utime, log_->servo[phases[p].end - 1].utime);
    for (int k = 0; k < kNumLegs; ++k) {
      EXPECT_GT(stop.utime, log_->ft[k][phases[p].end - 1].receipt_utime);
    }
    if (p + 1 < phases.size()) {
      EXPECT_LT(stop.utime, log_->markers[2 * p + 2].utime);
    }
    // 100 Hz per leg inside the phase.
    const double span_s = (last.t_s - first.t_s);
    const double rate = static_cast<double>(phases[p].end - phases[p].first - 1) / span_s;
    EXPECT_NEAR(rate, 100.0, 1e-6) << p;
    const double host_rate =
        static_cast<double>(phases[p].end - phases[p].first - 1) /
        (1e-6 * static_cast<double>(log_->ft[0][phases[p].end - 1].sample_utime.at(0) -
                                    log_->ft[0][phases[p].first].sample_utime.at(0)));
    EXPECT_NEAR(host_rate, 100.0, 1.0) << p;
  }
}

TEST_F(SimLogTest, SameSeedSameBytesOtherSeedOtherBytes) {
  const std::string again = *dir_ + "/b.lcmlog";
  {
    const BigAntTwin twin(*config_, Options());
    SimLogOptions lo;
    lo.seed = kSeed;
    lo.session_id = "sim-log-test";
    SimLogWriter writer(*config_, again, lo);
    WriteExperiment(twin, Plan(), &writer);
    writer.Commit();
  }
  const std::string a = ReadBytes(*dir_ + "/a.lcmlog");
  EXPECT_GT(a.size(), 1000000u);
  EXPECT_TRUE(a == ReadBytes(again));

  // Another jitter seed alone changes the stamps, not the values.
  const std::string other = *dir_ + "/c.lcmlog";
  {
    SimLogOptions lo;
    lo.seed = kSeed + 1;
    lo.session_id = "sim-log-test";
    SimLogWriter writer(*config_, other, lo);
    ExperimentPlan plan = Plan();
    WriteExperiment(*twin_, plan, &writer);
    writer.Commit();
  }
  const std::string c = ReadBytes(other);
  EXPECT_FALSE(a == c);
  const Decoded d = ReadLog(other);
  ASSERT_EQ(d.ft[2].size(), log_->ft[2].size());
  for (size_t i = 0; i < d.ft[2].size(); i += 97) {
    ASSERT_EQ(d.ft[2][i].n, 1);
    for (int a2 = 0; a2 < 6; ++a2) {
      ASSERT_EQ(d.ft[2][i].wrench[0][a2], log_->ft[2][i].wrench[0][a2]);
    }
  }
}

TEST_F(SimLogTest, RefusesFramesOutOfOrderAndUnwritablePaths) {
  const std::string path = *dir_ + "/order.lcmlog";
  {
    SimLogWriter writer(*config_, path, SimLogOptions{});
    writer.WriteFrame(expected_->frames[10]);
    EXPECT_THROW(writer.WriteFrame(expected_->frames[9]), std::invalid_argument);
    EXPECT_THROW(writer.WriteMarker(0, ExperimentPhase::kIdle, true, Vec3::Zero(), ""),
                 std::invalid_argument);
    // Never committed: nothing under the final name, no temporary left behind.
  }
  EXPECT_FALSE(Exists(path));
  EXPECT_FALSE(Exists(path + ".tmp." + std::to_string(::getpid())));
  try {
    SimLogWriter writer(*config_, *dir_ + "/no/such/dir/x.lcmlog", SimLogOptions{});
    ADD_FAILURE() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("no/such/dir/x.lcmlog"), std::string::npos) << e.what();
  }
  ExperimentPlan bad = Plan();
  bad.poses = 0;
  SimLogWriter writer(*config_, *dir_ + "/bad.lcmlog", SimLogOptions{});
  try {
    WriteExperiment(*twin_, bad, &writer);
    ADD_FAILURE() << "no exception";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("poses"), std::string::npos) << e.what();
  }
}

// The program: a short log and its truth file next to it, which loads and equals the twin's
// truth for the same seed; a bad flag leaves no files.
TEST_F(SimLogTest, ProgramWritesLogAndTruth) {
  const std::string out = *dir_ + "/prog.lcmlog";
  const std::string cmd = std::string(FTCAL_SIM_EXE) + " --config " + kConfig + " log --out " +
                          out + " --seed 11 --scenarios stand,walk --poses 2 --walk-s 3 > " +
                          *dir_ + "/prog.out 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << ReadBytes(*dir_ + "/prog.out");
  const std::string truth_path = *dir_ + "/prog.truth.pbtxt";
  ASSERT_TRUE(Exists(truth_path));
  const calibration::Calibration proto = ReadCalibrationFile(truth_path);
  TwinOptions o;
  o.seed = 11;
  const BigAntTwin twin(*config_, o);
  const RobotCalibration loaded = CalibrationFromProto(proto, config_->robot());
  for (int k = 0; k < kNumLegs; ++k) {
    EXPECT_LT((loaded.leg[k].offset - twin.Truth().leg[k].offset).norm(), 1e-9) << k;
    EXPECT_NEAR(loaded.leg[k].weight_n, twin.Truth().leg[k].weight_n, 1e-9) << k;
  }
  EXPECT_LT((loaded.p_C_B - twin.Truth().p_C_B).norm(), 1e-9);
  const Decoded d = ReadLog(out);
  EXPECT_EQ(d.undecodable, 0);
  ASSERT_EQ(d.markers.size(), 4u);
  EXPECT_EQ(d.markers[0].phase, int8_t{experiment_marker_t::STANDING});
  EXPECT_EQ(d.markers[2].phase, int8_t{experiment_marker_t::WALKING});
  EXPECT_EQ(d.markers[0].session_id, "sim-11");
  EXPECT_EQ(d.servo.size(), d.ft[0].size());

  const std::string bad_out = *dir_ + "/bad_prog.lcmlog";
  const std::string bad = std::string(FTCAL_SIM_EXE) + " --config " + kConfig + " log --out " +
                          bad_out + " --poses 0 > /dev/null 2>&1";
  const int rc = std::system(bad.c_str());
  EXPECT_TRUE(WIFEXITED(rc) && WEXITSTATUS(rc) != 0);
  EXPECT_FALSE(Exists(bad_out));
  EXPECT_FALSE(Exists(*dir_ + "/bad_prog.truth.pbtxt"));
}

}  // namespace
}  // namespace ftcal
