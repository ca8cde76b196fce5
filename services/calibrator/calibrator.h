// ftcal-calibrator's work, offline from a recording (--log) or live on the bus: the experiment
// in, the calibration file out (and, with --reestimate-offsets, offsets re-estimated on a base).
// The collector (session/collector.h) gathers the data from the bus; this file checks it and
// calibrates; outputs.h writes what goes beside the calibration.
//
// RunCalibration() checks what was collected (every series, markers present, the config's legs
// are the log's FT_* channels, no damaged bytes), runs Calibrate() and fills provenance. Every
// refusal is a CalibratorInputError naming what is wrong; main() turns it into exit code 2.
#pragma once

#include <functional>
#include <future>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "calibrator/outputs.h"
#include "ftcal/calibrate.h"
#include "ftcal/offset_reestimation.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"
#include "session/collector.h"

namespace ftcal {

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

// Offline: Calibrate() started on a thread of its own as soon as what it takes is in (the four
// hanging series, the poses of a poses log read before the session, the tare), that is when
// the session's STANDING phase starts and is not segmented again; the rest of the session (its
// STANDING span, the tripods, the walk: two fifths of the reading) is then read beside the
// solves. A change to those inputs afterwards (a series recorded again, more poses, a later
// tare) waits for the early run and discards it: RunCalibration() then calibrates with what
// was collected, as without this. Construct before reading; it outlives nothing it refers to.
class EarlyCalibration {
 public:
  EarlyCalibration(CalibrationCollector& collector, const config::Config& config,
                   const CalibratorOptions& options);
  ~EarlyCalibration();
  EarlyCalibration(const EarlyCalibration&) = delete;
  EarlyCalibration& operator=(const EarlyCalibration&) = delete;
  // The early run's result when its inputs are still the collector's and it succeeded; nullopt
  // otherwise (never started, discarded, or refused: the caller's own run says why).
  std::optional<CalibrationRun> Take();
  bool started() const { return started_; }

 private:
  void Start();
  void Discard();

  CalibrationCollector& collector_;
  const config::Config& config_;
  const CalibratorOptions& options_;
  std::future<CalibrationRun> job_;
  bool started_ = false;
  bool valid_ = false;
};

// Checks the collected data, runs Calibrate() (or takes `early`'s result, the same) and fills
// provenance. Throws CalibratorInputError.
CalibrationRun RunCalibration(const CalibrationCollector& collector, const config::Config& config,
                              const CalibratorOptions& options, EarlyCalibration* early = nullptr);

// Live mode: collects on `bus`; when a STANDING phase stops, calibrates from everything
// collected so far, writes the calibration (and its residuals CSV) atomically, publishes
// CALIBRATION (calibration_t: version counting up from the out file's, or 1, SHA-256 of the bytes,
// the binary proto) and calls on_calibrated. A refused calibration is logged and counted; the
// collector keeps listening (a later STANDING phase may complete it).
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
  // Calibrations made by this process.
  int64_t made() const { return made_; }
  // EXPERIMENT markers taken (verified and fresh).
  int64_t markers() const { return collector_.counters().markers; }
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
  // The last version published: at start, the one in the out file (versions rise across
  // restarts: a corrector refuses a version it has passed).
  int64_t version_ = 0;
  int64_t made_ = 0;
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

// The software version recorded in provenance: PROJECT_VERSION (+ git describe at build time).
std::string SoftwareVersion();

}  // namespace ftcal
