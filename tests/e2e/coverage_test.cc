// Honest uncertainty: over many twin seeds and both robot-CoM modes (fixed, and moving with the
// legs), how often the true value of each estimated parameter lies within the reported
// +-2 sigma of the default calibration (config/sim.pbtxt as shipped: exact hanging rotations,
// the gravity prior, the robot-CoM model chosen by the data). For Gaussian errors with exact
// sigmas that is 95.4%; sigmas from few leg cycles (a t distribution) or a covariance that
// misses a bias lower it. Goal: 85-99% per parameter class. Per seed the twin is cut down
// (fewer hanging cycles and standing poses) to keep the test short; noise and parameter ranges
// are the defaults. Also checked per run: the default picks the twin's robot-CoM model.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <map>
#include <string>

#include "twin_calibration.h"

namespace ftcal {
namespace {

using namespace testing_twin;  // NOLINT

constexpr int kSeeds = 20;
constexpr int kHangCycles = 6;
constexpr int kPoses = 243;

struct Tally {
  int inside = 0, total = 0;
  void Add(double error, double sigma) {
    ++total;
    if (std::abs(error) <= 2.0 * sigma) ++inside;
  }
  double Percent() const { return total ? 100.0 * inside / total : 0.0; }
};

double WrapAngle(double a) { return std::remainder(a, 2.0 * M_PI); }

TEST(Coverage, TrueValuesWithinTwoReportedSigmas) {
  const config::Config config = SimConfig();
  std::map<std::string, Tally> by_class;
  int wrong_com = 0;
  double worst_floor_ratio = 0.0;
  for (int run_index = 0; run_index < 2 * kSeeds; ++run_index) {
    const int seed = run_index / 2 + 1;
    const bool moving_com = run_index % 2 == 1;
    TwinOptions o;
    o.seed = 1000 + seed;
    o.hang_cycles = kHangCycles;
    o.physical_com = moving_com;
    const BigAntTwin twin(config, o);
    const CalibrationRun run = Calibrate(HangingOf(twin), twin.MakeSteadyPoses(kPoses), config);
    const RobotCalibration& truth = twin.Truth();
    const StandingFit& fit = run.standing.fit;
    if (run.standing.selected_leg_aware_com != moving_com || fit.model != StandingModel::kFull) {
      ++wrong_com;
      std::printf("coverage: seed %llu (%s CoM): selected %s\n",
                  static_cast<unsigned long long>(o.seed), moving_com ? "moving" : "fixed",
                  CandidateName(fit.model, run.standing.selected_leg_aware_com).c_str());
    }
    worst_floor_ratio = std::max(worst_floor_ratio, run.standing.residual_to_floor);
    for (int k = 0; k < kNumLegs; ++k) {
      const LegHangingResult& h = run.hanging.leg[k];
      const LegCalibration& t = truth.leg[k];
      for (int i = 0; i < 3; ++i) {
        by_class["force offset"].Add(h.with_s.force_offset_n.value[i] - t.offset[i],
                                     h.with_s.force_offset_n.sigma[i]);
        by_class["torque offset"].Add(h.with_s.torque_offset_nm.value[i] - t.offset[3 + i],
                                      h.with_s.torque_offset_nm.sigma[i]);
      }
      by_class["leg weight"].Add(h.with_s.weight_n.value - t.weight_n, h.with_s.weight_n.sigma);
      const LegComModel& c = h.com.model;
      by_class["CoM sinusoid"].Add(c.x.a - t.com.x.a, h.com.sigma_x[0]);
      by_class["CoM sinusoid"].Add(WrapAngle(c.x.c - t.com.x.c), h.com.sigma_x[1]);
      by_class["CoM sinusoid"].Add(c.x.d - t.com.x.d, h.com.sigma_x[2]);
      by_class["CoM sinusoid"].Add(c.y - t.com.y, h.com.sigma_y_m);
      by_class["CoM sinusoid"].Add(c.z.a - t.com.z.a, h.com.sigma_z[0]);
      by_class["CoM sinusoid"].Add(WrapAngle(c.z.c - t.com.z.c), h.com.sigma_z[1]);
      by_class["CoM sinusoid"].Add(c.z.d - t.com.z.d, h.com.sigma_z[2]);
      const Vec3 er = RotationErrorDeg(fit.R_tilde[k], t.R_tilde);
      const Vec3 ep = fit.p_tilde_prime[k] - t.p_tilde_prime;
      for (int i = 0; i < 3; ++i) {
        by_class[i == 2 ? "rotation z" : "rotation x,y"].Add(er[i], fit.sigma_rotation_deg[k][i]);
        by_class["p~'"].Add(ep[i], fit.sigma_p_tilde_prime_m[k][i]);
      }
    }
  }
  Tally all;
  for (const auto& [name, t] : by_class) {
    std::printf("coverage: %-14s %4d/%4d within 2 sigma = %.1f%%\n", name.c_str(), t.inside,
                t.total, t.Percent());
    EXPECT_GE(t.Percent(), 85.0) << name;
    EXPECT_LE(t.Percent(), 99.0) << name;
    all.inside += t.inside;
    all.total += t.total;
  }
  std::printf(
      "coverage: all            %4d/%4d within 2 sigma = %.1f%% (%d seeds x 2 CoM modes, "
      "%d hanging cycles, %d poses; goal 85-99%% per class)\n",
      all.inside, all.total, all.Percent(), kSeeds, kHangCycles, kPoses);
  std::printf(
      "coverage: the default chose the twin's robot-CoM model (and FULL) in %d of %d "
      "runs; largest residual / noise floor %.2f\n",
      2 * kSeeds - wrong_com, 2 * kSeeds, worst_floor_ratio);
  EXPECT_EQ(wrong_com, 0);
  EXPECT_GE(all.Percent(), 85.0);
  EXPECT_LE(all.Percent(), 99.0);
}

}  // namespace
}  // namespace ftcal
