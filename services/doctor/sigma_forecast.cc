#include "doctor/sigma_forecast.h"

#include <chrono>
#include <cmath>
#include <stdexcept>

#include "common/messages.h"
#include "ftcal/calibrate.h"
#include "plan/plan_predict.h"
#include "sim/twin.h"

namespace ftcal::doctor {

SigmaForecast ForecastSigma(const config::Config& config,
                            const std::vector<SeenHangSeries>& hanging,
                            const std::vector<PlannedPose>& poses) {
  const auto t0 = std::chrono::steady_clock::now();
  SigmaForecast f;
  PlanDesign design;
  plan::SetCalibratorChoices(config, &design);
  DeviceNoise noise;
  RobotCalibration nominal;
  try {
    noise = plan::PlannerNoise(config.planner());
    const BigAntTwin twin(config, plan::NominalTwin(config.planner()));
    nominal = twin.Truth();
    // The last completed phase of each series (a repeated one replaced the earlier).
    std::array<const SeenHangSeries*, kNumHangSeries> seen{};
    for (const SeenHangSeries& h : hanging) seen[static_cast<size_t>(h.series)] = &h;
    std::string missing, short_of_cycles;
    for (int s = 0; s < kNumHangSeries; ++s) {
      const auto series = static_cast<HangSeries>(s);
      const std::string name = PhaseName(experiment_marker_t::HANG_X_POS + s);
      const SeenHangSeries* h = seen[static_cast<size_t>(s)];
      if (h == nullptr) {
        missing += (missing.empty() ? "" : ", ") + name;
        continue;
      }
      PlannedHangSeries p;
      p.series = series;
      p.gravity_b =
          h->gravity_b.norm() > 0.5 ? Vec3(h->gravity_b.normalized()) : twin.StatedGravityB(series);
      p.cycles = static_cast<int>(std::floor(h->shaft_turns + 0.1));
      if (p.cycles < 1) {
        short_of_cycles += (short_of_cycles.empty() ? "" : ", ") + name;
        continue;
      }
      p.samples_per_cycle = h->samples / p.cycles;
      design.hanging.push_back(p);
    }
    if (!missing.empty()) {
      f.step1_missing = "hanging series " + missing +
                        " missing: step 1 cannot be predicted (the prediction needs all four)";
    } else if (!short_of_cycles.empty()) {
      f.step1_missing = "hanging series " + short_of_cycles +
                        " turned the legs through less than a cycle: step 1 cannot be predicted";
    }
    if (!f.step1_missing.empty()) design.hanging.clear();
  } catch (const std::exception& e) {
    f.error = e.what();
    return f;
  }
  if (poses.empty()) {
    f.step2_missing =
        "step 2 cannot be forecast from this log: no STEADY_POSE recorded (the calibrator "
        "segments the poses itself; run the segmenter over it first, e.g. ftcal-pose-segmenter "
        "--replay, to forecast step 2)";
  } else {
    design.poses = poses;
  }
  if (design.hanging.empty() && design.poses.empty()) return f;
  const auto predict = [&] {
    const PlanPrediction p = PredictPlan(
        nominal, design, noise, HangingOptionsFromConfig(config.calibrator(), config.mocap()),
        StandingOptionsFromConfig(config.calibrator()));
    f.classes = p.classes;
    f.step1 = !design.hanging.empty();
    f.step2 = !design.poses.empty();
    f.hanging_series = static_cast<int>(design.hanging.size());
    f.poses = p.standing_poses;
  };
  try {
    predict();
  } catch (const std::exception& e) {
    // Too few poses for the standing model, most likely: step 1 alone, and why not step 2.
    if (design.poses.empty()) {
      f.step1_missing = std::string("step 1 cannot be forecast: ") + e.what();
    } else if (design.hanging.empty()) {
      f.step2_missing = std::string("step 2 cannot be forecast: ") + e.what();
    } else {
      f.step2_missing = std::string("step 2 cannot be forecast: ") + e.what();
      design.poses.clear();
      try {
        predict();
      } catch (const std::exception& e1) {
        f.step1_missing = std::string("step 1 cannot be forecast: ") + e1.what();
      }
    }
  }
  f.elapsed_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return f;
}

}  // namespace ftcal::doctor
