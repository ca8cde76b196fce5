// The sigma of a plan before it runs (docs/method.md "Predicting a plan's sigma", issue 41):
// every parameter's 1-sigma from the model's information at the nominal parameters, with the
// noise the devices are stated to have and the samples each phase yields.
//
// Model: the measurements of the plan as the calibration sees them, noise-free at the nominal
// parameters (the caller predicts them: libcal has no physics of the robot's feet), plus
// independent Gaussian noise per sample (transducer force and torque components, attitude per
// axis, shaft angle). Step 1: every raw hanging sample of a leg is w = [m g R(s) d; r(phi) x
// m g R(s) d] + w_o, d the stated gravity in ft_k, s the series' small misalignment (its
// component about d unobservable, held at 0 as step 1 holds it); its information J^T J / sigma^2
// over the samples (Ceres evaluates J) is inverted per leg. Step 2: a steady pose is the median
// of n samples (variance pi/2 sigma^2 / n per measured component); the pose residual of eq. 8
// (libcal's own PoseCost, at R~ = I, p~' = 0) carries the measurement noise through its
// derivatives to a full 6 x 6 covariance per pose, and the K-weighted least squares the
// calibrator solves has the sandwich covariance H^-1 (sum_p J_p^T S_p J_p) H^-1 (H = J^T J).
// The hanging gravity prior enters with the sigma its directions would have.
//
// Besides that (the true sigma of the calibrator's estimator), the prediction gives the
// information bound (J^T S^-1 J)^-1 and the sigma the calibrator itself would report, whose
// middle term uses each residual component's variance alone (no correlation within a pose).
#pragma once

#include <array>
#include <string>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/hanging.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"
#include "ftcal/standing.h"

namespace ftcal {

// Per sample, 1-sigma, white.
struct DeviceNoise {
  double force_n = 0.05;
  double torque_nm = 0.002;
  double attitude_rad = 0.2 * M_PI / 180.0;  // motion capture, per axis of C
  double shaft_angle_rad = 0.0;
};

// One hanging series as planned: `cycles` full leg cycles at `samples_per_cycle` transducer
// samples each (rate x cycle time), with gravity stated along gravity_b (unit, in B).
struct PlannedHangSeries {
  HangSeries series = HangSeries::kXPos;
  Vec3 gravity_b = Vec3::UnitX();
  int cycles = 0;
  double samples_per_cycle = 0.0;
};

// One standing pose as planned: its noise-free medians and how many samples each median has.
struct PlannedPose {
  StandingPose pose;
  double samples = 0.0;
};

struct PlanDesign {
  std::vector<PlannedHangSeries> hanging;  // the four series (or none: no step-1 prediction)
  std::vector<PlannedPose> poses;
  bool gravity_prior = true;  // the hanging series carry motion capture
  // Step 2's robot-CoM target: the report's fixed C, or the leg-aware CoM (through which step
  // 1's CoM curves and leg weights enter step 2's residual).
  bool leg_aware_com = false;
};

// The sigma of one parameter three ways (see the opening comment).
struct PredictedSigma {
  std::string name;       // "HL f_o x", "ML p~' z", ...
  std::string klass;      // "force offset", "rotation x,y", ...
  double sigma = 0.0;     // the calibrator's estimator, true noise (sandwich, full pose covariance)
  double bound = 0.0;     // information bound (J^T S^-1 J)^-1
  double reported = 0.0;  // what the calibrator's covariance would say (per-component variances)
  // `sigma` with step 1's own errors carried into step 2 (step 2 holds step 1's offsets, leg
  // weights and CoM curves fixed, so its covariance leaves them out): sigma^2 + A C1 A^T with
  // A the step-2 estimate's derivative by step 1's parameters. Equal to sigma for step 1.
  double with_step1 = 0.0;
};

struct ClassSummary {
  std::string klass;
  std::string unit;           // of the numbers below, as printed
  double scale = 1.0;         // SI -> unit
  double median_sigma = 0.0;  // SI
  double median_reported = 0.0;
  double worst_sigma = 0.0;
  double worst_reported = 0.0;  // the worst parameter's, as the calibrator would report it
  std::string worst_name;
};

struct PlanPrediction {
  std::vector<PredictedSigma> parameters;
  std::vector<ClassSummary> classes;  // in a fixed order; classes with no parameter left out
  // The six p~'_z moving together (their mean) and the spread between legs (rms of the
  // deviations from the mean), m: what the chassis tilt and the legs' loads each show.
  PredictedSigma common_p_z;
  int standing_poses = 0;
  // The rms over poses of each residual component [fx fy fz tx ty tz] (N, N m, unweighted) the
  // noise alone leaves: what the calibrator's residual should show if the noise were all.
  Vec6 residual_rms = Vec6::Zero();
  double hanging_samples = 0.0;  // over the four series, per leg
};

// Throws std::invalid_argument naming what is wrong (no poses and no series, a series without
// cycles, a pose with no samples, noise not finite and >= 0, poses too few to determine the
// standing model).
PlanPrediction PredictPlan(const RobotCalibration& nominal, const PlanDesign& design,
                           const DeviceNoise& noise, const HangingOptions& hanging_options,
                           const StandingOptions& standing_options);

// Parameter classes in output order, and one parameter's class median / worst from a list.
std::vector<ClassSummary> SummariseClasses(const std::vector<PredictedSigma>& parameters);

}  // namespace ftcal
