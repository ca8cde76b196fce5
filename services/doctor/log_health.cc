#include "doctor/log_health.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <functional>
#include <utility>

#include "common/wire_guard.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "ftcal/steady_pose_t.hpp"

namespace ftcal::doctor {

namespace {

constexpr double kTwoPi = 6.283185307179586;
// The Net F/T's internal sample counter runs at 7000 Hz whatever its RDT output rate
// (docs/device-protocols.md); the servos' Realtime Tick counts ms; QTM's and NatNet's frame
// times are carried in us.
constexpr double kFtCounterHz = 7000.0;
constexpr double kServoTickHz = 1000.0;
constexpr double kMocapClockHz = 1e6;
// A silence of the host's receipt this long (or of ten sample periods, if longer) is a stall.
constexpr double kMinStallS = 0.05;

// A counter that was a u32 on the wire, widened: unwrapped across its wrap (a Net F/T counts
// 2^32 samples in about a week).
class Unwrap {
 public:
  int64_t operator()(int64_t v) {
    if (has_ && v < last_ && last_ - v > (int64_t{1} << 31)) offset_ += int64_t{1} << 32;
    has_ = true;
    last_ = v;
    return v + offset_;
  }

 private:
  bool has_ = false;
  int64_t last_ = 0, offset_ = 0;
};

double StallThresholdS(double rate_hz) {
  return rate_hz > 0 ? std::max(kMinStallS, 10.0 / rate_hz) : kMinStallS;
}

}  // namespace

void DelayHistogram::Add(double delay_s) {
  ++count_;
  max_s_ = std::max(max_s_, delay_s);
  const double us = std::max(delay_s * 1e6, 1.0);
  const int bin = std::min(kBins - 1, static_cast<int>(std::log(us) / std::log(1.1)));
  ++bins_[static_cast<size_t>(bin)];
}

double DelayHistogram::Quantile(double q) const {
  if (count_ == 0) return 0;
  const auto want = static_cast<int64_t>(std::ceil(q * static_cast<double>(count_)));
  int64_t seen = 0;
  for (int b = 0; b < kBins; ++b) {
    seen += bins_[static_cast<size_t>(b)];
    if (seen >= want) return std::min(max_s_, std::pow(1.1, b + 1) * 1e-6);
  }
  return max_s_;
}

// What one stream's reader keeps between messages: the last counter and receipt, and the
// running rate that decides how long a silence must be to be a stall.
struct StreamCursor {
  int64_t first_counter = -1, last_counter = -1;
  int64_t first_utime = -1, last_utime = -1;
  // Counts per second of host time since the counter's first value.
  double RateHz() const {
    const double span_s = 1e-6 * static_cast<double>(last_utime - first_utime);
    return span_s > 1.0 ? static_cast<double>(last_counter - first_counter) / span_s : 0.0;
  }
};

struct LogExaminer::FtState {
  StreamHealth h;
  StreamCursor cursor;  // by rdt_sequence (one per record)
  Unwrap rdt, sequence;
  DeviceClock clock{DeviceClockOptions{kFtCounterHz}};
};

struct LogExaminer::ServoState {
  StreamHealth h;
  std::array<std::unique_ptr<DeviceClock>, kNumLegs> clocks;
  std::array<int64_t, kNumLegs> last_tick{};
  std::array<double, kNumLegs> last_angle{};
  std::array<double, kNumLegs> travel_rad{};  // in the open phase
  bool have_angle = false;
};

struct LogExaminer::MocapState {
  StreamHealth h;
  StreamCursor cursor;  // by frame number
  DeviceClock clock{DeviceClockOptions{kMocapClockHz}};
};

LogExaminer::LogExaminer(const config::Config& config)
    : config_(config), inputs_(config), verifier_(auth::Verifier::FromConfig(config)) {
  for (int k = 0; k < kNumLegs; ++k) {
    ft_[static_cast<size_t>(k)] = std::make_unique<FtState>();
    ft_[static_cast<size_t>(k)]->h.name = inputs_.FtChannel(k);
    ft_[static_cast<size_t>(k)]->h.device = "Net F/T sample counter, 7000 Hz";
  }
  servo_ = std::make_unique<ServoState>();
  servo_->h.name = config.channels().servo_state();
  servo_->h.device = "servo Realtime Tick, 1 ms";
  for (auto& c : servo_->clocks)
    c = std::make_unique<DeviceClock>(DeviceClockOptions{kServoTickHz});
  mocap_ = std::make_unique<MocapState>();
  mocap_->h.name = config.channels().mocap_body();
  mocap_->h.device = "motion capture frame time, 1 us";
}

LogExaminer::~LogExaminer() = default;

void LogExaminer::Attach(Bus& bus) {
  const auto& ch = config_.channels();
  for (int k = 0; k < kNumLegs; ++k) {
    bus.SubscribeRaw(inputs_.FtChannel(k), [this, k](const MessageInfo& info, const void* data,
                                                     int size) { OnFt(k, info, data, size); });
  }
  bus.SubscribeRaw(ch.servo_state(), [this](const MessageInfo& info, const void* data, int size) {
    OnServo(info, data, size);
  });
  bus.SubscribeRaw(ch.mocap_body(), [this](const MessageInfo& info, const void* data, int size) {
    OnMocap(info, data, size);
  });
  // As the calibrator takes them (its collector): the same window against the recording's
  // receive times, the same keys.
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, static_cast<int64_t>(config_.auth().experiment_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo& info, const experiment_marker_t& m) { OnMarker(info, m); });
  bus.SubscribeRaw(ch.steady_pose(), [this](const MessageInfo& info, const void* data, int size) {
    OnSteadyPose(info, data, size);
  });
}

void LogExaminer::OnSteadyPose(const MessageInfo& info, const void* data, int size) {
  Seen(info.recv_utime);
  ++report_.steady_poses;
  if (open_phase_) ++report_.phases[*open_phase_].poses;
  // The forecast's step 2: the pose as the calibrator reads it (collector_results.cc).
  if (wire::Decode(data, size, &pose_scratch_)) return;
  try {
    const SteadyPoseOut p = FromLcm(pose_scratch_);
    if (!p.markers_ok || p.num_samples < 1) return;
    report_.steady.push_back({p.pose, static_cast<double>(p.num_samples)});
  } catch (const std::exception&) {
    // A pose the calibrator refuses too (an unknown leg): left out of the forecast.
  }
}

void LogExaminer::FileDone(const std::string& path, int64_t bytes, int64_t events,
                           const ServiceStats& stats) {
  report_.logs.push_back(path);
  report_.bytes += bytes;
  report_.events += events;
  const std::string suffix = " on " + config_.channels().experiment();
  for (const auto& [kind, n] : stats.kinds()) {
    if (kind.size() < suffix.size() ||
        kind.compare(kind.size() - suffix.size(), suffix.size(), suffix) != 0) {
      continue;
    }
    report_.markers_refused += n;
    if (report_.marker_refusal.empty()) report_.marker_refusal = kind;
  }
}

void LogExaminer::Seen(int64_t utime) {
  if (report_.first_utime < 0 || utime < report_.first_utime) report_.first_utime = utime;
  report_.last_utime = std::max(report_.last_utime, utime);
}

std::string LogExaminer::PhaseAt(double start_s) const {
  // A marker is written a moment before its phase's first samples (the sequencer's, and
  // ftcal-sim's 1 ms).
  constexpr double kMarkerLeadS = 0.01;
  if (!open_phase_) return "";
  const PhaseHealth& p = report_.phases[*open_phase_];
  return start_s >= p.start_s - kMarkerLeadS ? PhaseName(p.code) : "";
}

double LogExaminer::Since(int64_t utime) const {
  return 1e-6 * static_cast<double>(utime - report_.first_utime);
}

// A sample of a stream with a per-sample counter: what it lost before this one, or how long the
// host heard nothing although nothing was lost.
static void Advance(StreamHealth& h, StreamCursor& c, int64_t counter, int64_t utime, double t_s,
                    const std::function<std::string(double)>& phase_at) {
  ++h.samples;
  if (c.last_counter >= 0) {
    const int64_t step = counter - c.last_counter;
    const double rate_hz = c.RateHz();
    if (step == 0) {
      ++h.duplicates;
    } else if (step < 0) {
      ++h.counter_restarts;
    } else if (step > 1) {
      h.lost += step - 1;
      const double length_s = rate_hz > 0 ? static_cast<double>(step - 1) / rate_hz
                                          : 1e-6 * static_cast<double>(utime - c.last_utime);
      h.gaps.push_back({t_s - length_s, length_s, step - 1, phase_at(t_s - length_s)});
    } else if (1e-6 * static_cast<double>(utime - c.last_utime) > StallThresholdS(rate_hz)) {
      const double length_s = 1e-6 * static_cast<double>(utime - c.last_utime);
      h.stalls.push_back({t_s - length_s, length_s, 0, phase_at(t_s - length_s)});
    }
    if (step < 0) c.first_counter = -1;
  }
  if (c.first_counter < 0) {
    c.first_counter = counter;
    c.first_utime = utime;
  }
  c.last_counter = counter;
  c.last_utime = utime;
  if (h.first_utime < 0) h.first_utime = utime;
  h.last_utime = utime;
}

void LogExaminer::OnFt(int leg, const MessageInfo& /*info*/, const void* data, int size) {
  FtState& s = *ft_[static_cast<size_t>(leg)];
  FtBatch& batch = ft_batch_;
  if (!PeekFtBatch(data, size, leg, &batch)) {
    if (wire::Decode(data, size, &ft_scratch_) ||
        ft_scratch_.leg != kLegNames[static_cast<size_t>(leg)] || ft_scratch_.n < 1 ||
        ft_scratch_.n > kMaxFtRecords) {
      ++s.h.flagged["undecodable"];
      return;
    }
    FromLcm(ft_scratch_, leg, &batch);
  }
  for (const FtRecord& r : batch) {
    const int64_t utime = r.in.utime;
    Seen(utime);
    const int64_t lost_before = s.h.lost;
    const size_t gaps_before = s.h.gaps.size();
    Advance(s.h, s.cursor, s.rdt(r.rdt_sequence), utime, Since(utime), phase_at_);
    if (r.in.flags & ft_batch_t::FLAG_SATURATED) ++s.h.flagged["saturated"];
    if (r.in.flags & ft_batch_t::FLAG_STATUS_ERROR) ++s.h.flagged["status error"];
    if (open_phase_) {
      PhaseHealth& p = report_.phases[*open_phase_];
      ++p.ft_received[static_cast<size_t>(leg)];
      // What was lost before the phase began is not the phase's.
      if (s.h.gaps.size() > gaps_before && !s.h.gaps.back().phase.empty()) {
        p.ft_lost[static_cast<size_t>(leg)] += s.h.lost - lost_before;
      }
    }
  }
  // The box's clock against the host's: its datagram's last record against the receipt.
  const FtRecord& last = batch.records[static_cast<size_t>(batch.n - 1)];
  const int64_t mapped = s.clock.Observe(s.sequence(last.ft_sequence), batch.receipt_utime);
  s.h.queuing.Add(1e-6 * static_cast<double>(batch.receipt_utime - mapped));
}

void LogExaminer::OnServo(const MessageInfo& /*info*/, const void* data, int size) {
  ServoState& s = *servo_;
  if (wire::Decode(data, size, &servo_scratch_)) {
    ++s.h.flagged["undecodable"];
    return;
  }
  const servo_state_t& m = servo_scratch_;
  Seen(m.utime);
  ++s.h.samples;
  const double period_ms = 1000.0 / std::max(1.0, config_.dynamixel().rate_hz());
  // The cycles lost: by the tick of a servo that answered this cycle and the last.
  int64_t lost = -1;
  for (int k = 0; k < kNumLegs; ++k) {
    const auto i = static_cast<size_t>(k);
    const std::string leg(kLegNames[i]);
    if (m.flags[k] & servo_state_t::FLAG_STALE) ++s.h.flagged["stale " + leg];
    if (m.flags[k] & servo_state_t::FLAG_LOST) ++s.h.flagged["lost " + leg];
    if (m.flags[k] & servo_state_t::FLAG_HW_ERROR) ++s.h.flagged["hardware error " + leg];
    if (m.flags[k] & servo_state_t::FLAG_TORQUE_OFF) ++s.h.flagged["torque off " + leg];
    if (m.flags[k] & servo_state_t::FLAG_STALE) continue;
    if (s.h.samples > 1 && lost < 0 && m.device_tick_ms[k] > s.last_tick[i]) {
      lost = std::max<int64_t>(
          0,
          std::llround(static_cast<double>(m.device_tick_ms[k] - s.last_tick[i]) / period_ms) - 1);
    }
    s.last_tick[i] = m.device_tick_ms[k];
    const int64_t mapped = s.clocks[i]->Observe(m.device_tick_ms[k], m.utime);
    if (k == 0) s.h.queuing.Add(1e-6 * static_cast<double>(m.utime - mapped));
    // Wrapped angles (Position mode) jump by 2 pi where the shaft only passed pi.
    if (s.have_angle) {
      s.travel_rad[i] += std::abs(std::remainder(m.angle_rad[k] - s.last_angle[i], kTwoPi));
    }
    s.last_angle[i] = m.angle_rad[k];
  }
  s.have_angle = true;
  const double t_s = Since(m.utime);
  if (s.h.last_utime >= 0) {
    const double silence_s = 1e-6 * static_cast<double>(m.utime - s.h.last_utime);
    if (lost > 0) {
      s.h.lost += lost;
      s.h.gaps.push_back({t_s - silence_s, silence_s, lost, PhaseAt(t_s - silence_s)});
    } else if (silence_s > StallThresholdS(config_.dynamixel().rate_hz())) {
      s.h.stalls.push_back({t_s - silence_s, silence_s, 0, PhaseAt(t_s - silence_s)});
    }
  }
  if (s.h.first_utime < 0) s.h.first_utime = m.utime;
  s.h.last_utime = m.utime;
}

void LogExaminer::OnMocap(const MessageInfo& /*info*/, const void* data, int size) {
  MocapState& s = *mocap_;
  if (wire::Decode(data, size, &mocap_scratch_)) {
    ++s.h.flagged["undecodable"];
    return;
  }
  const mocap_body_t& m = mocap_scratch_;
  if (m.body != config_.mocap().body_name()) return;
  Seen(m.utime);
  Advance(s.h, s.cursor, m.frame_number, m.utime, Since(m.utime), phase_at_);
  if (!m.tracked) ++s.h.flagged["untracked"];
  bool all = m.tracked && m.num_markers >= static_cast<int>(config_.robot().chassis_marker_count());
  for (bool t : m.marker_tracked) all = all && t;
  if (m.tracked && !all) ++s.h.flagged["markers missing"];
  if (m.tracked) {
    const int64_t mapped = s.clock.Observe(m.device_utime, m.utime);
    s.h.queuing.Add(1e-6 * static_cast<double>(m.utime - mapped));
  }
}

void LogExaminer::OnMarker(const MessageInfo& info, const experiment_marker_t& m) {
  Seen(info.recv_utime);
  ++report_.markers;
  const PhaseChange c = tracker_.OnMarker(m.phase, m.start, m.session_id);
  const double t_s = Since(m.utime);
  if (c.closes && open_phase_) {
    PhaseHealth& p = report_.phases[*open_phase_];
    p.end_s = t_s;
    p.completed = c.completed;
    if (HangSeriesOfPhase(p.code)) {
      double least = std::numeric_limits<double>::infinity();
      for (double r : servo_->travel_rad) least = std::min(least, r);
      p.shaft_turns = least / kTwoPi;
    }
    open_phase_.reset();
  }
  if (c.opens) {
    PhaseHealth p;
    p.code = c.opened.code;
    p.session = c.opened.session;
    p.start_s = t_s;
    if (HangSeriesOfPhase(p.code))
      p.gravity_b = Vec3(m.gravity_b[0], m.gravity_b[1], m.gravity_b[2]);
    report_.phases.push_back(p);
    open_phase_ = report_.phases.size() - 1;
    servo_->travel_rad.fill(0);
  }
}

HealthReport LogExaminer::Finish() {
  if (open_phase_) {
    report_.phases[*open_phase_].end_s = Since(report_.last_utime);
    open_phase_.reset();
  }
  HealthReport r = report_;
  for (auto& s : ft_) {
    s->h.rate_hz = s->cursor.RateHz();
    s->h.has_clock = s->clock.started();
    s->h.skew_ppm = s->clock.skew_ppm();
    s->h.clock_restarts = s->clock.restarts();
    r.streams.push_back(s->h);
  }
  StreamHealth servo = servo_->h;
  const double servo_span_s = 1e-6 * static_cast<double>(servo.last_utime - servo.first_utime);
  servo.rate_hz =
      servo_span_s > 0 ? static_cast<double>(servo.samples + servo.lost - 1) / servo_span_s : 0;
  // The servos' clocks: the one furthest from the host's (each servo counts its own ticks).
  for (const auto& c : servo_->clocks) {
    if (!c->started()) continue;
    servo.clock_restarts += c->restarts();
    if (!servo.has_clock || std::abs(c->skew_ppm()) > std::abs(servo.skew_ppm)) {
      servo.skew_ppm = c->skew_ppm();
    }
    servo.has_clock = true;
  }
  r.streams.push_back(servo);
  StreamHealth mocap = mocap_->h;
  mocap.rate_hz = mocap_->cursor.RateHz();
  mocap.has_clock = mocap_->clock.started();
  mocap.skew_ppm = mocap_->clock.skew_ppm();
  mocap.clock_restarts = mocap_->clock.restarts();
  r.streams.push_back(mocap);
  Judge(r);
  Forecast(r);
  return r;
}

void LogExaminer::Forecast(HealthReport& r) const {
  std::vector<SeenHangSeries> hanging;
  const double rate_hz = config_.segmenter().sample_rate_hz();
  for (const PhaseHealth& p : r.phases) {
    const auto series = HangSeriesOfPhase(p.code);
    if (!series || !p.completed) continue;
    SeenHangSeries h;
    h.series = *series;
    h.gravity_b = p.gravity_b;
    h.shaft_turns = p.shaft_turns;
    // The calibrator's hanging samples are the aligner's, at most segmenter.sample_rate_hz
    // whatever rate the transducers sent; each leg's that arrived, the fewest of the six.
    const int64_t received = *std::min_element(p.ft_received.begin(), p.ft_received.end());
    h.samples = std::min(static_cast<double>(received), (p.end_s - p.start_s) * rate_hz);
    hanging.push_back(h);
  }
  r.forecast = ForecastSigma(config_, hanging, r.steady);
  if (!r.forecast.step1_missing.empty())
    r.warnings.push_back("sigma forecast: " + r.forecast.step1_missing);
  if (!r.forecast.error.empty()) r.notes.push_back({"", "no sigma forecast: " + r.forecast.error});
}

}  // namespace ftcal::doctor
