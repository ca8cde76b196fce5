// ftcal-pose-segmenter's work, transport-agnostic through the Bus: FT_<LEG>, SERVO_STATE and
// MOCAP_BODY go through the Aligner into SYNC_SAMPLE (every aligned sample); while the
// EXPERIMENT phase is STANDING (between its start and stop markers) the aligned samples also
// go through the PoseSegmenter and every steady pose is published on STEADY_POSE with the
// session id and a running pose index.
//
// The markers follow libcal's PhaseTracker rules (ftcal/experiment_phase.h), as the
// calibrator's do. When STANDING closes (its stop marker, or a start of another phase) the run
// in progress becomes a pose when long enough. A repeated STANDING start of the session already
// running changes nothing, so a sequencer that repeats its marker lets a restarted segmenter
// resume: a restart then loses only the pose in progress (the derivative window refills in
// savgol_window samples).
#pragma once

#include <memory>
#include <string>

#include "common/bus.h"
#include "common/messages.h"
#include "ftcal/aligner.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/experiment_phase.h"
#include "ftcal/segmenter.h"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "proto/config.pb.h"

namespace ftcal {

class PoseSegmenterStage {
 public:
  // Subscribes its handlers on `bus`. Throws std::invalid_argument for a config it cannot use.
  // publish_sync = false: SYNC_SAMPLE is counted but not encoded or published (a replay that
  // writes only the poses log).
  // servo_delay_s: the servo stream's delay a calibration applies (latencies.applied_servo_delay_s,
  // docs/method.md "Latencies"); servo stamps are moved back by it before alignment.
  PoseSegmenterStage(const config::Config& config, Bus& bus, bool publish_sync = true,
                     double servo_delay_s = 0.0);

  int64_t poses_published() const { return poses_published_; }
  const AlignerCounters& aligner_counters() const { return aligner_.counters(); }

 private:
  void OnFt(const FtBatch& batch);
  void OnServo(const ServoInput& in);
  void OnMocap(const MocapInput& in);
  void OnExperiment(const experiment_marker_t& msg);
  void OnAligned(const AlignedSample& s);
  void OnPose(const SteadyPoseOut& pose);
  // Counts an input the aligner refused, by reason, from the change of its counters.
  void CountAlignerDrop(const std::string& stream, const AlignerCounters& before);
  void PublishCounters();

  const config::Config& config_;
  // EXPERIMENT is a signed channel (common/envelope.h).
  auth::Verifier verifier_ = auth::Verifier::FromConfig(config_);
  Bus& bus_;
  const bool publish_sync_;
  DeviceInputs inputs_;
  SegmenterOptions segmenter_options_;
  Aligner aligner_;
  PhaseTracker phases_;
  std::unique_ptr<PoseSegmenter> segmenter_;  // while standing
  std::string session_id_;
  int32_t pose_index_ = 0;
  int64_t poses_published_ = 0;
  int64_t sync_aligned_ = 0;            // aligned samples, published or not (publish_sync_)
  SegmenterCounters segmenter_totals_;  // of the segmenters of earlier phases
  sync_sample_t sync_msg_;              // reused: no allocation per sample
  // The status counters (ServiceStats' map entries: their addresses are stable), updated on
  // every input without a lookup.
  struct Counters {
    int64_t *sync_samples, *standing_samples, *poses, *drop_out_of_order, *drop_non_finite,
        *drop_stale_servo, *servo_held, *attitude_not_ok, *pose_dropped_short,
        *pose_dropped_markers, *window_resets;
  } counters_{};
};

}  // namespace ftcal
