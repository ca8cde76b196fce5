// Step 2 at the report's scale: 729 standing poses ({-36, 0, 36} deg)^6 with the report's noise
// (0.05 N, 0.002 N*m per sample, 0.2 deg attitude, medians of 150 samples), generated from
// known parameters by the unit tests' generator. The target for the whole of step 2 (four
// models, 5-fold cross-validation each, the selected model's covariance) is < 0.5 s on the
// 2-core development machine.
//
//   <build>/tests/bench/standing_bench
#include <benchmark/benchmark.h>

#include "ftcal/offset_reestimation.h"
#include "ftcal/standing.h"
#include "standing_test_data.h"

namespace ftcal {
namespace {

using namespace testdata;  // NOLINT

struct Data {
  RobotCalibration truth = MakeTruth(21, Mounting::kFull);
  RobotCalibration step1 = Step1Of(truth);
  std::vector<StandingPose> poses = MakePoses(truth, Grid(), kReportNoise, false, 22);
  std::array<Vec6, kNumLegs> naive{};
};

const Data& TheData() {
  static const Data data;
  return data;
}

void BM_CalibrateStanding(benchmark::State& state) {
  const Data& d = TheData();
  StandingOptions options;
  for (auto _ : state) {
    StandingResult r = CalibrateStanding(d.step1, d.poses, d.naive, options);
    benchmark::DoNotOptimize(r);
  }
  state.SetLabel("729 poses, 4 models, 5-fold CV");
}
BENCHMARK(BM_CalibrateStanding)->Unit(benchmark::kMillisecond);

void BM_FitFullJoint(benchmark::State& state) {
  const Data& d = TheData();
  for (auto _ : state) {
    StandingFit f = FitStandingJoint(d.step1, d.poses, StandingModel::kFull, StandingOptions());
    benchmark::DoNotOptimize(f);
  }
}
BENCHMARK(BM_FitFullJoint)->Unit(benchmark::kMillisecond);

void BM_FitFullAlternating(benchmark::State& state) {
  const Data& d = TheData();
  for (auto _ : state) {
    StandingFit f =
        FitStandingAlternating(d.step1, d.poses, StandingModel::kFull, StandingOptions());
    benchmark::DoNotOptimize(f);
  }
}
BENCHMARK(BM_FitFullAlternating)->Unit(benchmark::kMillisecond);

void BM_ReestimateOffsetsFromStanding(benchmark::State& state) {
  const Data& d = TheData();
  OffsetReestimationOptions options;
  options.require_all = false;
  for (auto _ : state) {
    OffsetReestimate r = ReestimateOffsets(d.truth, d.poses, {}, options);
    benchmark::DoNotOptimize(r);
  }
}
BENCHMARK(BM_ReestimateOffsetsFromStanding)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
