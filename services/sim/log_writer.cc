#include "sim/log_writer.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <stdexcept>

#include "ftcal/geometry.h"

namespace ftcal {
namespace {

// MX-106 units (docs/device-protocols.md §2.7).
constexpr double kCountsPerRev = 4096.0;
constexpr double kVelocityUnitRadS = 0.229 * 2.0 * M_PI / 60.0;
constexpr double kFrameRateHz = 100.0;

double WrapToPi(double a) {
  // (-pi, pi]: the bridge's range for a wrapped angle.
  const double w = a - 2.0 * M_PI * std::floor(a / (2.0 * M_PI) + 0.5);
  return w <= -M_PI ? w + 2.0 * M_PI : w;
}

// Latency ranges, s (see the header): each below the 10 ms frame period, so a frame's events
// never pass the next frame's.
constexpr double kFtLatencyMinS = 0.0005;
constexpr double kFtLatencyLegSpreadS = 0.0003;
constexpr double kFtJitterS = 0.001;
constexpr double kServoLatencyS = 0.002;
constexpr double kServoJitterS = 0.0015;
constexpr double kMocapLatencyS = 0.004;
constexpr double kMocapJitterS = 0.0015;
constexpr int kServoSlot = kNumLegs;
constexpr int kMocapSlot = kNumLegs + 1;

}  // namespace

int64_t SimLogCounts::Total() const {
  int64_t n = servo + mocap + markers;
  for (int64_t c : ft) n += c;
  return n;
}

SimLogWriter::SimLogWriter(const config::Config& config, const std::string& out_path,
                           const SimLogOptions& options)
    : options_(options), log_(out_path, "sim log"), rng_(options.seed ^ 0x51D106ULL) {
  log_.SetTap(digest_.Tap());
  if (config.robot().leg_size() != kNumLegs) {
    throw std::invalid_argument("config: robot.leg: " + std::to_string(kNumLegs) +
                                " legs expected, got " + std::to_string(config.robot().leg_size()));
  }
  const auto& ch = config.channels();
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& leg = config.robot().leg(k);
    if (leg.name() != kLegNames[k]) {
      throw std::invalid_argument("config: robot.leg[" + std::to_string(k) + "].name: '" +
                                  leg.name() + "', expected '" + std::string(kLegNames[k]) + "'");
    }
    if (leg.servo().direction() != 1 && leg.servo().direction() != -1) {
      throw std::invalid_argument("config: robot.leg[" + std::to_string(k) +
                                  "].servo.direction: must be +1 or -1");
    }
    ft_channel_[k] = ch.ft_prefix() + leg.name();
    zero_count_[k] = leg.servo().zero_count();
    direction_[k] = leg.servo().direction();
    ft_latency_s_[k] = kFtLatencyMinS + kFtLatencyLegSpreadS * Uniform();
    ft_sequence0_[k] = static_cast<uint32_t>(rng_());
    tick0_ms_[k] = static_cast<int64_t>(Uniform() * 32768.0);

    // One record a message, as a box in real-time mode (k = 1) sends them.
    ft_batch_t& m = ft_[k];
    m = ft_batch_t{};
    m.leg = leg.name();
    m.n = 1;
    m.sample_utime.assign(1, 0);
    m.rdt_sequence.assign(1, 0);
    m.ft_sequence.assign(1, 0);
    m.status.assign(1, 0);
    m.counts.assign(1, std::vector<int32_t>(6, 0));
    m.wrench.assign(1, std::vector<double>(6, 0.0));
    m.gap.assign(1, 0);
    m.flags.assign(1, 0);
  }
  {
    std::array<int64_t, kNumLegs> count0{};
    for (int k = 0; k < kNumLegs; ++k) count0[k] = ft_sequence0_[k];
    stamps_ = std::make_unique<TwinDeviceStamps>(options_.clocks, options_.seed, options_.t0_utime,
                                                 count0, tick0_ms_);
  }
  servo_channel_ = ch.servo_state();
  mocap_channel_ = ch.mocap_body();
  experiment_channel_ = ch.experiment();

  servo_ = servo_state_t{};
  for (int k = 0; k < kNumLegs; ++k) {
    servo_.leg[k] = config.robot().leg(k).name();
    servo_.id[k] = static_cast<int32_t>(config.robot().leg(k).servo().id());
  }

  mocap_ = mocap_body_t{};
  mocap_.body = config.mocap().body_name();
  mocap_.num_markers = kNumChassisMarkers;
  mocap_.marker_m.assign(kNumChassisMarkers, std::vector<double>(3, 0.0));
  mocap_.marker_tracked.assign(kNumChassisMarkers, false);

  marker_ = experiment_marker_t{};
  marker_.session_id = options_.session_id;
}

// The temporary file goes with log_ unless Commit() ran.
SimLogWriter::~SimLogWriter() = default;

double SimLogWriter::Uniform() { return static_cast<double>(rng_() >> 11) * 0x1.0p-53; }

int64_t SimLogWriter::Utime(double t_s) const {
  return options_.t0_utime + std::llround(t_s * 1e6);
}

template <class Msg>
int SimLogWriter::EncodeInto(const Msg& msg, std::vector<uint8_t>* buffer) {
  const int size = msg.getEncodedSize();
  // Grows only: after the first frames no event allocates.
  if (buffer->size() < static_cast<size_t>(size)) buffer->resize(static_cast<size_t>(size));
  if (msg.encode(buffer->data(), 0, size) != size) {
    throw std::runtime_error(std::string("sim log: ") + Msg::getTypeName() + " did not encode");
  }
  return size;
}

void SimLogWriter::Write(int64_t utime, const std::string& channel,
                         const std::vector<uint8_t>& bytes, int size) {
  log_.Write(utime, channel, bytes.data(), size);
  last_utime_ = utime;
}

void SimLogWriter::WriteFrame(const TwinFrame& f) {
  if (log_.committed())
    throw std::logic_error("sim log '" + log_.path() + "': frame after Commit()");
  if (!std::isfinite(f.t_s)) {
    throw std::invalid_argument("sim log: frame time is not finite");
  }
  if (have_previous_ && !(f.t_s > previous_t_s_)) {
    throw std::invalid_argument("sim log: frame at t = " + std::to_string(f.t_s) +
                                " s does not follow the previous one at " +
                                std::to_string(previous_t_s_) + " s");
  }
  const int64_t t = Utime(f.t_s);
  std::array<Pending, 8> pending;

  for (int k = 0; k < kNumLegs; ++k) {
    ft_batch_t& m = ft_[k];
    const int64_t utime =
        stamps_->HostStamp(t + std::llround((ft_latency_s_[k] + kFtJitterS * Uniform()) * 1e6));
    const TwinDeviceStamps::Ft clock = stamps_->FtSample(k, f.t_s, utime);
    m.receipt_utime = utime;
    m.sample_utime[0] = clock.sample_utime;
    ++m.rdt_sequence[0];  // 1 for the first record of the stream
    m.ft_sequence[0] = static_cast<uint32_t>(clock.counter);  // the wire's 32 bits
    for (size_t i = 0; i < 6; ++i) {
      m.counts[0][i] = f.counts[k][i];
      m.wrench[0][i] = f.reading[k][i];
    }
    size_[k] = EncodeInto(m, &buffer_[k]);
    pending[k] = {utime, k};
  }

  // Consecutive frames 10 ms apart give a velocity; after a gap (a new scenario) the legs are
  // at rest.
  const bool consecutive = have_previous_ && f.t_s - previous_t_s_ < 1.5 / kFrameRateHz;
  const int64_t servo_utime =
      stamps_->HostStamp(t + std::llround((kServoLatencyS + kServoJitterS * Uniform()) * 1e6));
  const TwinDeviceStamps::Servo& ticks = stamps_->ServoSample(f.t_s, servo_utime);
  servo_.utime = servo_utime;
  servo_.sample_utime = ticks.sample_utime;
  for (int k = 0; k < kNumLegs; ++k) {
    // The MX-106 reports whole counts; the bridge maps them back with zero_count/direction.
    const double count =
        std::round(zero_count_[k] + direction_[k] * f.angle_rad[k] * kCountsPerRev / (2.0 * M_PI));
    const double theta = direction_[k] * (count - zero_count_[k]) * (2.0 * M_PI / kCountsPerRev);
    servo_.angle_rad[k] = WrapToPi(theta);
    const double omega =
        consecutive ? (f.angle_rad[k] - previous_angle_[k]) / (f.t_s - previous_t_s_) : 0.0;
    const double units = std::round(direction_[k] * omega / kVelocityUnitRadS);
    servo_.velocity_rad_s[k] = direction_[k] * units * kVelocityUnitRadS;
    // Same stand-in as the bus emulator: current follows velocity, not a motor model.
    servo_.current_a[k] =
        direction_[k] * 0.5 * std::tanh(units * 0.229 / 60.0 * kCountsPerRev / 100.0);
    servo_.device_tick_ms[k] = ticks.tick_ms[static_cast<size_t>(k)];
    previous_angle_[k] = f.angle_rad[k];
  }
  size_[kServoSlot] = EncodeInto(servo_, &buffer_[kServoSlot]);
  pending[kServoSlot] = {servo_utime, kServoSlot};

  const int64_t mocap_utime =
      stamps_->HostStamp(t + std::llround((kMocapLatencyS + kMocapJitterS * Uniform()) * 1e6));
  const TwinDeviceStamps::Mocap frame_clock = stamps_->MocapSample(f.t_s, mocap_utime);
  mocap_.utime = mocap_utime;
  mocap_.frame_number = 1 + std::llround(f.t_s * kFrameRateHz);
  mocap_.device_utime = frame_clock.device_utime;
  mocap_.sample_utime = frame_clock.sample_utime;
  mocap_.tracked = true;
  const Eigen::Vector4d q_gc = RotationToQuaternion(f.R_GC);
  const Eigen::Vector4d q_wc = RotationToQuaternion(RemoveHeading(f.R_GC));
  for (int i = 0; i < 4; ++i) {
    mocap_.q_gc[i] = q_gc[i];
    mocap_.q_wc[i] = q_wc[i];
  }
  for (int i = 0; i < 3; ++i) mocap_.position_m[i] = f.p_GB_m[i];
  mocap_.yaw_rad = HeadingYaw(f.R_GC);
  mocap_.residual_m = options_.mocap_residual_m;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (int i = 0; i < kNumChassisMarkers; ++i) {
    const bool seen = f.marker_tracked[i];
    mocap_.marker_tracked[i] = seen;
    for (int a = 0; a < 3; ++a) mocap_.marker_m[i][a] = seen ? f.marker_G_m[i][a] : nan;
  }
  size_[kMocapSlot] = EncodeInto(mocap_, &buffer_[kMocapSlot]);
  pending[kMocapSlot] = {mocap_utime, kMocapSlot};

  // Stable: equal stamps keep the FT, servo, mocap order.
  std::stable_sort(pending.begin(), pending.end(),
                   [](const Pending& a, const Pending& b) { return a.utime < b.utime; });
  if (pending.front().utime < last_utime_) {
    throw std::invalid_argument("sim log: frame at t = " + std::to_string(f.t_s) +
                                " s would be stamped before the previous event");
  }
  for (const Pending& p : pending) {
    const std::string& channel = p.slot < kNumLegs      ? ft_channel_[p.slot]
                                 : p.slot == kServoSlot ? servo_channel_
                                                        : mocap_channel_;
    Write(p.utime, channel, buffer_[p.slot], size_[p.slot]);
  }
  for (int k = 0; k < kNumLegs; ++k) ++counts_.ft[k];
  ++counts_.servo;
  ++counts_.mocap;
  have_previous_ = true;
  previous_t_s_ = f.t_s;
}

void SimLogWriter::WriteMarker(int64_t utime, ExperimentPhase phase, bool start,
                               const Vec3& gravity_b, const std::string& note) {
  if (log_.committed())
    throw std::logic_error("sim log '" + log_.path() + "': marker after Commit()");
  if (utime < last_utime_) {
    throw std::invalid_argument("sim log: marker at utime " + std::to_string(utime) +
                                " precedes the last event at " + std::to_string(last_utime_));
  }
  marker_.utime = utime;
  marker_.phase = static_cast<int8_t>(phase);
  marker_.start = start;
  for (int i = 0; i < 3; ++i) marker_.gravity_b[i] = gravity_b[i];
  marker_.note = note;
  const int size = EncodeInto(marker_, &marker_buffer_);
  Write(utime, experiment_channel_, marker_buffer_, size);
  ++counts_.markers;
}

std::string SimLogWriter::Commit() {
  log_.Commit();
  return digest_.HandOver(log_.path(), log_.committed_stat());
}

double WriteExperiment(const BigAntTwin& twin, const ExperimentPlan& plan, SimLogWriter* writer) {
  if (plan.standing && plan.poses < 1) {
    throw std::invalid_argument("experiment plan: poses must be at least 1, got " +
                                std::to_string(plan.poses));
  }
  if (plan.tripod && plan.tripod_stances < 1) {
    throw std::invalid_argument("experiment plan: tripod_stances must be at least 1, got " +
                                std::to_string(plan.tripod_stances));
  }
  if (plan.walking && !(plan.walk_s > 0.0 && std::isfinite(plan.walk_s))) {
    throw std::invalid_argument("experiment plan: walk_s must be positive, got " +
                                std::to_string(plan.walk_s));
  }
  if (!(plan.gap_s >= 0.05 && std::isfinite(plan.gap_s))) {
    throw std::invalid_argument("experiment plan: gap_s must be at least 0.05 s, got " +
                                std::to_string(plan.gap_s));
  }
  if (std::isnan(plan.drift_at_s)) {
    throw std::invalid_argument("experiment plan: drift_at_s is NaN");
  }
  const auto sink = [writer](const TwinFrame& f) { writer->WriteFrame(f); };
  double t = 0.0;
  // Start 1 ms before the first frame's instant (before any device latency); stop 9 ms after
  // the last frame's instant (after its events, before the next frame would be due).
  auto run = [&](ExperimentPhase phase, const Vec3& gravity_b, const std::string& note,
                 const std::function<double(const RunOptions&)>& scenario) {
    writer->WriteMarker(writer->Utime(t) - 1000, phase, true, gravity_b, note);
    RunOptions options;
    options.t0_s = t;
    options.drift_from_s = plan.drift_at_s;
    options.offset_change = plan.offset_change;
    const double end = scenario(options);
    writer->WriteMarker(
        std::max(writer->last_utime(), writer->Utime(writer->last_frame_t_s()) + 9000), phase,
        false, gravity_b, note);
    t = end + plan.gap_s;
  };
  if (plan.tare) {
    run(ExperimentPhase::kTare, Vec3::Zero(), "naive tare: upright, feet in the air, shafts at 0",
        [&](const RunOptions& r) { return twin.Tare(r, sink); });
  }
  if (plan.hanging) {
    static const char* kNotes[kNumHangSeries] = {"hanging, body +x down", "hanging, body -x down",
                                                 "hanging, body +z down", "hanging, body -z down"};
    for (int s = 0; s < kNumHangSeries; ++s) {
      const auto series = static_cast<HangSeries>(s);
      const auto phase =
          static_cast<ExperimentPhase>(static_cast<int>(ExperimentPhase::kHangXPos) + s);
      run(phase, twin.StatedGravityB(series), kNotes[s],
          [&](const RunOptions& r) { return twin.Hanging(series, r, sink); });
    }
  }
  if (plan.standing) {
    run(ExperimentPhase::kStanding, Vec3::Zero(), std::to_string(plan.poses) + " standing poses",
        [&](const RunOptions& r) { return twin.Standing(plan.poses, r, sink); });
  }
  if (plan.tripod) {
    run(ExperimentPhase::kTripod, Vec3::Zero(),
        std::to_string(plan.tripod_stances) + " tripod stances",
        [&](const RunOptions& r) { return twin.TripodStances(plan.tripod_stances, r, sink); });
  }
  if (plan.walking) {
    run(ExperimentPhase::kWalking, Vec3::Zero(), "tripod walk",
        [&](const RunOptions& r) { return twin.TripodWalk(plan.walk_s, r, sink); });
  }
  return t - plan.gap_s;
}

}  // namespace ftcal
