#include "frame_sequence.h"

#include <algorithm>
#include <iterator>

namespace ftcal::natnet {

uint64_t FrameSequence::Digest(const std::vector<uint8_t>& bytes) {
  uint64_t h = 14695981039346656037ull;
  for (uint8_t b : bytes) h = (h ^ b) * 1099511628211ull;
  return h;
}

void FrameSequence::Forget() {
  last_.reset();
  received_.clear();
  missing_.clear();
  open_.clear();
}

void FrameSequence::Start(const Frame& f) {
  Forget();
  last_ = f.number;
  last_timestamp_s_ = f.timestamp_s;
  received_[f.number] = {f.digest, f.transmit_ticks};
}

void FrameSequence::Prune() {
  const int64_t oldest = int64_t{*last_} - kWindow;
  received_.erase(
      received_.begin(),
      received_.lower_bound(static_cast<int32_t>(std::max<int64_t>(oldest, INT32_MIN))));
  // Numbers missing for longer than a frame can be late stay lost.
  for (auto it = missing_.begin(); it != missing_.end() && it->first < oldest;) {
    const auto gap = open_.find(it->second);
    if (gap != open_.end() && --gap->second == 0) open_.erase(gap);
    it = missing_.erase(it);
  }
}

bool FrameSequence::LooksLate(const Frame& f, bool after_silence) const {
  if (after_silence) return false;  // a datagram is not held up that long: Motive came back
  if (last_timestamp_s_ - f.timestamp_s > kMaxLateS) return false;
  if (int64_t{*last_} - f.number > kWindow) return false;
  if (f.transmit_ticks == 0) return true;
  // Sent between its neighbours: Motive's clock says so, whichever way a restart set it.
  const auto above = received_.upper_bound(f.number);
  if (above != received_.end() && above->second.transmit_ticks != 0 &&
      f.transmit_ticks > above->second.transmit_ticks) {
    return false;
  }
  if (above != received_.begin()) {
    const Seen& below = std::prev(above)->second;
    if (below.transmit_ticks != 0 && f.transmit_ticks < below.transmit_ticks) return false;
  }
  return true;
}

FrameSequence::Verdict FrameSequence::Accept(const Frame& f, bool after_silence) {
  if (!last_) {
    Start(f);
    return Verdict::kNext;
  }
  const int64_t step = int64_t{f.number} - *last_;
  if (step > 0) {
    if (f.timestamp_s + 1.0 < last_timestamp_s_) {
      ++restarts_;  // numbers on, Motive's time a second back: a rewound take
      Start(f);
      return Verdict::kRestart;
    }
    if (step > 1 && after_silence) {
      paused_ += step - 1;
    } else if (step > 1) {
      lost_ += step - 1;
      ++gaps_;
      // Remembered for a late arrival (the newest kWindow of them).
      const int32_t first = static_cast<int32_t>(std::max<int64_t>(*last_ + 1, f.number - kWindow));
      for (int32_t n = first; n < f.number; ++n) missing_[n] = first;
      open_[first] = f.number - first;
    }
    last_ = f.number;
    last_timestamp_s_ = f.timestamp_s;
    received_[f.number] = {f.digest, f.transmit_ticks};
    Prune();
    return Verdict::kNext;
  }
  const auto seen = received_.find(f.number);
  if (seen != received_.end() && seen->second.digest == f.digest) {
    ++duplicates_;
    return Verdict::kDuplicate;
  }
  if (seen != received_.end() || !LooksLate(f, after_silence)) {
    ++restarts_;
    Start(f);
    return Verdict::kRestart;
  }
  ++late_;
  received_[f.number] = {f.digest, f.transmit_ticks};  // so that a copy of it is a duplicate
  const auto missing = missing_.find(f.number);
  if (missing != missing_.end()) {
    --lost_;
    const auto gap = open_.find(missing->second);
    if (gap != open_.end() && --gap->second == 0) {
      --gaps_;  // the whole gap came late: it was none
      open_.erase(gap);
    }
    missing_.erase(missing);
  }
  return Verdict::kLate;
}

}  // namespace ftcal::natnet
