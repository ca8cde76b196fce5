// Motive's frame numbers as a NatNet client receives them over UDP (docs/natnet-protocol.md §6):
// which frame is the next one, a late one, a duplicate, or the first of a restarted Motive, and
// what was lost. Transport-free: the bridge feeds it each decoded frame and reads the counts.
//
// The rules, for a frame numbered n when the newest so far is `last`:
// - n > last: the next frame. The numbers in between are lost, unless no frame came for the
//   silence the caller names (Motive paused: its numbers ran on while it sent nothing), when
//   they are paused.
// - n <= last, and n came before with the same bytes: a duplicate (dropped).
// - n <= last otherwise, a late frame (dropped; it is no longer lost if it was counted so),
//   unless a restart shows: n came before with other bytes; or the frame comes after a
//   silence; or its timestamp lies more than kMaxLateS before the newest's; or n lies more
//   than kWindow numbers back; or its transmit ticks are not between those of the frames
//   received just below and just above it (a frame sent late was sent between them).
// - n > last with a timestamp more than a second back (a take rewound): a restart too.
// A restart starts the history afresh from this frame; counts are kept.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <vector>

namespace ftcal::natnet {

class FrameSequence {
 public:
  // How far back a late frame may be: numbers (history kept) and Motive's seconds.
  static constexpr int32_t kWindow = 512;
  static constexpr double kMaxLateS = 0.5;

  enum class Verdict { kNext, kLate, kDuplicate, kRestart };

  struct Frame {
    int32_t number = 0;
    double timestamp_s = 0;
    uint64_t transmit_ticks = 0;  // 0: not known
    uint64_t digest = 0;          // of the frame's bytes (Digest())
  };
  // FNV-1a over the bytes: tells a duplicate from another frame with the same number.
  static uint64_t Digest(const std::vector<uint8_t>& bytes);

  // `after_silence`: no frame came for the caller's silence time before this one.
  Verdict Accept(const Frame& f, bool after_silence);
  // A new session (a new SERVERINFO): the next frame starts the history; counts are kept.
  void Forget();

  std::optional<int32_t> last() const { return last_; }
  int64_t lost() const { return lost_; }      // numbers missing, not (yet) come late
  int64_t gaps() const { return gaps_; }      // runs of such numbers
  int64_t paused() const { return paused_; }  // numbers skipped during a silence
  int64_t late() const { return late_; }
  int64_t duplicates() const { return duplicates_; }
  int64_t restarts() const { return restarts_; }

 private:
  struct Seen {
    uint64_t digest;
    uint64_t transmit_ticks;
  };
  bool LooksLate(const Frame& f, bool after_silence) const;
  void Start(const Frame& f);
  void Prune();

  std::optional<int32_t> last_;
  double last_timestamp_s_ = 0;
  std::map<int32_t, Seen> received_;    // the last kWindow numbers received
  std::map<int32_t, int32_t> missing_;  // a lost number -> the first number of its gap
  std::map<int32_t, int32_t> open_;     // a gap's first number -> its numbers still missing
  int64_t lost_ = 0, gaps_ = 0, paused_ = 0, late_ = 0, duplicates_ = 0, restarts_ = 0;
};

}  // namespace ftcal::natnet
