// Step 1 of the method (docs/method.md "Step 1", report section III-A): from four hanging series,
// per leg the transducer offsets w_o = [f_o; tau_o], the leg weight m g and the leg CoM r(phi),
// each with a 1-sigma uncertainty, plus the baselines the report compares against (naive tare,
// the step without the misalignments s) and the hanging residual statistics (report Fig. 5).
//
// Uncertainties come from the spread over leg cycles: every quantity is also estimated from
// each full cycle alone, and its sigma is the standard error of those per-cycle values
// (calibration.proto: hanging_uncertainty = CYCLE_SPREAD).
#pragma once

#include <array>
#include <limits>
#include <string>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

inline std::array<Vec6, kNumLegs> UnlimitedRatedRange() {
  std::array<Vec6, kNumLegs> r;
  for (Vec6& v : r) v.setConstant(std::numeric_limits<double>::infinity());
  return r;
}

struct HangingOptions {
  // Phase grid for matching the two series of a pair: bins per leg cycle.
  int phase_bins = 200;
  // RTS smoother of the leg CoM (random-walk state r): variances on the diagonal.
  double smoother_transition_var_m2 = 0.01;
  double smoother_observation_var_nm2 = 0.01;
  // exp([s]) instead of I + [s] (docs/method.md, beyond the report): removes the low bias of m g.
  bool exact_rotations = false;
  // A series whose gravity (stated, or measured by motion capture) is farther than this from
  // a transducer axis is refused.
  double axis_tolerance_rad = 10.0 * M_PI / 180.0;
  // Fewest full leg cycles per series (the sigmas come from the spread over cycles).
  int min_cycles = 2;
  // Empty phase bins inside a series are interpolated from their neighbours across at most
  // this many bins; a longer gap leaves the bin out of the match.
  int max_gap_bins = 5;
  // Fraction of the phase bins that must be matched at least once in all four series.
  double min_phase_coverage = 0.95;
  // Naive tare baseline: samples of the upright series within this of theta = 0.
  double naive_tare_max_angle_rad = 5.0 * M_PI / 180.0;
  // Refine s+ by minimising the report's objective (Ceres, L-BFGS) after the closed form.
  bool refine_s_plus = true;
  // Per leg, the transducer's rated range per component [f; tau] (config ati.rated_range): a
  // sample with any |component| beyond it is saturated and left out of every fit (its phase
  // bins then fall out of the match like any gap). Infinite: no limit.
  std::array<Vec6, kNumLegs> rated_range = UnlimitedRatedRange();
};

// The rated ranges of the config's transducers (robot.leg[k].ati.rated_range; a leg without
// one keeps no limit).
void SetRatedRanges(const config::Robot& robot, HangingOptions* options);

// Options from the config (Calibrator: phase_bins, smoother variances,
// exact_hanging_rotations; Mocap: hang_axis_tolerance_deg).
HangingOptions HangingOptionsFromConfig(const config::Calibrator& calibrator,
                                        const config::Mocap& mocap);

// "HANG_X_POS", ... (the EXPERIMENT marker names), for messages and reports.
std::string HangSeriesName(HangSeries series);

struct ScalarSigma {
  double value = 0.0;
  double sigma = 0.0;
};

struct Vec3Sigma {
  Vec3 value = Vec3::Zero();
  Vec3 sigma = Vec3::Zero();
};

// One pair (x or z) before the two pairs are combined.
struct HangingPairResult {
  char axis = 'x';                             // transducer axis along gravity: 'x' or 'z'
  HangSeries down_series = HangSeries::kXPos;  // gravity along +axis in ft_k
  HangSeries up_series = HangSeries::kXNeg;    // gravity along -axis in ft_k
  Vec3Sigma s_plus_rad;   // (s_down + s_up)/2; component about the axis held at 0
  Vec3Sigma s_minus_rad;  // (s_down - s_up)/2; component about the axis held at 0
  ScalarSigma weight_n;   // m g
  Vec3Sigma force_offset_n;
  Vec3Sigma torque_offset_nm;
  int matched_samples = 0;
  int cycles = 0;  // full cycles behind the sigmas
};

// Statistics of a wrench residual [f; tau] per component.
struct WrenchResidualStats {
  std::string label;
  int count = 0;
  Vec6 mean = Vec6::Zero();
  Vec6 std = Vec6::Zero();
  Vec6 rms = Vec6::Zero();
  Vec6 p05 = Vec6::Zero();
  Vec6 p95 = Vec6::Zero();
};

// The step for one leg with or without the misalignments s.
struct HangingVariant {
  std::array<HangingPairResult, 2> pair;  // [0]: x pair, [1]: z pair
  ScalarSigma weight_n;                   // inverse-variance combination of the pairs
  Vec3Sigma force_offset_n;
  Vec3Sigma torque_offset_nm;
  // Reading minus model over every raw sample of the four series (report Fig. 5).
  WrenchResidualStats residual;
  Vec6 Offset() const;
};

// The fitted CoM curve with the 1-sigma of its coefficients.
struct ComFitResult {
  LegComModel model;            // r(phi) in ft_k, m
  Vec3 sigma_x = Vec3::Zero();  // sigma of (a_m, c_rad, d_m) of the x sinusoid
  double sigma_y_m = 0.0;
  Vec3 sigma_z = Vec3::Zero();  // sigma of (a_m, c_rad, d_m) of the z sinusoid
};

// Per phase bin: bin centre, median over cycles of the resolved CoM, and its spread (sample
// standard deviation over cycles) (report Fig. 4/7).
struct ComBins {
  std::vector<double> phase;
  std::vector<Vec3> median_m;
  std::vector<Vec3> sigma_m;
};

struct LegHangingResult {
  HangingVariant with_s;     // the calibration
  HangingVariant without_s;  // baseline: s+ = s- = 0 (Fig. 5, blue)
  ComFitResult com;
  ComBins com_bins;
  Vec6 naive_offset = Vec6::Zero();  // baseline: mean upright reading near theta = 0
  // Samples beyond the rated range left out, over the four series (HangingOptions.rated_range).
  int saturated_samples = 0;
  WrenchResidualStats naive_residual;
};

// What one transducer saw of gravity in one hanging series, beside what motion capture saw
// (ftcal's extension, docs/method.md "beyond the report"): with no ground contact the leg's whole
// weight passes through the transducer, so f - f_o points along gravity in ft_k at every
// phase, and R~_k u_B = v_C (f^C = R~ f', as in step 2). Four series per leg determine R~_k
// fully, including the common yaw of all six that the standing poses see only through the
// chassis tilt.
struct HangingGravityObservation {
  int leg = 0;
  HangSeries series = HangSeries::kXPos;
  Vec3 u_B = Vec3::UnitX();  // R_B_ft mean(f - f_o), unit: nominally transformed into B
  Vec3 v_C = Vec3::UnitX();  // mean gravity direction in C from the attitude samples, unit
  // 1-sigma per axis across the direction, rad: the spread of both directions over ten time
  // blocks of the series (standard error) and the force offset's sigma over |f|.
  double sigma_rad = 0.0;
};

struct HangingResult {
  std::array<LegHangingResult, kNumLegs> leg;
  // Filled when every series has attitude samples; empty otherwise.
  std::vector<HangingGravityObservation> gravity_observations;
  bool exact_rotations = false;
  int phase_bins = 0;
};

// Runs step 1 on the four hanging series (one recording of each HangSeries, any order).
// X_B_ft: the nominal transducer poses (config). Throws std::invalid_argument naming the
// series, leg and what is wrong for degenerate input (missing or duplicate series, stated
// gravity off every transducer x/z axis or off the motion capture, too few cycles, too little
// phase coverage, non-finite samples, mismatched vector lengths, unordered times).
HangingResult RunHanging(const std::vector<HangingRecording>& recordings,
                         const std::array<Pose3, kNumLegs>& X_B_ft, const HangingOptions& options);

// Offsets, leg weights and CoM curves of step 1 into the parameters of eq. 3.
void ApplyHangingResult(const HangingResult& result, RobotCalibration* cal);

// Writes step 1 into the calibration file: per leg (legs matched by name, created in config
// order when absent) force/torque offsets, leg weight, CoM fit with its bins, both hanging
// pairs, the naive tare; hanging_residual (per leg: "<LEG> with s", "<LEG> without s",
// "<LEG> naive tare"); hanging_uncertainty = CYCLE_SPREAD; solver.exact_hanging_rotations.
void WriteHangingToCalibration(const HangingResult& result, calibration::Calibration* out);

// --- The equations of step 1, exposed for tests and for the offset re-estimation. ---

// Closed-form s+ of the pair with gravity axis `axis` (unit e_x or e_z): the rotation (I + [s]
// or exp([s])) taking axis to the direction of f_minus_mean, with no component about axis.
Vec3 SPlusClosedForm(const Vec3& f_minus_mean, const Vec3& axis, bool exact_rotations);

// The report's objective for s+: rms over samples of the two components of
// (I + [s])^-1 f_minus (or exp(-[s]) f_minus) across the axis, plus the std of the component
// along it.
double SPlusObjective(const Vec3& s_plus, const std::vector<Vec3>& f_minus, const Vec3& axis,
                      bool exact_rotations);

// RTS smoother of the leg CoM over matched samples: tau_minus_i = -[f_minus_i] r_i + noise,
// r_{i+1} = r_i + process noise. Returns r_est,i (known up to + p_i f_minus_i).
std::vector<Vec3> SmoothLegCom(const std::vector<Vec3>& f_minus, const std::vector<Vec3>& tau_minus,
                               double transition_var_m2, double observation_var_nm2);

// Resolves the null space of one sample: the least-squares (p, p') of
// r + p f = r' + p' f', and the average of the two resulting CoMs.
Vec3 ResolveComNullSpace(const Vec3& r_est, const Vec3& f_minus, const Vec3& r_est_prime,
                         const Vec3& f_minus_prime);

// Least-squares fit of a sin(2 pi phi + c) + d (a >= 0).
SinusoidFit FitSinusoid(const std::vector<double>& phase, const std::vector<double>& value);

}  // namespace ftcal
