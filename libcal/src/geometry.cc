#include "ftcal/geometry.h"

#include <cmath>
#include <stdexcept>

#include <Eigen/LU>
#include <Eigen/SVD>

namespace ftcal {

Eigen::Matrix4d Pose3::Matrix() const {
  Eigen::Matrix4d m = Eigen::Matrix4d::Identity();
  m.topLeftCorner<3, 3>() = R;
  m.topRightCorner<3, 1>() = p;
  return m;
}

Mat3 Skew(const Vec3& v) {
  Mat3 m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

Vec3 Unskew(const Mat3& m) {
  return 0.5 * Vec3(m(2, 1) - m(1, 2), m(0, 2) - m(2, 0), m(1, 0) - m(0, 1));
}

Mat6 WrenchTransform(const Pose3& X_AB) {
  Mat6 x = Mat6::Zero();
  x.topLeftCorner<3, 3>() = X_AB.R;
  x.bottomLeftCorner<3, 3>() = Skew(X_AB.p) * X_AB.R;
  x.bottomRightCorner<3, 3>() = X_AB.R;
  return x;
}

Vec6 TransformWrench(const Pose3& X_AB, const Vec6& w_B) {
  Vec6 w_A;
  const Vec3 f_A = X_AB.R * w_B.head<3>();
  w_A.head<3>() = f_A;
  w_A.tail<3>() = X_AB.R * w_B.tail<3>() + X_AB.p.cross(f_A);
  return w_A;
}

Mat6 TwistTransform(const Pose3& X_AB) {
  Mat6 x = Mat6::Zero();
  x.topLeftCorner<3, 3>() = X_AB.R;
  x.topRightCorner<3, 3>() = Skew(X_AB.p) * X_AB.R;
  x.bottomRightCorner<3, 3>() = X_AB.R;
  return x;
}

Mat3 CayleyToRotation(const Vec3& q) {
  const Mat3 s = Skew(q);
  const Mat3 I = Mat3::Identity();
  // (I + [q]) is always invertible (its eigenvalues are 1 and 1 +- i|q|).
  return (I - s) * (I + s).inverse();
}

Vec3 RotationToCayley(const Mat3& R) {
  const Mat3 I = Mat3::Identity();
  const Mat3 a = I + R;
  // det(I + R) = 2 (1 + cos angle) (up to the trace identity): zero at angle = pi.
  const double det = a.determinant();
  if (!(std::abs(det) > 1e-12)) {
    throw std::domain_error("Cayley map undefined for a rotation by pi");
  }
  return Unskew(a.inverse() * (I - R));
}

Mat3 ExpSO3(const Vec3& w) {
  const double theta2 = w.squaredNorm();
  const Mat3 W = Skew(w);
  double a, b;
  if (theta2 < 1e-10) {
    // Series: sin(t)/t = 1 - t^2/6, (1 - cos t)/t^2 = 1/2 - t^2/24.
    a = 1.0 - theta2 / 6.0;
    b = 0.5 - theta2 / 24.0;
  } else {
    const double theta = std::sqrt(theta2);
    a = std::sin(theta) / theta;
    b = (1.0 - std::cos(theta)) / theta2;
  }
  return Mat3::Identity() + a * W + b * W * W;
}

Vec3 LogSO3(const Mat3& R) {
  const Eigen::AngleAxisd aa(Quat(R).normalized());
  double angle = aa.angle();
  Vec3 axis = aa.axis();
  if (angle > M_PI) {
    angle = 2.0 * M_PI - angle;
    axis = -axis;
  }
  return axis * angle;
}

Mat3 QuaternionToRotation(const Eigen::Vector4d& q) {
  return Quat(q[0], q[1], q[2], q[3]).normalized().toRotationMatrix();
}

Eigen::Vector4d RotationToQuaternion(const Mat3& R) {
  Quat q(R);
  q.normalize();
  // One of the two equivalent quaternions, chosen with w >= 0 so the output is unique.
  if (q.w() < 0) q.coeffs() *= -1.0;
  return Eigen::Vector4d(q.w(), q.x(), q.y(), q.z());
}

Mat3 RotationFromRollPitchYaw(double roll, double pitch, double yaw) {
  return (Eigen::AngleAxisd(yaw, Vec3::UnitZ()) * Eigen::AngleAxisd(pitch, Vec3::UnitY()) *
          Eigen::AngleAxisd(roll, Vec3::UnitX()))
      .toRotationMatrix();
}

double HeadingYaw(const Mat3& R_GC) {
  const Vec3 x = R_GC.col(0);
  return std::atan2(x.y(), x.x());
}

Mat3 RemoveHeading(const Mat3& R_GC) {
  return Eigen::AngleAxisd(-HeadingYaw(R_GC), Vec3::UnitZ()).toRotationMatrix() * R_GC;
}

double OrthonormalityError(const Mat3& m) {
  const double ortho = (m.transpose() * m - Mat3::Identity()).cwiseAbs().maxCoeff();
  return std::max(ortho, std::abs(m.determinant() - 1.0));
}

Mat3 ProjectToSO3(const Mat3& m) {
  Eigen::JacobiSVD<Mat3> svd(m, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Mat3 d = Mat3::Identity();
  d(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1.0 : 1.0;
  return svd.matrixU() * d * svd.matrixV().transpose();
}

}  // namespace ftcal
