#include "ftcal/sensing_model.h"

#include <algorithm>
#include <cmath>

namespace ftcal {

double LegPhase(double angle_rad) {
  const double turns = angle_rad / (2.0 * M_PI);
  double phase = turns - std::floor(turns);
  if (phase >= 1.0) phase = 0.0;  // floor rounding at -tiny
  return phase;
}

double SinusoidFit::operator()(double phase) const {
  return a * std::sin(2.0 * M_PI * phase + c) + d;
}

Vec3 LegComModel::At(double phase) const { return Vec3(x(phase), y, z(phase)); }

double MaxCurveDistance(const LegComModel& a, const LegComModel& b, int points) {
  double worst = 0.0;
  for (int i = 0; i < points; ++i) {
    const double phase = static_cast<double>(i) / points;
    worst = std::max(worst, (a.At(phase) - b.At(phase)).norm());
  }
  return worst;
}

Pose3 RobotCalibration::X_C_ft(int k) const {
  const LegCalibration& l = leg[k];
  return Pose3(l.R_tilde, l.R_tilde * l.p_tilde_prime) * X_B_ft[k];
}

Vec3 RobotCalibration::PTilde(int k) const { return leg[k].R_tilde * leg[k].p_tilde_prime - p_C_B; }

Vec3 GravityInC(const Mat3& R_WC, double g0) { return R_WC.transpose() * Vec3(0, 0, -g0); }

namespace {

// Eq. 3 in C for leg k given its X_C_ft (GroundWrenchC and GroundWrenchModel share it).
Vec6 LegGravityWrenchGiven(const Pose3& X_C_ft, const LegCalibration& l, double angle_rad,
                           const Mat3& R_WC) {
  // m_k g^C = weight * (unit gravity direction in C).
  const Vec3 f = l.weight_n * GravityInC(R_WC, 1.0);
  const Vec3 r_C = X_C_ft * l.com.At(LegPhase(angle_rad));
  Vec6 w;
  w << f, r_C.cross(f);
  return w;
}

Vec6 GroundWrenchGivenC(const Pose3& X_C_ft, const LegCalibration& l, const Vec6& w_m,
                        double angle_rad, const Mat3& R_WC) {
  return TransformWrench(X_C_ft, w_m - l.offset) -
         LegGravityWrenchGiven(X_C_ft, l, angle_rad, R_WC);
}

}  // namespace

Vec6 LegGravityWrenchC(const RobotCalibration& cal, int k, double angle_rad, const Mat3& R_WC) {
  return LegGravityWrenchGiven(cal.X_C_ft(k), cal.leg[k], angle_rad, R_WC);
}

Vec6 GroundWrenchC(const RobotCalibration& cal, int k, const Vec6& w_m, double angle_rad,
                   const Mat3& R_WC) {
  return GroundWrenchGivenC(cal.X_C_ft(k), cal.leg[k], w_m, angle_rad, R_WC);
}

Vec6 GroundWrenchW(const RobotCalibration& cal, int k, const Vec6& w_m, double angle_rad,
                   const Mat3& R_WC) {
  return TransformWrench(Pose3(R_WC, Vec3::Zero()), GroundWrenchC(cal, k, w_m, angle_rad, R_WC));
}

GroundWrenchModel::GroundWrenchModel(const RobotCalibration& cal) : cal_(cal) {
  for (int k = 0; k < kNumLegs; ++k) X_C_ft_[k] = cal.X_C_ft(k);
}

Vec6 GroundWrenchModel::W(int k, const Vec6& w_m, double angle_rad, const Mat3& R_WC) const {
  return TransformWrench(Pose3(R_WC, Vec3::Zero()),
                         GroundWrenchGivenC(X_C_ft_[k], cal_.leg[k], w_m, angle_rad, R_WC));
}

Vec6 TransducerReading(const RobotCalibration& cal, int k, const Vec6& w_gc_C, double angle_rad,
                       const Mat3& R_WC) {
  const Vec6 w_a_C = w_gc_C + LegGravityWrenchC(cal, k, angle_rad, R_WC);
  return TransformWrench(cal.X_C_ft(k).Inverse(), w_a_C) + cal.leg[k].offset;
}

Vec3 ComShiftC(const RobotCalibration& cal, const std::array<double, kNumLegs>& angle_rad) {
  Vec3 moment = Vec3::Zero();
  for (int k = 0; k < kNumLegs; ++k) {
    const Pose3 X = cal.X_C_ft(k);
    const LegComModel& com = cal.leg[k].com;
    moment += cal.leg[k].weight_n * (X * com.At(LegPhase(angle_rad[k])) - X * com.At(0.0));
  }
  return moment / cal.TotalWeightN();
}

}  // namespace ftcal
