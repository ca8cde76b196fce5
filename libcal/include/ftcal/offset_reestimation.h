// Offset drift (docs/method.md "Offset drift", report section V): re-estimate only the transducer
// offsets w_o,k with everything else (leg weights, CoM curves, mounting, p^C_B) fixed.
//
// Model: eq. 3 is affine in w_o.
//  - A standing pose p gives 6 equations:
//      sum_k R_WC X(X_C_ft,k) w_o,k = sum_k R_WC (X(X_C_ft,k) w_m,k - w^C_leg,k) - target_p,
//    target_p = (0, 0, G, 0, 0, 0) or, leg-aware, with torque delta_W x (0, 0, G).
//    All poses together see only the 6-vector sum (R_WC is invertible), not the 36 offsets.
//  - A leg k with no ground load (lifted tripod, swing) gives 6 equations on its own offset:
//      w_o,k = w_m,k - X(X_C_ft,k)^-1 w^C_leg,k.
// Residual: both sets K-weighted (diag K of eq. 8, in W resp. ft_k).
// Unknowns: the 36 offset components. Null space: whatever the rows leave undetermined; a
// component is determined iff its unit vector lies in the row space of the design matrix
// (orthogonal to the null space from the SVD). Only those are returned; asking for all when
// some are not is refused with the list of undetermined leg/components.
#pragma once

#include <array>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"

namespace ftcal {

struct OffsetReestimationOptions {
  Vec6 k_weights = (Vec6() << 1, 1, 1, 10, 10, 10).finished();
  bool leg_aware_com = false;
  // true: throw std::invalid_argument unless all 36 components are determined.
  // false: return the determined ones and list the rest.
  bool require_all = true;
  // Singular values below this fraction of the largest count as zero.
  double rank_tolerance = 1e-9;
};

struct OffsetReestimate {
  // Offsets in ft_k [f; tau]: re-estimated where determined, the input calibration's elsewhere.
  std::array<Vec6, kNumLegs> offset;
  // 1-sigma of the determined components (residual variance times (A^T A)^+), 0 elsewhere.
  std::array<Vec6, kNumLegs> sigma;
  std::array<std::array<bool, 6>, kNumLegs> determined{};
  std::vector<std::string> undetermined;  // e.g. "ML fx", "HR tz"
  int rank = 0;
  Eigen::VectorXd singular_values;  // of the K-weighted design matrix, descending
  int standing_rows = 0, unloaded_rows = 0;
  double residual_rms = 0.0;  // K-weighted rms of the rows at the solution
};

// Throws std::invalid_argument on no data, non-finite input, or (require_all) undetermined
// components, naming them.
OffsetReestimate ReestimateOffsets(const RobotCalibration& cal,
                                   const std::vector<StandingPose>& standing,
                                   const std::vector<LoadSample>& unloaded,
                                   const OffsetReestimationOptions& options);

// cal with the determined offset components replaced.
RobotCalibration ApplyOffsetReestimate(const RobotCalibration& cal, const OffsetReestimate& r);

}  // namespace ftcal
