// CalibrationCollector: the bus's messages into what Calibrate() consumes (calibrator.h).
#include "calibrator/collector.h"

#include <sys/mman.h>
#include <unistd.h>

#include <system_error>

#include <spdlog/fmt/fmt.h>
#include <spdlog/spdlog.h>

#include "common/wire_guard.h"
#include "ftcal/hanging.h"

namespace ftcal {

namespace {

bool IsHangPhase(int phase) { return HangSeriesOfPhase(phase).has_value(); }

HangSeries SeriesOfPhase(int phase) { return *HangSeriesOfPhase(phase); }

// Records arriving a little out of order (two sockets, a busy receiver) are not lost: a number
// up to this far below the highest seen fills a gap counted before.
constexpr int64_t kReorderWindow = 64;

// Room for a first hanging series before any is known: the report's ten 20 s cycles at 100
// aligned samples a second, and more.
constexpr size_t kFirstHangReserve = size_t{1} << 15;

// A vector's room, its whole capacity: [data, data + bytes).
struct Room {
  const void* data;
  size_t bytes;
};
template <typename T>
Room RoomOf(const std::vector<T>& v) {
  return Room{v.data(), v.capacity() * sizeof(T)};
}

// Faults in the pages of every room, slice by slice across all of them (the reader fills them
// side by side), with one madvise(MADV_POPULATE_WRITE) per slice instead of a trap per 4 KiB
// page as they are first written: on the paravirtualised VMs we measure on, each trap costs
// several microseconds, and a report-scale hanging series is ~2300 pages. The pages' contents
// are unchanged. Best effort: a kernel before 5.14 refuses the advice, and the pages are
// faulted in as they are written.
void Prefault(const std::vector<Room>& rooms) {
#ifdef MADV_POPULATE_WRITE
  constexpr int kSlices = 16;
  const auto page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
  for (int s = 0; s < kSlices; ++s) {
    for (const Room& r : rooms) {
      const auto at = reinterpret_cast<uintptr_t>(r.data);
      const uintptr_t begin = (at + r.bytes * s / kSlices + page - 1) & ~(page - 1);
      const uintptr_t end = (at + r.bytes * (s + 1) / kSlices) & ~(page - 1);
      if (end > begin &&
          ::madvise(reinterpret_cast<void*>(begin), end - begin, MADV_POPULATE_WRITE) != 0) {
        return;
      }
    }
  }
#else
  (void)rooms;
#endif
}

}  // namespace

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

// ---- The span index ----

CalibrationCollector::CountState CalibrationCollector::Counts() const {
  CountState c;
  c.received = current_gaps_.received;
  c.lost = current_gaps_.lost;
  c.restarts = current_gaps_.restarts;
  c.last_sequence = last_sequence_;
  return c;
}

void CalibrationCollector::SetCounts(const CountState& c) {
  current_gaps_.received = c.received;
  current_gaps_.lost = c.lost;
  current_gaps_.restarts = c.restarts;
  last_sequence_ = c.last_sequence;
}

const CalibrationCollector::Mark* CalibrationCollector::MarkRing::FirstFrom(int64_t offset) const {
  const size_t n = std::min(count, marks.size());
  const size_t first = count < marks.size() ? 0 : next;
  for (size_t i = 0; i < n; ++i) {
    const Mark& m = marks[(first + i) % marks.size()];
    if (m.offset >= offset) return &m;
  }
  return nullptr;
}

void CalibrationCollector::CountsToProto(
    const CountState& c, google::protobuf::RepeatedPtrField<logindex::LegCount>* out) {
  for (int k = 0; k < kNumLegs; ++k) {
    logindex::LegCount* leg = out->Add();
    leg->set_received(c.received[k]);
    leg->set_lost(c.lost[k]);
    leg->set_restarts(c.restarts[k]);
    leg->set_last_sequence(c.last_sequence[k]);
  }
}

CalibrationCollector::CountState CalibrationCollector::CountsFromProto(
    const google::protobuf::RepeatedPtrField<logindex::LegCount>& legs) {
  CountState c;
  for (int k = 0; k < kNumLegs; ++k) {
    c.received[k] = legs[k].received();
    c.lost[k] = legs[k].lost();
    c.restarts[k] = legs[k].restarts();
    c.last_sequence[k] = legs[k].last_sequence();
  }
  return c;
}

// Called first for every event while a not-segmented STANDING phase is read (NoteChannel):
// a span begins after the last event that changed more than the counts and the kept messages
// (`barrier`, or a handler that refused it), or after bytes that were not an event.
void CalibrationCollector::NoteSpanEvent(const MessageInfo& info, bool barrier) {
  if (info.log_offset < 0) {  // live: nothing to skip another time
    noting_.active = false;
    return;
  }
  if (noting_.barrier || info.log_offset != noting_.prev_end) {
    noting_.clean = Mark{info.log_offset, noting_.events, Counts()};
  }
  noting_.barrier = barrier;
  noting_.offset = info.log_offset;
  noting_.prev_end = info.log_end;
  ++noting_.events;
}

// At the phase's stop marker (the event noted last): the span runs from where it began to the
// first of the servo states and mocap frames the phase's end kept (the last kDepth of each,
// which a later run must read to keep the same), or to the marker.
void CalibrationCollector::EndSpanNoting(const std::string& session, int phase) {
  noting_.active = false;
  Mark end{noting_.offset, noting_.events - 1, Counts()};
  for (const MarkRing* ring : {&noting_.servo, &noting_.mocap}) {
    const Mark* m = ring->FirstFrom(noting_.clean.offset);
    if (m != nullptr && m->offset < end.offset) end = *m;
  }
  // Less than this is not worth an entry (a short test log's phase, a span cut by barriers).
  constexpr int64_t kMinSpanBytes = 64 * 1024;
  if (end.offset - noting_.clean.offset < kMinSpanBytes) return;
  logindex::SkippableSpan* span = produced_.add_span();
  span->set_session(session);
  span->set_phase(phase);
  span->set_from_offset(noting_.clean.offset);
  span->set_to_offset(end.offset);
  span->set_events(end.events - noting_.clean.events);
  CountsToProto(noting_.clean.counts, span->mutable_at_from());
  CountsToProto(end.counts, span->mutable_at_to());
}

// At the start of a phase read only for its counts: the first span of the index in it, if any.
void CalibrationCollector::ArmSkip(const std::string& session, int phase) {
  if (use_index_ == nullptr || replay_ == nullptr || event_end_ < 0) return;
  const logindex::SkippableSpan* best = nullptr;
  for (const logindex::SkippableSpan& s : use_index_->span()) {
    if (s.session() != session || s.phase() != phase || s.from_offset() < event_end_ ||
        s.to_offset() <= s.from_offset() || s.at_from_size() != kNumLegs ||
        s.at_to_size() != kNumLegs) {
      continue;
    }
    if (best == nullptr || s.from_offset() < best->from_offset()) best = &s;
  }
  if (best == nullptr) return;
  const CountState from = CountsFromProto(best->at_from()), to = CountsFromProto(best->at_to());
  const int64_t events = best->events(), bytes = best->to_offset() - best->from_offset();
  replay_->SkipAt(best->from_offset(), best->to_offset(), [=] {
    // Every event of the span would only have been counted or kept: the same phase, no sample
    // waiting in the aligner (so no servo state or mocap frame goes to it), the same counts.
    if (!counting_only_ || current_gaps_.phase != phase || current_gaps_.session != session ||
        !Deferring() || !(Counts() == from)) {
      log_->info("{} (session '{}'): the span index does not fit this reading; read",
                 PhaseName(phase), session);
      return false;
    }
    SetCounts(to);
    noting_.active = false;
    counters_.span_events_skipped += events;
    log_->info(
        "{} (session '{}'): {} events ({:.0f} MB) not read: their records were counted "
        "when this log was read before, by the segmenter or a calibrator (span index in the digest "
        "cache)",
        PhaseName(phase), session, events, 1e-6 * static_cast<double>(bytes));
    return true;
  });
}

void CalibrationCollector::SetIndexOnly() {
  index_only_ = true;
  collect_tripod_stances_ = false;
}

logindex::LogIndex CalibrationCollector::TakeSpanIndex() {
  logindex::LogIndex out = std::move(produced_);
  produced_.Clear();
  out.set_rules(SpanIndexRules());
  return out;
}

std::string CalibrationCollector::SpanIndexRules() const {
  const auto& ch = config_.channels();
  // v2: spans of TRIPOD phases too, each span naming its phase.
  std::string rules = "ftcal collector spans v2; kept " + std::to_string(DeferredTail::kDepth) +
                      "; reorder window " + std::to_string(kReorderWindow) + "; FT";
  for (int k = 0; k < kNumLegs; ++k) rules += " " + inputs_.FtChannel(k);
  rules += "; " + ch.servo_state() + " " + ch.mocap_body() + " " + ch.experiment() + " " +
           ch.steady_pose();
  return rules;
}

namespace {

// The wire guard's checks alone, with the drop kind a decode would give.
template <class Msg>
void CheckOrThrow(const MessageInfo& info, const void* data, int size) {
  static const wire::Schema* const schema = wire::FindSchema(static_cast<uint64_t>(Msg::getHash()));
  const std::optional<wire::Refusal> refused =
      schema != nullptr
          ? wire::Check(*schema, data, size)
          : wire::Refusal{"no wire schema", std::string("no schema for ") + Msg::getTypeName()};
  if (refused) {
    throw BadInput(std::string("undecodable ") + Msg::getTypeName() + " on " + info.channel + ": " +
                       refused->kind,
                   refused->detail);
  }
}

}  // namespace

void CalibrationCollector::OnFtRaw(int k, const MessageInfo& info, const void* data, int size) {
  if (counting_only_) {
    // Aligned samples of a phase read only for its counts (a STANDING phase not segmented
    // again, a TRIPOD phase whose stances are not collected) would go nowhere: the records are
    // only counted. Checked as a decode would check them, so a damaged log is refused the same.
    const bool barrier = noting_.barrier;
    noting_.barrier = true;  // unless counted
    std::optional<int> n = PeekRdtSequences(data, size, k, &sequences_);
    if (!n) {
      // Not the plain layout of this leg: the wire guard and FromLcm name what is wrong.
      DecodeOrThrow(info, data, size, &ft_scratch_);
      inputs_.FromFt(k, ft_scratch_, &batch_);
      n = batch_.n;
      for (int i = 0; i < batch_.n; ++i) {
        sequences_[static_cast<size_t>(i)] = batch_.records[static_cast<size_t>(i)].rdt_sequence;
      }
    }
    if (phases_.open()) {
      for (int i = 0; i < *n; ++i) CountRecord(k, sequences_[static_cast<size_t>(i)]);
    }
    noting_.barrier = barrier;
    return;
  }
  inputs_.FtOf(k, info, data, size, &ft_scratch_, &batch_);  // decoded into again: no allocation
  for (const FtRecord& r : batch_) {
    if (phases_.open()) CountRecord(k, r.rdt_sequence);
    aligner_.AddFt(r.in);
  }
}

void CalibrationCollector::DeferredTail::Push(const void* data, int size) {
  std::vector<uint8_t>& slot = ring_[next_];
  const auto* bytes = static_cast<const uint8_t*>(data);
  slot.assign(bytes, bytes + size);  // the slot's storage is reused: no allocation per message
  next_ = (next_ + 1) % kDepth;
  ++count_;
}

void CalibrationCollector::OnServoRaw(const MessageInfo& info, const void* data, int size) {
  if (Deferring()) {
    const bool barrier = noting_.barrier;
    noting_.barrier = true;  // unless kept
    CheckOrThrow<servo_state_t>(info, data, size);
    deferred_servo_.Push(data, size);
    if (noting_.active) noting_.servo.Push(Mark{info.log_offset, noting_.events - 1, Counts()});
    noting_.barrier = barrier;
    return;
  }
  noting_.barrier = true;  // into the aligner
  aligner_.AddServo(inputs_.ServoOf(info, data, size, &servo_scratch_));
}

void CalibrationCollector::OnMocapRaw(const MessageInfo& info, const void* data, int size) {
  if (Deferring()) {
    const bool barrier = noting_.barrier;
    noting_.barrier = true;  // unless kept
    CheckOrThrow<mocap_body_t>(info, data, size);
    deferred_mocap_.Push(data, size);
    if (noting_.active) noting_.mocap.Push(Mark{info.log_offset, noting_.events - 1, Counts()});
    noting_.barrier = barrier;
    return;
  }
  noting_.barrier = true;  // into the aligner
  if (const auto in = inputs_.MocapOf(info, data, size, &mocap_scratch_)) aligner_.AddMocap(*in);
}

// The deferred messages, in their order, through OnServoRaw/OnMocapRaw (no longer deferring:
// the phase has ended). The two streams do not meet in the aligner while it holds no pending
// sample, so each may go in after the other. A message refused now (checked whole when it
// came, so refused for its content, as the bus would have counted it then) is logged: the bus
// that read it may be gone (the input can end inside the span).
void CalibrationCollector::FlushDeferred() {
  const MessageInfo servo{config_.channels().servo_state(), 0},
      mocap{config_.channels().mocap_body(), 0};
  auto through = [this](void (CalibrationCollector::*handler)(const MessageInfo&, const void*, int),
                        const MessageInfo& info) {
    return [this, handler, &info](const void* data, int size) {
      try {
        (this->*handler)(info, data, size);
      } catch (const BadInput& e) {
        log_->warn("{}: a message kept from a phase read only for its counts, refused: {}",
                   info.channel, e.what());
      }
    };
  };
  deferred_servo_.Drain(through(&CalibrationCollector::OnServoRaw, servo));
  deferred_mocap_.Drain(through(&CalibrationCollector::OnMocapRaw, mocap));
}

void CalibrationCollector::CountRecord(int k, int64_t sequence) {
  int64_t& last = last_sequence_[k];
  if (last == 0) {
    ++current_gaps_.received[k];
  } else if (sequence > last) {
    ++current_gaps_.received[k];
    current_gaps_.lost[k] += sequence - last - 1;
  } else if (sequence == last) {
    return;  // the same record twice (a replayed log): not data, not a gap
  } else if (last - sequence <= kReorderWindow && current_gaps_.lost[k] > 0) {
    ++current_gaps_.received[k];
    --current_gaps_.lost[k];
    return;
  } else {
    ++current_gaps_.received[k];
    ++current_gaps_.restarts[k];
  }
  last = sequence;
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

void CalibrationCollector::StartPhase(const MarkedPhase& phase, const experiment_marker_t& msg) {
  current_gaps_ = PhaseGaps();
  current_gaps_.phase = phase.code;
  current_gaps_.session = phase.session;
  last_sequence_.fill(0);
  if (IsHangPhase(phase.code)) {
    WaitPrefault();  // before the room it touches is freed
    current_hang_ = HangingRecording();
    current_hang_.series = SeriesOfPhase(phase.code);
    current_hang_.gravity_b = Vec3(msg.gravity_b[0], msg.gravity_b[1], msg.gravity_b[2]);
    if (index_only_) return;  // nothing kept: no room
    // The series of one experiment are alike in length (the plan's cycles at one speed): room
    // for the longest so far, a little more, saves growing each vector by copies, and is faulted
    // in on another thread (Prefault) while this one reads. Before the first series, room for
    // a guess (the report's scale), faulted in the same way: what the series does not fill stays
    // resident (peak 86 MiB instead of 85 on the demo's logs), and the series is read in 52 ms
    // instead of 54 (medians of 12 runs in turn).
    size_t expected = 0;
    for (int s = 0; s < kNumHangSeries; ++s) {
      if (have_hang_[s]) expected = std::max(expected, hang_[s].legs[0].t_s.size());
    }
    const bool known = expected > 0;
    expected = known ? expected + expected / 16 : kFirstHangReserve;
    for (LegSamples& leg : current_hang_.legs) {
      leg.t_s.reserve(expected);
      leg.angle_rad.reserve(expected);
      leg.wrench.reserve(expected);
    }
    current_hang_.attitude.reserve(expected);
    std::vector<Room> rooms{RoomOf(current_hang_.attitude)};
    for (const LegSamples& leg : current_hang_.legs) {
      rooms.insert(rooms.end(), {RoomOf(leg.t_s), RoomOf(leg.angle_rad), RoomOf(leg.wrench)});
    }
    try {
      prefault_ = std::async(std::launch::async, Prefault, std::move(rooms));
    } catch (const std::system_error&) {
      // No thread to spare: the pages are faulted in as they are written.
    }
  } else if (phase.code == experiment_marker_t::STANDING) {
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
      noting_ = SpanNoting();
      noting_.active = event_end_ >= 0;  // replay
      ArmSkip(phase.session, phase.code);
      return;
    }
    segmenter_ =
        std::make_unique<PoseSegmenter>(segmenter_options_, [this](const SteadyPoseOut& p) {
          if (!p.markers_ok) return;
          current_poses_.push_back(p.pose);
          ++counters_.segmented_poses;
        });
  } else if (phase.code == experiment_marker_t::TARE) {
    for (Vec6& w : tare_sum_) w.setZero();
    tare_count_ = 0;
  } else if (phase.code == experiment_marker_t::TRIPOD && !collect_tripod_stances_) {
    counting_only_ = true;
    log_->info(
        "EXPERIMENT: TRIPOD started (session '{}'); its stances serve only offset "
        "re-estimation: records counted, not segmented",
        phase.session);
    noting_ = SpanNoting();
    noting_.active = event_end_ >= 0;  // replay
    ArmSkip(phase.session, phase.code);
    return;
  } else if (phase.code == experiment_marker_t::TRIPOD) {
    current_unloaded_.clear();
    segmenter_ = std::make_unique<PoseSegmenter>(
        segmenter_options_, [this](const SteadyPoseOut& p) { OnTripodStance(p); });
  } else if (phase.code == experiment_marker_t::WALKING && walking_.empty() && !index_only_) {
    // Room for all it may keep: grown by copies, the kept samples were copied about twice.
    // Address space only until written.
    current_walk_.reserve(kMaxWalkingSamples);
  }
  log_->info("EXPERIMENT: {} started (session '{}')", PhaseName(phase.code), phase.session);
}

void CalibrationCollector::EndPhase(const MarkedPhase& phase, bool completed) {
  // A STANDING or TRIPOD phase's segmenter hands over the pose in progress first.
  SegmenterCounters segmented;
  const bool not_segmented = counting_only_;
  if (noting_.active) {
    if (completed && not_segmented &&
        (phase.code == experiment_marker_t::STANDING ||
         phase.code == experiment_marker_t::TRIPOD)) {
      EndSpanNoting(phase.session, phase.code);
    }
    noting_.active = false;
  }
  counting_only_ = false;
  FlushDeferred();
  if (segmenter_) {
    segmenter_->Flush();
    segmented = segmenter_->counters();
    segmenter_.reset();
  }
  if (completed) phase_gaps_.push_back(current_gaps_);
  if (IsHangPhase(phase.code)) {
    WaitPrefault();  // the series' buffers are kept or freed below
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
  } else if (phase.code == experiment_marker_t::STANDING) {
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
  } else if (phase.code == experiment_marker_t::TARE) {
    if (completed && tare_count_ > 0) {
      std::array<Vec6, kNumLegs> mean;
      for (int k = 0; k < kNumLegs; ++k) mean[k] = tare_sum_[k] / static_cast<double>(tare_count_);
      BeforeInputsChange();
      tare_ = mean;
      log_->info("TARE complete (session '{}'): naive tare from {} samples", phase.session,
                 tare_count_);
    }
  } else if (phase.code == experiment_marker_t::TRIPOD) {
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
  } else if (phase.code == experiment_marker_t::WALKING) {
    if (completed && walking_.empty() && !current_walk_.empty()) {
      log_->info("WALKING complete (session '{}'): {} aligned samples kept for the report",
                 phase.session, current_walk_.size());
      walking_ = std::move(current_walk_);
    }
    current_walk_.clear();
  }
}

void CalibrationCollector::Flush() {
  const PhaseChange c = phases_.End();
  if (c.closes) {
    log_->warn("input ended inside {} (no stop marker): that phase is discarded",
               PhaseName(c.closed.code));
    EndPhase(c.closed, false);
  }
}

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
