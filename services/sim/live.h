// The BigAnt twin driving the device emulators in real time: the common part of `ftcal-sim
// live` (all three devices in one process) and of the standalone ftcal-emulate-* programs.
//
//   TwinSeries      a twin scenario as a 100 Hz series of frames, looped when a run outlasts it
//   *From...        what each device reports at a twin frame (ATI counts, servo counts, QTM pose)
//   *TruthCsv       the truth series each emulator produced, as the CSV files the tests read
//   LiveSim         six ATI Net F/T boxes (RDT + calibration page), the Dynamixel bus on a pty
//                   and the motion capture (the QTM RT server, or with mocap = "natnet" the
//                   Motive NatNet server), each on its own thread, until Stop()
//
// In the recorded scenarios (walk, stand, tripod, hang-*) every device reads the same twin
// series on the same clock (seconds since LiveSim started), so at any moment the wrenches, the
// shaft angles and the chassis attitude the bridges receive belong to the same twin frame (to
// within the devices' own sampling). The servos' positions are the scenario's shaft angles
// (DynamixelBusEmulator's StateSource): a Sync Write of goals is accepted by the servos' tables
// but does not move them.
//
// In the "commanded" scenario the legs follow the servos instead. The Dynamixel emulator has no
// StateSource: the servos start at `commanded_start_rad` (default: their zero counts, shaft
// angle 0) with torque off and, once a bridge enables torque, move toward their Goal Position
// with first-order dynamics (time constant `servo_time_constant_s`). The Dynamixel thread
// advances them between requests too and publishes their exact positions; a twin thread makes a
// frame every 1/100 s from those positions (counts -> rad as DxlAngleFromCounts) with
// BigAntTwin::Driven (standing on all six feet), and the ATI and QTM threads report the latest
// such frame. The truth CSVs record what each device sent, as in every scenario. SetSupport
// is the operator: it hangs the robot (the four hanging attitudes), lifts it upright, or sets it
// down, for the sequencer's hanging series, tare and standing phases.
#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "ati_emulator.h"
#include "dynamixel_emulator.h"
#include "natnet_emulator.h"
#include "proto/config.pb.h"
#include "qtm_emulator.h"
#include "sim/flags.h"
#include "sim/sim_clocks.h"
#include "sim/twin.h"

namespace ftcal::sim {

// The scenarios a live run can play: the first seven loop a twin series (TwinSeries); in
// "commanded" the legs follow the servos' goals (see the header comment).
inline constexpr const char* kLiveScenarios[] = {
    "walk", "stand", "tripod", "hang-x-pos", "hang-x-neg", "hang-z-pos", "hang-z-neg", "commanded"};
inline constexpr const char kCommandedScenario[] = "commanded";

class TwinSeries {
 public:
  // At least `span_s` of `scenario` (one of kLiveScenarios). Throws std::invalid_argument for an
  // unknown scenario and std::runtime_error when the twin produced no frame.
  TwinSeries(const BigAntTwin& twin, const std::string& scenario, double span_s);

  // The frame at `t_s` (>= 0; negative times give the first frame), the series repeating
  // after its end.
  const TwinFrame& At(double t_s) const;
  // Frame i of the series, the series repeating after its end.
  const TwinFrame& Frame(std::size_t i) const { return frames_[i % frames_.size()]; }
  // Shaft angle of leg k at `t_s`, linear between frames (a servo's encoder samples far faster
  // than 100 Hz), and its rate. At the loop's seam the last frame is held, never interpolated
  // into the first one.
  double AngleAt(int k, double t_s, double* rate_rad_s = nullptr) const;
  std::size_t size() const { return frames_.size(); }
  double period_s() const { return period_s_; }
  double length_s() const { return period_s_ * static_cast<double>(frames_.size()); }

 private:
  std::size_t Index(double t_s, double* frac) const;

  std::vector<TwinFrame> frames_;
  double period_s_ = 0.01;
};

// The Dynamixel driven state of a servo at shaft angle `angle_rad` turning at `rate_rad_s`:
// counts = zero + direction * angle / (2 pi / 4096).
DxlDrivenState DxlStateFromAngle(double angle_rad, double rate_rad_s, std::int32_t zero_count,
                                 int direction);
// The inverse: the shaft angle at (continuous) encoder position `counts`,
// direction * (counts - zero) * 2 pi / 4096.
double DxlAngleFromCounts(double counts, std::int32_t zero_count, int direction);
// The mocap's view of a twin frame.
QtmPose QtmPoseFromFrame(const TwinFrame& frame, double residual_m);
// The same view for the Motive emulator (it turns it into Motive's axes and pivot itself).
NatNetPose NatNetPoseFromFrame(const TwinFrame& frame, double residual_m);

// Truth CSVs (the formats of ftcal-emulate-ati --truth, ftcal-emulate-dynamixel --truth and
// ftcal-emulate-qtm --truth). `leg` indexes kLegNames.
struct AtiTruthRow {
  int leg = 0;
  AtiEmitted e;
};
std::string AtiTruthCsv(const std::vector<AtiTruthRow>& rows);
std::string DxlTruthCsv(const std::vector<DxlReplyRecord>& rows);
std::string QtmTruthCsv(const std::vector<std::string>& labels,
                        const std::vector<QtmSentFrame>& frames);
// natnet.csv: per frame sent, the tick, frame number, Motive timestamp, mid-exposure host time,
// faults, and the chassis pose in ftcal's frame G (rotation column-major).
std::string NatNetTruthCsv(const std::vector<NatNetSentFrame>& frames);

struct LiveOptions {
  std::string scenario = "walk";
  std::uint64_t seed = 1;
  // The devices' clocks: each box's counter, each servo's tick and the mocap clock at its own
  // rate (a lab's by default). The host's stalls are this machine's own, not injected.
  SimClocks clocks = SimClocks::Lab();
  // The twin's robot CoM: moving with the legs (TwinOptions::physical_com) or fixed.
  bool physical_com = false;
  // Length of the generated scenario before it repeats.
  double loop_s = 120.0;

  // ATI: the config's addresses and ports; the page's port replaced when http_port >= 0.
  int ati_rate_hz = 7000;
  int ati_http_port = -1;
  double counts_per_force = 1e6;
  double counts_per_torque = 1e6;
  // Per leg (kLegNames order); the seed of each is derived from `seed` when left at 0.
  std::array<AtiFaultOptions, 6> ati_faults{};

  // Dynamixel: the pty's slave is symlinked here (the bridge's config names it).
  std::string pty_link;
  DxlFaultRates dxl_rates;
  std::vector<DxlFaultEvent> dxl_events;
  struct Window {
    double start_s = 0, end_s = 0;
  };
  std::vector<Window> dxl_disconnects;  // the port vanishes, back as a new pty
  // "commanded" only: the servos' first-order time constant toward Goal Position, and their
  // shaft angles at the start (kLegNames order; rounded to whole encoder counts).
  double servo_time_constant_s = 0.05;
  std::array<double, 6> commanded_start_rad{};

  // QTM: the config's address and port unless given (port 0: any free port).
  int qtm_port = -1;
  double qtm_rate_hz = 100.0;
  QtmFaults qtm_faults;

  // Which motion capture the twin serves: "qtm" or "natnet" (the config's mocap.natnet
  // section gives Motive's address, ports, up axis and pivot; the transport can be overridden).
  std::string mocap = "qtm";
  natnet::Version natnet_version{4, 1};
  int natnet_multicast = -1;  // -1: the config's mocap.natnet.multicast
  double natnet_rate_hz = 100.0;
  NatNetFaults natnet_faults;
};

struct LiveCounts {
  std::array<AtiEmulatorCounters, 6> ati{};
  DxlFaultCounts dxl;
  std::int64_t dxl_replies = 0;
  std::int64_t dxl_reopens = 0;
  QtmEmulatorCounters qtm;
  NatNetEmulatorCounters natnet;
};

class LiveSim {
 public:
  // Binds every endpoint and opens the pty, then starts the device threads. Throws
  // std::invalid_argument for a bad option and std::runtime_error (or AtiEmulatorError)
  // naming the endpoint that could not be set up.
  LiveSim(const config::Config& config, const LiveOptions& options);
  ~LiveSim();
  LiveSim(const LiveSim&) = delete;
  LiveSim& operator=(const LiveSim&) = delete;

  // Seconds since the devices started (the twin's clock).
  double Now() const;
  // Ends the device threads (idempotent); the truth and counts are complete afterwards.
  void Stop();
  // After Stop(): the truth series in `dir` (ati.csv, dynamixel.csv, and qtm.csv or
  // natnet.csv), each atomically.
  void WriteTruth(const std::string& dir) const;
  LiveCounts Counts() const;  // after Stop()
  const std::string& pty_path() const { return pty_slave_; }
  std::uint16_t qtm_port() const;             // 0 with mocap "natnet"
  std::uint16_t natnet_command_port() const;  // 0 with mocap "qtm"
  int ati_boxes() const { return static_cast<int>(ati_.size()); }
  std::size_t ati_truth_rows() const { return ati_truth_.size(); }
  bool commanded() const { return commanded_; }
  // The twin behind the devices (its Truth() is what a calibration must recover).
  const BigAntTwin& twin() const { return *twin_; }
  // "commanded": the latest twin frame the devices report (any thread); null otherwise.
  std::shared_ptr<const TwinFrame> LatestFrame() const;
  // "commanded": the operator's hands (any thread). The robot hangs in `series`' attitude, is
  // lifted upright with its feet in the air, or stands, from the twin's next frame on (the
  // twin's own physics: BigAntTwin::Driven::SetSupport). Throws std::logic_error otherwise.
  using Support = BigAntTwin::Driven::Support;
  void SetSupport(Support support, HangSeries series = HangSeries::kXPos);
  // How many SetSupport calls the twin's frames reflect (the latest frame was made after them).
  std::int64_t supports_applied() const { return supports_applied_.load(); }

 private:
  void RunAti();
  void RunDxl();
  void RunTwin();  // "commanded" only
  // The servos' exact positions as shaft angles (any thread); "commanded" only.
  std::array<double, 6> ServoAngles() const;
  void SnapshotServos();  // on the Dynamixel thread

  LiveOptions options_;
  std::unique_ptr<BigAntTwin> twin_;
  std::unique_ptr<TwinSeries> series_;
  std::chrono::steady_clock::time_point t0_;
  std::atomic<bool> stop_{false};
  bool stopped_ = false;

  // The truth vectors are declared before the emulators that fill them, so they outlive them.
  std::vector<AtiTruthRow> ati_truth_;
  std::vector<DxlReplyRecord> dxl_truth_;
  std::vector<QtmSentFrame> qtm_truth_;

  std::vector<std::unique_ptr<AtiEmulator>> ati_;
  std::array<AtiEmulatorCounters, 6> ati_counts_{};

  std::unique_ptr<DynamixelBusEmulator> dxl_;
  std::unique_ptr<PtyBus> pty_;
  std::string pty_slave_;
  std::int64_t dxl_reopens_ = 0;

  std::unique_ptr<QtmEmulator> qtm_;
  std::vector<std::string> qtm_labels_;
  std::vector<NatNetSentFrame> natnet_truth_;
  std::unique_ptr<NatNetEmulator> natnet_;

  // "commanded": the legs follow the servos. The Dynamixel thread alone touches dxl_; it
  // copies the servos' positions into servo_counts_, which the twin thread reads to make the
  // frame the ATI and QTM threads read.
  bool commanded_ = false;
  std::unique_ptr<BigAntTwin::Driven> driven_;
  std::array<std::uint8_t, 6> dxl_id_{};
  std::array<std::int32_t, 6> dxl_zero_{};
  std::array<int, 6> dxl_direction_{};
  mutable std::mutex servo_mutex_;
  std::array<double, 6> servo_counts_{};
  mutable std::mutex frame_mutex_;
  std::shared_ptr<const TwinFrame> latest_;
  // The operator's latest request, taken by the twin thread before its next frame.
  std::mutex support_mutex_;
  Support support_ = Support::kStanding;
  HangSeries support_series_ = HangSeries::kXPos;
  std::int64_t supports_requested_ = 0;
  std::atomic<std::int64_t> supports_applied_{0};

  std::thread ati_thread_, dxl_thread_, qtm_thread_, twin_thread_;
};

}  // namespace ftcal::sim
