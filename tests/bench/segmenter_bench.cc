// Pose segmenter speed, as a multiple of real time (target >= 1000x for a one-hour
// six-transducer 100 Hz log): the aligner and the segmenter over one hour of the twin's
// standing frames held in memory (ten minutes of poses repeated six times, time shifted), fed
// in the order a log holds them (six readings, servo state, mocap frame per 10 ms).
//
//   <build>/tests/bench/segmenter_bench
#include <vector>

#include <benchmark/benchmark.h>

#include "ftcal/aligner.h"
#include "ftcal/config.h"
#include "ftcal/segmenter.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

constexpr int64_t kT0 = 1'700'000'000'000'000;
constexpr int kRepeats = 6;

struct Frame {
  int64_t utime;
  std::array<Vec6, kNumLegs> reading;
  std::array<double, kNumLegs> angle_rad;
  Mat3 R_WC;
};

struct Data {
  std::vector<Frame> frames;  // ten minutes
  double span_s = 0;
  Data() {
    const config::Config config = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    TwinOptions o;
    o.marker_dropout_rate_hz = 0;
    BigAntTwin twin(config, o);
    span_s = twin.Standing(108, {}, [this](const TwinFrame& f) {
      frames.push_back({kT0 + std::llround(f.t_s * 1e6), f.reading, f.angle_rad, RemoveHeading(f.R_GC)});
    });
  }
};

const Data& TheData() {
  static const Data data;
  return data;
}

void BM_AlignAndSegmentOneHour(benchmark::State& state) {
  const Data& d = TheData();
  const int64_t span_us = std::llround(d.span_s * 1e6) + 10'000;
  int64_t poses = 0, samples = 0;
  for (auto _ : state) {
    PoseSegmenter segmenter(SegmenterOptions{}, [&poses](const SteadyPoseOut&) { ++poses; });
    Aligner aligner({}, [&](const AlignedSample& s) {
      ++samples;
      segmenter.Add(s.sample);
    });
    for (int r = 0; r < kRepeats; ++r) {
      const int64_t shift = r * span_us;
      for (const Frame& f : d.frames) {
        const int64_t t = f.utime + shift;
        for (int k = 0; k < kNumLegs; ++k) aligner.AddFt({t, k, f.reading[k], 0});
        aligner.AddServo({t, f.angle_rad});
        aligner.AddMocap({t, true, f.R_WC, true});
      }
    }
    segmenter.Flush();
  }
  const double hours_of_data = kRepeats * d.span_s / 3600.0;
  state.counters["x_real_time"] = benchmark::Counter(
      static_cast<double>(state.iterations()) * kRepeats * d.span_s, benchmark::Counter::kIsRate);
  state.counters["poses_per_pass"] = static_cast<double>(poses) / static_cast<double>(state.iterations());
  state.SetLabel(std::to_string(hours_of_data).substr(0, 4) + " h of six 100 Hz transducers per pass");
  benchmark::DoNotOptimize(samples);
}
BENCHMARK(BM_AlignAndSegmentOneHour)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
