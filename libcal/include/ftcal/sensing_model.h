// The sensing model of docs/method.md (eq. 1-3) and the calibration parameters it is written in.
//
// Model: a transducer reading w_m,k (the wrench leg k exerts on the chassis, in ft_k, about
// its origin) is w_m = w_a + w_o + n, and quasi-statically the applied wrench is the leg's
// gravity plus the ground's wrench on the foot: w_a = w_leg + w_gc. The chain to the CoM frame
// is X_C_ft = (I, p^C_B) * T~_k * X_B_ft. Parameterised with p~' = R~^T (p~ + p^C_B)
// (docs/method.md, step 2) this is X_C_ft = (R~, R~ p~') * X_B_ft = R~ * (R_B_ft, p_B_ft + p~'):
// the nominally transformed wrench and CoM get shifted by p~' and rotated by R~.
// p~ acts about the BODY origin (T~ multiplies on the left): a transducer tilted by R~ about
// its own origin and shifted by d has p~ = d + (I - R~) p^B_ft.
#pragma once

#include <array>
#include <vector>

#include "ftcal/geometry.h"
#include "ftcal/legs.h"

namespace ftcal {

// Leg phase phi = wrap(theta / 2 pi) in [0, 1) (docs/method.md).
double LegPhase(double angle_rad);

// r(phi) = a sin(2 pi phi + c) + d.
struct SinusoidFit {
  double a = 0.0, c = 0.0, d = 0.0;
  double operator()(double phase) const;
};

// Leg CoM r_k(phi) in the transducer frame ft_k: x and z sinusoids, y constant (report Fig. 4/7).
struct LegComModel {
  SinusoidFit x;
  double y = 0.0;
  SinusoidFit z;
  Vec3 At(double phase) const;
};

// The largest distance between two leg CoM curves over a cycle, on a grid of `points` phases
// (m): how far one calibration's r_k(phi) is from another's, or from the truth.
double MaxCurveDistance(const LegComModel& a, const LegComModel& b, int points = 1000);

struct LegCalibration {
  Vec6 offset = Vec6::Zero();         // w_o,k = [f_o; tau_o] in ft_k (N, N*m)
  double weight_n = 0.0;              // m_k g
  LegComModel com;                    // r_k(phi), m, in ft_k
  Mat3 R_tilde = Mat3::Identity();    // R~_k
  Vec3 p_tilde_prime = Vec3::Zero();  // p~'_k = R~_k^T (p~_k + p^C_B), m
};

// Everything eq. 3 needs for all legs.
struct RobotCalibration {
  std::array<Pose3, kNumLegs> X_B_ft;  // nominal transducer poses (config)
  std::array<LegCalibration, kNumLegs> leg;
  Vec3 p_C_B = Vec3::Zero();  // body origin -> CoM, m (informational for correction)
  double g0 = 9.80665;        // m/s^2
  double total_mass_kg = 0.0;
  // The servo stream's delay relative to the transducers' (calibration.proto Latencies): the
  // corrector reads a servo state stamped u as the shaft at u - servo_delay_s.
  double servo_delay_s = 0.0;

  double TotalWeightN() const { return total_mass_kg * g0; }
  // X_C_ft for leg k (the mounted transducer in the CoM frame).
  Pose3 X_C_ft(int k) const;
  // p~_k = R~_k p~'_k - p^C_B.
  Vec3 PTilde(int k) const;
};

// g^C = (R^W_C)^T (0, 0, -g0).
Vec3 GravityInC(const Mat3& R_WC, double g0);

// Leg k's gravity wrench [m g^C; (X_C_ft r(phi)) x m g^C] in C, about the CoM.
Vec6 LegGravityWrenchC(const RobotCalibration& cal, int k, double angle_rad, const Mat3& R_WC);

// Eq. 3: the ground's wrench on foot k, in C about the CoM, from a raw reading w_m (ft_k).
Vec6 GroundWrenchC(const RobotCalibration& cal, int k, const Vec6& w_m, double angle_rad,
                   const Mat3& R_WC);

// The same rotated to W (axes of the floating base, about the CoM).
Vec6 GroundWrenchW(const RobotCalibration& cal, int k, const Vec6& w_m, double angle_rad,
                   const Mat3& R_WC);

// GroundWrenchW over many samples of one calibration: each leg's X_C_ft once, not twice per
// sample. The same arithmetic in the same order, so the same bits. Refers to `cal`, which
// must outlive it and not change.
class GroundWrenchModel {
 public:
  explicit GroundWrenchModel(const RobotCalibration& cal);
  Vec6 W(int k, const Vec6& w_m, double angle_rad, const Mat3& R_WC) const;

 private:
  const RobotCalibration& cal_;
  std::array<Pose3, kNumLegs> X_C_ft_;
};

// Forward model (the twin): the noise-free reading of transducer k when the ground exerts
// w_gc_C (in C about the CoM) on foot k.
Vec6 TransducerReading(const RobotCalibration& cal, int k, const Vec6& w_gc_C, double angle_rad,
                       const Mat3& R_WC);

// Whole-robot CoM shift (in C, m) of a pose relative to the reference shape (all shaft angles
// 0), from the legs' masses and CoM curves: delta = sum_k m_k (r_k^C(phi) - r_k^C(0)) / M.
// Used by the leg-aware step 2 (docs/method.md, "beyond the report").
Vec3 ComShiftC(const RobotCalibration& cal, const std::array<double, kNumLegs>& angle_rad);

}  // namespace ftcal
