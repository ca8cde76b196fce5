// Offset drift re-estimation (docs/method.md "Offset drift"); the model is in the header.
#include "ftcal/offset_reestimation.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

#include <Eigen/SVD>

namespace ftcal {

namespace {

constexpr const char* kComponentNames[6] = {"fx", "fy", "fz", "tx", "ty", "tz"};

void CheckFiniteSample(const std::array<Vec6, kNumLegs>& wrench,
                       const std::array<double, kNumLegs>& angle, const Mat3& R_WC,
                       const std::string& where) {
  for (int k = 0; k < kNumLegs; ++k) {
    if (!wrench[k].allFinite() || !std::isfinite(angle[k])) {
      throw std::invalid_argument("offset re-estimation: " + where + " leg " +
                                  std::string(kLegNames[k]) + " has a non-finite value");
    }
  }
  if (!R_WC.allFinite() || OrthonormalityError(R_WC) > 1e-3) {
    throw std::invalid_argument("offset re-estimation: " + where +
                                " attitude R_WC is not a rotation");
  }
}

}  // namespace

OffsetReestimate ReestimateOffsets(const RobotCalibration& cal,
                                   const std::vector<StandingPose>& standing,
                                   const std::vector<LoadSample>& unloaded,
                                   const OffsetReestimationOptions& options) {
  if (!(cal.TotalWeightN() > 0.0) || !std::isfinite(cal.TotalWeightN())) {
    throw std::invalid_argument("offset re-estimation: total weight must be finite and > 0");
  }
  if (!(options.k_weights.array() > 0.0).all() || !options.k_weights.allFinite()) {
    throw std::invalid_argument("offset re-estimation: k_weights must be finite and > 0");
  }
  int unloaded_legs = 0;
  for (const LoadSample& s : unloaded) {
    for (int k = 0; k < kNumLegs; ++k) unloaded_legs += s.unloaded[k] ? 1 : 0;
  }
  const int n_rows = 6 * (static_cast<int>(standing.size()) + unloaded_legs);
  if (n_rows == 0) {
    throw std::invalid_argument(
        "offset re-estimation: no data (no standing poses and no unloaded legs)");
  }
  const Vec6 sqrt_k = options.k_weights.cwiseSqrt();
  const double G = cal.TotalWeightN();
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n_rows, 6 * kNumLegs);
  Eigen::VectorXd b(n_rows);
  std::array<Mat6, kNumLegs> X_C_ft;
  for (int k = 0; k < kNumLegs; ++k) X_C_ft[k] = WrenchTransform(cal.X_C_ft(k));

  int row = 0;
  for (size_t p = 0; p < standing.size(); ++p) {
    const StandingPose& pose = standing[p];
    CheckFiniteSample(pose.wrench, pose.angle_rad, pose.R_WC, "standing pose " + std::to_string(p));
    const Mat3 R_WC = ProjectToSO3(pose.R_WC);
    Mat6 rot = Mat6::Zero();
    rot.topLeftCorner<3, 3>() = R_WC;
    rot.bottomRightCorner<3, 3>() = R_WC;
    Vec6 rhs = Vec6::Zero();
    for (int k = 0; k < kNumLegs; ++k) {
      const Mat6 M = rot * X_C_ft[k];
      A.block<6, 6>(row, 6 * k) = sqrt_k.asDiagonal() * M;
      rhs += M * pose.wrench[k] - rot * LegGravityWrenchC(cal, k, pose.angle_rad[k], R_WC);
    }
    Vec6 target;
    target << 0, 0, G, 0, 0, 0;
    if (options.leg_aware_com) {
      target.tail<3>() = (R_WC * ComShiftC(cal, pose.angle_rad)).cross(Vec3(0, 0, G));
    }
    b.segment<6>(row) = sqrt_k.cwiseProduct(rhs - target);
    row += 6;
  }
  for (size_t s = 0; s < unloaded.size(); ++s) {
    const LoadSample& sample = unloaded[s];
    CheckFiniteSample(sample.wrench, sample.angle_rad, sample.R_WC,
                      "load sample " + std::to_string(s));
    const Mat3 R_WC = ProjectToSO3(sample.R_WC);
    for (int k = 0; k < kNumLegs; ++k) {
      if (!sample.unloaded[k]) continue;
      // An unloaded leg's reading is its own gravity plus the offset.
      const Vec6 w_leg_ft = TransformWrench(cal.X_C_ft(k).Inverse(),
                                            LegGravityWrenchC(cal, k, sample.angle_rad[k], R_WC));
      A.block<6, 6>(row, 6 * k) = sqrt_k.asDiagonal();
      b.segment<6>(row) = sqrt_k.cwiseProduct(sample.wrench[k] - w_leg_ft);
      row += 6;
    }
  }

  // SVD of the design matrix itself (not the normal equations, which would square its
  // condition and blur an exact null space into rounding noise). JacobiSVD with its QR
  // preconditioner, not BDCSVD: Debian's Eigen 3.4.0 BDCSVD returned solutions off by 1e-7..1e-3
  // on these tall, consistent systems (offset_reestimation_test's noise-free case caught it).
  // The full V (36 x 36): with fewer rows than unknowns a thin V has only as many columns as
  // rows and leaves out most of the null space, which would make undetermined components look
  // determined.
  Eigen::JacobiSVD<Eigen::MatrixXd> svd(A, Eigen::ComputeThinU | Eigen::ComputeFullV);
  const Eigen::VectorXd& sv = svd.singularValues();
  OffsetReestimate out;
  out.singular_values = sv;
  out.standing_rows = 6 * static_cast<int>(standing.size());
  out.unloaded_rows = 6 * unloaded_legs;
  const double cutoff = options.rank_tolerance * (sv.size() > 0 ? sv[0] : 0.0);
  int rank = 0;
  while (rank < sv.size() && sv[rank] > cutoff) ++rank;
  out.rank = rank;
  const Eigen::MatrixXd& V = svd.matrixV();
  const Eigen::MatrixXd V_r = V.leftCols(rank);
  const Eigen::MatrixXd V_null = V.rightCols(V.cols() - rank);
  const Eigen::VectorXd inv_s = sv.head(rank).cwiseInverse();
  const Eigen::VectorXd x =
      V_r * inv_s.asDiagonal() * (svd.matrixU().leftCols(rank).transpose() * b);
  const Eigen::VectorXd e = A * x - b;
  const int redundancy = n_rows - rank;
  if (redundancy == 0) {
    // An exact fit: the residual is zero whatever the noise, so no sigma can be given.
    throw std::invalid_argument(
        "offset re-estimation: the data (" + std::to_string(standing.size()) + " standing poses, " +
        std::to_string(unloaded_legs) + " unloaded-leg samples) has no redundancy (" +
        std::to_string(n_rows) + " equations, rank " + std::to_string(rank) +
        "): the offsets would fit it exactly with no uncertainty; add standing poses or stances");
  }
  const double s2 = e.squaredNorm() / redundancy;
  out.residual_rms = std::sqrt(e.squaredNorm() / n_rows);
  const Eigen::MatrixXd W = V_r * inv_s.asDiagonal();  // cov = s2 W W^T

  for (int k = 0; k < kNumLegs; ++k) {
    out.offset[k] = cal.leg[k].offset;
    out.sigma[k].setZero();
    for (int i = 0; i < 6; ++i) {
      const int j = 6 * k + i;
      const bool determined = V_null.cols() == 0 || V_null.row(j).norm() < 1e-6;
      out.determined[k][i] = determined;
      if (determined) {
        out.offset[k][i] = x[j];
        out.sigma[k][i] = std::sqrt(s2 * W.row(j).squaredNorm());
      } else {
        out.undetermined.push_back(std::string(kLegNames[k]) + " " + kComponentNames[i]);
      }
    }
  }
  if (options.require_all && !out.undetermined.empty()) {
    std::ostringstream msg;
    msg << "offset re-estimation: the data (" << standing.size() << " standing poses, "
        << unloaded_legs << " unloaded-leg samples; rank " << rank << " of 36) does not determine "
        << out.undetermined.size() << " offset components: ";
    for (size_t i = 0; i < out.undetermined.size(); ++i) {
      msg << (i ? ", " : "") << out.undetermined[i];
    }
    msg << ". Standing poses see only the sum over legs; add samples with those legs unloaded "
           "(lifted tripod, swing phase)";
    throw std::invalid_argument(msg.str());
  }
  return out;
}

RobotCalibration ApplyOffsetReestimate(const RobotCalibration& cal, const OffsetReestimate& r) {
  RobotCalibration out = cal;
  for (int k = 0; k < kNumLegs; ++k) {
    for (int i = 0; i < 6; ++i) {
      if (r.determined[k][i]) out.leg[k].offset[i] = r.offset[k][i];
    }
  }
  return out;
}

}  // namespace ftcal
