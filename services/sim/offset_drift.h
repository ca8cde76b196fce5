// Offsets that move during a session (issue #40): the twin's transducer offsets as functions of
// time, so a tracker can be checked against a truth that drifts while the robot works.
//
// The report saw offsets move by up to 10 N between sessions; within one session three shapes
// are plausible and each is a term here, per leg and per axis [fx fy fz tx ty tz] (N, N*m):
//   - a ramp: a slow, steady creep (temperature, creep of the strain gauges' adhesive), linear
//     from `from_s` to `until_s` and held after, `change` being the whole change;
//   - a step: a leg knocks something and the zero jumps at `at_s`;
//   - a warm-up: the electronics settle after power-up, change * (1 - exp(-(t - from_s)/tau_s)).
// The terms add. OffsetChange(k, t) is what is added to leg k's reading at twin time t (the
// offsets of the truth calibration, or of the drifted truth after --drift-at-s, plus this).
//
// Flags (ftcal-sim log), repeatable, LEG a leg name or "all", six comma-separated numbers:
//   --drift-step   LEG:AT_S:fx,fy,fz,tx,ty,tz
//   --drift-ramp   LEG:FROM_S:UNTIL_S:fx,fy,fz,tx,ty,tz
//   --drift-warmup LEG:FROM_S:TAU_S:fx,fy,fz,tx,ty,tz
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"

namespace ftcal {

struct OffsetDriftTerm {
  enum class Shape { kStep, kRamp, kWarmup };
  Shape shape = Shape::kStep;
  int leg = 0;
  double t0_s = 0.0;  // step: at; ramp, warm-up: from
  double t1_s = 0.0;  // ramp: until; warm-up: tau
  Vec6 change = Vec6::Zero();
};

class OffsetDrift {
 public:
  // Throws std::invalid_argument naming the term for a leg out of range, a non-finite number,
  // a ramp that ends before it starts or a warm-up with tau <= 0.
  void Add(const OffsetDriftTerm& term);
  // Parses one flag's text (header) for `shape`; `flag` names it in errors. "all" adds a term
  // per leg.
  void AddFlag(OffsetDriftTerm::Shape shape, const std::string& text, const std::string& flag);
  bool empty() const { return terms_.empty(); }
  const std::vector<OffsetDriftTerm>& terms() const { return terms_; }

  // What is added to leg k's offsets at twin time t (zero before any term starts).
  Vec6 OffsetChange(int leg, double t_s) const;

 private:
  std::vector<OffsetDriftTerm> terms_;
};

// The drifted truth over time as CSV, one row per leg every `period_s` of twin time from 0 to
// end_s (and at end_s), and at both sides of every step (so a step is exact in the file):
//   t_s, utime, leg, d_fx_n .. d_tz_nm (the change from the calibration-time offsets),
//   offset_fx_n .. offset_tz_nm (the offsets the transducer then had).
// `offsets_at` gives the offsets before the drift terms at a time (the truth's, or the drifted
// truth's after --drift-at-s); `utime_at` the log's host time of a twin time.
std::string DriftTruthCsv(const OffsetDrift& drift, const RobotCalibration& truth,
                          const std::function<const RobotCalibration&(double)>& offsets_at,
                          const std::function<int64_t(double)>& utime_at, double end_s,
                          double period_s);

}  // namespace ftcal
