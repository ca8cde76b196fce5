#include "sim/live.h"

#include <poll.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <sstream>
#include <stdexcept>

#include "ftcal/calibration_io.h"
#include "ftcal/config.h"
#include "ftcal/legs.h"
#include "protocol2.h"

namespace ftcal::sim {

// ---- TwinSeries ----

TwinSeries::TwinSeries(const BigAntTwin& twin, const std::string& scenario, double span_s) {
  if (!(span_s > 0) || !std::isfinite(span_s)) {
    throw std::invalid_argument("scenario length must be positive, not " + std::to_string(span_s));
  }
  const TwinOptions& o = twin.Options();
  period_s_ = 1.0 / o.sample_rate_hz;
  // Scenarios come in whole units (poses, stances, cycles): make enough and keep span_s.
  const auto max_frames = static_cast<std::size_t>(std::ceil(span_s / period_s_));
  frames_.reserve(max_frames);
  const FrameSink sink = [this, max_frames](const TwinFrame& f) {
    if (frames_.size() < max_frames) frames_.push_back(f);
  };
  auto hang = [&](HangSeries series) { twin.Hanging(series, {}, sink); };
  if (scenario == "walk") {
    twin.TripodWalk(span_s, {}, sink);
  } else if (scenario == "stand") {
    const double per_pose = o.pose_move_s + o.pose_dwell_s;
    twin.Standing(std::min(729, static_cast<int>(std::ceil(span_s / per_pose)) + 1), {}, sink);
  } else if (scenario == "tripod") {
    // A stance lasts a few seconds: grow the count until the span is covered.
    for (int n = 4; frames_.size() < max_frames && n <= 4096; n *= 2) {
      frames_.clear();
      twin.TripodStances(n, {}, sink);
    }
  } else if (scenario == "hang-x-pos") {
    hang(HangSeries::kXPos);
  } else if (scenario == "hang-x-neg") {
    hang(HangSeries::kXNeg);
  } else if (scenario == "hang-z-pos") {
    hang(HangSeries::kZPos);
  } else if (scenario == "hang-z-neg") {
    hang(HangSeries::kZNeg);
  } else {
    throw std::invalid_argument("unknown scenario '" + scenario +
                                "' (walk, stand, tripod, hang-x-pos, hang-x-neg, hang-z-pos, "
                                "hang-z-neg)");
  }
  if (frames_.empty()) throw std::runtime_error("the twin produced no frames for " + scenario);
}

std::size_t TwinSeries::Index(double t_s, double* frac) const {
  // The nudge keeps a time computed as i * period (or tick / rate) on frame i when the
  // division lands a hair below it.
  const double x = std::max(0.0, t_s) / period_s_ + 1e-9;
  const double whole = std::floor(x);
  if (frac != nullptr) *frac = x - whole;
  return static_cast<std::size_t>(std::fmod(whole, static_cast<double>(frames_.size())));
}

const TwinFrame& TwinSeries::At(double t_s) const { return frames_[Index(t_s, nullptr)]; }

double TwinSeries::AngleAt(int k, double t_s, double* rate_rad_s) const {
  double a = 0;
  const std::size_t i = Index(t_s, &a);
  if (i + 1 >= frames_.size()) {  // the seam: hold
    if (rate_rad_s != nullptr) *rate_rad_s = 0;
    return frames_[i].angle_rad[k];
  }
  const double a0 = frames_[i].angle_rad[k], a1 = frames_[i + 1].angle_rad[k];
  if (rate_rad_s != nullptr) *rate_rad_s = (a1 - a0) / period_s_;
  return (1 - a) * a0 + a * a1;
}

DxlDrivenState DxlStateFromAngle(double angle_rad, double rate_rad_s, std::int32_t zero_count,
                                 int direction) {
  constexpr double kCountsPerRad = dxl::kCountsPerRev / (2.0 * M_PI);
  DxlDrivenState s;
  s.position_counts = zero_count + direction * angle_rad * kCountsPerRad;
  s.velocity_counts_s = direction * rate_rad_s * kCountsPerRad;
  // A current that rises with speed, only so the field is not constant.
  s.current_a = 0.5 * std::tanh(s.velocity_counts_s / 100.0);
  return s;
}

double DxlAngleFromCounts(double counts, std::int32_t zero_count, int direction) {
  constexpr double kRadPerCount = 2.0 * M_PI / dxl::kCountsPerRev;
  return direction * (counts - zero_count) * kRadPerCount;
}

QtmPose QtmPoseFromFrame(const TwinFrame& f, double residual_m) {
  QtmPose p;
  p.R_GC = f.R_GC;
  p.p_GoCo_G_m = f.p_GB_m;
  p.residual_m = residual_m;
  p.markers_G_m.assign(f.marker_G_m.begin(), f.marker_G_m.end());
  return p;
}

NatNetPose NatNetPoseFromFrame(const TwinFrame& f, double residual_m) {
  NatNetPose p;
  p.R_GC = f.R_GC;
  p.p_GoCo_G_m = f.p_GB_m;
  p.residual_m = residual_m;
  p.markers_G_m.assign(f.marker_G_m.begin(), f.marker_G_m.end());
  return p;
}

// ---- Truth CSVs ----

std::string AtiTruthCsv(const std::vector<AtiTruthRow>& rows) {
  std::string text =
      "leg,stream,t_s,rdt_sequence,ft_sequence,status,fx_counts,fy_counts,fz_counts,"
      "tx_counts,ty_counts,tz_counts,fault,datagram\n";
  text.reserve(text.size() + rows.size() * 90);
  char line[256];
  for (const AtiTruthRow& r : rows) {
    const auto& c = r.e.record.counts;
    std::snprintf(line, sizeof line, "%s,%u,%.6f,%u,%u,%u,%d,%d,%d,%d,%d,%d,%s,%u\n",
                  std::string(kLegNames.at(r.leg)).c_str(), r.e.stream, r.e.t_s,
                  r.e.record.rdt_sequence, r.e.record.ft_sequence, r.e.record.status, c[0], c[1],
                  c[2], c[3], c[4], c[5], AtiFaultName(r.e.fault), r.e.datagram);
    text += line;
  }
  return text;
}

std::string DxlTruthCsv(const std::vector<DxlReplyRecord>& rows) {
  std::string text =
      "t_s,id,instruction,address,length,fate,error,noise_bytes,tick_ms,position,velocity,"
      "current,torque_enable,hardware_error,position_exact_counts\n";
  text.reserve(text.size() + rows.size() * 80);
  char line[256];
  for (const auto& r : rows) {
    std::snprintf(line, sizeof line, "%.6f,%u,%u,%u,%u,%s,%u,%zu,%u,%d,%d,%d,%u,%u,%.6f\n", r.t_s,
                  r.id, r.instruction, r.address, r.length, DxlReplyFateName(r.fate), r.error,
                  r.noise_bytes, r.tick_ms, r.position, r.velocity, r.current, r.torque_enable,
                  r.hardware_error, r.position_exact_counts);
    text += line;
  }
  return text;
}

namespace {
void CsvValue(std::ostream& out, double v) {
  if (std::isnan(v)) {
    out << ",nan";
    return;
  }
  char buf[32];
  std::snprintf(buf, sizeof buf, ",%.9g", v);  // 9 digits round-trip an f32 exactly
  out << buf;
}
}  // namespace

std::string QtmTruthCsv(const std::vector<std::string>& labels,
                        const std::vector<QtmSentFrame>& frames) {
  std::ostringstream out;
  out << "tick,frame_number,timestamp_us,corrupt,tracked,px_mm,py_mm,pz_mm,"
         "r11,r21,r31,r12,r22,r32,r13,r23,r33,residual_mm";
  for (const auto& label : labels)
    out << "," << label << "_x_mm," << label << "_y_mm," << label << "_z_mm";
  out << "\n";
  for (const QtmSentFrame& s : frames) {
    out << s.tick << "," << s.frame_number << "," << s.timestamp_us << "," << int(s.corrupt) << ","
        << int(s.body.tracked());
    for (int i = 0; i < 3; ++i) CsvValue(out, s.body.p_GoBo_G_mm(i));
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) CsvValue(out, s.body.R_GB(i, j));
    }
    CsvValue(out, s.body.residual_mm);
    for (const auto& m : s.markers) {
      for (int i = 0; i < 3; ++i) CsvValue(out, m.p_GoM_G_mm(i));
    }
    out << "\n";
  }
  return out.str();
}

std::string NatNetTruthCsv(const std::vector<NatNetSentFrame>& frames) {
  std::ostringstream out;
  out << "tick,frame_number,timestamp_s,exposure_utime,corrupt,edit_mode,tracked,px_m,py_m,pz_m,"
         "r11,r21,r31,r12,r22,r32,r13,r23,r33\n";
  for (const NatNetSentFrame& s : frames) {
    char t[32];
    std::snprintf(t, sizeof t, "%.6f", s.timestamp_s);
    out << s.tick << "," << s.frame_number << "," << t << "," << s.exposure_utime << ","
        << int(s.corrupt) << "," << int(s.edit_mode) << "," << int(s.tracked);
    for (int i = 0; i < 3; ++i) CsvValue(out, s.p_GoCo_G_m(i));
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 3; ++i) CsvValue(out, s.R_GC(i, j));
    }
    out << "\n";
  }
  return out.str();
}

// ---- LiveSim ----

LiveSim::LiveSim(const config::Config& config, const LiveOptions& options) : options_(options) {
  if (options_.pty_link.empty()) throw std::invalid_argument("live: no pty link path given");
  if (config.robot().leg_size() != kNumLegs) {
    throw std::invalid_argument("live: the config lists " +
                                std::to_string(config.robot().leg_size()) + " legs, not 6");
  }
  TwinOptions twin_options;
  twin_options.seed = options_.seed;
  twin_options.physical_com = options_.physical_com;
  twin_options.counts_per_force = options_.counts_per_force;
  twin_options.counts_per_torque = options_.counts_per_torque;
  // Enough cycles for the loop (a hanging series is hang_cycles slow leg cycles).
  twin_options.hang_cycles =
      std::max(1, static_cast<int>(std::ceil(options_.loop_s / twin_options.hang_cycle_s)));
  twin_ = std::make_unique<BigAntTwin>(config, twin_options);
  commanded_ = options_.scenario == kCommandedScenario;
  if (commanded_) {
    if (!(options_.servo_time_constant_s > 0) || !std::isfinite(options_.servo_time_constant_s)) {
      throw std::invalid_argument("live: the servo time constant must be positive, not " +
                                  std::to_string(options_.servo_time_constant_s));
    }
    for (double a : options_.commanded_start_rad) {
      if (!std::isfinite(a)) throw std::invalid_argument("live: a start angle is not finite");
    }
    driven_ = std::make_unique<BigAntTwin::Driven>(*twin_);
  } else {
    series_ = std::make_unique<TwinSeries>(*twin_, options_.scenario, options_.loop_s);
  }
  const TwinSeries* series = series_.get();

  // ATI: the counts of the frame at each internal sample (the box's 7000 Hz samples hold a
  // 100 Hz twin frame).
  for (int k = 0; k < kNumLegs; ++k) {
    const config::Leg& leg = config.robot().leg(k);
    if (!leg.has_ati()) throw std::invalid_argument("live: leg " + leg.name() + " has no ati");
    AtiEmulatorOptions o;
    o.name = leg.name();
    o.address = leg.ati().address();
    o.rdt_port = static_cast<std::uint16_t>(leg.ati().rdt_port());
    o.http_port = static_cast<std::uint16_t>(options_.ati_http_port >= 0 ? options_.ati_http_port
                                                                         : leg.ati().http_port());
    o.counts_per_force = options_.counts_per_force;
    o.counts_per_torque = options_.counts_per_torque;
    if (leg.ati().rated_range_size() == 6) {
      for (int i = 0; i < 6; ++i) o.rated_range[i] = leg.ati().rated_range(i);
    }
    o.rdt_rate_hz = options_.ati_rate_hz;
    o.counter_rate_ppm = options_.clocks.ft[k].rate_ppm;
    // The box's RDT buffer size as the config names it, else the default of its rate: what
    // the bridge, reading the same config, expects.
    o.rdt_buffer_size = static_cast<int>(leg.ati().records_per_datagram());
    o.faults = options_.ati_faults[k];
    if (o.faults.seed == 0) o.faults.seed = options_.seed * 1000 + static_cast<std::uint64_t>(k);
    AtiStateSource source;
    if (commanded_) {
      source = [this, k](std::uint64_t, double) {  // the latest frame of the twin thread
        AtiDeviceSample s;
        s.counts = LatestFrame()->counts[k];
        return s;
      };
    } else {
      source = [series, k](std::uint64_t, double t_s) {
        AtiDeviceSample s;
        s.counts = series->At(t_s).counts[k];
        return s;
      };
    }
    // Called on the ATI thread only (Step), so the vector needs no lock.
    auto emit = [this, k](const AtiEmitted& e) { ati_truth_.push_back({k, e}); };
    ati_.push_back(std::make_unique<AtiEmulator>(o, source, emit));
  }

  // Dynamixel: ids, zero counts and directions from the config.
  DxlEmulatorOptions dxl_options;
  dxl_options.ids.clear();
  std::array<std::int32_t, kNumLegs> zero{};
  std::array<int, kNumLegs> direction{};
  std::array<int, 256> leg_of_id;
  leg_of_id.fill(-1);
  for (int k = 0; k < kNumLegs; ++k) {
    const auto& servo = config.robot().leg(k).servo();
    if (servo.id() > 252) {
      throw std::invalid_argument("live: leg " + config.robot().leg(k).name() + " servo id " +
                                  std::to_string(servo.id()) + " out of range");
    }
    dxl_options.ids.push_back(static_cast<std::uint8_t>(servo.id()));
    zero[k] = servo.zero_count();
    direction[k] = servo.direction();
    leg_of_id[servo.id()] = k;
  }
  dxl_options.rates = options_.dxl_rates;
  for (int k = 0; k < kNumLegs; ++k) {
    dxl_options.tick_rate_ppm.push_back(options_.clocks.servo[k].rate_ppm);
    dxl_options.tick_phase_ms.push_back(1e3 * options_.clocks.servo[k].offset_s);
  }
  dxl_options.events = options_.dxl_events;
  if (commanded_) {
    dxl_options.time_constant_s = options_.servo_time_constant_s;
    for (int k = 0; k < kNumLegs; ++k) {
      dxl_options.initial_positions.push_back(static_cast<std::int32_t>(
          std::lround(DxlStateFromAngle(options_.commanded_start_rad[k], 0, zero[k], direction[k])
                          .position_counts)));
      dxl_id_[k] = dxl_options.ids[k];
    }
    dxl_zero_ = zero;
    dxl_direction_ = direction;
  }
  dxl_ = std::make_unique<DynamixelBusEmulator>(dxl_options);
  dxl_->SetReplyObserver([this](const DxlReplyRecord& r) { dxl_truth_.push_back(r); });
  if (!commanded_) {
    dxl_->SetStateSource([series, zero, direction, leg_of_id](
                             std::uint8_t id, double now_s) -> std::optional<DxlDrivenState> {
      const int k = leg_of_id[id];
      if (k < 0) return std::nullopt;
      double rate = 0;
      const double angle = series->AngleAt(k, now_s, &rate);
      return DxlStateFromAngle(angle, rate, zero[k], direction[k]);
    });
  } else {
    // No state source: the servos follow their goals. The twin's first frame stands at the
    // start positions.
    SnapshotServos();
    latest_ = std::make_shared<const TwinFrame>(driven_->Frame(0.0, ServoAngles()));
  }
  pty_ = std::make_unique<PtyBus>(*dxl_, options_.pty_link);

  const double residual_m = twin_options.marker_noise_m;
  if (options_.mocap == "natnet") {
    // Motive, from the config's mocap.natnet section (the bridge reads the same).
    const config::NatNet& n = config.mocap().natnet();
    NatNetEmulatorOptions no;
    no.address = n.server_address().empty() ? config.mocap().server_address() : n.server_address();
    no.command_port = static_cast<std::uint16_t>(n.command_port());
    no.data_port = static_cast<std::uint16_t>(n.data_port());
    no.multicast = options_.natnet_multicast >= 0 ? options_.natnet_multicast != 0 : n.multicast();
    no.multicast_group = n.multicast_group();
    no.version = options_.natnet_version;
    no.clock_rate_ppm = options_.clocks.mocap.rate_ppm;
    no.clock_offset_s = options_.clocks.mocap.offset_s;
    no.rate_hz = options_.natnet_rate_hz;
    no.body_name = config.mocap().body_name();
    no.z_up = n.up_axis() == "Z";
    if (n.has_x_pivot_chassis()) {
      const Pose3 X_PC = ToPose3(n.x_pivot_chassis());
      no.R_PC = X_PC.R;
      no.p_PoCo_P_m = X_PC.p;
    }
    for (const auto& m : twin_->MarkersB()) no.body_points_C_m.push_back(m);
    no.faults = options_.natnet_faults;
    if (no.faults.seed == 0) no.faults.seed = options_.seed;
    const double rate = no.rate_hz;
    if (commanded_) {
      natnet_ = std::make_unique<NatNetEmulator>(
          no, [this, residual_m](int64_t) -> std::optional<NatNetPose> {
            return NatNetPoseFromFrame(*LatestFrame(), residual_m);
          });
    } else {
      natnet_ = std::make_unique<NatNetEmulator>(
          no, [series, rate, residual_m](int64_t tick) -> std::optional<NatNetPose> {
            return NatNetPoseFromFrame(series->At(static_cast<double>(tick) / rate), residual_m);
          });
    }
    natnet_->SetObserver([this](const NatNetSentFrame& s) { natnet_truth_.push_back(s); });
  } else if (options_.mocap == "qtm") {
    // QTM.
    QtmEmulatorOptions qo;
    qo.address = config.mocap().server_address();
    qo.port = static_cast<std::uint16_t>(options_.qtm_port >= 0 ? options_.qtm_port
                                                                : int(config.mocap().port()));
    qo.rate_hz = options_.qtm_rate_hz;
    qo.clock_rate_ppm = options_.clocks.mocap.rate_ppm;
    qo.clock_offset_s = options_.clocks.mocap.offset_s;
    qo.body_name = config.mocap().body_name();
    for (const auto& m : twin_->MarkersB()) qo.body_points_m.push_back(m);
    qo.labels = DefaultQtmLabels(kNumChassisMarkers);
    qtm_labels_ = qo.labels;
    qo.faults = options_.qtm_faults;
    if (qo.faults.seed == 0) qo.faults.seed = options_.seed;
    const double qtm_rate = qo.rate_hz;
    if (commanded_) {
      qtm_ =
          std::make_unique<QtmEmulator>(qo, [this, residual_m](int64_t) -> std::optional<QtmPose> {
            return QtmPoseFromFrame(*LatestFrame(), residual_m);
          });
    } else {
      qtm_ = std::make_unique<QtmEmulator>(
          qo, [series, qtm_rate, residual_m](int64_t tick) -> std::optional<QtmPose> {
            return QtmPoseFromFrame(series->At(static_cast<double>(tick) / qtm_rate), residual_m);
          });
    }
    qtm_->SetObserver([this](const QtmSentFrame& s) { qtm_truth_.push_back(s); });
  } else {
    throw std::invalid_argument("live: mocap '" + options_.mocap + "' is not qtm or natnet");
  }

  // Everything is bound: start the clock and the devices.
  pty_->Open();
  pty_slave_ = pty_->slave_path();
  t0_ = std::chrono::steady_clock::now();
  if (commanded_) twin_thread_ = std::thread([this] { RunTwin(); });
  ati_thread_ = std::thread([this] { RunAti(); });
  dxl_thread_ = std::thread([this] { RunDxl(); });
  if (qtm_) qtm_thread_ = std::thread([this] { qtm_->Run(-1, [this] { return !stop_.load(); }); });
  if (natnet_) {
    qtm_thread_ = std::thread([this] { natnet_->Run(-1, [this] { return !stop_.load(); }); });
  }
}

LiveSim::~LiveSim() { Stop(); }

double LiveSim::Now() const {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
}

std::uint16_t LiveSim::qtm_port() const { return qtm_ ? qtm_->port() : 0; }
std::uint16_t LiveSim::natnet_command_port() const { return natnet_ ? natnet_->command_port() : 0; }

void LiveSim::RunAti() {
  std::vector<pollfd> fds;
  for (const auto& b : ati_) fds.push_back({b->fd(), POLLIN, 0});
  // A short wait between steps keeps the records close to their schedule at 7000 Hz.
  const timespec wait{0, 200'000};
  while (!stop_.load()) {
    ::ppoll(fds.data(), fds.size(), &wait, nullptr);
    const auto now = AtiEmulator::Clock::now();
    for (auto& b : ati_) b->Step(now);
  }
  const auto now = AtiEmulator::Clock::now();
  for (auto& b : ati_) {
    b->Step(now);
    b->EndOfData();  // flushes a held (reordered) record, so the truth is complete
  }
}

void LiveSim::RunDxl() {
  const auto clock = [this] { return Now(); };
  while (!stop_.load()) {
    const double now_s = Now();
    bool down = false;
    for (const auto& w : options_.dxl_disconnects)
      down = down || (now_s >= w.start_s && now_s < w.end_s);
    if (down && pty_->is_open()) {
      pty_->Close();
    } else if (!down && !pty_->is_open()) {
      pty_->Open();
      ++dxl_reopens_;
    }
    if (pty_->is_open()) {
      pty_->ServeOnce(2, clock);
    } else {
      ::usleep(2000);
    }
    if (commanded_) {
      // The servos move whether or not they are asked (and with the port gone): advancing them
      // here keeps the twin's legs on the exact first-order curve between requests.
      dxl_->Advance(Now());
      SnapshotServos();
    }
  }
}

void LiveSim::SnapshotServos() {
  std::array<double, 6> counts{};
  for (int k = 0; k < kNumLegs; ++k) counts[k] = dxl_->ExactPosition(dxl_id_[k]);
  std::lock_guard<std::mutex> lock(servo_mutex_);
  servo_counts_ = counts;
}

std::array<double, 6> LiveSim::ServoAngles() const {
  std::array<double, 6> counts;
  {
    std::lock_guard<std::mutex> lock(servo_mutex_);
    counts = servo_counts_;
  }
  std::array<double, 6> angle{};
  for (int k = 0; k < kNumLegs; ++k) {
    angle[k] = DxlAngleFromCounts(counts[k], dxl_zero_[k], dxl_direction_[k]);
  }
  return angle;
}

std::shared_ptr<const TwinFrame> LiveSim::LatestFrame() const {
  std::lock_guard<std::mutex> lock(frame_mutex_);
  return latest_;
}

void LiveSim::SetSupport(Support support, HangSeries series) {
  if (!commanded_) throw std::logic_error("LiveSim::SetSupport: only the commanded scenario");
  const int s = static_cast<int>(series);
  if (s < 0 || s >= kNumHangSeries) {
    throw std::invalid_argument("LiveSim::SetSupport: unknown hanging series " + std::to_string(s));
  }
  std::lock_guard<std::mutex> lock(support_mutex_);
  support_ = support;
  support_series_ = series;
  ++supports_requested_;
}

void LiveSim::RunTwin() {
  // Frame i at i / rate on the twin's clock; a thread that fell behind skips to the present.
  const double period_s = 1.0 / twin_->Options().sample_rate_hz;
  std::int64_t i = 1;
  while (!stop_.load()) {
    const double t_s = static_cast<double>(i) * period_s;
    std::this_thread::sleep_until(t0_ +
                                  std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                                      std::chrono::duration<double>(t_s)));
    if (stop_.load()) break;
    std::int64_t requested;
    {
      std::lock_guard<std::mutex> lock(support_mutex_);
      driven_->SetSupport(support_, support_series_);
      requested = supports_requested_;
    }
    auto frame = std::make_shared<const TwinFrame>(driven_->Frame(t_s, ServoAngles()));
    {
      std::lock_guard<std::mutex> lock(frame_mutex_);
      latest_ = std::move(frame);
    }
    supports_applied_.store(requested);
    i = std::max(i + 1, static_cast<std::int64_t>(std::floor(Now() / period_s)));
  }
}

void LiveSim::Stop() {
  if (stopped_) return;
  stopped_ = true;
  stop_.store(true);
  if (qtm_) qtm_->RequestStop();
  if (natnet_) natnet_->RequestStop();
  for (std::thread* t : {&ati_thread_, &dxl_thread_, &qtm_thread_, &twin_thread_}) {
    if (t->joinable()) t->join();
  }
  for (std::size_t k = 0; k < ati_.size(); ++k) ati_counts_[k] = ati_[k]->counters();
  pty_->Close();
}

LiveCounts LiveSim::Counts() const {
  LiveCounts c;
  c.ati = ati_counts_;
  c.dxl = dxl_->fault_counts();
  c.dxl_replies = static_cast<std::int64_t>(dxl_truth_.size());
  c.dxl_reopens = dxl_reopens_;
  if (qtm_) c.qtm = qtm_->counters();
  if (natnet_) c.natnet = natnet_->counters();
  return c;
}

void LiveSim::WriteTruth(const std::string& dir) const {
  if (!stopped_) throw std::logic_error("LiveSim::WriteTruth before Stop()");
  WriteFileAtomic(dir + "/ati.csv", AtiTruthCsv(ati_truth_));
  WriteFileAtomic(dir + "/dynamixel.csv", DxlTruthCsv(dxl_truth_));
  if (qtm_) WriteFileAtomic(dir + "/qtm.csv", QtmTruthCsv(qtm_labels_, qtm_truth_));
  if (natnet_) WriteFileAtomic(dir + "/natnet.csv", NatNetTruthCsv(natnet_truth_));
}

}  // namespace ftcal::sim
