// The EXPERIMENT marker rules (ftcal/experiment_phase.h), marker by marker, against what each
// rule says by hand.
#include "ftcal/experiment_phase.h"

#include <gtest/gtest.h>

namespace ftcal {
namespace {

constexpr int kStanding = static_cast<int>(ExperimentPhase::kStanding);
constexpr int kTripod = static_cast<int>(ExperimentPhase::kTripod);
constexpr int kTare = static_cast<int>(ExperimentPhase::kTare);

TEST(PhaseTrackerTest, AStartThenItsStopOpensAndCompletesThePhase) {
  PhaseTracker t;
  EXPECT_FALSE(t.open());
  const PhaseChange a = t.OnMarker(kStanding, true, "s1");
  EXPECT_TRUE(a.opens);
  EXPECT_FALSE(a.closes);
  EXPECT_EQ(a.opened, (MarkedPhase{kStanding, "s1"}));
  EXPECT_EQ(t.current(), (MarkedPhase{kStanding, "s1"}));
  const PhaseChange b = t.OnMarker(kStanding, false, "s1");
  EXPECT_TRUE(b.closes);
  EXPECT_TRUE(b.completed);
  EXPECT_FALSE(b.opens);
  EXPECT_EQ(b.closed, (MarkedPhase{kStanding, "s1"}));
  EXPECT_FALSE(t.open());
  EXPECT_EQ(t.current().code, -1);
}

TEST(PhaseTrackerTest, ARepeatedStartOfTheOpenPhaseAndSessionChangesNothing) {
  PhaseTracker t;
  t.OnMarker(kStanding, true, "s1");
  for (int i = 0; i < 3; ++i) {
    const PhaseChange c = t.OnMarker(kStanding, true, "s1");
    EXPECT_TRUE(c.repeated);
    EXPECT_FALSE(c.opens);
    EXPECT_FALSE(c.closes);
  }
  EXPECT_TRUE(t.OnMarker(kStanding, false, "s1").completed);
}

TEST(PhaseTrackerTest, AStartWhileAnotherPhaseIsOpenClosesItNotCompleted) {
  PhaseTracker t;
  t.OnMarker(kTare, true, "s1");
  const PhaseChange c = t.OnMarker(kStanding, true, "s1");
  EXPECT_TRUE(c.closes);
  EXPECT_FALSE(c.completed);
  EXPECT_EQ(c.closed, (MarkedPhase{kTare, "s1"}));
  EXPECT_TRUE(c.opens);
  EXPECT_EQ(c.opened, (MarkedPhase{kStanding, "s1"}));
  // The same phase of another session is another phase.
  const PhaseChange d = t.OnMarker(kStanding, true, "s2");
  EXPECT_TRUE(d.closes);
  EXPECT_FALSE(d.completed);
  EXPECT_EQ(d.closed, (MarkedPhase{kStanding, "s1"}));
  EXPECT_EQ(d.opened, (MarkedPhase{kStanding, "s2"}));
  // The replaced phase's stop is now a stray.
  EXPECT_TRUE(t.OnMarker(kStanding, false, "s1").stray_stop);
  EXPECT_EQ(t.current(), (MarkedPhase{kStanding, "s2"}));
}

TEST(PhaseTrackerTest, AStopOfNoOpenPhaseIsAStrayAndLeavesTheOpenPhaseOpen) {
  PhaseTracker t;
  const PhaseChange none = t.OnMarker(kTripod, false, "s1");
  EXPECT_TRUE(none.stray_stop);
  EXPECT_FALSE(none.closes);
  EXPECT_EQ(none.closed, (MarkedPhase{kTripod, "s1"}));  // what it named
  t.OnMarker(kTripod, true, "s1");
  for (const auto& [code, session] : {std::pair{kStanding, "s1"}, std::pair{kTripod, "s0"}}) {
    const PhaseChange c = t.OnMarker(code, false, session);
    EXPECT_TRUE(c.stray_stop) << code << " " << session;
    EXPECT_FALSE(c.closes);
    EXPECT_FALSE(c.opens);
  }
  EXPECT_EQ(t.current(), (MarkedPhase{kTripod, "s1"}));
}

TEST(PhaseTrackerTest, TheEndOfTheInputClosesAnOpenPhaseNotCompleted) {
  PhaseTracker t;
  EXPECT_FALSE(t.End().closes);
  t.OnMarker(kStanding, true, "s1");
  const PhaseChange c = t.End();
  EXPECT_TRUE(c.closes);
  EXPECT_FALSE(c.completed);
  EXPECT_EQ(c.closed, (MarkedPhase{kStanding, "s1"}));
  EXPECT_FALSE(t.open());
  EXPECT_FALSE(t.End().closes);
}

}  // namespace
}  // namespace ftcal
