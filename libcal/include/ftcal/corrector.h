// The corrector: every transducer sample into ground-contact wrenches (docs/method.md,
// "Correction"; what ftcal-corrector runs on every sample).
//
// Model: eq. 3 rotated to W (the same as GroundWrenchW in sensing_model.h),
//   w^W_gc,k = X(R_WC) [ X(X_C_ft,k) (w_m,k - w_o,k) - (m_k g^C ; (X_C_ft,k r_k(phi_k)) x m_k g^C)
//   ],
// g^C = R_WC^T (0, 0, -g0), phi_k = wrap(theta_k / 2 pi). Nothing is estimated here: the
// calibration fixes every parameter, so there are no unknowns and no null spaces. The sum of
// the six, standing still, is (0, 0, G, 0, 0, 0) (eq. 8's target); its difference from that is
// published as the residual.
//
// Per sample: the angle of the sample's leg comes from the servo states interpolated to the
// sample's time (held, never extrapolated, when no later state has arrived yet: the corrector
// cannot wait), R_WC from the latest motion-capture frame, or level (identity) flagged
// kFlagStaleMocap when there is none, it was untracked, or it is older than max_mocap_age_s.
// Each leg keeps the wrench of its own latest sample; the output carries all six and their sum.
// An input older than its configured age sets its stale flag: the number is still published,
// flagged, never silently used.
//
// Sums at one instant (NextSum): the six legs' transducers sample on clocks of their own, and a
// leg's samples arrive a datagram at a time, so "the latest of each leg" mixes moments up to a
// datagram apart. A sum is taken instead at each sample instant t of the pace leg (the first
// leg in config order that is not silent: its latest sample, or for a leg never seen the first
// of any leg, within max_ft_age_s of the newest of any leg), from each leg's corrected sample
// nearest t (kept in a short history), once every leg that is not silent has a sample at or after
// t; a silent leg is not waited for, and its sample (or none) flags the sum kFlagStaleFt. So a
// sum's six wrenches are of the same moment to within half a sample period, whatever the order the
// legs' messages arrive in.
//
// Speed: the per-leg constant transforms (R, p of X_C_ft,k, the offset, the weight, the CoM
// curve) are precomputed when a calibration is set; a sample costs one leg's correction and a
// six-term sum, with no allocation.
#pragma once

#include <array>
#include <cstdint>
#include <optional>

#include "ftcal/aligner.h"
#include "ftcal/geometry.h"
#include "ftcal/legs.h"
#include "ftcal/sensing_model.h"

namespace ftcal {

struct CorrectorOptions {
  double max_ft_age_s = 0.05;
  double max_servo_age_s = 0.05;
  double max_mocap_age_s = 0.05;
};

// Output flags: the same bits as contact_wrench_t's FLAG_* (libcal does not include it).
inline constexpr int32_t kFlagStaleFt = 1;
inline constexpr int32_t kFlagStaleServo = 2;
inline constexpr int32_t kFlagStaleMocap = 4;  // no fresh attitude: level assumed
inline constexpr int32_t kFlagSaturated = 8;

struct ContactWrenches {
  int64_t utime = 0;  // the triggering sample's time
  int updated_leg = 0;
  std::array<Vec6, kNumLegs> wrench_W;  // NaN for a leg that has no sample yet
  Vec6 total_W = Vec6::Zero();
  Vec6 residual_W = Vec6::Zero();  // total_W - (0, 0, G, 0, 0, 0)
  int64_t calibration_version = 0;
  std::array<double, kNumLegs> ft_age_s{};  // -1: no sample yet
  double servo_age_s = -1.0;                // -1: no servo state
  double mocap_age_s = -1.0;                // -1: no mocap frame
  int32_t flags = 0;
  // The flags of the triggering sample's own correction (kFlagStaleServo, kFlagStaleMocap,
  // kFlagSaturated).
  int32_t leg_flags = 0;
};

// One leg-sample's correction, as published on CONTACT_WRENCH.
struct LegWrench {
  int64_t utime = 0;
  int leg = 0;
  Vec6 wrench_W = Vec6::Zero();
  double servo_age_s = -1.0;
  double mocap_age_s = -1.0;
  int32_t flags = 0;  // kFlagStaleServo, kFlagStaleMocap, kFlagSaturated of this sample
};
LegWrench LegWrenchOf(const ContactWrenches& c);

// The six legs' sum, as published on CONTACT_WRENCH_SUM.
struct WrenchSum {
  int64_t utime = 0;  // the instant: a sample time of the pace leg
  Vec6 total_W = Vec6::Zero();
  Vec6 residual_W = Vec6::Zero();
  int64_t calibration_version = 0;
  // The largest distance in time of a leg's sample used from utime; -1: a leg has none yet.
  double oldest_ft_age_s = -1.0;
  int32_t flags = 0;  // the six samples' flags or-ed, with kFlagStaleFt
};

struct CorrectorCounters {
  int64_t ft_in = 0, servo_in = 0, mocap_in = 0;
  int64_t corrected = 0;
  int64_t no_calibration = 0;  // samples that came before any calibration
  int64_t out_of_order = 0;
  int64_t non_finite = 0;
  int64_t no_servo = 0;  // samples before any servo state (corrected, flagged)
};

class Corrector {
 public:
  explicit Corrector(const CorrectorOptions& options);

  // Precomputes the per-leg transforms. Throws std::invalid_argument naming the leg and
  // quantity when a parameter is not finite or a rotation is not one.
  void SetCalibration(const RobotCalibration& cal, int64_t version);
  bool has_calibration() const { return has_calibration_; }
  int64_t calibration_version() const { return version_; }

  // Return false when the input was dropped (out of order, non-finite: counted).
  bool AddServo(const ServoInput& in);
  bool AddMocap(const MocapInput& in);
  // A transducer sample of leg `in.leg`. Returns the corrected wrenches of all legs, or
  // nullopt when the sample was dropped or no calibration is set yet. `saturated` flags it.
  std::optional<ContactWrenches> AddFt(const FtInput& in, bool saturated);
  // Same without the optional (the hot path): false when there is no output.
  bool AddFt(const FtInput& in, bool saturated, ContactWrenches* out);
  // The next sum that is due (header comment), oldest first; false when none is yet. Call it
  // until false after each AddFt. With `input_ended` (the end of a replay, a shutdown) a sum is
  // not waited for: the instants still held back are summed from the samples there are, nearest
  // first as always, so the last instants of a recording are not lost.
  bool NextSum(WrenchSum* out, bool input_ended = false);

  const CorrectorCounters& counters() const { return counters_; }

 private:
  struct LegConst {
    Mat3 R_C_ft;  // rotation of X_C_ft
    Vec3 p_C_ft;  // translation of X_C_ft
    Vec6 offset;
    double weight_n;
    LegComModel com;
  };
  // r_C, leg k's CoM in C at `angle_rad`; see com_memo_.
  const Vec3& ComInC(int k, double angle_rad);
  Vec6 CorrectLeg(int k, const Vec6& w_m, const Vec3& r_C, const Mat3& R_WC) const;

  CorrectorOptions options_;
  bool has_calibration_ = false;
  int64_t version_ = 0;
  double weight_total_n_ = 0.0;
  std::array<LegConst, kNumLegs> leg_;
  ServoHistory servo_;
  int64_t servo_delay_us_ = 0;  // the calibration's servo delay, subtracted from servo stamps
  std::optional<MocapInput> mocap_;
  struct LegState {
    bool seen = false;
    int64_t utime = 0;
    int32_t flags = 0;  // of its own correction
    Vec6 wrench_W = Vec6::Zero();
  };
  std::array<LegState, kNumLegs> state_;
  // The last CoM computed per leg and the angle it was computed at (bit for bit). The CoM
  // curve costs two sin() per sample, and a leg's angle repeats from sample to sample
  // whenever it stands still (most of a calibration session) or the transducers run faster
  // than the servos: the same expression of the same angle, so the same bits, computed once.
  struct ComMemo {
    bool valid = false;
    uint64_t angle_bits = 0;
    Vec3 r_C = Vec3::Zero();
  };
  std::array<ComMemo, kNumLegs> com_memo_;
  // Each leg's latest corrected samples, for the sums (oldest overwritten): 256 samples are
  // 37 ms at 7 kHz, more than one leg's messages lag another's on a loaded host.
  struct Past {
    int64_t utime = 0;
    int32_t flags = 0;
    Vec6 wrench_W = Vec6::Zero();
  };
  static constexpr int kHistory = 256;
  struct History {
    std::array<Past, kHistory> ring;
    int64_t count = 0;  // pushed so far; ring[(count - 1) % kHistory] is the latest
    const Past& At(int64_t i) const { return ring[static_cast<size_t>(i % kHistory)]; }
  };
  std::array<History, kNumLegs> history_;
  int64_t newest_utime_ = 0;     // of any leg's sample (0: none since the calibration)
  int64_t first_utime_ = 0;      // the first sample's since the calibration
  int64_t last_sum_utime_ = -1;  // the last sum's instant (-1: none yet)
  CorrectorCounters counters_;
};

}  // namespace ftcal
