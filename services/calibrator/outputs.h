// What ftcal-calibrator writes besides the calibration file, and the tables it prints.
#pragma once

#include <string>
#include <vector>

#include "ftcal/calibrate.h"
#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/segmenter.h"

namespace ftcal {

// Writes the calibration file and <out>.residuals.csv beside it, both atomically.
void WriteCalibrationOutputs(const CalibrationRun& run, const std::string& out_path);

// Results in the journal's terms (docs/method.md): the RMSE of the summed ground-contact force
// and torque against the balance target, naive tare vs calibration, over the standing poses
// and (when given) the walk; per leg against the true parameters when `truth` is given. Into
// run->proto.result_rmse.
void AddResultRmse(const std::vector<SyncSample>& walk, const RobotCalibration* truth,
                   CalibrationRun* run);

// The short table printed at the end: per leg offsets, weights, mounting; model selection;
// standing residuals before/after.
std::string SummaryTable(const CalibrationRun& run);

// Per-pose residuals of the total wrench at the CoM in W, one row per pose and variant:
// "pose,variant,fx_n,fy_n,fz_n,tx_nm,ty_nm,tz_nm" (variants: naive tare, without T~, full
// calibration). The report's violin plots read this.
std::string ResidualsCsv(const StandingResult& standing);

// The path of the residuals file written beside a calibration file: cal.pbtxt -> cal.residuals.csv.
std::string ResidualsPathFor(const std::string& calibration_path);

// The walking session corrected (eq. 3 in W, about the CoM: GroundWrenchW, the corrector's
// model) by each calibration: "t_s,variant,<LEG>_fx_n,...,<LEG>_tz_nm for the six legs,
// total_fx_n,...,total_tz_nm". Variants: "full calibration" (run.calibration), "naive tare"
// (the step-1 naive offsets, no leg gravity, nominal mounting) and "truth" when `truth` is
// given. Samples without a tracked attitude are left out (the corrector would assume level and
// flag them); one sample per `period_s` is kept (the figure's resolution, not the data's).
// Throws std::invalid_argument when `samples` is empty.
std::string WalkingCsv(const std::vector<SyncSample>& samples, const CalibrationRun& run,
                       const RobotCalibration* truth, double period_s = 0.04);
// cal.pbtxt -> cal.walking.csv.
std::string WalkingPathFor(const std::string& calibration_path);

}  // namespace ftcal
