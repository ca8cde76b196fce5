// natnet::FrameSequence on hand-made sequences (docs/natnet-protocol.md §6): every count
// below is worked out from the frame numbers as written.
#include "frame_sequence.h"

#include <gtest/gtest.h>

namespace ftcal::natnet {
namespace {

using V = FrameSequence::Verdict;

// Frame n of one Motive session at 100 Hz: its time, its transmit ticks (10 MHz, a second
// after Motive started) and bytes of its own.
FrameSequence::Frame F(int32_t n, uint64_t variant = 0) {
  return {n, (n - 1) / 100.0, 10'000'000 + static_cast<uint64_t>(n) * 100'000,
          static_cast<uint64_t>(n) * 7919 + variant};
}

TEST(NatNetFrameSequenceTest, NumbersSkippedInTheStreamAreLost) {
  FrameSequence s;
  for (int32_t n : {1, 2, 5, 6, 8}) EXPECT_EQ(s.Accept(F(n), false), V::kNext) << n;
  EXPECT_EQ(s.lost(), 3);  // 3, 4, 7
  EXPECT_EQ(s.gaps(), 2);
  EXPECT_EQ(s.restarts(), 0);
}

TEST(NatNetFrameSequenceTest, ALateFrameIsDroppedAndNoLongerLost) {
  FrameSequence s;
  for (int32_t n : {1, 2, 4, 5}) s.Accept(F(n), false);
  ASSERT_EQ(s.lost(), 1);
  EXPECT_EQ(s.Accept(F(3), false), V::kLate);
  EXPECT_EQ(s.lost(), 0);
  EXPECT_EQ(s.gaps(), 0);  // the gap was none
  EXPECT_EQ(s.late(), 1);
  EXPECT_EQ(s.restarts(), 0);
  EXPECT_EQ(s.last(), 5);
  // Its second copy, later still, is a duplicate.
  EXPECT_EQ(s.Accept(F(3), false), V::kDuplicate);
  EXPECT_EQ(s.duplicates(), 1);
}

TEST(NatNetFrameSequenceTest, AFrameLateIntoAWiderGapLeavesTheRestLost) {
  FrameSequence s;
  for (int32_t n : {1, 6}) s.Accept(F(n), false);
  EXPECT_EQ(s.Accept(F(3), false), V::kLate);
  EXPECT_EQ(s.lost(), 3);  // 2, 4, 5
  EXPECT_EQ(s.gaps(), 1);
}

TEST(NatNetFrameSequenceTest, ACopyOfTheNewestIsADuplicate) {
  FrameSequence s;
  s.Accept(F(1), false);
  s.Accept(F(2), false);
  EXPECT_EQ(s.Accept(F(2), false), V::kDuplicate);
  EXPECT_EQ(s.duplicates(), 1);
  EXPECT_EQ(s.lost(), 0);
}

TEST(NatNetFrameSequenceTest, AFrameLateBeforeTheFirstOneReceivedIsLate) {
  FrameSequence s;
  s.Accept(F(10), false);
  EXPECT_EQ(s.Accept(F(9), false), V::kLate);
  EXPECT_EQ(s.lost(), 0);
  EXPECT_EQ(s.restarts(), 0);
}

TEST(NatNetFrameSequenceTest, NumbersSkippedDuringASilenceArePausedNotLost) {
  FrameSequence s;
  s.Accept(F(1), false);
  s.Accept(F(2), false);
  EXPECT_EQ(s.Accept(F(300), true), V::kNext);
  EXPECT_EQ(s.paused(), 297);
  EXPECT_EQ(s.lost(), 0);
}

TEST(NatNetFrameSequenceTest, TheSameNumberWithOtherBytesIsARestart) {
  // Motive back within a few frames: frame 2 again, but not the frame 2 received before.
  FrameSequence s;
  for (int32_t n : {1, 2, 3, 4}) s.Accept(F(n), false);
  EXPECT_EQ(s.Accept(F(2, 1), false), V::kRestart);
  EXPECT_EQ(s.restarts(), 1);
  EXPECT_EQ(s.last(), 2);
  EXPECT_EQ(s.Accept(F(3, 1), false), V::kNext);
  EXPECT_EQ(s.lost(), 0);
}

TEST(NatNetFrameSequenceTest, ALowerNumberAfterASilenceIsARestart) {
  FrameSequence s;
  for (int32_t n : {10, 11, 13}) s.Accept(F(n), false);
  EXPECT_EQ(s.Accept(F(12), true), V::kRestart);
  EXPECT_EQ(s.lost(), 1);  // 12 was lost in the old session; counts are kept
}

TEST(NatNetFrameSequenceTest, AFrameFarBackInTimeOrNumbersIsARestart) {
  FrameSequence a;
  for (int32_t n : {100, 200}) a.Accept(F(n), false);
  EXPECT_EQ(a.Accept(F(140), false), V::kRestart);  // 0.6 s before the newest
  FrameSequence b;                                  // numbers far back, time not
  b.Accept(F(1), false);
  b.Accept(F(2000), false);
  FrameSequence::Frame back = F(1000);
  back.timestamp_s = F(2000).timestamp_s - 0.1;
  EXPECT_EQ(b.Accept(back, false), V::kRestart);
}

TEST(NatNetFrameSequenceTest, AFrameSentAfterItsSuccessorIsARestart) {
  // A restarted Motive on a clock that ran on (the host's counter): frame 3's ticks lie after
  // those of frame 5, which a late frame 3 could not have.
  FrameSequence s;
  for (int32_t n : {1, 2, 5}) s.Accept(F(n), false);
  FrameSequence::Frame again = F(3, 1);
  again.transmit_ticks = F(5).transmit_ticks + 100'000;
  EXPECT_EQ(s.Accept(again, false), V::kRestart);
}

TEST(NatNetFrameSequenceTest, ForgettingStartsANewHistoryAndKeepsTheCounts) {
  FrameSequence s;
  for (int32_t n : {1, 3}) s.Accept(F(n), false);
  s.Forget();
  EXPECT_EQ(s.Accept(F(1, 1), false), V::kNext);
  EXPECT_EQ(s.restarts(), 0);
  EXPECT_EQ(s.lost(), 1);
}

TEST(NatNetFrameSequenceTest, AnOldTimestampWithARisingNumberIsARewind) {
  FrameSequence s;
  s.Accept(F(500), false);
  FrameSequence::Frame rewound = F(501);
  rewound.timestamp_s = 0.5;
  EXPECT_EQ(s.Accept(rewound, false), V::kRestart);
}

}  // namespace
}  // namespace ftcal::natnet
