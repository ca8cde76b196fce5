#include "ftcal/experiment_phase.h"

#include <utility>

namespace ftcal {

PhaseChange PhaseTracker::OnMarker(int code, bool start, const std::string& session) {
  PhaseChange c;
  const bool same = open() && open_.code == code && open_.session == session;
  if (!start) {
    if (!same) {
      c.stray_stop = true;
      c.closed = MarkedPhase{code, session};  // what the stray stop named
      return c;
    }
    c.closes = true;
    c.completed = true;
    c.closed = std::exchange(open_, MarkedPhase{});
    return c;
  }
  if (same) {
    c.repeated = true;
    return c;
  }
  if (open()) {
    c.closes = true;
    c.closed = open_;
  }
  open_ = MarkedPhase{code, session};
  c.opens = true;
  c.opened = open_;
  return c;
}

PhaseChange PhaseTracker::End() {
  PhaseChange c;
  if (!open()) return c;
  c.closes = true;
  c.closed = std::exchange(open_, MarkedPhase{});
  return c;
}

}  // namespace ftcal
