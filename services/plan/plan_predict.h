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

namespace ftcal::plan {

struct PlanPredictionReport {
  std::string plan_name;
  PlanPrediction prediction;
  double robot_time_s = 0.0;  // motion, dwell, hanging cycles; the operator's re-hangs excluded
};

// The plan named `plan_name` ("" = the config's first). Throws std::invalid_argument naming the
// plan, phase or config field when the plan cannot be expanded or predicted.
PlanPredictionReport PredictConfigPlan(const config::Config& config, const std::string& plan_name);

// The design alone (for tests): the noise-free poses and hanging series of the plan.
PlanDesign DesignOfPlan(const config::Config& config, const std::string& plan_name,
                        DeviceNoise* noise, RobotCalibration* nominal);

// The table: one line per class (median and worst sigma, what the calibrator would report),
// the p~'_z common mode, and as its last line "robot time: M min".
std::string FormatReport(const PlanPredictionReport& report);

}  // namespace ftcal::plan
