// ftcal-sim log at the report's scale: the whole experiment (4 hanging series of ten cycles,
// 729 standing poses, 20 tripod stances, 120 s walk; about 86 min of robot time) synthesized by
// the twin and written as an LCM log. Reports wall time per run, events/s and robot time per
// wall second; and the twin alone (frames into a sink that drops them), so the log's own cost
// is the difference. Target: the full experiment in under 10 s on the project machine.
#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <string>

#include <benchmark/benchmark.h>

#include "ftcal/config.h"
#include "sim/log_writer.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";

void BM_FullExperimentLog(benchmark::State& state) {
  const config::Config config = LoadConfigFile(kConfig);
  const BigAntTwin twin(config, TwinOptions{});
  char tmpl[] = "/tmp/sim_log_bench.XXXXXX";
  const char* dir = ::mkdtemp(tmpl);
  if (!dir) {
    state.SkipWithError("cannot create a temporary directory");
    return;
  }
  const std::string path = std::string(dir) + "/full.lcmlog";
  int64_t events = 0;
  double robot_s = 0.0;
  for (auto _ : state) {
    SimLogWriter writer(config, path, SimLogOptions{});
    robot_s = WriteExperiment(twin, ExperimentPlan{}, &writer);
    writer.Commit();
    events += writer.counts().Total();
  }
  struct stat st {};
  ::stat(path.c_str(), &st);
  ::unlink(path.c_str());
  ::rmdir(dir);
  state.counters["events_per_s"] =
      benchmark::Counter(static_cast<double>(events), benchmark::Counter::kIsRate);
  state.counters["events"] = static_cast<double>(events) / static_cast<double>(state.iterations());
  state.counters["robot_s"] = robot_s;
  state.counters["log_MB"] = static_cast<double>(st.st_size) / 1e6;
  state.counters["x_real_time"] = benchmark::Counter(
      robot_s * static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_FullExperimentLog)->Unit(benchmark::kSecond)->Iterations(1)->UseRealTime();

// The twin's frames alone, for the same plan: what the log adds is the difference.
void BM_FullExperimentTwinOnly(benchmark::State& state) {
  const config::Config config = LoadConfigFile(kConfig);
  const BigAntTwin twin(config, TwinOptions{});
  const ExperimentPlan plan;
  int64_t frames = 0;
  for (auto _ : state) {
    const FrameSink sink = [&frames](const TwinFrame& f) {
      benchmark::DoNotOptimize(f.reading[0][0]);
      ++frames;
    };
    double t = 0.0;
    for (int s = 0; s < kNumHangSeries; ++s) {
      t = twin.Hanging(static_cast<HangSeries>(s), RunOptions{t}, sink) + plan.gap_s;
    }
    t = twin.Standing(plan.poses, RunOptions{t}, sink) + plan.gap_s;
    t = twin.TripodStances(plan.tripod_stances, RunOptions{t}, sink) + plan.gap_s;
    twin.TripodWalk(plan.walk_s, RunOptions{t}, sink);
  }
  state.counters["frames_per_s"] =
      benchmark::Counter(static_cast<double>(frames), benchmark::Counter::kIsRate);
}
BENCHMARK(BM_FullExperimentTwinOnly)->Unit(benchmark::kSecond)->Iterations(1)->UseRealTime();

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
