// ftcal-drift's work, transport-agnostic through the Bus (docs/method.md, "Offset drift while the
// robot works"): FT_<LEG>, SERVO_STATE and MOCAP_BODY into libcal's OffsetTracker, which tracks
// each leg's offset change from the windows where that leg is in the air and quasi-static, and
// once every drift.publish_period_s of bus time a DRIFT message (drift_t): per leg the change
// +- sigma, the windows used, and the balance of the six corrected wrenches with and without the
// tracked offsets. EXPERIMENT tells it when the robot hangs (no balance then).
//
// Calibration: from --calibration FILE at start and/or a CALIBRATION message (signed, fresh, a
// version above the last one used, as the corrector takes it). A new calibration restarts the
// tracking relative to it: the changes are always the offsets' since the calibration in use.
// Until one is in use DRIFT says NO_CALIBRATION and the state is DEGRADED.
//
// --apply (EnableApply): at each DRIFT, the legs with a significant change (LegsToApply:
// beyond drift.apply_factor x the tracker's sigma and beyond the calibration's own sigma, at
// most once per drift.apply_min_interval_s of the inputs' time) get their tracked offsets in a
// new calibration, version + 1 (and above any this stage published before), checked and put in
// use here (the tracking restarts relative to it, as for any new calibration), then published
// on CALIBRATION (signed with the stage's key, the calibrator's publishing path,
// common/calibration_publish.h). Its offset_reestimation and a warning name the windows each
// applied leg's offsets come from.
//
// WARN: a component whose tracked change is beyond drift.warn_factor x the calibration's own
// sigma of that offset (DriftBeyondCalibration) sets DRIFT's status WARN and its warn_mask, the
// service state DEGRADED with the components in last_error, and logs once per change of the set.
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "common/bus.h"
#include "common/envelope.h"
#include "common/messages.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/drift_t.hpp"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/offset_tracker.h"
#include "ftcal/service_status_t.hpp"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

OffsetTrackerOptions OffsetTrackerOptionsFromConfig(const config::Config& config);

// The calibration's own 1-sigma of each leg's offsets [fx fy fz tx ty tz] (0 where it has none).
std::array<Vec6, kNumLegs> OffsetSigmas(const calibration::Calibration& proto);

class DriftStage {
 public:
  using StateSink = std::function<void(int8_t service_state)>;
  DriftStage(const config::Config& config, Bus& bus, StateSink set_state);

  // Validates and adopts a calibration (throws std::runtime_error with the reason; nothing
  // changes then). `sha256` identifies it: a repeat changes nothing.
  void UseCalibration(const calibration::Calibration& proto, int64_t version,
                      const std::string& sha256);
  bool has_calibration() const { return tracker_ != nullptr; }
  // Says in the status why nothing is tracked yet; called once the start-up calibration, if
  // any, is in use.
  void ReportWaitingForCalibration();

  // --apply: publish a calibration with the significant tracked offsets (signed by `signer`
  // when not null; it must outlive the stage). Off unless called.
  void EnableApply(auth::Signer* signer);
  // Calibrations published by --apply.
  int64_t applied() const { return applied_; }

  // Publishes DRIFT now (the periodic work), and with --apply a calibration when one is due.
  void PublishDrift();
  // The input ended: the open windows are judged, and a last DRIFT goes out.
  void Finish();

  // The calibration in use with the tracked offsets (what --out-calibration writes): offsets
  // and their sigmas replaced for every leg that had a window, version + 1, the provenance of
  // the tracking in offset_reestimation. Throws std::logic_error without a calibration.
  calibration::Calibration TrackedCalibrationProto(const std::string& base_path,
                                                   const std::vector<std::string>& inputs,
                                                   const std::string& command_line) const;
  // The DRIFT series published so far, as CSV (one row per message and leg).
  const std::string& csv() const { return csv_; }
  const drift_t& last() const { return msg_; }
  int64_t published() const { return published_; }

 private:
  void OnFt(const FtBatch& batch);
  void OnServo(const ServoInput& in);
  void OnMocap(const MocapInput& in);
  void OnExperiment(const experiment_marker_t& msg);
  void OnCalibration(const MessageInfo& info, const calibration_t& msg);
  void UpdateCounters();
  // The calibration in use with leg k's offsets (and sigmas) replaced by the tracked ones for
  // every leg with bit k in `legs`; the rest as they are. Returns the windows used.
  int64_t WithTrackedOffsets(int legs, int64_t utime, calibration::Calibration* out) const;
  void Apply(int legs, const std::array<LegDrift, kNumLegs>& drift);

  const config::Config& config_;
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  Bus& bus_;
  StateSink set_state_;
  DeviceInputs inputs_;
  OffsetTrackerOptions options_;
  std::unique_ptr<OffsetTracker> tracker_;
  calibration::Calibration proto_;
  std::array<Vec6, kNumLegs> calibration_sigma_{};
  int64_t version_ = 0;
  std::string sha256_;
  std::map<std::string, int64_t> last_version_;  // per signer
  std::string warned_;                           // the warn masks last logged ("": none beyond)
  drift_t msg_{};
  std::string csv_;
  int64_t published_ = 0, calibrations_ = 0, refused_ = 0;
  ExperimentPhase phase_ = ExperimentPhase::kIdle;  // carried into a new tracker
  bool apply_ = false;
  auth::Signer* signer_ = nullptr;
  DriftApplyPolicy apply_policy_;
  int64_t last_apply_utime_ = 0, applied_ = 0, last_applied_version_ = 0;
  struct Counters {
    int64_t *windows, *bins_air, *bins_loaded, *bins_moving, *bins_no_servo, *bins_no_attitude,
        *warn, *version, *applied;
  } counters_{};
};

}  // namespace ftcal
