#include "session/span_noting.h"

#include <algorithm>

namespace ftcal {

const SpanMark* MarkRing::FirstFrom(int64_t offset) const {
  const size_t n = std::min(count, marks.size());
  const size_t first = count < marks.size() ? 0 : next;
  for (size_t i = 0; i < n; ++i) {
    const SpanMark& m = marks[(first + i) % marks.size()];
    if (m.offset >= offset) return &m;
  }
  return nullptr;
}

void CountsToProto(const CountState& c,
                   google::protobuf::RepeatedPtrField<logindex::LegCount>* out) {
  for (int k = 0; k < kNumLegs; ++k) {
    logindex::LegCount* leg = out->Add();
    leg->set_received(c.received[k]);
    leg->set_lost(c.lost[k]);
    leg->set_restarts(c.restarts[k]);
    leg->set_last_sequence(c.last_sequence[k]);
  }
}

CountState CountsFromProto(const google::protobuf::RepeatedPtrField<logindex::LegCount>& legs) {
  CountState c;
  for (int k = 0; k < kNumLegs; ++k) {
    c.received[k] = legs[k].received();
    c.lost[k] = legs[k].lost();
    c.restarts[k] = legs[k].restarts();
    c.last_sequence[k] = legs[k].last_sequence();
  }
  return c;
}

}  // namespace ftcal
