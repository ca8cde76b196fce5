// The twin's experiment as an LCM log, as the bridges would have published it (ftcal-sim log).
//
// SimLogWriter turns TwinFrames into the device channels (FT_<LEG>, SERVO_STATE, MOCAP_BODY)
// and EXPERIMENT markers and writes them to an LCM log in time order. Each device's host
// timestamp is the twin time plus a small seeded latency (FT 0.5-1.8 ms, servo sync read
// 2-3.5 ms, mocap 4-5.5 ms), so the aligner has real work yet every event of frame i lies
// before every event of frame i+1 (frames are 10 ms apart): sorting each frame's eight events
// is enough to keep the whole log in order. Device conventions follow the emulators/bridges:
//   FT_<LEG>     rdt_sequence 1, 2, ... per leg; ft_sequence a seeded power-up count + 70 per
//                the box's clock's 7000 Hz count at the sample (SimLogOptions::clocks), u32;
//                status 0; counts and wrench from the twin's reading (sign +1, as
//                config/sim.pbtxt); sample time: the counter mapped as the ATI bridge maps it.
//   SERVO_STATE  all six servos in config order with the config's ids; angle as the MX-106
//                reports it (Present Position in whole counts around zero_count, direction
//                applied), wrapped to (-pi, pi]; velocity from consecutive frames in the
//                device's 0.229 rpm unit; device tick = seeded start + the servo's clock in
//                ms; sample time: the ticks mapped as the Dynamixel bridge maps them.
//   MOCAP_BODY   frame number 1 + round(t * 100), device time = the mocap clock at t, sample
//                time that clock mapped as the mocap bridges map it; q_gc, q_wc = R_GC with
//                the heading removed (RemoveHeading), yaw, position, residual = the twin's
//                marker noise; markers with their tracked flags (NaN when untracked).
// Every host stamp is also taken late while the host stalls (SimClocks' bursts).
// Output is atomic: a temporary file beside the log, renamed onto it by Commit().
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "common/atomic_log.h"
#include "common/written_digest.h"
#include "proto/config.pb.h"
#include "sim/device_stamps.h"
#include "sim/sim_clocks.h"
#include "sim/twin.h"

namespace ftcal {

// us since the epoch of twin time 0 in the logs ftcal-sim writes (2023-11-14): fixed, so the
// same seed gives the same bytes.
inline constexpr int64_t kSimLogT0Utime = 1'700'000'000'000'000;

struct SimLogOptions {
  std::string session_id = "sim";
  int64_t t0_utime = kSimLogT0Utime;
  uint64_t seed = 1;  // timestamp jitter and device counters
  double mocap_residual_m = 0.0005;
  // Each device's clock rate and offset and the host's stalls (sim/sim_clocks.h); a lab's by
  // default. The sample times in the log are these clocks mapped as the bridges map them.
  SimClocks clocks = SimClocks::Lab();
};

// Events written per channel kind.
struct SimLogCounts {
  std::array<int64_t, kNumLegs> ft{};
  int64_t servo = 0;
  int64_t mocap = 0;
  int64_t markers = 0;
  int64_t Total() const;
};

class SimLogWriter {
 public:
  // Throws std::invalid_argument naming the field for a config whose legs are not kLegNames in
  // order, std::runtime_error naming the file when the temporary log cannot be created.
  SimLogWriter(const config::Config& config, const std::string& out_path,
               const SimLogOptions& options);
  // Removes the temporary file unless Commit() ran.
  ~SimLogWriter();
  SimLogWriter(const SimLogWriter&) = delete;
  SimLogWriter& operator=(const SimLogWriter&) = delete;

  // One 100 Hz frame: six FT samples, a servo state and a mocap body. Frames must come in
  // time order; throws std::invalid_argument for one that does not, or for a non-finite time.
  void WriteFrame(const TwinFrame& frame);
  // An EXPERIMENT marker stamped `utime` (must not precede the last event written).
  // gravity_b is zero for phases that are not hanging.
  void WriteMarker(int64_t utime, ExperimentPhase phase, bool start, const Vec3& gravity_b,
                   const std::string& note);
  // Host time of twin time t (no latency).
  int64_t Utime(double t_s) const;
  // The newest timestamp written so far, and the twin time of the last frame.
  int64_t last_utime() const { return last_utime_; }
  double last_frame_t_s() const { return previous_t_s_; }
  const SimLogCounts& counts() const { return counts_; }
  // The devices' clocks, the host's stamps and the maps the bridges would have made of them.
  const TwinDeviceStamps& stamps() const { return *stamps_; }

  // fsync, close, rename onto the final name, and the log's SHA-256 (taken as it was written)
  // handed to the digest cache. Returns that digest when the cache took it, else "". Throws
  // std::runtime_error on I/O failure.
  std::string Commit();

 private:
  struct Pending {
    int64_t utime;
    int slot;  // 0-5 FT legs, 6 servo, 7 mocap
  };
  double Uniform();  // [0, 1), portable across standard libraries (unlike the distributions)
  void Write(int64_t utime, const std::string& channel, const std::vector<uint8_t>& bytes,
             int size);
  template <class Msg>
  int EncodeInto(const Msg& msg, std::vector<uint8_t>* buffer);

  SimLogOptions options_;
  AtomicLogFile log_;
  WrittenDigest digest_;
  std::mt19937_64 rng_;

  std::array<std::string, kNumLegs> ft_channel_;
  std::string servo_channel_;
  std::string mocap_channel_;
  std::string experiment_channel_;
  std::array<int32_t, kNumLegs> zero_count_{};
  std::array<int, kNumLegs> direction_{};
  std::array<double, kNumLegs> ft_latency_s_{};    // per-leg fixed part
  std::array<uint32_t, kNumLegs> ft_sequence0_{};  // power-up counter at the first record
  std::array<int64_t, kNumLegs> tick0_ms_{};
  std::unique_ptr<TwinDeviceStamps> stamps_;

  // Messages and encode buffers reused for every frame (no allocation per event).
  std::array<ft_batch_t, kNumLegs> ft_;
  servo_state_t servo_;
  mocap_body_t mocap_;
  experiment_marker_t marker_;
  std::array<std::vector<uint8_t>, 8> buffer_;
  std::array<int, 8> size_{};
  std::vector<uint8_t> marker_buffer_;

  bool have_previous_ = false;
  double previous_t_s_ = 0.0;
  std::array<double, kNumLegs> previous_angle_{};
  int64_t last_utime_ = std::numeric_limits<int64_t>::min();
  SimLogCounts counts_;
};

// What ftcal-sim log runs, in this order: the four hanging series, the standing poses, the
// tripod stances, the walk; each between EXPERIMENT start/stop markers (hanging ones carry the
// stated gravity_b), with `gap_s` of silence between scenarios (the robot being re-hung or set
// down).
struct ExperimentPlan {
  bool tare = true;  // the naive tare phase (TARE), before the hanging series
  bool hanging = true;
  bool standing = true;
  bool tripod = true;
  bool walking = true;
  int poses = 729;
  int tripod_stances = 20;
  double walk_s = 120.0;
  double gap_s = 2.0;
  double drift_at_s = std::numeric_limits<double>::infinity();  // twin time
  // Offsets moving during the session (RunOptions::offset_change, sim/offset_drift.h).
  std::function<Vec6(int leg, double t_s)> offset_change;
};

// Runs the plan on the twin into the writer (not committed). Returns the twin time at the end.
// Throws std::invalid_argument naming the field for a plan it cannot run.
double WriteExperiment(const BigAntTwin& twin, const ExperimentPlan& plan, SimLogWriter* writer);

}  // namespace ftcal
