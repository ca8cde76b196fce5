// Corrector throughput (the architecture issue's target: >= 3,000,000 leg-samples/s over a log,
// log in -> log out, on 2 cores).
//
// A leg-sample is one FT_<LEG> sample (one record of a leg's ft_batch_t) turned into a corrected
// wrench: in the stage, one CONTACT_WRENCH message (that leg's wrench) and a sixth of a
// CONTACT_WRENCH_SUM (the six legs' sum and residual) encoded and written to the output log.
// Servo states and mocap frames are read and used but not counted. bytes_per_leg_sample is the
// output log's size over the leg-samples: what a leg-sample costs on disk.
//
// BM_CorrectorStageReplay is the definition: what `ftcal-corrector --calibration F
// --replay IN --out OUT` does, log in -> log out, in this process (LogReplayBus +
// CorrectorStage as main.cc builds them; process start-up and config parsing left out): read
// and decode every event, correct, encode, write, fsync and rename the output. The plain run
// divides by the main thread's CPU time (the input's read-ahead and the output's writer run on
// threads of their own and are not in it); the /real_time run divides by wall time, which
// includes waiting for the disk at fsync and, on a shared machine, for a core: the figure a
// user sees.
// BM_CorrectorEngine is libcal's Corrector alone over the same frames held in memory.
// The input is six minutes of the standing grid at 100 Hz (221,760 leg-samples, 56 MB in,
// 32 MB out): with one minute, a pass took 17 ms of which the output's fsync, rename and
// directory sync (a cost per file, not per sample) were 4.6 ms, so the figure measured the
// commit more than the throughput.
//
//   <build>/tests/bench/corrector_bench
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <vector>

#include <benchmark/benchmark.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/log_replay_bus.h"
#include "corrector/corrector_stage.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/config.h"
#include "ftcal/corrector.h"
#include "sim/twin.h"

namespace ftcal {
namespace {

constexpr int64_t kT0 = 1'700'000'000'000'000;
const std::string kConfig = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";

struct Data {
  config::Config config = LoadConfigFile(kConfig);
  BigAntTwin twin{config, TwinOptions{}};
  std::vector<TwinFrame> frames;
  std::string log_path;
  Data() {
    twin.Standing(66, {}, [this](const TwinFrame& f) { frames.push_back(f); });  // ~6 min
    log_path = "/tmp/ftcal_corrector_bench_" + std::to_string(::getpid()) + ".lcmlog";
    lcm::LogFile log(log_path, "w");
    int64_t n = 0;
    auto write = [&](int64_t t, const std::string& channel, const auto& msg) {
      std::vector<uint8_t> buf(static_cast<size_t>(msg.getEncodedSize()));
      msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
      lcm::LogEvent ev;
      ev.eventnum = n++;
      ev.timestamp = t;
      ev.channel = channel;
      ev.datalen = static_cast<int32_t>(buf.size());
      ev.data = buf.data();
      log.writeEvent(&ev);
    };
    write(kT0 - 1, config.channels().calibration(), ToLcm(twin.TruthProto(), 1, kT0));
    for (const TwinFrame& f : frames) {
      const int64_t t = Utime(f);
      servo_state_t s{};
      s.utime = s.sample_utime = t;
      for (int k = 0; k < kNumLegs; ++k) {
        s.leg[k] = std::string(kLegNames[k]);
        s.id[k] = k + 1;
        s.angle_rad[k] = f.angle_rad[k];
        s.velocity_rad_s[k] = 0;
        s.current_a[k] = 0;
        s.hardware_error[k] = 0;
        s.device_tick_ms[k] = 0;
        s.flags[k] = 0;
      }
      write(t, config.channels().servo_state(), s);
      mocap_body_t b{};
      b.utime = b.sample_utime = t;
      b.body = config.mocap().body_name();
      b.tracked = true;
      const Eigen::Vector4d q = RotationToQuaternion(RemoveHeading(f.R_GC));
      for (int i = 0; i < 4; ++i) b.q_wc[i] = b.q_gc[i] = q[i];
      b.num_markers = 0;
      write(t, config.channels().mocap_body(), b);
      for (int k = 0; k < kNumLegs; ++k) {
        const ft_batch_t m = ToLcm(BatchOf(FtInput{t, k, f.reading[k], 0}, t));
        write(t, config.channels().ft_prefix() + m.leg, m);
      }
    }
  }
  ~Data() { ::unlink(log_path.c_str()); }
  static int64_t Utime(const TwinFrame& f) { return kT0 + std::llround(f.t_s * 1e6); }
};

const Data& TheData() {
  static const Data data;
  return data;
}

void BM_CorrectorEngine(benchmark::State& state) {
  const Data& d = TheData();
  const RobotCalibration cal = d.twin.Truth();
  ContactWrenches out;
  int64_t samples = 0;
  double checksum = 0;
  for (auto _ : state) {
    Corrector c({});
    c.SetCalibration(cal, 1);
    for (const TwinFrame& f : d.frames) {
      const int64_t t = Data::Utime(f);
      c.AddServo({t, f.angle_rad});
      c.AddMocap({t, true, f.R_WC, true});
      for (int k = 0; k < kNumLegs; ++k) {
        if (c.AddFt({t, k, f.reading[k], 0}, false, &out)) checksum += out.total_W[2];
        ++samples;
      }
    }
  }
  benchmark::DoNotOptimize(checksum);
  state.counters["leg_samples_per_s"] =
      benchmark::Counter(static_cast<double>(samples), benchmark::Counter::kIsRate);
  state.SetLabel("engine alone, in memory; " + std::to_string(d.frames.size() * kNumLegs) +
                 " leg-samples per pass");
}
BENCHMARK(BM_CorrectorEngine)->Unit(benchmark::kMillisecond);

// The process's handler code end to end (replay at full speed), output log written.
void BM_CorrectorStageReplay(benchmark::State& state) {
  const Data& d = TheData();
  auto log = std::make_shared<spdlog::logger>("corrector_bench",
                                              std::make_shared<spdlog::sinks::null_sink_mt>());
  const std::string out = d.log_path + ".out";
  int64_t samples = 0;
  double out_bytes = 0;
  for (auto _ : state) {
    ServiceStats stats(log);
    LogReplayBus bus(d.log_path, out, stats);
    CorrectorStage stage(d.config, bus, [](int8_t) {});
    bus.Run([] {}, 100'000);
    bus.Commit();
    samples += static_cast<int64_t>(d.frames.size()) * kNumLegs;
    state.PauseTiming();
    struct stat st {};
    if (::stat(out.c_str(), &st) == 0) out_bytes = static_cast<double>(st.st_size);
    state.ResumeTiming();
    if (stats.Counter("corrected") != static_cast<int64_t>(d.frames.size()) * kNumLegs) {
      state.SkipWithError("the stage did not correct every sample");
    }
  }
  ::unlink(out.c_str());
  state.counters["bytes_per_leg_sample"] =
      out_bytes / static_cast<double>(d.frames.size() * kNumLegs);
  state.counters["leg_samples_per_s"] =
      benchmark::Counter(static_cast<double>(samples), benchmark::Counter::kIsRate);
  state.counters["x_real_time"] = benchmark::Counter(
      static_cast<double>(samples) / kNumLegs / 100.0, benchmark::Counter::kIsRate);
  state.SetLabel(
      "ftcal-corrector --replay path, log in -> log out; " +
      std::to_string(d.frames.size() * kNumLegs) +
      " leg-samples (FT_<LEG> sample -> CONTACT_WRENCH, 1/6 CONTACT_WRENCH_SUM) per pass");
}
BENCHMARK(BM_CorrectorStageReplay)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_CorrectorStageReplay)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace
}  // namespace ftcal

BENCHMARK_MAIN();
