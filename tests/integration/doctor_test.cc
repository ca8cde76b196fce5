// ftcal-doctor (services/doctor) on recordings of the twin whose faults the test put there and
// so knows: a transducer that lost a quarter second of records inside STANDING, one whose
// records all came a third of a second late, a missing hanging series, and a transducer whose
// sample counter runs 300 ppm slow against the host. The real program, its text and its exit
// code (docs/exit-codes.md: 0 calibratable, 6 with warnings, 2 not calibratable); its sigma
// forecast against the sigma ftcal-calibrator reports on the same recording. No network.
#include <sys/wait.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <map>
#include <memory>
#include <regex>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "child_process.h"
#include "ftcal/calibration_io.h"
#include "twin_log.h"

namespace ftcal {
namespace {

using testing::Child;
using testing::ReadFile;
using namespace twin_log;

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
constexpr char kSession[] = "doctor";

struct Fixture {
  std::string dir;
  config::Config config;
  std::vector<Event> events;  // a healthy session
  double standing_start_s = 0;
};
Fixture* fx = nullptr;

class DoctorTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    fx = new Fixture;
    fx->dir = testing::MakeTempDir();
    fx->config = LoadConfigFile(kConfig);
    TwinOptions opt;
    opt.seed = 43;
    opt.marker_dropout_rate_hz = 0.0;
    opt.hang_cycles = 3;
    opt.hang_cycle_s = 4.0;
    opt.pose_dwell_s = 3.0;
    opt.settle_cutoff_s = 1.0;
    BigAntTwin twin(fx->config, opt);
    AppendSession(twin, fx->config, kSession, 32, 0.0, &fx->events);
    for (const Event& e : fx->events) {
      experiment_marker_t m;
      if (e.channel == fx->config.channels().experiment() &&
          m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0 &&
          m.phase == experiment_marker_t::STANDING && m.start) {
        fx->standing_start_s = 1e-6 * static_cast<double>(e.utime - kT0);
      }
    }
    ASSERT_GT(fx->standing_start_s, 0);
  }
  static void TearDownTestSuite() {
    testing::RemoveTree(fx->dir);
    delete fx;
    fx = nullptr;
  }

  struct Result {
    int exit_code = -1;
    std::string out;
  };
  // Writes `events` as a log and runs the doctor on it.
  static Result Doctor(const std::string& tag, std::vector<Event> events) {
    std::stable_sort(events.begin(), events.end(),
                     [](const Event& a, const Event& b) { return a.utime < b.utime; });
    const std::string log = fx->dir + "/" + tag + ".lcmlog";
    WriteLog(log, events);
    Child child({FTCAL_DOCTOR, "--config", kConfig, log}, fx->dir + "/" + tag + ".out",
                fx->dir + "/" + tag + ".err");
    const auto status = child.Wait(60);
    Result r;
    EXPECT_TRUE(status.has_value()) << tag << ": the doctor did not finish";
    if (status && WIFEXITED(*status)) r.exit_code = WEXITSTATUS(*status);
    r.out = ReadFile(fx->dir + "/" + tag + ".out") + ReadFile(fx->dir + "/" + tag + ".err");
    return r;
  }
  // The FT messages (ft_batch_t) of `leg` changed by `edit` (false: dropped).
  static std::vector<Event> EditFt(const std::string& leg,
                                   const std::function<bool(Event&, ft_batch_t&)>& edit) {
    std::vector<Event> out;
    const std::string channel = fx->config.channels().ft_prefix() + leg;
    for (Event e : fx->events) {
      if (e.channel == channel) {
        ft_batch_t m;
        EXPECT_EQ(m.decode(e.data.data(), 0, static_cast<int>(e.data.size())),
                  static_cast<int>(e.data.size()));
        EXPECT_GE(m.n, 1);
        if (!edit(e, m)) continue;
        e = Encode(e.utime, channel, m);
      }
      out.push_back(e);
    }
    return out;
  }
  static double T(int64_t utime) { return 1e-6 * static_cast<double>(utime - kT0); }
  // The healthy session without the EXPERIMENT markers of `phase`.
  static std::vector<Event> WithoutPhase(int8_t phase) {
    std::vector<Event> events;
    for (const Event& e : fx->events) {
      experiment_marker_t m;
      if (e.channel == fx->config.channels().experiment() &&
          m.decode(e.data.data(), 0, static_cast<int>(e.data.size())) > 0 && m.phase == phase) {
        continue;
      }
      events.push_back(e);
    }
    return events;
  }
};

// "<what> at <t> s for <length> s": the numbers of the first stretch after `prefix`.
bool FirstStretch(const std::string& out, const std::string& prefix, double* t_s, double* len_s) {
  const size_t at = out.find(prefix);
  if (at == std::string::npos) return false;
  std::smatch m;
  const std::string rest = out.substr(at);
  if (!std::regex_search(rest, m, std::regex("at ([0-9.]+) s for ([0-9.]+) s"))) return false;
  *t_s = std::stod(m[1]);
  *len_s = std::stod(m[2]);
  return true;
}

TEST_F(DoctorTest, AHealthySessionIsCalibratable) {
  const Result r = Doctor("healthy", fx->events);
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("verdict: calibratable\n"), std::string::npos) << r.out;
  // The four hanging series and the standing poses, completed.
  for (const char* phase : {"HANG_X_POS", "HANG_X_NEG", "HANG_Z_POS", "HANG_Z_NEG", "STANDING"}) {
    EXPECT_TRUE(std::regex_search(r.out, std::regex(std::string("\n  ") + phase +
                                                    " +[0-9.]+ \\.\\. +[0-9.]+ s +[0-9.]+ s  "
                                                    "completed")))
        << phase << "\n"
        << r.out;
  }
  // Each hanging series turned the shafts through the twin's 3 cycles, a turn each.
  for (const char* phase : {"HANG_X_POS", "HANG_X_NEG", "HANG_Z_POS", "HANG_Z_NEG"}) {
    EXPECT_TRUE(std::regex_search(
        r.out, std::regex(std::string("\n  ") + phase + " .* completed +shaft travel 3.0 turns")))
        << phase << "\n"
        << r.out;
  }
}

TEST_F(DoctorTest, AGapInsideStandingIsFoundWithItsTimeAndLength) {
  // 25 records of FT_HL (0.25 s at 100 Hz), two seconds into STANDING.
  const double from_s = fx->standing_start_s + 2.0;
  double first_lost_s = -1;
  const Result r = Doctor("gap", EditFt("HL", [&](Event& e, ft_batch_t&) {
                            const double t = T(e.utime);
                            if (t < from_s || t >= from_s + 0.25 - 1e-6) return true;
                            if (first_lost_s < 0) first_lost_s = t;
                            return false;
                          }));
  EXPECT_EQ(r.exit_code, 6) << r.out;
  EXPECT_NE(r.out.find("warning: FT_HL: 1 gaps in STANDING, 25 samples lost"), std::string::npos)
      << r.out;
  double t = 0, len = 0;
  ASSERT_TRUE(FirstStretch(r.out, "warning: FT_HL: 1 gaps", &t, &len)) << r.out;
  EXPECT_NEAR(t, first_lost_s, 0.002) << r.out;
  EXPECT_NEAR(len, 0.25, 0.002) << r.out;
  // The others lost nothing there.
  EXPECT_EQ(r.out.find("warning: FT_ML"), std::string::npos) << r.out;
}

TEST_F(DoctorTest, AStallIsFoundWithItsTimeAndLengthAndNothingCountedLost) {
  // FT_ML's records of 0.3 s inside STANDING all arrive at its end, at once: nothing lost.
  const double from_s = fx->standing_start_s + 5.0;
  double last_before_s = -1, released_s = -1;
  // Received then and stamped then: the records' sample times as well as the receipt.
  const Result r = Doctor("stall", EditFt("ML", [&](Event& e, ft_batch_t& m) {
                            const double t = T(e.utime);
                            if (t < from_s) last_before_s = t;
                            if (t >= from_s + 0.3 && released_s < 0) released_s = t;
                            if (t >= from_s && t < from_s + 0.3) {
                              e.utime = kT0 + std::llround((from_s + 0.3) * 1e6);
                              m.receipt_utime = e.utime;
                              for (int64_t& u : m.sample_utime) u = e.utime;
                            }
                            return true;
                          }));
  EXPECT_EQ(r.exit_code, 6) << r.out;
  EXPECT_NE(r.out.find("warning: FT_ML: 1 stalls (nothing received, nothing lost) in STANDING"),
            std::string::npos)
      << r.out;
  double t = 0, len = 0;
  ASSERT_TRUE(FirstStretch(r.out, "warning: FT_ML: 1 stalls", &t, &len)) << r.out;
  EXPECT_NEAR(t, last_before_s, 0.002) << r.out;
  EXPECT_NEAR(len, from_s + 0.3 - last_before_s, 0.002) << r.out;
  EXPECT_EQ(r.out.find("warning: FT_ML: 1 gaps"), std::string::npos) << r.out;
}

TEST_F(DoctorTest, AMissingHangingSeriesIsNotCalibratableAndNamed) {
  const Result r = Doctor("missing", WithoutPhase(experiment_marker_t::HANG_Z_NEG));
  EXPECT_EQ(r.exit_code, 2) << r.out;
  EXPECT_NE(r.out.find("verdict: NOT calibratable"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("problem: hanging series missing (no completed start..stop): HANG_Z_NEG:"),
            std::string::npos)
      << r.out;
}

// The forecast's median sigma of `klass` (its unit as printed), or -1 when it has no line.
double ForecastMedian(const std::string& out, const std::string& klass, const std::string& unit) {
  std::smatch m;
  if (!std::regex_search(out, m,
                         std::regex("\n  " + klass + " +([0-9.e+-]+) " + unit + " +worst "))) {
    return -1;
  }
  return std::stod(m[1]);
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const size_t m = v.size() / 2;
  return v.size() % 2 ? v[m] : 0.5 * (v[m - 1] + v[m]);
}

TEST_F(DoctorTest, TheStepOneForecastIsTheSigmaTheCalibratorReports) {
  const Result r = Doctor("forecast", fx->events);
  EXPECT_EQ(r.exit_code, 0) << r.out;
  EXPECT_NE(r.out.find("sigma forecast (from 4 hanging series, 0 STEADY_POSE poses"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("step 2 cannot be forecast from this log: no STEADY_POSE recorded"),
            std::string::npos)
      << r.out;
  // The independent truth: the calibrator's own sigma on the same recording (its step 1's
  // covariance and cycle spread, from the data's noise; the forecast saw only the phases' turns
  // and sample counts and the planner's noise).
  const std::string cal_path = fx->dir + "/forecast.pbtxt";
  Child child({FTCAL_CALIBRATOR, "--config", kConfig, "--log", fx->dir + "/forecast.lcmlog",
               "--out", cal_path},
              fx->dir + "/forecast-cal.out", fx->dir + "/forecast-cal.err");
  const auto status = child.Wait(120);
  ASSERT_TRUE(status.has_value() && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << ReadFile(fx->dir + "/forecast-cal.err");
  const calibration::Calibration cal = ReadCalibrationFile(cal_path);
  std::map<std::string, std::vector<double>> reported;  // per class, in the forecast's unit
  for (const calibration::LegCalibration& leg : cal.leg()) {
    const calibration::Vec3Estimate& f = leg.force_offset_n();
    for (const double s : {f.sigma_x(), f.sigma_y(), f.sigma_z()})
      reported["force offset"].push_back(s);
    const calibration::Vec3Estimate& t = leg.torque_offset_nm();
    for (const double s : {t.sigma_x(), t.sigma_y(), t.sigma_z()})
      reported["torque offset"].push_back(1e3 * s);
    reported["leg weight"].push_back(leg.leg_weight_n().sigma());
    const calibration::LegCom& c = leg.com();
    for (const double s : {c.x().sigma_a_m(), c.x().sigma_d_m(), c.y_m().sigma(), c.z().sigma_a_m(),
                           c.z().sigma_d_m()}) {
      reported["leg CoM"].push_back(1e3 * s);
    }
  }
  ASSERT_EQ(reported["leg weight"].size(), 6u);
  // Predicted / reported over 12 seeds of a small plan: 0.98-1.10 for the offsets and leg weights
  // (docs/method.md, "Predicting a plan's sigma"); this one short recording (3 cycles of 4 s)
  // gives 0.89, 0.69, 1.98, hence the floor of 0.6 for the torque offsets. The calibrator's sigma
  // here is the spread of three cycles (two degrees of freedom: its own 95 % range is 0.16-1.9
  // times the true sigma; the median over six legs narrows it less than six-fold, the legs'
  // cycles share the sweep), so the leg weights', one number per leg, is allowed 0.5-2.5; the
  // many-seed check of the same prediction is plan_prediction_test's. Step 1's CoM estimator
  // falls short of the information bound the prediction gives (0.81 there): 0.6 for it too.
  const struct {
    const char* klass;
    const char* unit;
    double low, high;
  } classes[] = {{"force offset", "N", 0.7, 1.5},
                 {"torque offset", "mN m", 0.6, 1.5},
                 {"leg weight", "N", 0.5, 2.5},
                 {"leg CoM", "mm", 0.6, 1.5}};
  for (const auto& c : classes) {
    const double forecast = ForecastMedian(r.out, c.klass, c.unit);
    const double truth = Median(reported[c.klass]);
    ASSERT_GT(forecast, 0) << c.klass << "\n" << r.out;
    std::printf("doctor forecast: %-13s %.4g %s, the calibrator reports %.4g: ratio %.2f\n",
                c.klass, forecast, c.unit, truth, forecast / truth);
    EXPECT_GE(forecast / truth, c.low) << c.klass << ": " << forecast << " vs " << truth;
    EXPECT_LE(forecast / truth, c.high) << c.klass << ": " << forecast << " vs " << truth;
  }
}

TEST_F(DoctorTest, WithTheSegmentersPosesStepTwoIsForecastToo) {
  const std::string log = fx->dir + "/forecast2.lcmlog";
  WriteLog(log, fx->events);
  const std::string poses = fx->dir + "/forecast2-poses.lcmlog";
  {
    Child seg({FTCAL_SEGMENTER, "--config", kConfig, "--replay", log, "--out", poses},
              fx->dir + "/seg.out", fx->dir + "/seg.err");
    const auto status = seg.Wait(60);
    ASSERT_TRUE(status.has_value() && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
        << ReadFile(fx->dir + "/seg.err");
  }
  Child doctor({FTCAL_DOCTOR, "--config", kConfig, log, poses}, fx->dir + "/forecast2.out",
               fx->dir + "/forecast2.err");
  ASSERT_TRUE(doctor.Wait(60).has_value());
  const std::string out = ReadFile(fx->dir + "/forecast2.out");
  const std::string cal_path = fx->dir + "/forecast2.pbtxt";
  Child cal(
      {FTCAL_CALIBRATOR, "--config", kConfig, "--log", log, "--log", poses, "--out", cal_path},
      fx->dir + "/forecast2-cal.out", fx->dir + "/forecast2-cal.err");
  const auto status = cal.Wait(120);
  ASSERT_TRUE(status.has_value() && WIFEXITED(*status) && WEXITSTATUS(*status) == 0)
      << ReadFile(fx->dir + "/forecast2-cal.err");
  const calibration::Calibration c = ReadCalibrationFile(cal_path);
  std::vector<double> rot_xy, rot_z, p;
  for (const calibration::LegCalibration& leg : c.leg()) {
    const calibration::Vec3Estimate& r = leg.mounting().rotation_vector_deg();
    rot_xy.insert(rot_xy.end(), {r.sigma_x(), r.sigma_y()});
    rot_z.push_back(r.sigma_z());
    const calibration::Vec3Estimate& t = leg.mounting().p_tilde_prime_m();
    for (const double s : {t.sigma_x(), t.sigma_y(), t.sigma_z()}) p.push_back(1e3 * s);
  }
  const struct {
    const char* klass;
    const char* unit;
    double truth;
  } classes[] = {{"rotation x,y", "deg", Median(rot_xy)},
                 {"rotation z", "deg", Median(rot_z)},
                 {"p~'", "mm", Median(p)}};
  for (const auto& k : classes) {
    const double forecast = ForecastMedian(out, k.klass, k.unit);
    ASSERT_GT(forecast, 0) << k.klass << "\n" << out;
    std::printf("doctor forecast: %-13s %.4g %s, the calibrator reports %.4g: ratio %.2f\n",
                k.klass, forecast, k.unit, k.truth, forecast / k.truth);
    EXPECT_GE(forecast / k.truth, 0.7) << k.klass << "\n" << out;
    EXPECT_LE(forecast / k.truth, 1.5) << k.klass << "\n" << out;
  }
}

TEST_F(DoctorTest, AMissingHangingSeriesIsNamedInTheForecastsWarning) {
  const Result r = Doctor("forecast-missing", WithoutPhase(experiment_marker_t::HANG_X_POS));
  EXPECT_NE(r.out.find("warning: sigma forecast: hanging series HANG_X_POS missing: step 1 "
                       "cannot be predicted (the prediction needs all four)"),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("sigma forecast (from 0 hanging series"), std::string::npos) << r.out;
  EXPECT_EQ(r.out.find("\n  force offset "), std::string::npos) << r.out;
}

TEST_F(DoctorTest, ScriptsCalibrateStopsOnANotCalibratableRecordingUnlessForced) {
  std::vector<Event> events = WithoutPhase(experiment_marker_t::HANG_X_NEG);
  std::stable_sort(events.begin(), events.end(),
                   [](const Event& a, const Event& b) { return a.utime < b.utime; });
  const std::string log = fx->dir + "/no-x-neg.lcmlog";
  WriteLog(log, events);
  testing::ScopedEnv build("FTCAL_BUILD_DIR", FTCAL_BUILD_DIR);
  for (const bool force : {false, true}) {
    const std::string out = fx->dir + (force ? "/forced" : "/stopped");
    std::vector<std::string> argv = {std::string(FTCAL_SOURCE_DIR) + "/scripts/calibrate",
                                     "--config", kConfig, log, out};
    if (force) argv.insert(argv.begin() + 1, "--force");
    Child child(argv, out + ".out", out + ".err");
    const auto status = child.Wait(120);
    ASSERT_TRUE(status.has_value());
    const std::string said = ReadFile(out + ".out") + ReadFile(out + ".err");
    EXPECT_EQ(testing::DescribeWaitStatus(*status), "exit 2") << said;
    EXPECT_NE(ReadFile(out + "/doctor.txt").find("HANG_X_NEG"), std::string::npos) << said;
    if (!force) {
      EXPECT_NE(said.find("ftcal-doctor finds " + log + " not calibratable"), std::string::npos)
          << said;
      EXPECT_EQ(said.find("ftcal-calibrator"), std::string::npos) << "the calibrator ran\n" << said;
    } else {
      // The calibrator's own refusal: the doctor foretold it.
      EXPECT_NE(said.find("missing hanging series: HANG_X_NEG"), std::string::npos) << said;
    }
  }
}

TEST_F(DoctorTest, ASkewedTransducerClockIsMeasured) {
  // FT_FR's 7 kHz sample counter 300 ppm slow: 1.0003 host seconds per counted second. The
  // doctor fits each message's last ft_sequence against its receipt_utime: that record's count
  // is set from the receipt, and any earlier record's counted back from it by the sample times.
  constexpr double kSkewPpm = 300;
  constexpr double kCountsPerHostS = 7000.0 / (1 + kSkewPpm * 1e-6);
  const auto skew = [&](Event&, ft_batch_t& m) {
    const size_t last = static_cast<size_t>(m.n - 1);
    m.ft_sequence[last] = std::llround(T(m.receipt_utime) * kCountsPerHostS) + 123456;
    for (size_t j = 0; j < last; ++j) {
      const double before_s = 1e-6 * static_cast<double>(m.sample_utime[last] - m.sample_utime[j]);
      m.ft_sequence[j] = m.ft_sequence[last] - std::llround(before_s * kCountsPerHostS);
    }
    return true;
  };
  const Result r = Doctor("skew", EditFt("FR", skew));
  std::smatch row;
  ASSERT_TRUE(std::regex_search(r.out, row, std::regex("\nFT_FR .* ([-+][0-9.]+) ppm"))) << r.out;
  EXPECT_NEAR(std::stod(row[1]), kSkewPpm, 2.0) << r.out;
  ASSERT_TRUE(std::regex_search(r.out, row, std::regex("\nFT_HR .* ([-+][0-9.]+) ppm"))) << r.out;
  EXPECT_NEAR(std::stod(row[1]), 0.0, 2.0) << r.out;
  EXPECT_EQ(r.exit_code, 6) << r.out;
  EXPECT_NE(r.out.find("warning: FT_FR: its clock runs +300 ppm against the host's"),
            std::string::npos)
      << r.out;
}

}  // namespace
}  // namespace ftcal
