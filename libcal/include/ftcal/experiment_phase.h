// The EXPERIMENT markers' rules, once, for every stage that follows the experiment's phases
// (ftcal-pose-segmenter, ftcal-calibrator's collector). Transport-free: a marker is its phase
// code, start/stop edge and session id, whatever carried it.
//
// Markers are edges, and a stage may hear them in any order a network or an operator makes:
//   - a start opens that phase of that session;
//   - a start of the phase and session already open changes nothing: the sequencer repeats
//     the start marker while a phase runs, so that a stage restarted mid-phase picks it up;
//   - a start while another phase (or the same phase of another session) is open closes the
//     open one as not completed, then opens the new one;
//   - the stop marker of the open phase and session closes it as completed;
//   - a stop marker that matches no open phase is a stray: ignored, and said so;
//   - the end of the input closes an open phase as not completed.
// What a stage does with a phase that closed not completed is its own policy (the calibrator
// discards it; the segmenter keeps the poses it already published).
#pragma once

#include <cstdint>
#include <string>

namespace ftcal {

// The EXPERIMENT phase codes, the same values as experiment_marker_t's constants (checked in
// services/common/messages.cc; libcal-side code never includes the generated LCM headers).
enum class ExperimentPhase : int8_t {
  kIdle = 0,
  kHangXPos = 1,
  kHangXNeg = 2,
  kHangZPos = 3,
  kHangZNeg = 4,
  kStanding = 5,
  kWalking = 6,
  kTripod = 7,
  kTare = 8,  // naive tare: upright, feet in the air, shaft angles 0
};

struct MarkedPhase {
  int code = -1;  // an ExperimentPhase code as the marker carried it; -1: none
  std::string session;
  bool operator==(const MarkedPhase& o) const { return code == o.code && session == o.session; }
};

// What one marker did. `closed` and `opened` are meaningful when `closes` / `opens` are set;
// when a start replaces an open phase, both are.
struct PhaseChange {
  bool closes = false;
  bool completed = false;  // `closed` ended by its own stop marker
  bool opens = false;
  bool repeated = false;    // a start of the phase already open: nothing changed
  bool stray_stop = false;  // a stop of no open phase: nothing changed
  MarkedPhase closed;
  MarkedPhase opened;
};

class PhaseTracker {
 public:
  PhaseChange OnMarker(int code, bool start, const std::string& session);
  // The input ended: an open phase closes, not completed.
  PhaseChange End();

  bool open() const { return open_.code >= 0; }
  // The open phase ({-1, ""} when none).
  const MarkedPhase& current() const { return open_; }

 private:
  MarkedPhase open_;
};

}  // namespace ftcal
