#include "ftcal/segmenter.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>

#include <Eigen/Dense>

namespace ftcal {

std::vector<double> SavitzkyGolayDerivative(int window, int order) {
  if (window < 3 || window % 2 == 0) {
    throw std::invalid_argument("Savitzky-Golay window must be odd and >= 3, got " +
                                std::to_string(window));
  }
  if (order < 1 || order >= window) {
    throw std::invalid_argument("Savitzky-Golay order must be in [1, window), got " +
                                std::to_string(order));
  }
  const int half = window / 2;
  // Least-squares polynomial p(x) = sum_j a_j x^j through the window; p'(0) = a_1, and
  // a = (A^T A)^-1 A^T y, so the derivative weights are row 1 of the pseudo-inverse.
  Eigen::MatrixXd A(window, order + 1);
  for (int i = 0; i < window; ++i) {
    const double x = i - half;
    double xp = 1.0;
    for (int j = 0; j <= order; ++j) {
      A(i, j) = xp;
      xp *= x;
    }
  }
  const Eigen::MatrixXd pinv =
      A.colPivHouseholderQr().solve(Eigen::MatrixXd::Identity(window, window));
  std::vector<double> c(window);
  for (int i = 0; i < window; ++i) c[i] = pinv(1, i);
  return c;
}

namespace {

bool Finite(const SyncSample& s) {
  for (int k = 0; k < kNumLegs; ++k) {
    if (!s.wrench[k].allFinite() || !std::isfinite(s.angle_rad[k])) return false;
  }
  return s.R_WC.allFinite();
}

double Median(std::vector<double>& v) {
  const size_t n = v.size();
  const size_t mid = n / 2;
  std::nth_element(v.begin(), v.begin() + mid, v.end());
  double m = v[mid];
  if (n % 2 == 0) {
    m = 0.5 * (m + *std::max_element(v.begin(), v.begin() + mid));
  }
  return m;
}

// Whether pose->wrench already holds the median of each wrench component over the samples
// (MedianPose's own result): the MAD about it then skips 36 of the scatter's 78 medians. The
// medians of a pose were most of the calibrator's segmenting time.
enum class WrenchMedians { kCompute, kInPose };

void Scatter(const std::vector<SyncSample>& samples, WrenchMedians medians, StandingPose* pose) {
  const size_t n = samples.size();
  pose->samples = static_cast<int>(n);
  if (n == 0) return;
  const double to_sem = 1.4826 * std::sqrt(M_PI / 2.0) / std::sqrt(static_cast<double>(n));
  std::vector<double> buf(n);
  auto mad_about = [&buf](double m) {
    for (double& v : buf) v = std::abs(v - m);
    return Median(buf);
  };
  for (int k = 0; k < kNumLegs; ++k) {
    for (int c = 0; c < 6; ++c) {
      for (size_t i = 0; i < n; ++i) buf[i] = samples[i].wrench[k][c];
      const double m = medians == WrenchMedians::kInPose ? pose->wrench[k][c] : Median(buf);
      pose->wrench_sem[k][c] = to_sem * mad_about(m);
    }
  }
  std::vector<Vec3> deviation(n);
  for (size_t i = 0; i < n; ++i) deviation[i] = LogSO3(samples[i].R_WC * pose->R_WC.transpose());
  for (int c = 0; c < 3; ++c) {
    for (size_t i = 0; i < n; ++i) buf[i] = deviation[i][c];
    pose->attitude_sem_rad[c] = to_sem * mad_about(Median(buf));
  }
}

}  // namespace

StandingPose MedianPose(const std::vector<SyncSample>& samples) {
  if (samples.empty()) throw std::invalid_argument("MedianPose: no samples");
  StandingPose pose;
  std::vector<double> buf(samples.size());
  for (int k = 0; k < kNumLegs; ++k) {
    for (int c = 0; c < 6; ++c) {
      for (size_t i = 0; i < samples.size(); ++i) buf[i] = samples[i].wrench[k][c];
      pose.wrench[k][c] = Median(buf);
    }
    for (size_t i = 0; i < samples.size(); ++i) buf[i] = samples[i].angle_rad[k];
    pose.angle_rad[k] = Median(buf);
  }
  const Quat q_ref(samples.front().R_WC);
  Eigen::Vector4d q_med;
  for (int c = 0; c < 4; ++c) {
    for (size_t i = 0; i < samples.size(); ++i) {
      Quat q(samples[i].R_WC);
      if (q.dot(q_ref) < 0) q.coeffs() *= -1.0;
      buf[i] = q.coeffs()[c];
    }
    q_med[c] = Median(buf);
  }
  Quat q(q_med[3], q_med[0], q_med[1], q_med[2]);  // coeffs() order is x, y, z, w
  pose.R_WC = q.normalized().toRotationMatrix();
  pose.t_s = 0.5e-6 * static_cast<double>(samples.front().utime + samples.back().utime);
  Scatter(samples, WrenchMedians::kInPose, &pose);
  return pose;
}

void SetWithinPoseScatter(const std::vector<SyncSample>& samples, StandingPose* pose) {
  Scatter(samples, WrenchMedians::kCompute, pose);
}

PoseSegmenter::PoseSegmenter(const SegmenterOptions& options, PoseCallback on_pose)
    : options_(options),
      on_pose_(std::move(on_pose)),
      coeff_(SavitzkyGolayDerivative(options.savgol_window, options.savgol_order)),
      last_rate_(std::numeric_limits<double>::quiet_NaN()) {
  if (!(options_.sample_rate_hz > 0) || !(options_.max_force_rate_n_s > 0) ||
      !(options_.min_steady_s > 0)) {
    throw std::invalid_argument(
        "PoseSegmenter: sample rate, rate threshold and min steady time must be > 0");
  }
}

void PoseSegmenter::Add(const SyncSample& sample) {
  const double period_us = 1e6 / options_.sample_rate_hz;
  const bool ordered = window_.empty() || sample.utime > window_.back().utime;
  if (!Finite(sample) || !ordered) {
    // A bad sample ends any run: we cannot say the pose stayed steady across it.
    ++counters_.rejected_samples;
    ++counters_.window_resets;
    CloseRun();
    window_.clear();
    return;
  }
  if (!window_.empty() && static_cast<double>(sample.utime - window_.back().utime) >
                              options_.max_gap_periods * period_us) {
    ++counters_.window_resets;
    CloseRun();
    window_.clear();
  }
  ++counters_.samples;
  window_.push_back(sample);
  if (static_cast<int>(window_.size()) > options_.savgol_window) window_.pop_front();
  if (static_cast<int>(window_.size()) == options_.savgol_window) Evaluate();
}

void PoseSegmenter::Evaluate() {
  // Derivative at the window's centre sample, per leg force, then the L2 norm over all legs.
  const double inv_dt = options_.sample_rate_hz;
  double sum_sq = 0.0;
  for (int k = 0; k < kNumLegs; ++k) {
    Vec3 d = Vec3::Zero();
    for (int i = 0; i < options_.savgol_window; ++i)
      d += coeff_[i] * window_[i].wrench[k].head<3>();
    sum_sq += (d * inv_dt).squaredNorm();
  }
  last_rate_ = std::sqrt(sum_sq);
  const SyncSample& centre = window_[options_.savgol_window / 2];
  if (last_rate_ < options_.max_force_rate_n_s) {
    if (run_steady_samples_ == 0) {
      run_markers_ok_ = true;
      run_start_utime_ = centre.utime;
    }
    ++run_steady_samples_;
    run_end_utime_ = centre.utime;
    // A sample without a fresh, tracked attitude (a late or lost motion-capture frame) carries
    // no attitude to take a median of, and no marker verdict: it leaves the median, and the run
    // goes on, since the forces say the robot held still through it. Dropping the whole pose for
    // it loses a good pose to a 40 ms scheduling stall.
    if (centre.attitude_ok) {
      run_.push_back(centre);
      if (options_.require_all_markers && !centre.markers_ok) run_markers_ok_ = false;
    }
    const double span_s = 1e-6 * static_cast<double>(run_end_utime_ - run_start_utime_);
    if (span_s >= options_.max_pose_s) CloseRun();
  } else {
    CloseRun();
  }
}

void PoseSegmenter::CloseRun() {
  if (run_steady_samples_ == 0) return;
  const int64_t steady = run_steady_samples_;
  run_steady_samples_ = 0;
  std::vector<SyncSample> run;
  run.swap(run_);
  const double span_s =
      1e-6 * static_cast<double>(run_end_utime_ - run_start_utime_) + 1.0 / options_.sample_rate_hz;
  if (span_s <= options_.min_steady_s) {
    ++counters_.dropped_short;
    return;
  }
  // Attitude for under half the run is no longer a short lapse: the median would rest on a
  // fraction of the pose, so it goes with the runs whose markers failed.
  if (!run_markers_ok_ || 2 * static_cast<int64_t>(run.size()) < steady) {
    ++counters_.dropped_markers;
    return;
  }
  SteadyPoseOut out;
  out.pose = MedianPose(run);
  out.start_utime = run.front().utime;
  out.end_utime = run.back().utime;
  out.num_samples = static_cast<int>(run.size());
  out.markers_ok = true;
  ++counters_.poses;
  if (on_pose_) on_pose_(out);
}

void PoseSegmenter::Flush() {
  CloseRun();
  window_.clear();
}

}  // namespace ftcal
