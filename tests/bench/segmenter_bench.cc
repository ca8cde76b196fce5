// Pose segmenter speed, as a multiple of real time (issue #5's target: a one-hour
// six-transducer 100 Hz log segmented at >= 1000x real time).
//
// BM_SegmenterStageReplay is the definition: what `ftcal-pose-segmenter --replay IN
// --out OUT` does, log in -> log out, in this process (LogReplayBus + PoseSegmenterStage, as
// main.cc builds them; only process start-up and config parsing are left out): read and
// decode every event, align, publish every STEADY_POSE into the output log, fsync and rename
// it; /1 also publishes every SYNC_SAMPLE into it (--sync-samples), /0 does not (the default). The
// log is ten minutes of the twin's standing poses as the bridges publish them
// (services/sim/log_writer.h) between EXPERIMENT STANDING markers. x_real_time = seconds of log per
// second; the plain run divides by CPU time, the /real_time run by wall time (on a loaded shared
// machine the two differ: quote the wall figure's median from a quiet machine, or both).
//
// BM_AlignAndSegmentOneHour is the logic alone (no log, no LCM): the aligner and the segmenter
// over one hour of the same frames held in memory (repeated six times, time shifted).
//
//   <build>/tests/bench/segmenter_bench
#include <unistd.h>

#include <chrono>
#include <vector>

#include <benchmark/benchmark.h>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/log_replay_bus.h"
#include "ftcal/aligner.h"
#include "ftcal/config.h"
#include "ftcal/segmenter.h"
#include "pose_segmenter/pose_segmenter_stage.h"
#include "sim/log_writer.h"
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
    const config::Config config =
        LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
    TwinOptions o;
    o.marker_dropout_rate_hz = 0;
    BigAntTwin twin(config, o);
    span_s = twin.Standing(108, {}, [this](const TwinFrame& f) {
      frames.push_back(
          {kT0 + std::llround(f.t_s * 1e6), f.reading, f.angle_rad, RemoveHeading(f.R_GC)});
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
  state.counters["poses_per_pass"] =
      static_cast<double>(poses) / static_cast<double>(state.iterations());
  state.SetLabel(std::to_string(hours_of_data).substr(0, 4) +
                 " h of six 100 Hz transducers per pass");
  benchmark::DoNotOptimize(samples);
}
BENCHMARK(BM_AlignAndSegmentOneHour)->Unit(benchmark::kMillisecond);

// The same ten minutes of standing poses as an LCM log.
struct LogData {
  config::Config config = LoadConfigFile(std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt");
  std::string path = "/tmp/ftcal_segmenter_bench_" + std::to_string(::getpid()) + ".lcmlog";
  double span_s = 0;
  int64_t ft_samples = 0;
  LogData() {
    TwinOptions o;
    o.marker_dropout_rate_hz = 0;
    BigAntTwin twin(config, o);
    SimLogOptions lo;
    lo.session_id = "segmenter-bench";
    SimLogWriter log(config, path, lo);
    log.WriteMarker(log.Utime(0) - 1000, ExperimentPhase::kStanding, true, Vec3::Zero(), "");
    span_s = twin.Standing(108, {}, [&log](const TwinFrame& f) { log.WriteFrame(f); });
    log.WriteMarker(log.last_utime() + 1000, ExperimentPhase::kStanding, false, Vec3::Zero(), "");
    for (int64_t n : log.counts().ft) ft_samples += n;
    log.Commit();
  }
  ~LogData() { ::unlink(path.c_str()); }
};

const LogData& TheLog() {
  static const LogData data;
  return data;
}

void BM_SegmenterStageReplay(benchmark::State& state) {
  const LogData& d = TheLog();
  auto log = std::make_shared<spdlog::logger>("segmenter_bench",
                                              std::make_shared<spdlog::sinks::null_sink_mt>());
  const std::string out = d.path + ".out";
  int64_t poses = 0;
  for (auto _ : state) {
    ServiceStats stats(log);
    LogReplayBus bus(d.path, out, stats);
    PoseSegmenterStage stage(d.config, bus, /*publish_sync=*/state.range(0) != 0);
    bus.Run([] {}, 100'000);
    bus.Commit();
    poses = stage.poses_published();
    if (stats.drops() != 0 || stats.errors() != 0 || poses < 100 ||
        stats.Counter("sync_samples") < d.ft_samples / kNumLegs - 10) {
      state.SkipWithError("the stage did not segment the log cleanly");
    }
  }
  ::unlink(out.c_str());
  state.counters["x_real_time"] = benchmark::Counter(
      static_cast<double>(state.iterations()) * d.span_s, benchmark::Counter::kIsRate);
  state.counters["poses_per_pass"] = static_cast<double>(poses);
  state.SetLabel(std::string("ftcal-pose-segmenter --replay path") +
                 (state.range(0) != 0 ? " --sync-samples" : "") + ", log in -> log out, " +
                 std::to_string(static_cast<int>(d.span_s)) + " s log");
}
BENCHMARK(BM_SegmenterStageReplay)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SegmenterStageReplay)->Arg(0)->Arg(1)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
