// CalibrationCollector: the transducer, servo and mocap messages as they come, into the aligner
// or, over a phase read only for its counts, counted and kept (collector.h).
#include "session/collector.h"

#include "common/wire_guard.h"

namespace ftcal {

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

template <class Msg>
bool CalibrationCollector::Defer(const MessageInfo& info, const void* data, int size,
                                 DeferredTail& tail, MarkRing& marks) {
  if (!Deferring()) return false;
  const bool barrier = noting_.barrier;
  noting_.barrier = true;  // unless kept
  CheckOrThrow<Msg>(info, data, size);
  tail.Push(data, size);
  if (noting_.active) marks.Push(SpanMark{info.log_offset, noting_.events - 1, Counts()});
  noting_.barrier = barrier;
  return true;
}

void CalibrationCollector::OnServoRaw(const MessageInfo& info, const void* data, int size) {
  if (Defer<servo_state_t>(info, data, size, deferred_servo_, noting_.servo)) return;
  noting_.barrier = true;  // into the aligner
  aligner_.AddServo(inputs_.ServoOf(info, data, size, &servo_scratch_));
}

void CalibrationCollector::OnMocapRaw(const MessageInfo& info, const void* data, int size) {
  if (Defer<mocap_body_t>(info, data, size, deferred_mocap_, noting_.mocap)) return;
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

}  // namespace ftcal
