// CalibrationCollector: the phases, each started and ended by a step of its own (collector.h).
// A phase's start resets its counts and readies what it keeps; its end hands over what it kept
// when its stop marker came, and drops it otherwise.
#include "session/collector.h"

#include "ftcal/hanging.h"

namespace ftcal {

void CalibrationCollector::StartPhase(const MarkedPhase& phase, const experiment_marker_t& msg) {
  current_gaps_ = PhaseGaps();
  current_gaps_.phase = phase.code;
  current_gaps_.session = phase.session;
  last_sequence_.fill(0);
  bool announce = true;
  if (IsHangPhase(phase.code)) {
    announce = StartHanging(phase, msg);
  } else if (phase.code == experiment_marker_t::STANDING) {
    announce = StartStanding(phase);
  } else if (phase.code == experiment_marker_t::TARE) {
    StartTare();
  } else if (phase.code == experiment_marker_t::TRIPOD) {
    announce = StartTripod(phase);
  } else if (phase.code == experiment_marker_t::WALKING) {
    StartWalking();
  }
  if (announce) {
    log_->info("EXPERIMENT: {} started (session '{}')", PhaseName(phase.code), phase.session);
  }
}

bool CalibrationCollector::StartHanging(const MarkedPhase& phase, const experiment_marker_t& msg) {
  hang_memory_.Wait();  // before the room it touches is freed
  current_hang_ = HangingRecording();
  current_hang_.series = *HangSeriesOfPhase(phase.code);
  hang_start_utime_ = msg.utime;
  current_hang_.gravity_b = Vec3(msg.gravity_b[0], msg.gravity_b[1], msg.gravity_b[2]);
  if (index_only_) return false;  // nothing kept: no room
  ReserveHangingRoom();
  return true;
}

// The series of one experiment are alike in length (the plan's cycles at one speed): room for
// the longest so far, a little more, saves growing each vector by copies, and is faulted in on
// another thread while this one reads. Before the first series, room for a guess (the report's
// scale), faulted in the same way: what the series does not fill stays resident, and the series
// is read a little faster (docs/performance.md).
void CalibrationCollector::ReserveHangingRoom() {
  size_t expected = 0;
  for (int s = 0; s < kNumHangSeries; ++s) {
    if (have_hang_[s]) expected = std::max(expected, hang_[s].legs[0].t_s.size());
  }
  const bool known = expected > 0;
  expected = known ? expected + expected / 16 : kFirstHangReserve;
  for (LegSamples& leg : current_hang_.legs) {
    hang_memory_.Reserve(leg.t_s, expected);
    hang_memory_.Reserve(leg.angle_rad, expected);
    hang_memory_.Reserve(leg.wrench, expected);
  }
  hang_memory_.Reserve(current_hang_.attitude, expected);
  hang_memory_.FaultInAhead();
}

bool CalibrationCollector::StartStanding(const MarkedPhase& phase) {
  current_poses_.clear();
  const auto logged = logged_sessions_scatter_.find(phase.session);
  if (index_only_ ||
      (skip_logged_sessions_ && logged != logged_sessions_scatter_.end() && logged->second)) {
    counting_only_ = true;
    if (!index_only_) {
      log_->info(
          "EXPERIMENT: STANDING started (session '{}'); its STEADY_POSE events, read before, "
          "carry their within-pose scatter: not segmented again",
          phase.session);
    }
    if (on_inputs_ready_) on_inputs_ready_();
    StartSpanNoting(phase);
    return false;
  }
  segmenter_ = std::make_unique<PoseSegmenter>(segmenter_options_, [this](const SteadyPoseOut& p) {
    if (!p.markers_ok) return;
    current_poses_.push_back(p.pose);
    ++counters_.segmented_poses;
  });
  return true;
}

void CalibrationCollector::StartTare() {
  for (Vec6& w : tare_sum_) w.setZero();
  tare_count_ = 0;
}

bool CalibrationCollector::StartTripod(const MarkedPhase& phase) {
  if (!collect_tripod_stances_) {
    counting_only_ = true;
    log_->info(
        "EXPERIMENT: TRIPOD started (session '{}'); its stances serve only offset "
        "re-estimation: records counted, not segmented",
        phase.session);
    StartSpanNoting(phase);
    return false;
  }
  current_unloaded_.clear();
  segmenter_ = std::make_unique<PoseSegmenter>(
      segmenter_options_, [this](const SteadyPoseOut& p) { OnTripodStance(p); });
  return true;
}

void CalibrationCollector::StartWalking() {
  // Room for all it may keep: grown by copies, the kept samples were copied about twice.
  // Address space only until written.
  if (walking_.empty() && !index_only_) current_walk_.reserve(kMaxWalkingSamples);
}

// A phase read only for its counts: its span noted for the index (replay), and the first span
// of an index given skipped.
void CalibrationCollector::StartSpanNoting(const MarkedPhase& phase) {
  noting_ = SpanNoting();
  noting_.active = event_end_ >= 0;  // replay
  ArmSkip(phase.session, phase.code);
}

void CalibrationCollector::EndPhase(const MarkedPhase& phase, bool completed) {
  const bool not_segmented = counting_only_;
  EndCountingOnly(phase, completed);
  // A STANDING or TRIPOD phase's segmenter hands over the pose in progress first.
  const SegmenterCounters segmented = EndSegmenting();
  if (completed) phase_gaps_.push_back(current_gaps_);
  if (IsHangPhase(phase.code)) {
    EndHanging(completed);
  } else if (phase.code == experiment_marker_t::STANDING) {
    EndStanding(phase, completed, not_segmented);
  } else if (phase.code == experiment_marker_t::TARE) {
    EndTare(phase, completed);
  } else if (phase.code == experiment_marker_t::TRIPOD) {
    EndTripod(phase, completed, not_segmented, segmented);
  } else if (phase.code == experiment_marker_t::WALKING) {
    EndWalking(phase, completed);
  }
}

// The span of a phase read only for its counts goes into the index when its stop marker came;
// the servo states and mocap frames kept go to the aligner.
void CalibrationCollector::EndCountingOnly(const MarkedPhase& phase, bool completed) {
  if (noting_.active) {
    if (completed && counting_only_ &&
        (phase.code == experiment_marker_t::STANDING ||
         phase.code == experiment_marker_t::TRIPOD)) {
      EndSpanNoting(phase.session, phase.code);
    }
    noting_.active = false;
  }
  counting_only_ = false;
  FlushDeferred();
}

SegmenterCounters CalibrationCollector::EndSegmenting() {
  SegmenterCounters segmented;
  if (segmenter_) {
    segmenter_->Flush();
    segmented = segmenter_->counters();
    segmenter_.reset();
  }
  return segmented;
}

void CalibrationCollector::EndHanging(bool completed) {
  hang_memory_.Wait();  // the series' buffers are kept or freed below
  if (completed) {
    const int s = static_cast<int>(current_hang_.series);
    if (hang_gaps_index_[s] >= 0) phase_gaps_[hang_gaps_index_[s]].superseded = true;
    hang_gaps_index_[s] = static_cast<int>(phase_gaps_.size()) - 1;
    if (have_hang_[s]) {
      log_->warn("{} recorded again: the later recording replaces the earlier one",
                 HangSeriesName(current_hang_.series));
    }
    log_->info("{} complete: {} samples per leg, {} attitude samples",
               HangSeriesName(current_hang_.series), current_hang_.legs[0].t_s.size(),
               current_hang_.attitude.size());
    BeforeInputsChange();
    hang_[s] = std::move(current_hang_);
    have_hang_[s] = true;
  }
  current_hang_ = HangingRecording();
}

void CalibrationCollector::EndStanding(const MarkedPhase& phase, bool completed,
                                       bool not_segmented) {
  if (completed) {
    if (not_segmented) {
      log_->info("STANDING complete (session '{}')", phase.session);
    } else {
      log_->info("STANDING complete (session '{}'): {} steady poses segmented", phase.session,
                 current_poses_.size());
    }
    if (!current_poses_.empty()) BeforeInputsChange();
    segmented_poses_.insert(segmented_poses_.end(), current_poses_.begin(), current_poses_.end());
    standing_session_ = phase.session;
  }
  current_poses_.clear();
}

void CalibrationCollector::EndTare(const MarkedPhase& phase, bool completed) {
  if (completed && tare_count_ > 0) {
    std::array<Vec6, kNumLegs> mean;
    for (int k = 0; k < kNumLegs; ++k) mean[k] = tare_sum_[k] / static_cast<double>(tare_count_);
    BeforeInputsChange();
    tare_ = mean;
    log_->info("TARE complete (session '{}'): naive tare from {} samples", phase.session,
               tare_count_);
  }
}

void CalibrationCollector::EndTripod(const MarkedPhase& phase, bool completed, bool not_segmented,
                                     const SegmenterCounters& segmented) {
  if (completed && not_segmented) {
    log_->info("TRIPOD complete (session '{}'): not segmented", phase.session);
  } else if (completed) {
    log_->info(
        "TRIPOD complete (session '{}'): {} steady stances with a leg lifted; left "
        "out: {} steady runs shorter than {} s, {} with a marker untracked, {} (so far) "
        "with no leg lifted",
        phase.session, current_unloaded_.size(), segmented.dropped_short,
        segmenter_options_.min_steady_s, segmented.dropped_markers,
        counters_.tripod_stances_dropped);
    unloaded_.insert(unloaded_.end(), current_unloaded_.begin(), current_unloaded_.end());
  }
  current_unloaded_.clear();
}

void CalibrationCollector::EndWalking(const MarkedPhase& phase, bool completed) {
  if (completed && walking_.empty() && !current_walk_.empty()) {
    log_->info("WALKING complete (session '{}'): {} aligned samples kept for the report",
               phase.session, current_walk_.size());
    walking_ = std::move(current_walk_);
  }
  current_walk_.clear();
}

}  // namespace ftcal
