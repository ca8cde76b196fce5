// Step 1 at the report's scale: six legs, four hanging series, ten leg cycles of 9.7 s at
// 100 Hz (~9700 samples per leg and series), the report's noise (0.05 N, 0.002 N*m), encoder
// quantisation, generated from known parameters by the unit tests' generator. The whole
// calibration's target is < 0.5 s; step 1 should take a small part of it.
//
//   <build>/tests/bench/hanging_bench
#include <benchmark/benchmark.h>

#include "ftcal/hanging.h"
#include "hanging_test_data.h"

namespace ftcal {
namespace {

using namespace hanging_testdata;  // NOLINT

struct Data {
  std::array<Pose3, kNumLegs> X = NominalPoses();
  std::vector<HangingRecording> recordings;
  Data() {
    Motion m;
    m.aligned = false;
    m.samples_per_cycle = 970.0;
    m.cycles = 10.02;
    m.angle_quantum_rad = kTwoPi / 4096;
    m.f_noise_n = 0.05;
    m.tau_noise_nm = 0.002;
    std::mt19937 rng(7);
    recordings = MakeRecordings(X, MakeTruth(0.03), m, &rng);
  }
};

const Data& TheData() {
  static const Data data;
  return data;
}

void BM_RunHanging(benchmark::State& state) {
  const Data& d = TheData();
  HangingOptions options;
  options.refine_s_plus = state.range(0) != 0;
  options.exact_rotations = state.range(1) != 0;
  for (auto _ : state) {
    HangingResult r = RunHanging(d.recordings, d.X, options);
    benchmark::DoNotOptimize(r);
  }
  state.SetLabel(std::string(options.refine_s_plus ? "report objective refine" : "closed-form s+") +
                 (options.exact_rotations ? ", exact rotations" : ", I + [s]"));
}
BENCHMARK(BM_RunHanging)->Args({1, 0})->Args({0, 0})->Args({1, 1})->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
