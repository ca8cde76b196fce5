// ftcal-doctor's forecast: the sigma each parameter class will have, from the data the recording
// holds, before the solve (issue 38; docs/method.md "ftcal-doctor"). ftcal-plan's predictor
// (libcal PredictPlan) on a design made of what the doctor saw instead of a plan: each completed
// hanging series (its stated gravity from the start marker, its cycles from the shaft turns, its
// samples per cycle from the transducer samples received, at most the aligner's rate), each
// recorded STEADY_POSE (its medians and sample count, as the calibrator reads them), with the
// config's nominal robot and the planner's noise (plan/plan_predict.h, shared with ftcal-plan).
#pragma once

#include <string>
#include <vector>

#include "ftcal/plan_prediction.h"
#include "proto/config.pb.h"

namespace ftcal::doctor {

// A completed hanging phase as the forecast takes it.
struct SeenHangSeries {
  HangSeries series = HangSeries::kXPos;
  Vec3 gravity_b = Vec3::Zero();  // the start marker's; zero when it stated none
  double shaft_turns = 0;         // of the slowest servo
  double samples = 0;             // transducer samples per leg (the fewest of the six)
};

struct SigmaForecast {
  bool step1 = false, step2 = false;  // forecast made
  int hanging_series = 0, poses = 0;  // what it was made from
  std::vector<ClassSummary> classes;  // PredictPlan's, in its order
  // Why a step is not forecast (empty when it is): the recording lacks what it needs. The
  // step-1 one is also a warning (a hanging series missing or short).
  std::string step1_missing, step2_missing;
  // The forecast could not be made at all (the config's planner section, a robot the twin's
  // statics cannot model): worth a note, not the recording's fault.
  std::string error;
  double elapsed_s = 0;  // the prediction's own time
};

// Never throws on the recording's content: what cannot be predicted is said in *_missing.
SigmaForecast ForecastSigma(const config::Config& config,
                            const std::vector<SeenHangSeries>& hanging,
                            const std::vector<PlannedPose>& poses);

}  // namespace ftcal::doctor
