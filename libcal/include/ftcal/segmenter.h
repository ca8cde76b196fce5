// Steady standing poses from aligned samples (docs/method.md, step 2; report section I-B).
//
// A pose is steady while the L2 norm over all legs of the force derivative is below a
// threshold (default 1 N/s); a steady run longer than min_steady_s (1.5 s) becomes one pose,
// represented by the median of its steady samples. A run during which any chassis marker was
// untracked is dropped (counted), as the report drops poses without all 12 markers.
//
// The derivative is a Savitzky-Golay differentiator (2nd order, 41 samples at 100 Hz by
// default): a centred window, so the decision for a sample is known (window-1)/2 samples
// later. The detector is a streaming state machine: feed samples in time order; poses come out
// as their runs end. A restart loses at most the pose in progress.
#pragma once

#include <array>
#include <cstdint>
#include <deque>
#include <functional>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"

namespace ftcal {

// Coefficients c such that sum_i c_i x_{i} over a centred window of `window` samples is the
// derivative at the centre of the least-squares polynomial of degree `order`, per unit sample
// spacing (divide by dt). Hand-written: no Debian C++ library provides Savitzky-Golay filters;
// it is a small least-squares problem solved with Eigen.
std::vector<double> SavitzkyGolayDerivative(int window, int order);

// One time-aligned sample of all legs (the segmenter's SYNC_SAMPLE).
struct SyncSample {
  int64_t utime = 0;                  // us
  std::array<Vec6, kNumLegs> wrench;  // readings in ft_k
  std::array<double, kNumLegs> angle_rad{};
  Mat3 R_WC = Mat3::Identity();
  bool attitude_ok = false;
  bool markers_ok = false;
};

struct SegmenterOptions {
  double sample_rate_hz = 100.0;
  int savgol_window = 41;
  int savgol_order = 2;
  double max_force_rate_n_s = 1.0;
  double min_steady_s = 1.5;
  // Drop a run when a sample with an attitude says a chassis marker is untracked (the report).
  // Samples with no attitude at all leave the median instead (segmenter.cc).
  bool require_all_markers = true;
  // A steady run longer than this is closed as one pose and a new run starts (bounds memory).
  double max_pose_s = 60.0;
  // A gap in time larger than this many sample periods resets the derivative window.
  double max_gap_periods = 3.5;
};

struct SteadyPoseOut {
  StandingPose pose;  // medians; pose.t_s = centre of the run, s
  int64_t start_utime = 0;
  int64_t end_utime = 0;
  int num_samples = 0;
  bool markers_ok = true;
};

struct SegmenterCounters {
  int64_t samples = 0;
  int64_t poses = 0;
  int64_t dropped_short = 0;     // steady runs shorter than min_steady_s
  int64_t dropped_markers = 0;   // runs with an untracked marker, or attitude for < half
  int64_t window_resets = 0;     // time gaps or non-finite samples
  int64_t rejected_samples = 0;  // non-finite or out-of-order samples
};

class PoseSegmenter {
 public:
  using PoseCallback = std::function<void(const SteadyPoseOut&)>;
  PoseSegmenter(const SegmenterOptions& options, PoseCallback on_pose);

  // Feed samples in time order. Out-of-order or non-finite samples are rejected (counted)
  // and reset the window: they never enter a median.
  void Add(const SyncSample& sample);
  // End of input: closes a run in progress (it becomes a pose if long enough).
  void Flush();

  // The latest derivative norm (N/s) computed, NaN before the window first fills.
  double last_force_rate() const { return last_rate_; }
  const SegmenterCounters& counters() const { return counters_; }

 private:
  void Evaluate();
  void CloseRun();

  SegmenterOptions options_;
  PoseCallback on_pose_;
  std::vector<double> coeff_;
  std::deque<SyncSample> window_;
  std::vector<SyncSample> run_;     // the steady samples with an attitude
  int64_t run_steady_samples_ = 0;  // all steady samples, with an attitude or not
  int64_t run_start_utime_ = 0;
  int64_t run_end_utime_ = 0;
  bool run_markers_ok_ = true;
  double last_rate_;
  SegmenterCounters counters_;
};

// Median of each component over the samples of a run (rotations: component-wise median of
// sign-aligned quaternions, normalised).
StandingPose MedianPose(const std::vector<SyncSample>& samples);
// The within-pose scatter of `samples` as the standard error of `pose`'s medians (its
// wrench_sem, attitude_sem_rad, samples): 1.4826 MAD per component (a stray sample does not
// move it) times sqrt(pi / 2) / sqrt(n), the standard error of a median of n independent
// Gaussian samples. Samples correlated in time make this an underestimate (a floor).
void SetWithinPoseScatter(const std::vector<SyncSample>& samples, StandingPose* pose);

}  // namespace ftcal
