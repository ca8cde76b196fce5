// The whole method in one call (docs/method.md, steps 1 and 2): hanging recordings and steady
// standing poses in, a complete calibration file and the parameters of eq. 3 out.
//
// Order: step 1 (RunHanging) on the four hanging series gives offsets, leg weights and CoM
// curves; those are applied to the nominal robot (config) and held fixed while step 2
// (CalibrateStanding) fits the four mounting models, with both robot-CoM targets (fixed C and
// leg-aware) unless the config fixes one, by the configured solver, selects the candidate with
// the lowest BIC (5-fold CV MSE reported beside it) and makes its parameters the calibration.
// Optionally the report's alternating scheme is run on the selected model too, for comparison.
//
// Profiles (config calibrator.profile, docs/method.md): FTCAL (default) uses exact hanging
// rotations, lets the data choose the robot-CoM model and uses the hanging gravity prior when
// every hanging series carries motion capture (skipped with a warning otherwise, never a
// refusal); REPORT is the report's procedure: first-order rotations, fixed C, no prior.
#pragma once

#include <array>
#include <stdexcept>
#include <string>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/hanging.h"
#include "ftcal/latency.h"
#include "ftcal/sensing_model.h"
#include "ftcal/standing.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

// A stage refused its input; what() reads "step 1 (hanging): <the stage's message>" or
// "step 2 (standing): ...". Derives from std::invalid_argument like the stages' own errors.
class CalibrationStageError : public std::invalid_argument {
 public:
  using std::invalid_argument::invalid_argument;
};

// The configured total mass disagrees with the data's (CalibrationRun's mass check); what()
// names both masses.
class MassMismatchError : public CalibrationStageError {
 public:
  using CalibrationStageError::CalibrationStageError;
};

// A transducer's standing data follows another leg's shaft far better than its own (the
// config's servo ids or transducer addresses of those legs swapped); what() names the legs and
// the figures.
class LegMapMismatchError : public CalibrationStageError {
 public:
  using CalibrationStageError::CalibrationStageError;
};

// The leg map check (docs/method.md "The data checks the config"): rms_nm[k][j] the rms torque
// misfit of transducer k's standing readings when its foot is taken to turn with shaft j (the
// model of calibration.proto's LegMapCheck, linear least squares, 18 unknowns per pair). Needs
// kMinLegMapPoses poses; fewer give checked = false.
struct LegMapResult {
  static constexpr int kMinLegMapPoses = 30;
  // Another shaft fitting a transducer this many times better (rms) than its own is a
  // contradiction. With the config right the own shaft fits 64-116 times better than any other
  // on the twin (tests/unit/recovery_test.cc); swapped, the other way round by as much: a factor
  // of 2 leaves margin both ways.
  static constexpr double kRatioLimit = 2.0;
  bool checked = false;
  int poses = 0;
  std::array<std::array<double, kNumLegs>, kNumLegs> rms_nm{};
  // Per transducer: the best other shaft and whether it beats the own one by kRatioLimit.
  std::array<int, kNumLegs> best_other{};
  std::array<bool, kNumLegs> contradicted{};
  bool consistent() const;
  // "" when consistent, else the sentence naming the legs and figures.
  std::string Describe() const;
};
LegMapResult CheckLegMap(const std::vector<StandingPose>& poses);

struct CalibrateOptions {
  // Calibrate even when a transducer's data follows another leg's shaft (LegMapMismatchError
  // otherwise); recorded in the file and as a warning.
  bool accept_leg_map_mismatch = false;
  // Calibrate even when the configured total mass disagrees with the data (the mismatch is
  // recorded in the file and as a warning) instead of throwing MassMismatchError.
  bool accept_mass_mismatch = false;
  // The naive tare baseline from a TARE phase (mean reading per leg: upright, feet in the air,
  // shafts at 0); without it, step 1's (the upright hanging series near theta = 0).
  bool has_naive_tare = false;
  std::array<Vec6, kNumLegs> naive_tare;
  // Also run the report's alternating scheme on the selected model (StandingRun.alternating);
  // the calibration stays the configured solver's.
  bool compare_alternating = false;
};

struct CalibrationRun {
  HangingResult hanging;
  RobotCalibration step1;   // nominal robot + step 1 (R~ = I, p~' = 0)
  StandingResult standing;  // the four fits, Table I, residuals
  bool has_alternating = false;
  StandingFit alternating;  // the report's scheme on the selected model
  // The servo stream's delay (Calibrate only; not estimated under the REPORT profile); the
  // calibration applies it when selected (calibration.servo_delay_s).
  ServoDelayEstimate servo_delay;
  RobotCalibration calibration;    // step 1 + the selected model: the parameters of eq. 3
  calibration::Calibration proto;  // everything, as written to the calibration file
  // What the user should know (also proto.warning): e.g. the gravity prior skipped.
  std::vector<std::string> warnings;
};

// The nominal robot of the config (X_B_ft, total mass, g0) with no calibration applied.
RobotCalibration NominalRobot(const config::Config& config);

// Step 1 + step 2 + the calibration file. Options come from config.calibrator() (and
// config.mocap() for the hanging axis tolerance). Throws CalibrationStageError naming the stage
// for degenerate input (the stage's message kept in full).
CalibrationRun Calibrate(const std::vector<HangingRecording>& hanging,
                         const std::vector<StandingPose>& poses, const config::Config& config,
                         const CalibrateOptions& options = CalibrateOptions());

// Step 2 fed from a finished step 1 (for callers that vary only step 2's options).
CalibrationRun CalibrateFromHanging(const HangingResult& hanging,
                                    const std::vector<StandingPose>& poses,
                                    const config::Config& config,
                                    const StandingOptions& standing_options,
                                    const CalibrateOptions& options = CalibrateOptions());

}  // namespace ftcal
