// The whole method at the report's scale on the twin (default seed and noise): four hanging
// series of ten 20 s leg cycles and all 729 standing poses (those without a marker dropout),
// config/sim.pbtxt. Prints each stage's wall and CPU time, a `total` line (Calibrate() as one
// call) and the peak resident memory (getrusage). Run by hand:
//   <build>/tests/bench/calibration_bench
#include <sys/resource.h>

#include <chrono>
#include <cstdio>
#include <ctime>
#include <functional>
#include <string>

#include "ftcal/calibrate.h"
#include "ftcal/config.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

double CpuSeconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// Runs `stage` and prints "<name>: wall <s> s, cpu <s> s"; returns wall seconds.
double Timed(const std::string& name, const std::function<void()>& stage) {
  const auto t0 = std::chrono::steady_clock::now();
  const double c0 = CpuSeconds();
  stage();
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("%-44s wall %8.3f s  cpu %8.3f s\n", name.c_str(), wall, CpuSeconds() - c0);
  std::fflush(stdout);
  return wall;
}

int Run() {
  const config::Config config = LoadConfigFile(FTCAL_SOURCE_DIR "/config/sim.pbtxt");
  const BigAntTwin twin(config, TwinOptions());
  std::vector<HangingRecording> hanging;
  std::vector<StandingPose> poses;
  Timed("twin: hanging series (not the method)", [&] {
    for (int s = 0; s < kNumHangSeries; ++s)
      hanging.push_back(twin.MakeHangingRecording(static_cast<HangSeries>(s)));
  });
  Timed("twin: 729 standing poses (not the method)", [&] { poses = twin.MakeSteadyPoses(729); });
  std::printf("input: %zu hanging series, %zu steady poses\n", hanging.size(), poses.size());

  HangingResult step1;
  RobotCalibration step1_cal = NominalRobot(config);
  const StandingOptions standing_options = StandingOptionsFromConfig(config.calibrator());
  StandingResult standing;
  double sum = 0.0;
  sum += Timed("step 1: hanging (RunHanging)", [&] {
    step1 = RunHanging(hanging, NominalTransducerPoses(config.robot()),
                       HangingOptionsFromConfig(config.calibrator(), config.mocap()));
    ApplyHangingResult(step1, &step1_cal);
  });
  std::array<Vec6, kNumLegs> naive{};
  for (int k = 0; k < kNumLegs; ++k) naive[k] = step1.leg[k].naive_offset;
  sum += Timed("step 2: 4 models x 2 CoM, 5-fold CV, BIC", [&] {
    StandingOptions o = standing_options;
    o.gravity_prior = step1.gravity_observations;
    standing = CalibrateStanding(step1_cal, poses, naive, o);
  });
  sum += Timed("calibration file (proto)", [&] {
    calibration::Calibration out;
    WriteHangingToCalibration(step1, &out);
    FillStandingProto(standing, &out);
  });
  std::printf("%-44s wall %8.3f s\n", "sum of the method's stages", sum);
  Timed("comparison: report's alternating scheme (FULL)", [&] {
    (void)FitStandingAlternating(step1_cal, poses, StandingModel::kFull, standing_options);
  });
  CalibrationRun run;
  const auto t0 = std::chrono::steady_clock::now();
  const double c0 = CpuSeconds();
  run = Calibrate(hanging, poses, config);
  std::printf(
      "total (Calibrate(), one call, the default): wall %.3f s, cpu %.3f s; selected model %s\n",
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count(),
      CpuSeconds() - c0, StandingModelName(run.standing.selected));
  {
    // The report's procedure (profile REPORT: first-order hanging rotations, fixed CoM, four
    // candidates instead of eight).
    config::Config report = config;
    report.mutable_calibrator()->set_profile(config::REPORT);
    const auto t1 = std::chrono::steady_clock::now();
    const double c1 = CpuSeconds();
    run = Calibrate(hanging, poses, report);
    std::printf("total, the report's profile: wall %.3f s, cpu %.3f s; selected model %s\n",
                std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count(),
                CpuSeconds() - c1, StandingModelName(run.standing.selected));
  }
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  std::printf("peak memory (max RSS, getrusage): %.1f MiB\n", u.ru_maxrss / 1024.0);
  return 0;
}

}  // namespace
}  // namespace ftcal

int main() { return ftcal::Run(); }
