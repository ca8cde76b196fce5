// CalibrationCollector: the span index (log_index.proto) it writes while it reads a phase only
// for its counts, and the spans of an index it skips (collector.h, span_noting.h).
#include "session/collector.h"

#include <spdlog/fmt/fmt.h>

namespace ftcal {

CountState CalibrationCollector::Counts() const {
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

// Called first for every event while a not-segmented STANDING phase is read (NoteChannel):
// a span begins after the last event that changed more than the counts and the kept messages
// (`barrier`, or a handler that refused it), or after bytes that were not an event.
void CalibrationCollector::NoteSpanEvent(const MessageInfo& info, bool barrier) {
  if (info.log_offset < 0) {  // live: nothing to skip another time
    noting_.active = false;
    return;
  }
  if (noting_.barrier || info.log_offset != noting_.prev_end) {
    noting_.clean = SpanMark{info.log_offset, noting_.events, Counts()};
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
  SpanMark end{noting_.offset, noting_.events - 1, Counts()};
  for (const MarkRing* ring : {&noting_.servo, &noting_.mocap}) {
    const SpanMark* m = ring->FirstFrom(noting_.clean.offset);
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

}  // namespace ftcal
