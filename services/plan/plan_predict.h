// ftcal-plan --predict: an experiment plan of the config (the sequencer's plan format) turned
// into what ftcal/plan_prediction.h predicts from, and the table it prints.
//
// The robot's statics come from the twin's model of BigAnt (services/sim/twin.h) with no
// mounting error: the feet's positions at each shaft angle, hence the chassis tilt and the
// legs' loads in every standing pose, which the config does not hold. The noise, the settling
// and the self-balancing foot forces come from the config's `planner` section, the samples per
// median from segmenter.sample_rate_hz, the robot time from the sequencer's own schedule.
#pragma once

#include <string>

#include "ftcal/plan_prediction.h"
#include "proto/config.pb.h"
#include "sim/twin.h"

namespace ftcal::plan {

struct PlanPredictionReport {
  std::string plan_name;
  PlanPrediction prediction;
  double robot_time_s = 0.0;  // motion, dwell, hanging cycles; the operator's re-hangs excluded
};

// The plan named `plan_name` ("" = the config's first). Throws std::invalid_argument naming the
// plan, phase or config field when the plan cannot be expanded or predicted.
PlanPredictionReport PredictConfigPlan(const config::Config& config, const std::string& plan_name);

// What every prediction from this config shares (ftcal-plan's from a plan, ftcal-doctor's from a
// recording): the planner's per-sample noise (throws std::invalid_argument naming a planner field
// that is not finite and >= 0, or > 0 where it must be); the nominal robot as the twin models it
// (the config's geometry, Table II legs, no mounting error, no offsets spread; only its statics
// are used, its noise is never drawn); and the calibrator's step-2 choices the design carries
// (leg-aware CoM, the hanging gravity prior).
DeviceNoise PlannerNoise(const config::Planner& planner);
TwinOptions NominalTwin(const config::Planner& planner);
void SetCalibratorChoices(const config::Config& config, PlanDesign* design);

// The design alone (for tests): the noise-free poses and hanging series of the plan.
PlanDesign DesignOfPlan(const config::Config& config, const std::string& plan_name,
                        DeviceNoise* noise, RobotCalibration* nominal);

// The table: one line per class (median and worst sigma, what the calibrator would report),
// the p~'_z common mode, and as its last line "robot time: M min".
std::string FormatReport(const PlanPredictionReport& report);

}  // namespace ftcal::plan
