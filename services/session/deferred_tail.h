// The last messages of a stream kept as bytes, decoded only when wanted (the collector's
// counting-only phases).
//
// Over a STANDING phase not segmented again no transducer sample goes to the aligner, so of its
// servo states and mocap frames only the last few shape what the aligner holds when the phase
// ends (ServoHistory keeps 16 states, the mocap input 1 frame). Those are checked by the wire
// guard as they come (a damaged log is still refused) but decoded only at the phase's end, from
// this ring of their bytes: decoding all the others went nowhere. The ring is deeper than the
// aligner's history so that states it would refuse (not newer, not finite) and other bodies'
// frames still leave it full.
#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace ftcal {

class DeferredTail {
 public:
  static constexpr size_t kDepth = 64;
  void Push(const void* data, int size) {
    std::vector<uint8_t>& slot = ring_[next_];
    const auto* bytes = static_cast<const uint8_t*>(data);
    slot.assign(bytes, bytes + size);  // the slot's storage is reused: no allocation per message
    next_ = (next_ + 1) % kDepth;
    ++count_;
  }
  // Calls fn(data, size) on each message held, oldest first, and empties the ring.
  template <class Fn>
  void Drain(Fn&& fn) {
    const size_t first = count_ < kDepth ? 0 : next_;
    for (size_t i = 0; i < std::min(count_, kDepth); ++i) {
      const std::vector<uint8_t>& m = ring_[(first + i) % kDepth];
      fn(m.data(), static_cast<int>(m.size()));
    }
    count_ = next_ = 0;
  }
  bool empty() const { return count_ == 0; }

 private:
  std::array<std::vector<uint8_t>, kDepth> ring_;
  size_t next_ = 0, count_ = 0;
};

}  // namespace ftcal
