// Geometry core: SO(3)/SE(3) and the wrench transform of docs/method.md.
//
// Conventions (docs/method.md, "Conventions"):
//  - Skew(v) u = v x u.
//  - A pose X_AB = (R_AB, p_AB) maps a point from frame B to frame A: x_A = R x_B + p
//    (the report's T^A_B).
//  - A wrench w = [f; tau] has its torque about its frame's origin. WrenchTransform(X_AB)
//    moves it from B to A: f_A = R f_B, tau_A = R tau_B + p x (R f_B). This is the
//    report's transposed adjoint of the inverse; call it X(T).
//  - A twist t = [v; omega] (velocity of the origin, angular velocity) moves with
//    TwistTransform(X_AB) = Ad(X_AB), so that w_A^T t_A = w_B^T t_B (power is invariant).
//  - Cayley map (report section III-B): R = (I - [q]) (I + [q])^-1, defined for rotations
//    by less than pi; |q| = tan(angle / 2).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace ftcal {

using Vec3 = Eigen::Vector3d;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using Mat3 = Eigen::Matrix3d;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using Quat = Eigen::Quaterniond;

// A rigid transform X_AB.
struct Pose3 {
  Mat3 R = Mat3::Identity();
  Vec3 p = Vec3::Zero();

  Pose3() = default;
  Pose3(const Mat3& rotation, const Vec3& translation) : R(rotation), p(translation) {}

  static Pose3 Identity() { return Pose3(); }
  // X_AC = X_AB * X_BC.
  Pose3 operator*(const Pose3& other) const { return Pose3(R * other.R, R * other.p + p); }
  // x_A = X_AB * x_B.
  Vec3 operator*(const Vec3& x) const { return R * x + p; }
  Pose3 Inverse() const { return Pose3(R.transpose(), -(R.transpose() * p)); }
  Eigen::Matrix4d Matrix() const;
};

Mat3 Skew(const Vec3& v);
// Inverse of Skew on the skew-symmetric part of m.
Vec3 Unskew(const Mat3& m);

// X(T): the 6x6 matrix moving a wrench [f; tau] from frame B to frame A.
Mat6 WrenchTransform(const Pose3& X_AB);
Vec6 TransformWrench(const Pose3& X_AB, const Vec6& w_B);
// Ad(T): the 6x6 matrix moving a twist [v; omega] from frame B to frame A.
Mat6 TwistTransform(const Pose3& X_AB);

// Cayley map R = (I - [q])(I + [q])^-1 and its inverse [q] = (I + R)^-1 (I - R).
Mat3 CayleyToRotation(const Vec3& q);
// Throws std::domain_error for a rotation by (nearly) pi, where the map is singular.
Vec3 RotationToCayley(const Mat3& R);

// Rotation vector (axis * angle) <-> rotation matrix, with small-angle series near 0.
Mat3 ExpSO3(const Vec3& rotation_vector);
Vec3 LogSO3(const Mat3& R);

// Quaternions are (w, x, y, z) wherever they cross a boundary.
Mat3 QuaternionToRotation(const Eigen::Vector4d& q_wxyz);
Eigen::Vector4d RotationToQuaternion(const Mat3& R);

// R = Rz(yaw) Ry(pitch) Rx(roll), angles in rad.
Mat3 RotationFromRollPitchYaw(double roll, double pitch, double yaw);

// Heading of a body whose axes are rotated by R_GC in a z-up global frame G: the yaw
// of its x axis projected on the ground plane.
double HeadingYaw(const Mat3& R_GC);
// R_WC: the attitude with the heading removed (W: z up, x along the heading).
Mat3 RemoveHeading(const Mat3& R_GC);

// Largest |R^T R - I| entry and |det R - 1|: how far m is from SO(3).
double OrthonormalityError(const Mat3& m);
// Projects a near-rotation onto SO(3) (polar decomposition via SVD).
Mat3 ProjectToSO3(const Mat3& m);

}  // namespace ftcal
