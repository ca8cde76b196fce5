// The servo-vs-transducer delay (libcal/include/ftcal/latency.h, docs/method.md "Latencies")
// against the twin's truth: a sim log with constant extra delays on each device's host stamp,
// read back by the calibrator's collector as a real recording would be, the delay estimated
// from the hanging series and step 1 run on the shifted angles.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/log_replay_bus.h"
#include "common/service_stats.h"
#include "ftcal/calibrate.h"
#include "ftcal/config.h"
#include "ftcal/hanging.h"
#include "ftcal/latency.h"
#include "session/collector.h"
#include "sim/log_writer.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

config::Config SimConfig() { return LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt"); }

TEST(HangSweep, EndsAtWholeCyclesAndPassesEachAngleAtDifferentSpeeds) {
  const double cycle_s = 20.0;
  const int cycles = 10;
  EXPECT_NEAR(HangSweepAngle(cycles * cycle_s, cycle_s, cycles), 2.0 * M_PI * cycles, 1e-9);
  EXPECT_EQ(HangSweepAngle(0.0, cycle_s, cycles), 0.0);
  double peak = 0.0, low = 1e9;
  double previous = 0.0;
  const double dt = 1e-3;
  for (double t = dt; t <= cycles * cycle_s; t += dt) {
    const double a = HangSweepAngle(t, cycle_s, cycles);
    const double rate = (a - previous) / dt;
    ASSERT_GT(rate, 0.0) << "the sweep turns one way only, t = " << t;
    peak = std::max(peak, rate);
    low = std::min(low, rate);
    previous = a;
  }
  EXPECT_NEAR(peak, HangSweepPeakRate(cycle_s), 1e-3);
  EXPECT_NEAR(low, (1.0 - kHangSweepSpeedDepth) * 2.0 * M_PI / cycle_s, 1e-3);
  // The speed at which cycles 0 and 1 pass the same angle (a delay is then no encoder offset).
  auto speed_at_angle = [&](double angle) {
    double lo = 0.0, hi = cycles * cycle_s;
    for (int i = 0; i < 100; ++i) {
      const double mid = 0.5 * (lo + hi);
      (HangSweepAngle(mid, cycle_s, cycles) < angle ? lo : hi) = mid;
    }
    return (HangSweepAngle(lo + 1e-4, cycle_s, cycles) -
            HangSweepAngle(lo - 1e-4, cycle_s, cycles)) /
           2e-4;
  };
  const double first = speed_at_angle(1.0), second = speed_at_angle(1.0 + 2.0 * M_PI);
  EXPECT_GT(std::abs(first - second), 0.5 * kHangSweepSpeedDepth * 2.0 * M_PI / cycle_s)
      << first << " vs " << second << " rad/s";
}

TEST(ShiftServoAngles, TakesTheAngleAtTheLaterTime) {
  HangingRecording r;
  LegSamples& s = r.legs[0];
  for (int i = 0; i < 100; ++i) {
    s.t_s.push_back(0.01 * i);
    // 2 rad/s, wrapped as the bridge publishes it: the shift unwraps across the seam.
    s.angle_rad.push_back(std::remainder(3.0 + 2.0 * 0.01 * i, 2.0 * M_PI));
    s.wrench.push_back(Vec6::Zero());
  }
  const std::vector<HangingRecording> out = ShiftServoAngles({r}, 0.016);
  for (int i = 0; i < 100; ++i) {
    const double want = std::remainder(3.0 + 2.0 * (0.01 * i + 0.016), 2.0 * M_PI);
    EXPECT_NEAR(std::remainder(out[0].legs[0].angle_rad[i] - want, 2.0 * M_PI), 0.0, 1e-12) << i;
  }
}

struct Delays {
  double ft_s = 0.0, servo_s = 0.0, mocap_s = 0.0;
};

struct Collected {
  std::vector<HangingRecording> hanging;
  double true_delay_s = 0.0;  // servo's mean sample-time latency minus the pace leg's transducer's
};

// The twin's hanging series through a sim log with `delays`, read back by the collector.
Collected HangingThroughLog(const BigAntTwin& twin, const config::Config& config,
                            const Delays& delays, const std::string& name) {
  const std::string path = ::testing::TempDir() + "latency_test_" + name + ".lcmlog";
  SimLogOptions options;
  options.seed = 7;
  options.ft_delay_s = delays.ft_s;
  options.servo_delay_s = delays.servo_s;
  options.mocap_delay_s = delays.mocap_s;
  Collected out;
  {
    SimLogWriter writer(config, path, options);
    ExperimentPlan plan;
    plan.tare = plan.standing = plan.tripod = plan.walking = false;
    WriteExperiment(twin, plan, &writer);
    writer.Commit();
    // The aligner takes every sample at the pace leg's (leg 0's) transducer stamp.
    out.true_delay_s = writer.MeanLatencyS(kNumLegs) - writer.MeanLatencyS(0);
  }
  auto log = std::make_shared<spdlog::logger>("latency_test",
                                              std::make_shared<spdlog::sinks::null_sink_mt>());
  ServiceStats stats(log);
  CalibrationCollector collector(config);
  {
    LogReplayBus bus(path, path + ".out", stats);
    collector.Attach(bus);
    bus.Run([] {}, 60'000'000);
    collector.Flush();
  }
  out.hanging = collector.HangingRecordings();
  std::remove(path.c_str());
  return out;
}

struct Step1Errors {
  double com_m = 0.0, weight_n = 0.0, force_n = 0.0, torque_nm = 0.0;
  // The largest sigma step 1 states for each (spread over leg cycles).
  double weight_sigma_n = 0.0, force_sigma_n = 0.0, torque_sigma_nm = 0.0;
};

Step1Errors ErrorsOf(const HangingResult& h, const RobotCalibration& truth) {
  RobotCalibration cal = truth;
  ApplyHangingResult(h, &cal);
  Step1Errors e;
  for (int k = 0; k < kNumLegs; ++k) {
    const LegCalibration& a = cal.leg[k];
    const LegCalibration& b = truth.leg[k];
    e.com_m = std::max(e.com_m, MaxCurveDistance(a.com, b.com));
    e.weight_n = std::max(e.weight_n, std::abs(a.weight_n - b.weight_n));
    e.force_n =
        std::max(e.force_n, (a.offset.head<3>() - b.offset.head<3>()).cwiseAbs().maxCoeff());
    e.torque_nm =
        std::max(e.torque_nm, (a.offset.tail<3>() - b.offset.tail<3>()).cwiseAbs().maxCoeff());
    const HangingVariant& v = h.leg[k].with_s;
    e.weight_sigma_n = std::max(e.weight_sigma_n, v.weight_n.sigma);
    e.force_sigma_n = std::max(e.force_sigma_n, v.force_offset_n.sigma.maxCoeff());
    e.torque_sigma_nm = std::max(e.torque_sigma_nm, v.torque_offset_nm.sigma.maxCoeff());
  }
  return e;
}

// What Calibrate() does with the hanging series: the delay estimated and, when selected,
// applied before step 1.
HangingResult Step1(const std::vector<HangingRecording>& hanging, const config::Config& config,
                    ServoDelayEstimate* delay) {
  *delay = EstimateServoDelay(hanging);
  HangingOptions options = HangingOptionsFromConfig(config.calibrator(), config.mocap());
  const double applied = delay->selected ? delay->delay_s : 0.0;
  return RunHanging(ShiftServoAngles(hanging, applied), NominalTransducerPoses(config.robot()),
                    options);
}

TEST(ServoDelay, EstimatedFromTheHangingSeriesAndStepOneKeepsItsAccuracy) {
  const config::Config config = SimConfig();
  TwinOptions twin_options;
  twin_options.seed = 3;
  const BigAntTwin twin(config, twin_options);

  const Collected plain = HangingThroughLog(twin, config, Delays{}, "plain");
  const Collected delayed = HangingThroughLog(twin, config, Delays{0.002, 0.016, 0.008}, "delayed");

  ServoDelayEstimate d0, d1;
  const HangingResult h0 = Step1(plain.hanging, config, &d0);
  const HangingResult h1 = Step1(delayed.hanging, config, &d1);
  const Step1Errors e0 = ErrorsOf(h0, twin.Truth());
  const Step1Errors e1 = ErrorsOf(h1, twin.Truth());
  std::printf(
      "no extra delay: tau %.3f +- %.3f ms (truth %.3f ms, dBIC %.1f, %s); CoM %.4f mm, weight "
      "%.4f N, force offset %.4f N, torque offset %.5f N m\n",
      1e3 * d0.delay_s, 1e3 * d0.sigma_s, 1e3 * plain.true_delay_s, d0.delta_bic,
      d0.selected ? "selected" : "rejected", 1e3 * e0.com_m, e0.weight_n, e0.force_n, e0.torque_nm);
  std::printf(
      "FT 2 / servo 16 / mocap 8 ms: tau %.3f +- %.3f ms (truth %.3f ms, dBIC %.1f, %s); CoM %.4f "
      "mm, weight %.4f N, force offset %.4f N, torque offset %.5f N m\n",
      1e3 * d1.delay_s, 1e3 * d1.sigma_s, 1e3 * delayed.true_delay_s, d1.delta_bic,
      d1.selected ? "selected" : "rejected", 1e3 * e1.com_m, e1.weight_n, e1.force_n, e1.torque_nm);

  std::printf("sigma: covariance %.3f ms, spread %.3f ms; per leg and series (ms):",
              1e3 * d1.sigma_covariance_s, 1e3 * d1.sigma_spread_s);
  for (double v : d1.group_delay_s) std::printf(" %.1f", 1e3 * v);
  std::printf("\n");
  // The delay: within 1 ms of the truth and within 3 of its own sigma, a sigma that says
  // something (under 0.5 ms).
  ASSERT_TRUE(d1.estimated);
  EXPECT_TRUE(d1.selected) << "dBIC " << d1.delta_bic;
  EXPECT_NEAR(d1.delay_s, delayed.true_delay_s, 1e-3);
  EXPECT_NEAR(d1.delay_s, delayed.true_delay_s, 3.0 * d1.sigma_s);
  EXPECT_LT(d1.sigma_s, 0.5e-3);
  // Without extra delays the twin's own stamps still differ (servo 2-3.5 ms, transducers
  // 0.5-1.8 ms after the instant): either kept out, or estimated as that.
  ASSERT_TRUE(d0.estimated);
  if (d0.selected) {
    EXPECT_NEAR(d0.delay_s, plain.true_delay_s, 1e-3);
    EXPECT_NEAR(d0.delay_s, plain.true_delay_s, 3.0 * d0.sigma_s);
  }
  // Step 1 on the delayed data as good as on the same data without delay: the leg CoM curve,
  // which the delay biases, within 1.2x; the leg weights and offsets, which do not depend on
  // the angle's timing, differ between the two runs only by which samples the phase grid
  // matches: within 1.2x or three of their own stated sigmas.
  EXPECT_LE(e1.com_m, 1.2 * e0.com_m);
  EXPECT_LE(e1.weight_n, std::max(1.2 * e0.weight_n, e0.weight_n + 3.0 * e1.weight_sigma_n));
  EXPECT_LE(e1.force_n, std::max(1.2 * e0.force_n, e0.force_n + 3.0 * e1.force_sigma_n));
  EXPECT_LE(e1.torque_nm, std::max(1.2 * e0.torque_nm, e0.torque_nm + 3.0 * e1.torque_sigma_nm));

  // And the delay matters: step 1 on the delayed data without it is worse.
  HangingOptions options = HangingOptionsFromConfig(config.calibrator(), config.mocap());
  const Step1Errors unshifted = ErrorsOf(
      RunHanging(delayed.hanging, NominalTransducerPoses(config.robot()), options), twin.Truth());
  std::printf(
      "FT 2 / servo 16 / mocap 8 ms, no delay applied: CoM %.4f mm, weight %.4f N, force offset "
      "%.4f N, torque offset %.5f N m\n",
      1e3 * unshifted.com_m, unshifted.weight_n, unshifted.force_n, unshifted.torque_nm);
  EXPECT_GT(unshifted.com_m, 1.5 * e1.com_m);
}

}  // namespace
}  // namespace ftcal
