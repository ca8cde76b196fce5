// Offsets tracked while the robot works (docs/method.md "Offset drift while the robot works";
// issue #40): the live generalisation of offset_reestimation.h's unloaded-leg equations.
//
// Model. A leg in the air and quasi-static carries no ground wrench and no inertial load, so
// its transducer reads its own leg's gravity plus its offset (eq. 1-3 with w_gc = 0):
//   w_m,k = X(X_C_ft,k)^-1 w^C_leg,k(phi_k, g^C) + w_o,k + d_k + n,
// with w_o,k the calibration's offset and d_k the offset's change since (the drift). The leg's
// gravity is the calibration's (m_k, r_k(phi), R~_k, p~'_k) with g^C from the body's attitude:
//   y_k = w_m,k - w_o,k - X(X_C_ft,k)^-1 w^C_leg,k = d_k + n    (UnloadedResidual)
// is a direct observation of all six components of d_k: the observation matrix is I.
// Unknowns: d_k (6 per leg), each a random walk d(t + dt) = d(t) + v, v ~ N(0, Q dt) with
// Q = diag(process_noise^2) from the config. No null space: every component is observed in
// every window (a standing robot sees only the sum over legs, offset_reestimation.h; that sum is
// kept here as a check, the balance residual, not as an observation).
//
// Estimator: one 6-state Kalman filter per leg (H = I), updated once per window (below) with
// the window's mean y and its covariance (the scatter of its bins over their number, plus a
// configured floor for what the model misses). A Kalman filter and not a sliding-window least
// squares: with a random-walk state the filter *is* the optimal smoother's forward pass, it
// costs O(1) per window where a window of the last N updates costs O(N), its sigma grows
// between windows as the drift could (the sliding window has no model of the time between
// windows), and the process noise, not a window length, sets how fast it follows.
//
// Windows. Samples are binned per leg in bins of bin_s (the transducers run at up to 7 kHz;
// the leg's gravity changes on the servo's time scale). A bin qualifies when the leg's foot
// force, |f| of eq. 3's ground wrench with the offsets tracked so far (|y_f - d_f|: a rotation
// keeps the norm), is below max_foot_force_n, the shaft's angular acceleration (a second
// difference over +-accel_baseline_s of the servo angles) is below max_shaft_accel_rad_s2 (the
// leg's inertia must not be taken for an offset), its speed below max_shaft_speed_rad_s (the
// centripetal force m w^2 r; 0: no limit), and a fresh attitude and servo state exist. A run of
// qualifying bins is a window; it is cut at max_window_s (no trim there), its ends next to a
// bin that did not qualify lose edge_trim_s (lift-off and touch-down load the leg gradually),
// and it is used when min_window_s of it remain.
//
// Balance (the check): at every bin instant where all six legs have a bin, the six ground
// wrenches moved to the CoM in W, summed, against (0, 0, G, 0, 0, 0) (eq. 8's target, as the
// corrector publishes it), with the calibration's offsets and with the tracked ones; counted
// when at least three feet carry load (the robot stands or walks), not in a hanging phase.
#pragma once

#include <array>
#include <cstdint>
#include <deque>
#include <map>
#include <optional>
#include <vector>

#include "ftcal/aligner.h"
#include "ftcal/experiment_phase.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"

namespace ftcal {

struct OffsetTrackerOptions {
  double bin_s = 0.01;
  double max_foot_force_n = 4.0;
  double max_shaft_accel_rad_s2 = 2.0;
  double max_shaft_speed_rad_s = 0.0;  // 0: no limit
  double accel_baseline_s = 0.05;
  double min_window_s = 0.5;
  double max_window_s = 5.0;
  double edge_trim_s = 0.2;
  double max_servo_age_s = 0.05;
  double max_mocap_age_s = 0.05;
  // Random-walk density of the offsets, per sqrt(s): [N x3, N*m x3].
  Vec6 process_noise = (Vec6() << 0.01, 0.01, 0.01, 5e-4, 5e-4, 5e-4).finished();
  // Prior sigma of the change at the start (the offsets may have moved since the calibration).
  Vec6 initial_sigma = (Vec6() << 5.0, 5.0, 5.0, 0.2, 0.2, 0.2).finished();
  // Added (in quadrature) to a window's sigma: what averaging does not remove.
  Vec6 window_floor = Vec6::Zero();
};

// One used window of one leg.
struct DriftWindow {
  int leg = 0;
  int64_t utime = 0;  // mean time of its bins
  double seconds = 0.0;
  Vec6 mean = Vec6::Zero();   // mean y: the observed change
  Vec6 sigma = Vec6::Zero();  // its sigma (scatter over bins / sqrt(bins), floor)
};

struct LegDrift {
  Vec6 change = Vec6::Zero();  // d_k, [N; N*m] in ft_k
  Vec6 sigma = Vec6::Zero();   // at the time asked, grown by the process noise since the update
  int64_t windows = 0;
  double window_seconds = 0.0;    // of data used
  int64_t last_window_utime = 0;  // 0: none yet
};

// The summed ground wrenches' residual against (0, 0, G, 0, 0, 0) over the bin instants
// counted: |f| and |tau| with the calibration's offsets [0] and with the tracked ones [1].
struct BalanceStats {
  int64_t count = 0;
  double sq_force[2] = {0.0, 0.0};  // sums of |f|^2, N^2
  double sq_torque[2] = {0.0, 0.0};
  double ForceRmsN(int tracked) const;
  double TorqueRmsNm(int tracked) const;
  void Add(const BalanceStats& o);
};

struct OffsetTrackerCounters {
  int64_t ft_in = 0, servo_in = 0, mocap_in = 0;
  int64_t out_of_order = 0, non_finite = 0;
  int64_t bins = 0;
  int64_t bins_air = 0;       // qualified
  int64_t bins_loaded = 0;    // foot force at or above the limit
  int64_t bins_moving = 0;    // shaft acceleration or speed over its limit
  int64_t bins_no_servo = 0;  // no servo state bracketing the bin's instants
  int64_t bins_no_attitude = 0;
  int64_t windows_used = 0, windows_short = 0;
};

// Leg k's reading when nothing touches its foot, without offset: X(X_C_ft,k)^-1 w^C_leg,k.
Vec6 UnloadedReading(const RobotCalibration& cal, int k, double angle_rad, const Mat3& R_WC);

// Drift beyond what the calibration itself is sure of (ftcal-drift's WARN): component i is
// flagged when |d_i| > max(factor * calibration_sigma_i, min_change_i), the calibration's own
// 1-sigma of that offset scaled, and the tracker is sure of it (|d_i| > 3 sigma_i): a tracker
// that has not yet seen a window (sigma = its prior) never warns. Bit i set for component i.
int DriftBeyondCalibration(const LegDrift& d, const Vec6& calibration_sigma, double factor,
                           const Vec6& min_change);

// ftcal-drift --apply's test of one leg (docs/method.md, "Applying the tracked offsets"):
// component i is significant when the tracker is sure of its change by `factor`,
// |d_i| > factor * sigma_i, and the change is more than the calibration itself is unsure of,
// |d_i| > max(calibration_sigma_i, min_change_i): a new calibration then holds a better offset
// than the old. Bit i set for component i.
int DriftSignificant(const LegDrift& d, const Vec6& calibration_sigma, double factor,
                     const Vec6& min_change);

struct DriftApplyPolicy {
  double factor = 5.0;
  Vec6 min_change = Vec6::Zero();
  double min_interval_s = 60.0;
};

// The legs whose tracked offsets go into a new calibration at `utime` (bit k for leg k; 0:
// none, publish nothing): those with a significant component (DriftSignificant), and none
// before policy.min_interval_s has passed since `last_apply_utime` (0: nothing applied yet).
int LegsToApply(const std::array<LegDrift, kNumLegs>& drift,
                const std::array<Vec6, kNumLegs>& calibration_sigma, const DriftApplyPolicy& policy,
                int64_t utime, int64_t last_apply_utime);

class OffsetTracker {
 public:
  // Throws std::invalid_argument naming the option that is not finite or out of range.
  OffsetTracker(const OffsetTrackerOptions& options, const RobotCalibration& cal);

  // Each returns false when the input was dropped (out of order, non-finite: counted).
  bool AddFt(const FtInput& in);
  bool AddServo(const ServoInput& in);
  bool AddMocap(const MocapInput& in);
  void SetPhase(ExperimentPhase phase) { phase_ = phase; }
  // The input ended: the bins and windows still open are judged with what there is.
  void Finish();

  // Leg k's tracked change, its sigma grown to `utime` (not before the last update).
  LegDrift Drift(int leg, int64_t utime) const;
  // The calibration's offsets plus the tracked changes.
  RobotCalibration TrackedCalibration() const;
  // The windows used since the last call (oldest first), and the balance since the last call.
  std::vector<DriftWindow> TakeWindows();
  BalanceStats TakeBalance();
  const BalanceStats& balance_total() const { return balance_total_; }
  const OffsetTrackerCounters& counters() const { return counters_; }
  int64_t newest_utime() const { return newest_utime_; }

 private:
  struct Bin {
    int64_t index = 0;
    int64_t utime_sum = 0;  // relative to index * bin_us
    Vec6 sum = Vec6::Zero();
    int n = 0;
  };
  struct Judged {
    int64_t utime = 0;
    Vec6 y = Vec6::Zero();
  };
  struct Leg {
    Bin open;
    std::deque<Bin> pending;  // closed, waiting for the servo and mocap to pass them
    std::vector<Judged> window;
    bool window_trim_start = true;
    int64_t last_ft_utime = INT64_MIN;
    // Kalman state.
    Vec6 x = Vec6::Zero();
    Mat6 P = Mat6::Zero();
    int64_t updated_utime = 0;  // 0: prior only
    int64_t windows = 0;
    double window_seconds = 0.0;
  };
  struct Slot {
    int have = 0;  // bit per leg
    int loaded = 0;
    bool ok = true;
    Vec6 sum[2] = {Vec6::Zero(), Vec6::Zero()};
  };

  void CloseBin(int k);
  void JudgePending(int k, bool input_ended);
  void JudgeBin(int k, const Bin& bin);
  void CloseWindow(int k, bool trim_end);
  void Update(int k, const DriftWindow& w);
  const MocapInput* MocapNearest(int64_t utime) const;
  void AddToBalance(int64_t index, int k, bool ok, bool loaded, const Vec6& y, const Mat3& R_WC);

  OffsetTrackerOptions options_;
  RobotCalibration cal_;
  std::array<Pose3, kNumLegs> X_C_ft_;
  int64_t bin_us_, baseline_us_, max_servo_age_us_, max_mocap_age_us_;
  ExperimentPhase phase_ = ExperimentPhase::kIdle;
  ServoHistory servo_{256};
  std::optional<MocapInput> mocap_;
  std::deque<MocapInput> mocap_history_;
  std::array<Leg, kNumLegs> leg_;
  std::map<int64_t, Slot> slots_;
  std::vector<DriftWindow> windows_;
  BalanceStats balance_, balance_total_;
  int64_t newest_utime_ = 0;
  OffsetTrackerCounters counters_;
};

}  // namespace ftcal
