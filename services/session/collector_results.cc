// CalibrationCollector: what the phases keep, and what it hands over once the session is read
// (collector.h).
#include "session/collector.h"

#include <cmath>

#include "ftcal/hanging.h"

namespace ftcal {

void CalibrationCollector::OnSteadyPose(const steady_pose_t& msg) {
  ++counters_.logged_poses;
  SteadyPoseHeader header;
  const SteadyPoseOut p = FromLcm(msg, &header);
  const auto session = logged_sessions_scatter_.emplace(header.session_id, true).first;
  session->second = session->second && p.pose.samples > 0;
  if (!p.markers_ok) {
    ++counters_.poses_dropped_markers;
    return;
  }
  BeforeInputsChange();
  // Room for a report-scale experiment's poses at once (address space until written), not
  // grown by copies that move and fault in every pose read so far.
  if (logged_poses_.capacity() == 0) logged_poses_.reserve(1024);
  logged_poses_.push_back(p.pose);
  if (on_steady_pose_) on_steady_pose_();
}

void CalibrationCollector::OnAligned(const AlignedSample& a) {
  ++counters_.aligned_samples;
  if (index_only_) return;
  const SyncSample& s = a.sample;
  const int phase = phases_.current().code;
  if (IsHangPhase(phase)) {
    if (s.utime < hang_start_utime_) {
      ++counters_.hanging_before_start;
      return;
    }
    ++counters_.hanging_samples;
    const double t_s = 1e-6 * static_cast<double>(s.utime);
    for (int k = 0; k < kNumLegs; ++k) {
      LegSamples& leg = current_hang_.legs[k];
      leg.t_s.push_back(t_s);
      leg.angle_rad.push_back(s.angle_rad[k]);
      leg.wrench.push_back(s.wrench[k]);
    }
    if (s.attitude_ok) current_hang_.attitude.push_back(s.R_WC);
  } else if (phase == experiment_marker_t::STANDING && segmenter_) {
    ++counters_.standing_samples;
    segmenter_->Add(s);
  } else if (phase == experiment_marker_t::TRIPOD && segmenter_) {
    ++counters_.tripod_samples;
    segmenter_->Add(s);
  } else if (phase == experiment_marker_t::TARE) {
    for (int k = 0; k < kNumLegs; ++k) tare_sum_[k] += s.wrench[k];
    ++tare_count_;
  } else if (phase == experiment_marker_t::WALKING) {
    ++counters_.walking_samples;
    if (walking_.empty() && current_walk_.size() < kMaxWalkingSamples) current_walk_.push_back(s);
  }
}

// The shaft angle, not the reading, says which legs are off the ground: the reading is what
// the offsets are being re-estimated from, and a drifted offset can be as large as a light load.
void CalibrationCollector::OnTripodStance(const SteadyPoseOut& p) {
  const double min_rad = config_.calibrator().unloaded_leg_min_angle_deg() * M_PI / 180.0;
  LoadSample sample;
  sample.wrench = p.pose.wrench;
  sample.angle_rad = p.pose.angle_rad;
  sample.R_WC = p.pose.R_WC;
  bool any = false;
  for (int k = 0; k < kNumLegs; ++k) {
    sample.unloaded[k] = std::abs(std::remainder(p.pose.angle_rad[k], 2.0 * M_PI)) > min_rad;
    any = any || sample.unloaded[k];
  }
  if (!p.markers_ok || !any) {
    ++counters_.tripod_stances_dropped;
    return;
  }
  ++counters_.tripod_stances;
  current_unloaded_.push_back(sample);
}

const std::vector<HangingRecording>& CalibrationCollector::HangingRecordings() const {
  std::string missing;
  for (int s = 0; s < kNumHangSeries; ++s) {
    if (!have_hang_[s]) {
      missing += (missing.empty() ? "" : ", ") + HangSeriesName(static_cast<HangSeries>(s));
    }
  }
  if (!missing.empty()) {
    throw CalibratorInputError("missing hanging series: " + missing +
                               " (no EXPERIMENT start..stop marker pair with samples)");
  }
  for (const HangingRecording& r : hang_) {
    if (r.legs[0].t_s.empty()) {
      throw CalibratorInputError("hanging series " + HangSeriesName(r.series) +
                                 " has markers but no aligned samples (FT_*/SERVO_STATE "
                                 "missing in that span)");
    }
  }
  return hang_;
}

std::vector<StandingPose> CalibrationCollector::StandingPoses() const {
  // Poses a segmenter already published are what the operator saw; when the log has none, the
  // same segmenter logic over the STANDING spans gives them.
  if (logged_poses_.empty()) return segmented_poses_;
  // A STEADY_POSE message carries its within-pose scatter (the noise floor, docs/method.md).
  // One that does not (a publisher that computed none) takes it from this collector's own
  // segmentation of the same span, matched by time (the same logic on the same samples finds
  // the same runs) and shaft angles.
  std::vector<StandingPose> out = logged_poses_;
  if (segmented_poses_.empty()) return out;
  std::vector<const StandingPose*> by_time;
  for (const StandingPose& p : segmented_poses_) by_time.push_back(&p);
  std::sort(by_time.begin(), by_time.end(),
            [](const StandingPose* a, const StandingPose* b) { return a->t_s < b->t_s; });
  for (StandingPose& pose : out) {
    if (pose.samples > 0) continue;
    auto it = std::lower_bound(by_time.begin(), by_time.end(), pose.t_s,
                               [](const StandingPose* p, double t) { return p->t_s < t; });
    for (auto c : {it, it == by_time.begin() ? it : it - 1}) {
      if (c == by_time.end()) continue;
      const StandingPose& seg = **c;
      bool same = std::abs(seg.t_s - pose.t_s) < 0.5;
      for (int k = 0; k < kNumLegs && same; ++k) {
        same = std::abs(seg.angle_rad[k] - pose.angle_rad[k]) < 1e-3;
      }
      if (!same) continue;
      pose.samples = seg.samples;
      pose.wrench_sem = seg.wrench_sem;
      pose.attitude_sem_rad = seg.attitude_sem_rad;
      break;
    }
  }
  return out;
}

void CalibrationCollector::CheckMarkersAndLegs(const std::string& phases) const {
  const std::string& channel = config_.channels().experiment();
  const int64_t refused = unsigned_markers_ + verifier_.unsigned_seen();
  if (counters_.markers == 0 && refused > 0 && !config_.auth().allow_unsigned()) {
    throw CalibratorInputError(
        "no EXPERIMENT markers accepted: " + std::to_string(refused) + " on channel '" + channel +
        "' were refused as unsigned, and the config requires them signed (auth.allow_unsigned "
        "is false). Record them from a sequencer run with --signing-key whose public key is an "
        "auth.trusted_key for '" +
        channel +
        "', or, for an unsigned recording you trust (the loopback twin's), set auth { "
        "allow_unsigned: true } in the config. Without markers the calibrator cannot tell " +
        phases);
  }
  if (counters_.markers == 0) {
    throw CalibratorInputError("no EXPERIMENT markers (channel '" + channel +
                               "') in the input: cannot tell " + phases);
  }
  std::string unknown, silent;
  std::set<std::string> expected;
  for (int k = 0; k < kNumLegs; ++k) expected.insert(inputs_.FtChannel(k));
  for (const std::string& c : ft_channels_seen_) {
    if (!expected.count(c)) unknown += (unknown.empty() ? "" : ", ") + c;
  }
  for (const std::string& c : expected) {
    if (!ft_channels_seen_.count(c)) silent += (silent.empty() ? "" : ", ") + c;
  }
  if (!unknown.empty() || !silent.empty()) {
    std::string msg = "the config's legs do not match the log's FT channels:";
    if (!unknown.empty()) msg += " channels for legs the config does not have: " + unknown + ";";
    if (!silent.empty()) msg += " config legs with no channel in the log: " + silent + ";";
    std::string all;
    for (const std::string& c : channels_seen_) all += (all.empty() ? "" : ", ") + c;
    msg += " the log's channels: " + (all.empty() ? std::string("none") : all);
    throw CalibratorInputError(msg);
  }
}

}  // namespace ftcal
