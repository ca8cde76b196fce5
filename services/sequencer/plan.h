// An experiment plan (config.proto ExperimentPlan) turned into the schedule the sequencer runs.
//
// The schedule is a flat list of steps in time order. A phase opens with its preparation
// (operator confirmation where the phase needs one, the pre-checks of its kind, the move to its
// first shaft angles) and the EXPERIMENT start marker; its body is moves, holds and turns; it
// ends with the stop marker. Goals are absolute shaft angles (rad, 0 = leg straight down, the
// config's leg order). Every goal of the schedule lies inside the servos' configured limits
// minus the margin, and every move is timed so that no shaft exceeds max_velocity_rad_s:
// Expand() refuses a plan that cannot keep either, naming the phase and the number.
//
// Resuming: the body steps that begin a unit of work the calibrator can use on its own (a
// standing pose, a tripod stance) are resume points. After an abort or a restart the sequencer
// re-runs the phase's preparation, then continues at the last resume point at or before the
// first unfinished step; a hanging series, a tare and a walk are one unit each and restart whole.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "ftcal/legs.h"
#include "proto/config.pb.h"

namespace ftcal::sequencer {

using Angles = std::array<double, kNumLegs>;

enum class StepKind {
  kConfirm,      // wait for the operator (terminal prompt, LCM or --yes)
  kPrecheck,     // the phase's pre-checks must pass before anything moves
  kMarkerStart,  // publish the EXPERIMENT start marker of the phase
  kMarkerStop,   // ... and its stop marker
  kMove,         // from `from` to `to` along a smooth blend in duration_s
  kHold,         // hold `to` for duration_s (counted from arrival)
  kTurn,         // every leg turns: from + dir * HangSweepAngle(t, cycle_s, cycles) (varying speed)
  kWalk,         // the Buehler-clock tripod gait for duration_s
};

// What the pre-checks of a phase require of the robot before it starts.
enum class Precheck { kNone, kAirborne, kStanding };

struct Step {
  StepKind kind = StepKind::kHold;
  int phase = 0;                        // index into the plan's phases
  int8_t marker = 0;                    // experiment_marker_t phase constant of this step's phase
  double duration_s = 0.0;              // kMove, kHold, kTurn, kWalk
  Angles from{};                        // goals at the step's start
  Angles to{};                          // goals at its end
  Precheck precheck = Precheck::kNone;  // kPrecheck
  int unit = -1;  // standing pose / tripod stance index within the phase, else -1
  bool resume_point = false;
  // kTurn: one full leg cycle every cycle_s, in the direction of `direction` per leg.
  double cycle_s = 0.0;
  Angles direction{};
  // kWalk
  double clock_hz = 0.0, duty = 0.0;
  Angles sweep_rad{};  // per leg: the stance sweep (left and right differ to turn)
  std::string prompt;  // kConfirm: what the operator is asked to do
};

struct Schedule {
  std::string plan_name;
  std::vector<Step> steps;
  // The gravity direction in B the operator states for each hanging phase (zero otherwise),
  // carried in the marker (experiment_marker_t.gravity_b).
  std::vector<std::array<double, 3>> phase_gravity_b;
  std::vector<std::string> phase_names;
  std::vector<int8_t> phase_marker;  // experiment_marker_t phase of each plan phase
  double duration_s = 0.0;           // the sum of the timed steps (confirmations take no time)
};

// The plan named `plan_name` ("" = the config's first plan). Throws std::invalid_argument with
// the plan, phase and number named when the plan is missing, or a goal or speed would break a
// limit.
Schedule Expand(const config::Config& config, const std::string& plan_name);

// How long a smooth move from `from` to `to` takes so that no shaft's peak speed exceeds
// `max_velocity_rad_s` (never shorter than the servos' profile needs).
double MoveDurationS(const Angles& from, const Angles& to, double max_velocity_rad_s);

// The goals of `step` at `t` seconds into it (clamped to [0, duration]).
Angles GoalAt(const Step& step, double t);

// The shaft angles of every pose of a standing grid: {angles}^6 in reflected Gray order
// (consecutive poses differ in one leg, by one grid step).
std::vector<Angles> GrayGrid(const std::vector<double>& angles_rad);

// The marker phase (experiment_marker_t constant) of a plan phase.
int8_t MarkerOf(const config::PlanPhase& phase);

// The legs of the two tripods (HL FL MR, and ML HR FR).
inline constexpr std::array<int, kNumLegs> kTripodOf = {0, 1, 0, 1, 0, 1};

}  // namespace ftcal::sequencer
