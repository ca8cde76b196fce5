// The plan prediction on cases worked by hand (ftcal/plan_prediction.h) and ftcal-plan's
// reading of the config's plans (services/plan).
#include "ftcal/plan_prediction.h"

#include <gtest/gtest.h>

#include <cmath>
#include <stdexcept>
#include <string>

#include "ftcal/calibrate.h"
#include "ftcal/config.h"
#include "plan/plan_predict.h"
#include "sequencer/plan.h"

namespace ftcal {
namespace {

config::Config SimConfig() { return LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt"); }

RobotCalibration LegsWithCom(const config::Config& config) {
  RobotCalibration cal = NominalRobot(config);
  for (LegCalibration& l : cal.leg) {
    l.weight_n = 5.0;
    l.com.x = {0.015, M_PI, 0.0};
    l.com.y = 0.02;
    l.com.z = {0.015, -0.5 * M_PI, -0.05};
  }
  return cal;
}

double SigmaOf(const PlanPrediction& p, const std::string& name) {
  for (const PredictedSigma& s : p.parameters) {
    if (s.name == name) return s.sigma;
  }
  ADD_FAILURE() << "no parameter " << name;
  return 0.0;
}

// Hanging alone, N samples per series: the force offset along a pair's axis comes from the
// half-sum of that pair only (2N samples: sigma_f / sqrt(2N)); each series' own misalignment
// takes the components across it. m g from both pairs' half-differences: sigma_f / sqrt(4N).
// Exact when the torques say nothing about the misalignments, so their noise is made large
// (1 N m: they add a relative 1e-5 to the forces' information).
TEST(PlanPredictionTest, HangingOffsetAlongTheAxisAndLegWeightAsWorkedByHand) {
  const config::Config config = SimConfig();
  const RobotCalibration cal = LegsWithCom(config);
  PlanDesign d;
  const int cycles = 3;
  const double per_cycle = 600.0;
  const double n = cycles * per_cycle;
  // Gravity along +-x and +-z of the first leg's transducer, as the stated body axes.
  const Mat3& R = cal.X_B_ft[0].R;
  const Vec3 g[4] = {R * Vec3::UnitX(), -(R * Vec3::UnitX()), R * Vec3::UnitZ(),
                     -(R * Vec3::UnitZ())};
  for (int s = 0; s < kNumHangSeries; ++s)
    d.hanging.push_back({static_cast<HangSeries>(s), g[s], cycles, per_cycle});
  DeviceNoise noise;
  noise.force_n = 0.05;
  noise.torque_nm = 1.0;
  const PlanPrediction p = PredictPlan(cal, d, noise, HangingOptions(), StandingOptions());
  for (int k = 0; k < kNumLegs; ++k) {
    const std::string leg = std::string(kLegNames[k]) + " ";
    EXPECT_NEAR(SigmaOf(p, leg + "f_o x"), 0.05 / std::sqrt(2 * n), 1e-4 * 0.05 / std::sqrt(n))
        << leg;
    EXPECT_NEAR(SigmaOf(p, leg + "f_o z"), 0.05 / std::sqrt(2 * n), 1e-4 * 0.05 / std::sqrt(n))
        << leg;
    EXPECT_NEAR(SigmaOf(p, leg + "m g"), 0.05 / std::sqrt(4 * n), 1e-4 * 0.05 / std::sqrt(n))
        << leg;
  }
  EXPECT_EQ(p.standing_poses, 0);
  EXPECT_DOUBLE_EQ(p.hanging_samples, 4 * n);
}

// Four times the samples halve every sigma (white noise, one linearisation point).
TEST(PlanPredictionTest, FourTimesTheSamplesHalveEverySigma) {
  const config::Config config = SimConfig();
  DeviceNoise noise;
  RobotCalibration nominal;
  PlanDesign d = plan::DesignOfPlan(config, "experiment", &noise, &nominal);
  const PlanPrediction a = PredictPlan(nominal, d, noise, HangingOptions(), StandingOptions());
  for (PlannedHangSeries& s : d.hanging) s.samples_per_cycle *= 4;
  for (PlannedPose& pp : d.poses) pp.samples *= 4;
  const PlanPrediction b = PredictPlan(nominal, d, noise, HangingOptions(), StandingOptions());
  ASSERT_EQ(a.parameters.size(), b.parameters.size());
  for (size_t i = 0; i < a.parameters.size(); ++i)
    EXPECT_NEAR(b.parameters[i].sigma / a.parameters[i].sigma, 0.5, 1e-6) << a.parameters[i].name;
}

// The plan "experiment" of sim.pbtxt: 3 cycles of 6 s per series at 100 Hz, every 16th of the
// 729 poses (46) with 3 s dwell minus 2.5 s settling, and the sequencer's robot time.
TEST(PlanPredictionTest, ReadsTheConfigsPlanAsTheSequencerRunsIt) {
  const config::Config config = SimConfig();
  DeviceNoise noise;
  RobotCalibration nominal;
  const PlanDesign d = plan::DesignOfPlan(config, "experiment", &noise, &nominal);
  ASSERT_EQ(d.hanging.size(), 4u);
  for (const PlannedHangSeries& s : d.hanging) {
    EXPECT_EQ(s.cycles, 3);
    EXPECT_DOUBLE_EQ(s.samples_per_cycle, 600.0);
  }
  ASSERT_EQ(d.poses.size(), 46u);
  for (const PlannedPose& p : d.poses) EXPECT_NEAR(p.samples, 50.0, 1e-9);
  EXPECT_DOUBLE_EQ(noise.force_n, 0.05);
  const plan::PlanPredictionReport r = plan::PredictConfigPlan(config, "experiment");
  EXPECT_DOUBLE_EQ(r.robot_time_s, sequencer::Expand(config, "experiment").duration_s);
  const std::string text = plan::FormatReport(r);
  char last[64];
  std::snprintf(last, sizeof last, "robot time: %.1f min\n", r.robot_time_s / 60.0);
  EXPECT_EQ(text.substr(text.size() - std::string(last).size()), last);
  EXPECT_NE(text.find("p~'_z common"), std::string::npos);
}

TEST(PlanPredictionTest, RefusesWhatItCannotPredictNamingIt) {
  config::Config config = SimConfig();
  DeviceNoise noise;
  RobotCalibration nominal;
  try {
    plan::PredictConfigPlan(config, "no-such-plan");
    ADD_FAILURE() << "no throw";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("no-such-plan"), std::string::npos) << e.what();
  }
  config.mutable_planner()->set_force_noise_n(-1.0);
  try {
    plan::DesignOfPlan(config, "", &noise, &nominal);
    ADD_FAILURE() << "no throw";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("planner.force_noise_n"), std::string::npos) << e.what();
  }
  config = SimConfig();
  config.mutable_planner()->set_settle_s(10.0);
  try {
    plan::DesignOfPlan(config, "short", &noise, &nominal);
    ADD_FAILURE() << "no throw";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("planner.settle_s"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace ftcal
