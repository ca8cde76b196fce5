// ftcal-calibrator's work (pipeline items 3 and 5): the recorded (or live) experiment in, the
// calibration file out.
//
// CalibrationCollector listens on a Bus (a LogReplayBus per input log, or live LCM) and turns
// FT_<LEG>, SERVO_STATE, MOCAP_BODY, EXPERIMENT and STEADY_POSE into what Calibrate() consumes:
//   - every aligned sample (libcal's Aligner, the same rule as ftcal-pose-segmenter) between a
//     HANG_* start and its stop marker goes into that series' HangingRecording (per leg: time,
//     shaft angle, reading; gravity_b from the start marker; the attitude when tracked);
//   - steady standing poses: the STEADY_POSE events of the log when it has any, else the
//     PoseSegmenter run over the STANDING spans (as ftcal-pose-segmenter would have);
//   - the aligned samples of the first WALKING phase (up to kMaxWalkingSamples), for the
//     report's walking figure (the report's Fig. 9): corrected vs naive tare;
//   - steady tripod stances (the same segmenter over the TRIPOD spans), with the legs turned
//     past calibrator.unloaded_leg_min_angle_deg marked unloaded: the per-leg equations of the
//     offset re-estimation (docs/method.md "Offset drift").
// Nothing is guessed: a series without its start..stop pair is missing, not reconstructed.
//
// RunCalibration() checks what was collected (every series, markers present, the config's legs
// are the log's FT_* channels, no damaged bytes), runs Calibrate() and fills provenance. Every
// refusal is a CalibratorInputError naming what is wrong; main() turns it into exit code 2.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <stdexcept>
#include <regex>
#include <string>
#include <unordered_map>
#include <vector>

#include "common/bus.h"
#include "common/messages.h"
#include "ftcal/aligner.h"
#include "ftcal/calibrate.h"
#include "ftcal/dataset.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/offset_reestimation.h"
#include "ftcal/segmenter.h"
#include "ftcal/steady_pose_t.hpp"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

// The input cannot give a calibration (missing series, no markers, a config for another robot,
// a damaged log, a stage that refused its data). what() names the problem.
class CalibratorInputError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct CollectorCounters {
  int64_t markers = 0;
  int64_t aligned_samples = 0;
  int64_t hanging_samples = 0;
  int64_t standing_samples = 0;
  int64_t logged_poses = 0;      // STEADY_POSE events seen
  int64_t segmented_poses = 0;   // poses the collector's own segmenter found
  int64_t poses_dropped_markers = 0;  // logged poses without every marker
  int64_t walking_samples = 0;        // aligned samples inside WALKING phases (kept or not)
  int64_t tripod_samples = 0;         // aligned samples inside TRIPOD phases
  int64_t tripod_stances = 0;         // steady tripod stances with a leg unloaded, kept
  int64_t tripod_stances_dropped = 0; // steady, but no leg lifted
};

// One completed phase's transducer records per leg, counted by the devices' RDT sequence
// numbers (ft_sample_t.rdt_sequence rises by 1 a record): what reached this input and what
// did not, wherever it was lost (network, bridge, the recorder's socket).
struct PhaseGaps {
  int phase = -1;  // experiment_marker_t phase code
  std::string session;
  std::array<int64_t, kNumLegs> received{};
  std::array<int64_t, kNumLegs> lost{};
  // A number that fell back far (a new RDT stream: the bridge or the device restarted): the
  // records of the outage have no numbers to miss, so it is counted apart from the gaps.
  std::array<int64_t, kNumLegs> restarts{};
  bool superseded = false;  // a hanging series recorded again later: this one is not used
  double LostShare(int k) const {
    const int64_t n = received[k] + lost[k];
    return n > 0 ? static_cast<double>(lost[k]) / static_cast<double>(n) : 0.0;
  }
};

class CalibrationCollector {
 public:
  // Throws std::invalid_argument for a config whose legs are not kLegNames in order.
  explicit CalibrationCollector(const config::Config& config);

  // Subscribes the handlers on `bus` (call once per bus; several logs = several buses, fed in
  // order).
  void Attach(Bus& bus);
  // Ends a phase in progress (its samples are kept only if its stop marker came).
  void Flush();

  // Called when a STANDING phase stops (live mode calibrates then).
  void SetOnStandingStop(std::function<void()> fn) { on_standing_stop_ = std::move(fn); }
  // Called after every STEADY_POSE event (live mode waits for the segmenter's last pose).
  void SetOnSteadyPose(std::function<void()> fn) { on_steady_pose_ = std::move(fn); }
  // Poses with every marker tracked: from STEADY_POSE events, and found by the collector's own
  // segmenter over the completed STANDING phases (the same rule as ftcal-pose-segmenter).
  size_t logged_pose_count() const { return logged_poses_.size(); }
  size_t segmented_pose_count() const { return segmented_poses_.size(); }

  // What was collected. Throws CalibratorInputError naming what is missing or inconsistent.
  std::vector<HangingRecording> HangingRecordings() const;
  std::vector<StandingPose> StandingPoses() const;
  // Throws CalibratorInputError when there were no EXPERIMENT markers (`phases`: what cannot be
  // told apart without them) or the FT_* channels seen are not the config's legs.
  void CheckMarkersAndLegs(const std::string& phases) const;

  // The aligned samples of the first completed WALKING phase (empty when there was none).
  // Bounded: ten minutes at 100 Hz is more than a figure shows.
  static constexpr size_t kMaxWalkingSamples = 60000;
  const std::vector<SyncSample>& walking_samples() const { return walking_; }

  // The naive tare of the last completed TARE phase (mean reading per leg; upright, feet in the
  // air, shafts at 0), when there was one.
  const std::optional<std::array<Vec6, kNumLegs>>& tare() const { return tare_; }

  // Steady tripod stances of the completed TRIPOD phases, with their unloaded legs.
  const std::vector<LoadSample>& unloaded_samples() const { return unloaded_; }

  // Every completed phase, in order, with its records counted (PhaseGaps).
  const std::vector<PhaseGaps>& phase_gaps() const { return phase_gaps_; }
  const std::string& ft_channel(int k) const { return inputs_.FtChannel(k); }

  const CollectorCounters& counters() const { return counters_; }
  const std::string& standing_session() const { return standing_session_; }

 private:
  void OnFtRaw(const MessageInfo& info, const void* data, int size);
  void OnExperiment(const experiment_marker_t& msg);
  void OnSteadyPose(const steady_pose_t& msg);
  void OnAligned(const AlignedSample& a);
  void OnTripodStance(const SteadyPoseOut& p);
  void EndPhase(bool completed);

  const config::Config& config_;
  // EXPERIMENT is a signed channel (common/envelope.h).
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  DeviceInputs inputs_;
  SegmenterOptions segmenter_options_;
  Aligner aligner_;
  std::unique_ptr<PoseSegmenter> segmenter_;

  // The phase in progress (experiment_marker_t phase code, -1 for none).
  int phase_ = -1;
  std::string phase_session_;
  HangingRecording current_hang_;
  std::vector<StandingPose> current_poses_;
  std::vector<SyncSample> current_walk_;
  std::vector<SyncSample> walking_;
  std::vector<LoadSample> current_unloaded_;
  std::vector<LoadSample> unloaded_;
  std::array<Vec6, kNumLegs> tare_sum_;
  int64_t tare_count_ = 0;
  std::optional<std::array<Vec6, kNumLegs>> tare_;

  std::array<std::optional<HangingRecording>, kNumHangSeries> hang_;
  std::vector<StandingPose> segmented_poses_;
  std::vector<StandingPose> logged_poses_;
  std::string standing_session_;
  std::set<std::string> ft_channels_seen_;
  std::set<std::string> channels_seen_;  // every channel, to name them when the config's are absent
  // Per channel name heard: its leg index among the config's FT channels (-1: not a leg's, or
  // not an FT channel). One hash lookup per event instead of a std::set insertion (two per FT
  // event) and six name comparisons: a report-scale log has 4 M events on ten channels.
  std::unordered_map<std::string, int> channel_leg_;
  // The FT subscription's pattern, as the bus matches it (every FT_* channel, not just the
  // config's).
  std::regex ft_pattern_{config_.channels().ft_prefix() + ".*", std::regex::extended};
  int LegOfChannel(const std::string& channel);
  ft_sample_t ft_scratch_;
  void CountRecord(int k, int64_t sequence);
  PhaseGaps current_gaps_;
  std::array<int64_t, kNumLegs> last_sequence_{};  // 0: none yet in this phase
  std::vector<PhaseGaps> phase_gaps_;
  std::array<int, kNumHangSeries> hang_gaps_index_;  // into phase_gaps_, -1: none
  std::function<void()> on_standing_stop_;
  std::function<void()> on_steady_pose_;
  CollectorCounters counters_;
};

struct CalibratorOptions {
  std::vector<std::string> log_paths;  // provenance inputs (empty live)
  std::string config_path;
  std::string command_line;
  // --accept-mass-mismatch: calibrate when the configured total mass disagrees with the data.
  bool accept_mass_mismatch = false;
  // --accept-leg-map-mismatch: calibrate when a transducer's data follows another leg's shaft.
  bool accept_leg_map_mismatch = false;
  // --allow-gaps: calibrate when a phase used lost more than calibrator.max_gap_share of a
  // transducer's records (recorded in the calibration file as a warning); refused otherwise.
  bool allow_gaps = false;
  // The SHA-256 of an input log for provenance; empty: Sha256File. Offline runs hash the logs
  // on another thread while they are read (a second pass over ~1 GB otherwise).
  std::function<std::string(const std::string& path)> sha256;
};

// The recording gaps of the completed phases: `used` says which phase codes the calibration
// takes data from (a superseded hanging series is not used). Logs a line per phase with any
// loss; throws CalibratorInputError naming every used phase and channel above
// calibrator.max_gap_share unless `allow_gaps` (then each is a warning in `warnings`).
std::vector<calibration::RecordingGaps> CheckRecordingGaps(const CalibrationCollector& collector,
                                                          const config::Config& config,
                                                          const std::set<int>& used,
                                                          bool allow_gaps,
                                                          std::vector<std::string>* warnings);

// Checks the collected data, runs Calibrate() and fills provenance. Throws CalibratorInputError.
CalibrationRun RunCalibration(const CalibrationCollector& collector, const config::Config& config,
                              const CalibratorOptions& options);

// Live mode: collects on `bus`; when a STANDING phase stops, calibrates from everything
// collected so far, writes the calibration (and its residuals CSV) atomically, publishes
// CALIBRATION (calibration_t: version counting up from 1, SHA-256 of the bytes, the binary
// proto) and calls on_calibrated. A refused calibration is logged and counted; the collector
// keeps listening (a later STANDING phase may complete it).
//
// The segmenter publishes the pose in progress when it hears the same stop marker, so its last
// STEADY_POSE arrives after the stop. When STEADY_POSE events are being used and fewer have come
// than the collector's own segmenter found, the calibration waits for them: it runs when the
// count is reached, or at the first Tick() kLatePoseWaitS after the stop with what came.
class LiveCalibrator {
 public:
  using Callback = std::function<void(const CalibrationRun&)>;
  static constexpr double kLatePoseWaitS = 2.0;
  LiveCalibrator(const config::Config& config, Bus& bus, std::string out_path,
                 CalibratorOptions options, Callback on_calibrated);
  // Call periodically (the bus loop's tick): ends a wait for late poses.
  void Tick();
  // Publish CALIBRATION signed by `signer` (outlives this); unsigned without one.
  void SetSigner(auth::Signer* signer) { signer_ = signer; }
  int64_t version() const { return version_; }
  int64_t refused() const { return refused_; }
  const std::string& last_refusal() const { return last_refusal_; }

 private:
  void OnStandingStop();
  void CalibrateNow();

  const config::Config& config_;
  Bus& bus_;
  std::string out_path_;
  CalibratorOptions options_;
  Callback on_calibrated_;
  CalibrationCollector collector_;
  int64_t version_ = 0;
  int64_t refused_ = 0;
  std::string last_refusal_;
  int64_t waiting_since_utime_ = -1;  // STANDING stopped, the segmenter's last poses not all in
  auth::Signer* signer_ = nullptr;
};

// Offset drift (docs/method.md "Offset drift"): the offsets of `base` re-estimated from the
// collected standing poses and steady tripod stances, everything else kept. Refuses
// (CalibratorInputError) a base calibration for another robot, missing markers or data, and,
// unless `allow_partial`, data that leaves any offset component undetermined (naming them); with
// `allow_partial` those keep the base value and are listed in the result.
struct OffsetReestimationRun {
  calibration::Calibration proto;  // base with the new offsets and offset_reestimation filled
  OffsetReestimate estimate;
  RobotCalibration before, after;
};
OffsetReestimationRun RunOffsetReestimation(const CalibrationCollector& collector,
                                            const config::Config& config,
                                            const std::string& base_path, bool allow_partial,
                                            const CalibratorOptions& options);
// Per leg: the offsets before and after, their difference (the drift) and the sigma of the new
// ones; the undetermined components and the data used.
std::string OffsetSummaryTable(const OffsetReestimationRun& run);

// Writes the calibration file and <out>.residuals.csv beside it, both atomically.
void WriteCalibrationOutputs(const CalibrationRun& run, const std::string& out_path);

// Results in the journal's terms (docs/method.md): the RMSE of the summed ground-contact force
// and torque against the balance target, naive tare vs calibration, over the standing poses
// and (when given) the walk; per leg against the true parameters when `truth` is given. Into
// run->proto.result_rmse.
void AddResultRmse(const std::vector<SyncSample>& walk, const RobotCalibration* truth,
                   CalibrationRun* run);

// The software version recorded in provenance: PROJECT_VERSION (+ git describe at build time).
std::string SoftwareVersion();

// The short table printed at the end: per leg offsets, weights, mounting; model selection;
// standing residuals before/after.
std::string SummaryTable(const CalibrationRun& run);

// Per-pose residuals of the total wrench at the CoM in W, one row per pose and variant:
// "pose,variant,fx_n,fy_n,fz_n,tx_nm,ty_nm,tz_nm" (variants: naive tare, without T~, full
// calibration). The report's violin plots read this.
std::string ResidualsCsv(const StandingResult& standing);

// The path of the residuals file written beside a calibration file: cal.pbtxt -> cal.residuals.csv.
std::string ResidualsPathFor(const std::string& calibration_path);

// The walking session corrected (eq. 3 in W, about the CoM: GroundWrenchW, the corrector's
// model) by each calibration: "t_s,variant,<LEG>_fx_n,...,<LEG>_tz_nm for the six legs,
// total_fx_n,...,total_tz_nm". Variants: "full calibration" (run.calibration), "naive tare"
// (the step-1 naive offsets, no leg gravity, nominal mounting) and "truth" when `truth` is
// given. Samples without a tracked attitude are left out (the corrector would assume level and
// flag them); one sample per `period_s` is kept (the figure's resolution, not the data's).
// Throws std::invalid_argument when `samples` is empty.
std::string WalkingCsv(const std::vector<SyncSample>& samples, const CalibrationRun& run,
                       const RobotCalibration* truth, double period_s = 0.04);
// cal.pbtxt -> cal.walking.csv.
std::string WalkingPathFor(const std::string& calibration_path);

}  // namespace ftcal
