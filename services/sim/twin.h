// The BigAnt twin: a truth model of the robot that generates what its devices would report
// (six transducer wrenches, six shaft angles, chassis motion capture) for the experiments of
// the report, with known calibration parameters, so every stage of the method can be checked
// against the parameters that made the data.
//
// The readings follow the agreed sensing model exactly (ftcal/sensing_model.h, docs/method.md
// eq. 1-3): w_m,k = X(X_C_ft,k)^-1 (w_gc,k + w_leg,k) + w_o,k + n, with the true RobotCalibration.
//
// Geometry. The nominal transducer poses, the total mass and g0 come from the config
// (config/sim.pbtxt). Each leg is a 1-DoF module hanging under its transducer; in the module's
// (= transducer's) frame the foot traces the closed curve
//   foot_ft(theta) = (-rx sin(theta), 0, -h - rz sgn(cos theta) |cos theta|^e),
// flattened at the bottom so the stance poses (|theta| <= 36 deg) differ in foot height by a
// few millimetres only. The right modules are turned 180 deg about z (the config), so the same
// shaft angle moves a right foot the other way in B; the walking gait turns them the other way.
// The true transducer frame carries the foot: a_C = X_C_ft,k(true) * foot_ft.
//
// Contact. Feet are linear springs on a flat floor (stiffness diag(kh, kh, kz) in W). For a
// given set of feet on the ground the chassis' small displacement delta = [dp; dw] solves the
// 6x6 equilibrium  sum_k J_k^T K (s_k - J_k delta) = target  with J_k = [I, -[a_k]], so the load
// distribution is unique; a second solve at the tilted attitude makes the sum exact with the
// actual lever arms. Self-balancing horizontal forces of a few newtons (like those the report
// saw) are added in the null space of the equilibrium map. Target: (0, 0, G, 0, 0, 0) in W about
// C (fixed CoM, the report's assumption) or (0, 0, G, delta_W x (0, 0, G)) with delta = ComShiftC
// (physical CoM: the legs carry nearly half the mass, so the CoM moves with the shaft angles).
//
// Everything is deterministic for a given seed: every scenario draws from its own random
// stream, so the order in which scenarios are generated does not matter.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "ftcal/dataset.h"
#include "ftcal/experiment_phase.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

inline constexpr int kNumChassisMarkers = 12;

struct TwinOptions {
  uint64_t seed = 1;
  // true: the CoM moves with the legs (C + ComShiftC); false: fixed at C (the report's model).
  bool physical_com = false;
  // false: R~ = I, p~ = 0 (for the model-selection test).
  bool mounting_errors = true;

  // Noise (1 sigma), per sample.
  double force_noise_n = 0.05;
  double torque_noise_nm = 0.002;
  double attitude_noise_deg = 0.2;  // mocap R_GC, per axis
  double marker_noise_m = 0.0005;   // mocap marker positions, per axis
  // Chassis marker dropouts: each marker independently drops out at this rate (events per
  // second) for an exponentially distributed time with this mean.
  double marker_dropout_rate_hz = 0.004;
  double marker_dropout_mean_s = 0.5;
  // Quantize readings to integer counts (the Net F/T's resolution).
  bool quantize = false;
  double counts_per_force = 1e6;
  double counts_per_torque = 1e6;
  double sample_rate_hz = 100.0;

  // True parameter ranges (drawn uniformly from the seed).
  double offset_force_spread_n = 1.0;  // around the report's Table II offsets
  double offset_torque_spread_nm = 0.03;
  double weight_spread_n = 0.1;                             // around Table II's m g
  double tilt_min_deg = 1.0, tilt_max_deg = 3.0;            // mounting tilt about ft origin
  double shift_min_m = 0.002, shift_max_m = 0.008;          // mounting shift
  double p_C_B_min_m = 0.008, p_C_B_max_m = 0.012;          // |p^C_B|
  double hang_tilt_min_deg = 1.0, hang_tilt_max_deg = 3.0;  // whole robot, per hanging series
  double drift_force_n = 3.0, drift_torque_nm = 0.1;        // offset drift, uniform +-

  // Leg module (foot curve in ft_k, see the header comment).
  double foot_drop_m = 0.10;  // h
  double foot_rx_m = 0.06;
  double foot_rz_m = 0.04;
  double foot_flatten = 0.3;  // e
  double foot_stiffness_vertical_n_m = 1000.0;
  double foot_stiffness_horizontal_n_m = 1000.0;
  double internal_force_n = 3.0;  // rms per foot and horizontal axis before projection

  // Naive tare phase (upright, feet in the air, shaft angles 0).
  double tare_s = 2.0;
  // Hanging: ten slow leg cycles.
  double hang_cycle_s = 20.0;
  int hang_cycles = 10;
  // Standing poses: {-a, 0, +a}^6, servo motion, then dwell; a damped oscillation after each
  // change (chassis height and tilt), cut to exactly zero `settle_cutoff_s` after the motion.
  double stance_angle_deg = 36.0;
  double pose_move_s = 0.6;
  double pose_dwell_s = 5.0;
  double settle_tau_s = 0.3;
  double settle_freq_hz = 4.0;
  double settle_height_m = 0.001;
  double settle_tilt_deg = 0.2;
  double settle_cutoff_s = 2.5;
  // Tripod stances: lifted legs turn to pi +- this.
  double lift_spread_rad = 0.3;
  // Tripod walk (Buehler clock; a negative turn is to the right).
  double walk_clock_hz = 0.08;
  double walk_turn_deg_per_cycle = -9.08;
  double walk_duty = 0.6;
  double walk_sweep_deg = 72.0;
};

// One 100 Hz sample of everything the devices report, with the truth beside it.
struct TwinFrame {
  double t_s = 0.0;
  ExperimentPhase phase = ExperimentPhase::kIdle;
  // Hanging: series; standing: pose number in the sequence; tripod: stance; walk: gait cycle.
  int segment = -1;
  // Quasi-static (no servo motion, no settling oscillation): the ground wrenches are in exact
  // equilibrium with the target. Walking frames are quasi-static throughout.
  bool steady = false;

  // Devices.
  std::array<Vec6, kNumLegs> reading;  // w_m,k in ft_k, [N; N*m] (quantized when asked)
  std::array<std::array<int32_t, 6>, kNumLegs> counts;  // reading * cpf / cpt, rounded
  std::array<double, kNumLegs> angle_rad;               // shaft angles, continuous (not wrapped)
  Mat3 R_GC = Mat3::Identity();                         // mocap attitude (noisy); G: z up
  Vec3 p_GB_m = Vec3::Zero();                           // mocap position of the body origin B in G
  std::array<Vec3, kNumChassisMarkers> marker_G_m;      // NaN when untracked
  std::array<bool, kNumChassisMarkers> marker_tracked;

  // Truth.
  Mat3 R_WC = Mat3::Identity();
  std::array<bool, kNumLegs> in_contact;
  std::array<Vec6, kNumLegs> ground_w_C;  // ground on foot k, in C about C's origin
  Vec3 com_shift_C = Vec3::Zero();        // actual CoM - C (zero with a fixed CoM)
  bool drifted = false;                   // offsets are the drifted ones
  // What RunOptions::offset_change added to each leg's offsets at this frame (zero without).
  std::array<Vec6, kNumLegs> offset_change;
};

using FrameSink = std::function<void(const TwinFrame&)>;

struct RunOptions {
  double t0_s = 0.0;
  // From this time on the transducer offsets are the drifted ones (DriftedTruth()).
  double drift_from_s = std::numeric_limits<double>::infinity();
  // Offsets that move during the run (sim/offset_drift.h): added to leg k's offsets at twin
  // time t, on top of the truth's (or the drifted truth's). Empty: none.
  std::function<Vec6(int leg, double t_s)> offset_change;
};

// The quasi-static state of the robot standing on the feet in `contact`.
struct StanceState {
  std::array<bool, kNumLegs> contact{};
  Mat3 R_WC = Mat3::Identity();
  std::array<Vec3, kNumLegs> foot_C;   // a_k in C
  std::array<Vec3, kNumLegs> force_W;  // ground on foot k, W axes
  std::array<Vec6, kNumLegs> ground_w_C;
  Vec3 com_shift_C = Vec3::Zero();
  Vec6 target_W = Vec6::Zero();  // what the ground wrenches sum to (about C, W axes)
  double height_m = 0.0;         // C above the floor
};

class BigAntTwin {
 public:
  // Throws std::invalid_argument naming the field for a config or option the twin cannot use.
  BigAntTwin(const config::Config& config, const TwinOptions& options);

  const TwinOptions& Options() const { return options_; }
  const RobotCalibration& Truth() const { return truth_; }
  // Truth with every offset moved by its drift.
  const RobotCalibration& DriftedTruth() const { return drifted_; }
  // The truth as a calibration file (uncertainty source TRUTH); WriteTruthFile writes it
  // atomically as text.
  // `drifted`: with the drifted offsets (DriftedTruth()), the truth of a drift session.
  calibration::Calibration TruthProto(bool drifted = false) const;
  void WriteTruthFile(const std::string& path, bool drifted = false) const;

  // The operator's stated gravity direction in B for a hanging series (a body axis), and the
  // actual attitude R_WC of that series (stated axis tilted by 1-3 deg).
  Vec3 StatedGravityB(HangSeries series) const;
  Mat3 HangingAttitude(HangSeries series) const { return hang_R_WC_[static_cast<int>(series)]; }
  // Foot k in C at shaft angle theta, and the chassis markers in B.
  Vec3 FootC(int k, double angle_rad) const;
  const std::array<Vec3, kNumChassisMarkers>& MarkersB() const { return markers_B_; }
  // Shaft angles of standing pose `index` of the sequence (a seeded order of all 729).
  std::array<double, kNumLegs> StandingPoseAngles(int index) const;
  // Quasi-static equilibrium on the feet in `contact` (at least three, not collinear), with
  // `internal_h` the self-balancing horizontal forces before projection (zero for none).
  // Throws std::invalid_argument when the contact set cannot carry the robot.
  StanceState Equilibrium(const std::array<double, kNumLegs>& angle_rad,
                          const std::array<bool, kNumLegs>& contact,
                          const std::array<Vec3, kNumLegs>& internal_h) const;

  // The robot off the ground, as the hanging series and the tare hold it: hanging in `series`'
  // attitude (HangingAttitude), or lifted upright and level; no foot touches anything, the CoM
  // moves with the legs when physical_com. And where the chassis hangs in G (above the origin).
  StanceState HangingState(HangSeries series, const std::array<double, kNumLegs>& angle_rad) const;
  StanceState LiftedState(const std::array<double, kNumLegs>& angle_rad) const;
  Vec3 HangingPositionG() const;

  // Scenarios: each emits 100 Hz frames in time order from run.t0_s and returns the end time.
  double Tare(const RunOptions& run, const FrameSink& sink) const;
  double Hanging(HangSeries series, const RunOptions& run, const FrameSink& sink) const;
  double Standing(int num_poses, const RunOptions& run, const FrameSink& sink) const;
  double TripodStances(int num_stances, const RunOptions& run, const FrameSink& sink) const;
  double TripodWalk(double duration_s, const RunOptions& run, const FrameSink& sink) const;

 private:
  class Generator;  // twin.cc: noise, quantization and motion capture for one random stream

 public:
  // Frames at shaft angles given from outside, e.g. the legs following commanded servos
  // (`ftcal-sim live --scenario commanded`). Standing (the start), the robot stands
  // quasi-statically on all six feet (Equilibrium with every foot down and one set of
  // self-balancing forces, drawn once from its own stream), the chassis over the twin's origin at
  // its first heading. The operator can hang it in one of the four series' attitudes or lift it
  // upright (HangingState, LiftedState: the physics of Hanging() and Tare()) and set it down
  // again. The readings and the motion capture are made as in every scenario (noise,
  // quantization, marker dropouts, drift) from a random stream of their own. Deterministic for
  // a seed and a sequence of calls; the internal forces do not depend on the noise options.
  class Driven {
   public:
    enum class Support { kStanding, kHanging, kLifted };
    // Where the robot is from the next Frame() on (an operator's re-hang takes no twin time);
    // `series` only for kHanging.
    void SetSupport(Support support, HangSeries series = HangSeries::kXPos);
    Support support() const { return support_; }
    HangSeries hang_series() const { return series_; }

    // `twin` must outlive this object.
    explicit Driven(const BigAntTwin& twin, const RunOptions& run = RunOptions{});
    ~Driven();
    Driven(const Driven&) = delete;
    Driven& operator=(const Driven&) = delete;

    // The frame at `t_s` (non-decreasing from call to call) with the shafts at `angle_rad`;
    // `steady` when the angles are those of the previous call (and on the first call). The
    // reference is valid until the next call. Throws std::invalid_argument for a non-finite
    // angle or time.
    const TwinFrame& Frame(double t_s, const std::array<double, kNumLegs>& angle_rad);
    // The self-balancing horizontal forces (before projection) the feet carry.
    const std::array<Vec3, kNumLegs>& InternalForces() const { return internal_; }

   private:
    const BigAntTwin& twin_;
    RunOptions run_;
    FrameSink sink_;
    TwinFrame frame_;
    std::array<Vec3, kNumLegs> internal_;
    std::unique_ptr<Generator> gen_;
    std::array<double, kNumLegs> last_angle_{};
    bool first_ = true;
    Support support_ = Support::kStanding;
    HangSeries series_ = HangSeries::kXPos;
  };

  // Convenience for the method's tests.
  HangingRecording MakeHangingRecording(HangSeries series) const;
  // Median of the steady part of each of the first `num_poses` poses (its readings, angles and
  // attitude R_WC from the mocap with the heading removed); poses with a chassis marker
  // dropout during that part are excluded, as the segmenter does.
  std::vector<StandingPose> MakeSteadyPoses(int num_poses) const;
  // The same for tripod stances, with the lifted legs marked unloaded.
  std::vector<LoadSample> MakeTripodLoadSamples(int num_stances, bool drifted) const;

 private:
  TwinOptions options_;
  std::string robot_name_;
  RobotCalibration truth_;
  RobotCalibration drifted_;
  std::array<Mat3, kNumHangSeries> hang_R_WC_;
  std::array<Vec3, kNumChassisMarkers> markers_B_;
  std::array<int, 729> pose_order_;
  double yaw0_rad_ = 0.0;
  Vec3 origin_G_m_ = Vec3::Zero();
};

}  // namespace ftcal
