// What the collector notes, reading a phase only for its counts, to write the span index
// (log_index.proto) a later reading skips by; and the counts a span carries.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

#include <google/protobuf/repeated_ptr_field.h>

#include "ftcal/legs.h"
#include "proto/log_index.pb.h"
#include "session/deferred_tail.h"

namespace ftcal {

// The counts of the phase in progress per leg (the state the collector's CountRecord changes).
struct CountState {
  std::array<int64_t, kNumLegs> received{}, lost{}, restarts{}, last_sequence{};
  bool operator==(const CountState& o) const {
    return received == o.received && lost == o.lost && restarts == o.restarts &&
           last_sequence == o.last_sequence;
  }
};
void CountsToProto(const CountState& c,
                   google::protobuf::RepeatedPtrField<logindex::LegCount>* out);
CountState CountsFromProto(const google::protobuf::RepeatedPtrField<logindex::LegCount>& legs);

// A place in the log while a not-segmented phase is read whole: where the events began from
// which each one only counted or kept (SpanNoting::clean), or a servo state or mocap frame
// kept, each with the counts before it.
struct SpanMark {
  int64_t offset = -1;
  int64_t events = 0;  // events of the span before this one
  CountState counts;
};

// The marks of the last DeferredTail::kDepth servo states (or mocap frames) kept.
struct MarkRing {
  std::array<SpanMark, DeferredTail::kDepth> marks;
  size_t next = 0, count = 0;
  void Push(const SpanMark& m) {
    marks[next] = m;
    next = (next + 1) % marks.size();
    ++count;
  }
  // The oldest mark at or after `offset`: of the kept messages, the first a skip must not pass.
  const SpanMark* FirstFrom(int64_t offset) const;
};

struct SpanNoting {
  bool active = false;
  bool barrier = true;  // the event now handled changed more than the counts and kept ones
  int64_t prev_end = -1, offset = -1, events = 0;
  SpanMark clean;  // where the span begins
  MarkRing servo, mocap;
};

}  // namespace ftcal
