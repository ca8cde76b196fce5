// The whole method in one call. Model, residuals and unknowns of each stage are documented at
// the stages (hanging.h, standing.h); this file only sequences them, adds the stage to their
// errors and assembles the calibration file.
#include "ftcal/calibrate.h"

#include <string>
#include <utility>

#include "ftcal/config.h"

namespace ftcal {

RobotCalibration NominalRobot(const config::Config& config) {
  RobotCalibration cal;
  cal.X_B_ft = NominalTransducerPoses(config.robot());
  cal.total_mass_kg = config.robot().total_mass_kg();
  cal.g0 = config.robot().g0_m_s2();
  return cal;
}

CalibrationRun CalibrateFromHanging(const HangingResult& hanging,
                                    const std::vector<StandingPose>& poses,
                                    const config::Config& config,
                                    const StandingOptions& standing_options,
                                    const CalibrateOptions& options) {
  CalibrationRun run;
  run.hanging = hanging;
  run.step1 = NominalRobot(config);
  ApplyHangingResult(hanging, &run.step1);

  StandingOptions standing = standing_options;
  if (config.calibrator().hanging_gravity_prior()) {
    if (hanging.gravity_observations.empty()) {
      throw CalibrationStageError(
          "step 2 (standing): calibrator.hanging_gravity_prior needs motion capture attitude "
          "during every hanging series, and at least one series has none");
    }
    standing.gravity_prior = hanging.gravity_observations;
  }

  std::array<Vec6, kNumLegs> naive{};
  for (int k = 0; k < kNumLegs; ++k) naive[k] = hanging.leg[k].naive_offset;
  try {
    run.standing = CalibrateStanding(run.step1, poses, naive, standing);
    if (options.compare_alternating) {
      run.alternating = FitStandingAlternating(run.step1, poses, run.standing.selected,
                                               standing);
      run.has_alternating = true;
    }
  } catch (const std::invalid_argument& e) {
    throw CalibrationStageError(std::string("step 2 (standing): ") + e.what());
  }
  run.calibration = run.standing.calibration;

  calibration::Calibration& out = run.proto;
  out.set_robot_name(config.robot().name());
  out.set_g0_m_s2(run.step1.g0);
  out.set_total_mass_kg(run.step1.total_mass_kg);
  out.set_version(1);
  // Legs in config order before the stages fill them by name.
  for (int k = 0; k < kNumLegs; ++k) out.add_leg()->set_name(std::string(kLegNames[k]));
  WriteHangingToCalibration(hanging, &out);
  FillStandingProto(run.standing, &out);
  // FillStandingProto rewrites the solver block; keep step 1's flag in it.
  out.mutable_solver()->set_exact_hanging_rotations(hanging.exact_rotations);
  out.mutable_solver()->set_hanging_gravity_prior(!standing.gravity_prior.empty());
  return run;
}

CalibrationRun Calibrate(const std::vector<HangingRecording>& hanging,
                         const std::vector<StandingPose>& poses, const config::Config& config,
                         const CalibrateOptions& options) {
  HangingResult step1;
  try {
    step1 = RunHanging(hanging, NominalTransducerPoses(config.robot()),
                       HangingOptionsFromConfig(config.calibrator(), config.mocap()));
  } catch (const std::invalid_argument& e) {
    throw CalibrationStageError(std::string("step 1 (hanging): ") + e.what());
  }
  return CalibrateFromHanging(step1, poses, config, StandingOptionsFromConfig(config.calibrator()),
                              options);
}

}  // namespace ftcal
