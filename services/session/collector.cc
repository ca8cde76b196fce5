// CalibrationCollector: reading the bus, its subscriptions and the markers that open and close
// the phases (collector.h). The other jobs: collector_inputs.cc, collector_phases.cc,
// collector_results.cc, collector_spans.cc.
#include "session/collector.h"

namespace ftcal {

CalibrationCollector::CalibrationCollector(const config::Config& config)
    : config_(config),
      inputs_(config),
      segmenter_options_(SegmenterOptionsFromConfig(config.segmenter())),
      aligner_(AlignerOptionsFromConfig(config), [this](const AlignedSample& a) { OnAligned(a); }) {
  PoseSegmenter check(segmenter_options_, nullptr);  // refuse unusable options at start
  hang_gaps_index_.fill(-1);
}

void CalibrationCollector::Attach(LogReplayBus& bus) {
  Attach(static_cast<Bus&>(bus));
  replay_ = &bus;
}

void CalibrationCollector::Attach(Bus& bus) {
  const auto& ch = config_.channels();
  // Each input log's signers count their sequences afresh: logs may be given in any order.
  unsigned_markers_ += verifier_.unsigned_seen();
  verifier_ = auth::Verifier::FromConfig(config_);
  replay_ = nullptr;
  event_end_ = -1;
  noting_.active = false;
  produced_.Clear();
  channel_ids_barrier_.clear();
  // Every channel, FT_* ones of legs the config does not have among them: a log from a robot
  // with other legs must be told apart from one whose legs are silent.
  channel_ids_noted_.clear();
  bus.SubscribeRaw(".*", [this](const MessageInfo& info, const void*, int) { NoteChannel(info); });
  for (int k = 0; k < kNumLegs; ++k) {
    bus.SubscribeRaw(inputs_.FtChannel(k), [this, k](const MessageInfo& info, const void* data,
                                                     int size) { OnFtRaw(k, info, data, size); });
  }
  bus.SubscribeRaw(ch.servo_state(), [this](const MessageInfo& info, const void* data, int size) {
    OnServoRaw(info, data, size);
  });
  bus.SubscribeRaw(ch.mocap_body(), [this](const MessageInfo& info, const void* data, int size) {
    OnMocapRaw(info, data, size);
  });
  // Markers repeat once a second while a phase runs: a live stage takes only fresh ones, so an
  // old session's start marker cannot open a phase here (offline, the window holds against the
  // recording's receive times; markers played to live stages from a recording are refused).
  bus.SubscribeSigned<experiment_marker_t>(
      ch.experiment(), &verifier_, static_cast<int64_t>(config_.auth().experiment_window_s() * 1e6),
      config_.auth().allow_unsigned(),
      [this](const MessageInfo&, const experiment_marker_t& m) { OnExperiment(m); });
  bus.Subscribe<steady_pose_t>(
      ch.steady_pose(), [this](const MessageInfo&, const steady_pose_t& m) { OnSteadyPose(m); });
}

void CalibrationCollector::NoteChannel(const MessageInfo& info) {
  event_end_ = info.log_end;
  const int id = info.channel_id;
  if (id >= 0 && static_cast<size_t>(id) < channel_ids_noted_.size() && channel_ids_noted_[id]) {
    if (noting_.active) NoteSpanEvent(info, channel_ids_barrier_[id]);
    return;
  }
  const std::string& channel = info.channel;
  // Markers and poses change what is collected; every other channel is counted, kept or only
  // noted here.
  const bool acts =
      channel == config_.channels().experiment() || channel == config_.channels().steady_pose();
  if (id >= 0) {
    if (static_cast<size_t>(id) >= channel_ids_noted_.size()) {
      channel_ids_noted_.resize(id + 1);
      channel_ids_barrier_.resize(id + 1);
    }
    channel_ids_noted_[id] = true;
    channel_ids_barrier_[id] = acts;
  }
  const bool first = channels_seen_.insert(channel).second;
  // First event on this channel.
  if (first && std::regex_match(channel, ft_pattern_)) ft_channels_seen_.insert(channel);
  if (noting_.active) NoteSpanEvent(info, acts || first || id < 0);
}

void CalibrationCollector::OnExperiment(const experiment_marker_t& msg) {
  ++counters_.markers;
  const PhaseChange c = phases_.OnMarker(msg.phase, msg.start, msg.session_id);
  if (c.stray_stop) {
    log_->warn("EXPERIMENT: stop marker of {} (session '{}') without its start; ignored",
               PhaseName(msg.phase), msg.session_id);
    return;
  }
  if (c.closes) {
    if (!c.completed) {
      log_->warn("EXPERIMENT: {} started while {} had no stop marker; {} discarded",
                 PhaseName(c.opened.code), PhaseName(c.closed.code), PhaseName(c.closed.code));
    }
    EndPhase(c.closed, c.completed);
    if (c.completed && c.closed.code == experiment_marker_t::STANDING && on_standing_stop_) {
      on_standing_stop_();
    }
  }
  if (c.opens) StartPhase(c.opened, msg);
}

void CalibrationCollector::Flush() {
  const PhaseChange c = phases_.End();
  if (c.closes) {
    log_->warn("input ended inside {} (no stop marker): that phase is discarded",
               PhaseName(c.closed.code));
    EndPhase(c.closed, false);
  }
}

void CalibrationCollector::SetIndexOnly() {
  index_only_ = true;
  collect_tripod_stances_ = false;
}

}  // namespace ftcal
