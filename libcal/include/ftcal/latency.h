// Latencies the data reveals (docs/method.md "Clocks and delays", "Latencies"): a constant delay
// of the servo stream against the transducer stream, estimated from the hanging series, and the
// speed profile of a hanging sweep that makes it identifiable.
//
// Model. tau_servo (s) is the servo's delay relative to the transducer's: a servo state stamped
// u describes the shaft at the instant a transducer sample stamped u - tau_servo describes. The
// angle that belongs to a transducer sample stamped t is then the servo stream's at t + tau,
// ~ theta(t) + tau omega(t). Hanging, each transducer's gravity direction is fixed in ft_k for a
// series, so its torque is a smooth periodic function of the shaft angle alone (eq. 4-7:
// r(phi) x m g + tau_o): per leg and series, a Fourier series of the angle to `harmonics` orders,
// its coefficients linear unknowns (projected out: variable projection). tau is one unknown
// shared by every leg and series (one bus, one adapter), solved by Ceres; sigma from its
// covariance scaled by the reduced chi^2, or from the spread of the per-leg-and-series estimates
// when that is larger.
//
// Why the sweep speed must vary: at a constant speed omega the delay shifts every angle by the
// same omega tau, which the Fourier coefficients (a phase offset, i.e. the encoder's zero) absorb
// whole; and with a speed that is a function of the shaft angle alone, omega(theta) tau is again a
// fixed re-parametrisation of the angle that the series absorbs. Only a speed that differs
// between visits to the same angle separates the two: HangSweepAngle modulates the speed at 1.5
// periods per leg cycle, so consecutive cycles pass each angle at different speeds.
//
// Model selection: BIC of the fits with and without tau over the same residuals (each leg and
// series' torque components scaled by their rms at tau = 0); tau is applied when it lowers the
// BIC.
#pragma once

#include <vector>

#include "ftcal/dataset.h"

namespace ftcal {

// The relative amplitude of the hanging sweep's speed modulation: speed (1 +- this) x mean.
inline constexpr double kHangSweepSpeedDepth = 0.5;

// Shaft angle (rad, from the sweep's start angle) of a hanging sweep of `cycles` leg cycles of
// mean duration `cycle_s`, `t_s` after its start: mean rate 2 pi / cycle_s, modulated
// (1 + depth sin(W t)) with W chosen so that the whole sweep holds a whole number of modulation
// periods near 1.5 per cycle (then it ends at exactly 2 pi cycles, at the mean rate). Clamped
// to [0, cycles cycle_s]. Used by the sequencer's hanging turns and the twin's hanging series.
double HangSweepAngle(double t_s, double cycle_s, int cycles, double depth = kHangSweepSpeedDepth);
// Its peak rate, rad/s: (1 + depth) 2 pi / cycle_s.
double HangSweepPeakRate(double cycle_s, double depth = kHangSweepSpeedDepth);

struct ServoDelayOptions {
  int harmonics = 3;                 // Fourier orders of the torque model per leg and series
  double derivative_window_s = 0.1;  // omega: central difference of the angle over this span
  double max_delay_s = 0.2;          // bound on |tau| for the solver
};

struct ServoDelayEstimate {
  bool estimated = false;             // false: too little data (fewer than 2 leg-and-series groups)
  double delay_s = 0.0;               // tau_servo
  double sigma_s = 0.0;               // max(sigma_covariance_s, sigma_spread_s)
  double sigma_covariance_s = 0.0;    // Ceres covariance x reduced chi^2
  double sigma_spread_s = 0.0;        // standard error over the per-group estimates
  int groups = 0;                     // legs x series
  std::vector<double> group_delay_s;  // each leg and series alone (recording-major, leg-minor)
  long residuals = 0;                 // N: torque components used
  int parameters_without = 0;         // linear coefficients (the model without tau)
  double rss_without = 0.0, rss_with = 0.0;  // scaled residuals
  double bic_without = 0.0, bic_with = 0.0;
  double delta_bic = 0.0;  // bic_with - bic_without; < 0 selects tau
  bool selected = false;
};

// Estimates tau_servo from the hanging recordings (each sample's angle the servo stream's at the
// sample's own time, as the aligner pairs them). Throws std::invalid_argument naming the series
// and leg for non-finite or unordered samples, or options out of range.
ServoDelayEstimate EstimateServoDelay(const std::vector<HangingRecording>& recordings,
                                      const ServoDelayOptions& options = ServoDelayOptions());

// The recordings with each sample's angle taken at t + delay_s (linear interpolation of the
// unwrapped angle series, extrapolated at the ends by the nearest pair), wrapped to (-pi, pi].
std::vector<HangingRecording> ShiftServoAngles(const std::vector<HangingRecording>& recordings,
                                               double delay_s);

}  // namespace ftcal
