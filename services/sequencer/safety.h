// The sequencer's safety rules, transport-free: what the robot must look like before a phase
// starts and while it runs. Each check returns the first violation as a sentence that names the
// measured number and the limit (config section `sequencer`), or nothing.
//
//   before hanging / tare:  the transducers' summed force opposes gravity by at most
//                           airborne_max_support_n (the robot is in the air, its legs hanging
//                           from it), and, when motion capture is present, gravity within
//                           mocap.hang_axis_tolerance_deg of the stated body axis;
//   before standing:        motion capture shows the body tilted less than max_tilt_deg, and
//                           the summed vertical force (nominal transducer rotations) is within
//                           [standing_min_weight_share, standing_max_weight_share] of m g;
//   always, while moving:   every input fresher than max_input_age_s (six transducers, the
//                           servos, and motion capture where the phase needs it), every bridge's
//                           FTCAL_STATUS RUNNING, no transducer beyond its rated range or
//                           flagged saturated, and (standing phases) the tilt below max_tilt_deg.
#pragma once

#include <array>
#include <cstdint>
#include <deque>
#include <map>
#include <set>
#include <optional>
#include <string>

#include "ftcal/aligner.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "proto/config.pb.h"

namespace ftcal::sequencer {

struct StatusReading {
  int64_t utime = 0;
  int8_t state = 0;  // service_status_t state
  std::string last_error;
  // The Dynamixel bridge's command gate mode (its `mode` counter: CommandGate::Mode), -1 when
  // the status carries none.
  int mode = -1;
};

// The latest of every input, as the sequencer last saw it.
struct Inputs {
  std::array<std::optional<FtInput>, kNumLegs> ft;  // a message's extremes (sequencer.cc)
  std::optional<ServoInput> servo;
  std::optional<MocapInput> mocap;
  // Bridges' heartbeats by process name (ftcal-ati-bridge, ...; only the names the sequencer
  // watches, WatchedStatusNames): every one heard in the last kStatusExpiryS must be RUNNING; a
  // bridge that has gone quiet is caught by its data's age.
  std::map<std::string, StatusReading> status;
};

// A heartbeat comes once a second: one older than this says nothing about the process now (an
// entry heard once, forged or from a process gone since, must not hold a verdict forever).
constexpr double kStatusExpiryS = 2.5;

// The heartbeat names whose state gates the motion: the bridges this config needs
// (ftcal-ati-bridge, ftcal-dynamixel-bridge, and ftcal-mocap-bridge or ftcal-natnet-bridge by
// mocap.system) and the other bridges (status name ending in "-bridge") of the config's launch
// group that runs ftcal-sequencer. Any other name is not the sequencer's business.
std::set<std::string> WatchedStatusNames(const config::Config& config);

// The spans in which the sequencer itself did not run (a write blocked in fsync, the scheduler
// gave its core away). An input's age counts only the time the sequencer was listening: after
// its own stall it has not yet read what queued meanwhile, and a bridge must not be blamed for
// that. Only the stalls are taken out, so a sequencer that stalls often still sees a dead
// input once it has listened for max_input_age_s.
class OwnStalls {
 public:
  // A gap between two readings of the clock longer than this is a stall (the loop runs every
  // 20 ms; a busy machine delays it by tens of milliseconds).
  static constexpr int64_t kStallUs = 100'000;
  // Stalls older than this are forgotten (far beyond any sensible max_input_age_s).
  static constexpr int64_t kMemoryUs = 60'000'000;

  // The sequencer runs at `now_utime`; returns the stall it ended, in microseconds, or 0.
  int64_t Awake(int64_t now_utime);
  // How much of (since_utime, now_utime] the sequencer spent stalled.
  int64_t StalledUs(int64_t since_utime, int64_t now_utime) const;

 private:
  struct Span {
    int64_t from, to;
  };
  int64_t last_utime_ = 0;
  std::deque<Span> stalls_;
};

class Safety {
 public:
  explicit Safety(const config::Config& config);

  // Inputs missing or older than max_input_age_s at `now_utime` (not counting the sequencer's
  // own stalls), or a bridge not RUNNING.
  std::optional<std::string> Stale(const Inputs& in, int64_t now_utime, bool need_mocap,
                                   const OwnStalls& own = OwnStalls()) const;
  // A transducer beyond its rated range or flagged saturated.
  std::optional<std::string> OverRange(const Inputs& in) const;
  // The body tilted further than max_tilt_deg (needs a tracked motion-capture frame).
  std::optional<std::string> Tilted(const Inputs& in) const;
  // Pre-checks of a hanging (or tare) phase; `stated_gravity_b` is zero for the tare (upright).
  std::optional<std::string> Airborne(const Inputs& in, const Vec3& stated_gravity_b) const;
  // Pre-checks of a standing phase.
  std::optional<std::string> Standing(const Inputs& in) const;

  static double TiltDeg(const Mat3& R_WC);

 private:
  const config::Config& config_;
  const config::Sequencer& seq_;
  std::array<Mat3, kNumLegs> R_B_ft_;
  std::array<Vec6, kNumLegs> rated_;  // per axis; +inf where the config gives none
  double weight_n_;
};

}  // namespace ftcal::sequencer
