#include "pose_segmenter/pose_segmenter_stage.h"

#include <stdexcept>

namespace ftcal {

SegmenterOptions SegmenterOptionsFromConfig(const config::Segmenter& s) {
  SegmenterOptions o;
  o.sample_rate_hz = s.sample_rate_hz();
  o.savgol_window = static_cast<int>(s.savgol_window());
  o.savgol_order = static_cast<int>(s.savgol_order());
  o.max_force_rate_n_s = s.max_force_rate_n_s();
  o.min_steady_s = s.min_steady_s();
  o.require_all_markers = s.require_all_markers();
  return o;
}

AlignerOptions AlignerOptionsFromConfig(const config::Config& config) {
  AlignerOptions o;
  o.max_servo_age_s = config.corrector().max_servo_age_s();
  o.max_mocap_age_s = config.corrector().max_mocap_age_s();
  return o;
}

PoseSegmenterStage::PoseSegmenterStage(const config::Config& config, Bus& bus)
    : config_(config),
      bus_(bus),
      inputs_(config),
      segmenter_options_(SegmenterOptionsFromConfig(config.segmenter())),
      aligner_(AlignerOptionsFromConfig(config),
               [this](const AlignedSample& s) { OnAligned(s); }) {
  ServiceStats& st = bus.stats();
  counters_ = {&st.Counter("sync_samples"),      &st.Counter("standing_samples"),
               &st.Counter("poses"),             &st.Counter("drop_out_of_order"),
               &st.Counter("drop_non_finite"),   &st.Counter("drop_stale_servo"),
               &st.Counter("servo_held"),        &st.Counter("attitude_not_ok"),
               &st.Counter("pose_dropped_short"), &st.Counter("pose_dropped_markers"),
               &st.Counter("window_resets")};
  // Fail at start, not at the first STANDING marker, on options the segmenter refuses.
  PoseSegmenter check(segmenter_options_, nullptr);

  sync_msg_.num_legs = kNumLegs;
  sync_msg_.leg.assign(kLegNames.begin(), kLegNames.end());
  sync_msg_.wrench.assign(kNumLegs, std::vector<double>(6));
  sync_msg_.angle_rad.assign(kNumLegs, 0.0);

  const auto& ch = config.channels();
  for (int k = 0; k < kNumLegs; ++k) {
    bus.Subscribe<ft_sample_t>(inputs_.FtChannel(k),
                               [this, k](const MessageInfo&, const ft_sample_t& m) { OnFt(k, m); });
  }
  bus.Subscribe<servo_state_t>(ch.servo_state(),
                               [this](const MessageInfo&, const servo_state_t& m) { OnServo(m); });
  bus.Subscribe<mocap_body_t>(ch.mocap_body(),
                              [this](const MessageInfo&, const mocap_body_t& m) { OnMocap(m); });
  // No time window: markers replayed from a recording (lcm-logplayer) are old by design; the
  // signature and the rising sequence still hold.
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, /*window_us=*/0, config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const experiment_marker_t& m) { OnExperiment(m); });
  PublishCounters();
}

void PoseSegmenterStage::CountAlignerDrop(const std::string& stream, const AlignerCounters& before) {
  const AlignerCounters& now = aligner_.counters();
  if (now.non_finite > before.non_finite) {
    bus_.stats().Drop("non-finite " + stream, "NaN or inf in the message's numbers");
  } else if (now.out_of_order > before.out_of_order) {
    bus_.stats().Drop("out-of-order " + stream, "utime not newer than the previous one");
  }
}

void PoseSegmenterStage::OnFt(int leg, const ft_sample_t& msg) {
  const AlignerCounters before = aligner_.counters();
  if (!aligner_.AddFt(inputs_.FromFt(leg, msg))) CountAlignerDrop(inputs_.FtChannel(leg), before);
  PublishCounters();
}

void PoseSegmenterStage::OnServo(const servo_state_t& msg) {
  const AlignerCounters before = aligner_.counters();
  if (!aligner_.AddServo(inputs_.FromServo(msg))) CountAlignerDrop(config_.channels().servo_state(), before);
  PublishCounters();
}

void PoseSegmenterStage::OnMocap(const mocap_body_t& msg) {
  const auto in = inputs_.FromMocap(msg);
  if (!in) return;  // another rigid body
  const AlignerCounters before = aligner_.counters();
  if (!aligner_.AddMocap(*in)) CountAlignerDrop(config_.channels().mocap_body(), before);
  PublishCounters();
}

void PoseSegmenterStage::OnExperiment(const experiment_marker_t& msg) {
  const bool standing_start = msg.phase == experiment_marker_t::STANDING && msg.start;
  if (standing_start && segmenter_ && msg.session_id == session_id_) return;  // repeated
  if (segmenter_) {
    segmenter_->Flush();  // the run in progress becomes a pose when long enough
    const SegmenterCounters& c = segmenter_->counters();
    segmenter_totals_.samples += c.samples;
    segmenter_totals_.dropped_short += c.dropped_short;
    segmenter_totals_.dropped_markers += c.dropped_markers;
    segmenter_totals_.window_resets += c.window_resets;
    segmenter_.reset();
  }
  if (standing_start) {
    if (msg.session_id != session_id_) pose_index_ = 0;
    session_id_ = msg.session_id;
    segmenter_ = std::make_unique<PoseSegmenter>(
        segmenter_options_, [this](const SteadyPoseOut& p) { OnPose(p); });
  }
  PublishCounters();
}

void PoseSegmenterStage::OnAligned(const AlignedSample& a) {
  const SyncSample& s = a.sample;
  sync_msg_.utime = s.utime;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) sync_msg_.wrench[k][i] = s.wrench[k][i];
    sync_msg_.angle_rad[k] = s.angle_rad[k];
  }
  RotationToQuaternionArray(s.R_WC, sync_msg_.q_wc);
  sync_msg_.attitude_ok = s.attitude_ok;
  sync_msg_.markers_ok = s.markers_ok;
  sync_msg_.flags = a.flags;
  bus_.Publish(config_.channels().sync_sample(), sync_msg_);
  ++sync_published_;
  if (segmenter_) segmenter_->Add(s);
}

void PoseSegmenterStage::OnPose(const SteadyPoseOut& p) {
  steady_pose_t msg;
  msg.utime = bus_.NowUtime();
  msg.session_id = session_id_;
  msg.pose_index = pose_index_++;
  msg.start_utime = p.start_utime;
  msg.end_utime = p.end_utime;
  msg.num_samples = p.num_samples;
  msg.num_legs = kNumLegs;
  msg.leg.assign(kLegNames.begin(), kLegNames.end());
  msg.wrench.assign(kNumLegs, std::vector<double>(6));
  msg.angle_rad.assign(kNumLegs, 0.0);
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) msg.wrench[k][i] = p.pose.wrench[k][i];
    msg.angle_rad[k] = p.pose.angle_rad[k];
  }
  RotationToQuaternionArray(p.pose.R_WC, msg.q_wc);
  msg.markers_ok = p.markers_ok;
  bus_.Publish(config_.channels().steady_pose(), msg);
  ++poses_published_;
}

void PoseSegmenterStage::PublishCounters() {
  const AlignerCounters& a = aligner_.counters();
  SegmenterCounters s = segmenter_totals_;
  if (segmenter_) {
    const SegmenterCounters& c = segmenter_->counters();
    s.samples += c.samples;
    s.dropped_short += c.dropped_short;
    s.dropped_markers += c.dropped_markers;
    s.window_resets += c.window_resets;
  }
  Counters& o = counters_;
  *o.sync_samples = sync_published_;
  *o.standing_samples = s.samples;
  *o.poses = poses_published_;
  *o.drop_out_of_order = a.out_of_order;
  *o.drop_non_finite = a.non_finite;
  *o.drop_stale_servo = a.stale_servo;
  *o.servo_held = a.servo_held;
  *o.attitude_not_ok = a.stale_mocap;
  *o.pose_dropped_short = s.dropped_short;
  *o.pose_dropped_markers = s.dropped_markers;
  *o.window_resets = s.window_resets;
}

}  // namespace ftcal
