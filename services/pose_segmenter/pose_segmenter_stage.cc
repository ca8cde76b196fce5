#include "pose_segmenter/pose_segmenter_stage.h"

#include <stdexcept>

namespace ftcal {

namespace {

AlignerOptions WithServoDelay(AlignerOptions o, double servo_delay_s) {
  o.servo_delay_s = servo_delay_s;
  return o;
}

}  // namespace

PoseSegmenterStage::PoseSegmenterStage(const config::Config& config, Bus& bus, bool publish_sync,
                                       double servo_delay_s)
    : config_(config),
      bus_(bus),
      publish_sync_(publish_sync),
      inputs_(config),
      segmenter_options_(SegmenterOptionsFromConfig(config.segmenter())),
      aligner_(WithServoDelay(AlignerOptionsFromConfig(config), servo_delay_s),
               [this](const AlignedSample& s) { OnAligned(s); }) {
  ServiceStats& st = bus.stats();
  counters_ = {&st.Counter("sync_samples"),
               &st.Counter("standing_samples"),
               &st.Counter("poses"),
               &st.Counter("drop_out_of_order"),
               &st.Counter("drop_non_finite"),
               &st.Counter("drop_stale_servo"),
               &st.Counter("servo_held"),
               &st.Counter("attitude_not_ok"),
               &st.Counter("pose_dropped_short"),
               &st.Counter("pose_dropped_markers"),
               &st.Counter("window_resets")};
  // Fail at start, not at the first STANDING marker, on options the segmenter refuses.
  PoseSegmenter check(segmenter_options_, nullptr);

  const auto& ch = config.channels();
  inputs_.Subscribe(bus, {[this](const FtBatch& batch) { OnFt(batch); },
                          [this](const ServoInput& in) { OnServo(in); },
                          [this](const MocapInput& in) { OnMocap(in); }});
  // Markers repeat once a second while a phase runs: a live stage takes only fresh ones, so an
  // old session's start marker cannot open a phase here (offline, the window holds against the
  // recording's receive times; markers played to live stages from a recording are refused).
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, static_cast<int64_t>(config_.auth().experiment_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const experiment_marker_t& m) { OnExperiment(m); });
  PublishCounters();
}

void PoseSegmenterStage::CountAlignerDrop(const std::string& stream,
                                          const AlignerCounters& before) {
  const AlignerCounters& now = aligner_.counters();
  if (now.non_finite > before.non_finite) {
    bus_.stats().Drop("non-finite " + stream, "NaN or inf in the message's numbers");
  } else if (now.out_of_order > before.out_of_order) {
    bus_.stats().Drop("out-of-order " + stream, "utime not newer than the previous one");
  }
}

void PoseSegmenterStage::OnFt(const FtBatch& batch) {
  for (const FtRecord& r : batch) {
    const AlignerCounters before = aligner_.counters();
    if (!aligner_.AddFt(r.in)) CountAlignerDrop(inputs_.FtChannel(batch.leg), before);
  }
  PublishCounters();
}

void PoseSegmenterStage::OnServo(const ServoInput& in) {
  const AlignerCounters before = aligner_.counters();
  if (!aligner_.AddServo(in)) CountAlignerDrop(config_.channels().servo_state(), before);
  PublishCounters();
}

void PoseSegmenterStage::OnMocap(const MocapInput& in) {
  const AlignerCounters before = aligner_.counters();
  if (!aligner_.AddMocap(in)) CountAlignerDrop(config_.channels().mocap_body(), before);
  PublishCounters();
}

void PoseSegmenterStage::OnExperiment(const experiment_marker_t& msg) {
  const PhaseChange c = phases_.OnMarker(msg.phase, msg.start, msg.session_id);
  if (c.closes && segmenter_) {
    segmenter_->Flush();  // the run in progress becomes a pose when long enough
    const SegmenterCounters& n = segmenter_->counters();
    segmenter_totals_.samples += n.samples;
    segmenter_totals_.dropped_short += n.dropped_short;
    segmenter_totals_.dropped_markers += n.dropped_markers;
    segmenter_totals_.window_resets += n.window_resets;
    segmenter_.reset();
  }
  if (c.opens && c.opened.code == experiment_marker_t::STANDING) {
    if (c.opened.session != session_id_) pose_index_ = 0;
    session_id_ = c.opened.session;
    segmenter_ = std::make_unique<PoseSegmenter>(segmenter_options_,
                                                 [this](const SteadyPoseOut& p) { OnPose(p); });
  }
  PublishCounters();
}

void PoseSegmenterStage::OnAligned(const AlignedSample& a) {
  if (publish_sync_) {
    ToLcm(a, &sync_msg_);
    bus_.Publish(config_.channels().sync_sample(), sync_msg_);
  }
  ++sync_aligned_;
  if (segmenter_) segmenter_->Add(a.sample);
}

void PoseSegmenterStage::OnPose(const SteadyPoseOut& p) {
  bus_.Publish(config_.channels().steady_pose(),
               ToLcm(p, {bus_.NowUtime(), session_id_, pose_index_++}));
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
  *o.sync_samples = sync_aligned_;
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
