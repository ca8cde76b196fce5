// The message boundary: every conversion between the LCM messages (lcmtypes/) and libcal's
// transport-free types, in one place, as a named pair per type (FromLcm / ToLcm), and the
// device-input subscriptions every stage needs. No service folder converts messages itself.
//
// Validation happens here: a message from an unknown leg, on the wrong channel, without every
// leg, or with a quaternion that is not one is refused with a BadInput naming what was wrong;
// non-finite numbers are passed on for the aligner/corrector to count (they own the drop rule).
// The fields a libcal type does not carry (device sequence numbers, servo ids and currents,
// marker positions) are left zero or NaN by ToLcm: ToLcm is for the stages' outputs and for
// tests, not for the bridges, which fill every field from their device.
#pragma once

#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include "common/bus.h"
#include "ftcal/aligner.h"
#include "ftcal/calibration_t.hpp"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/corrector.h"
#include "ftcal/dataset.h"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/experiment_phase.h"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/segmenter.h"
#include "ftcal/servo_state_t.hpp"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "proto/calibration.pb.h"
#include "proto/config.pb.h"

namespace ftcal {

// ---- constants that lcmtypes/ and libcal both define (libcal does not include lcmtypes) ----
static_assert(contact_wrench_t::FLAG_STALE_SERVO == kFlagStaleServo);
static_assert(contact_wrench_t::FLAG_STALE_MOCAP == kFlagStaleMocap);
static_assert(contact_wrench_t::FLAG_SATURATED == kFlagSaturated);
static_assert(contact_wrench_sum_t::FLAG_STALE_FT == kFlagStaleFt);
static_assert(contact_wrench_sum_t::FLAG_STALE_SERVO == kFlagStaleServo);
static_assert(contact_wrench_sum_t::FLAG_STALE_MOCAP == kFlagStaleMocap);
static_assert(contact_wrench_sum_t::FLAG_SATURATED == kFlagSaturated);
static_assert(experiment_marker_t::HANG_X_NEG - experiment_marker_t::HANG_X_POS ==
              static_cast<int>(HangSeries::kXNeg));
static_assert(experiment_marker_t::HANG_Z_POS - experiment_marker_t::HANG_X_POS ==
              static_cast<int>(HangSeries::kZPos));
static_assert(experiment_marker_t::HANG_Z_NEG - experiment_marker_t::HANG_X_POS ==
              static_cast<int>(HangSeries::kZNeg));
static_assert(kNumHangSeries == 4);
static_assert(experiment_marker_t::IDLE == static_cast<int>(ExperimentPhase::kIdle));
static_assert(experiment_marker_t::HANG_X_POS == static_cast<int>(ExperimentPhase::kHangXPos));
static_assert(experiment_marker_t::HANG_X_NEG == static_cast<int>(ExperimentPhase::kHangXNeg));
static_assert(experiment_marker_t::HANG_Z_POS == static_cast<int>(ExperimentPhase::kHangZPos));
static_assert(experiment_marker_t::HANG_Z_NEG == static_cast<int>(ExperimentPhase::kHangZNeg));
static_assert(experiment_marker_t::STANDING == static_cast<int>(ExperimentPhase::kStanding));
static_assert(experiment_marker_t::WALKING == static_cast<int>(ExperimentPhase::kWalking));
static_assert(experiment_marker_t::TRIPOD == static_cast<int>(ExperimentPhase::kTripod));
static_assert(experiment_marker_t::TARE == static_cast<int>(ExperimentPhase::kTare));

// ---- FT_<LEG>: ft_batch_t <-> FtBatch ----
// One record of an FT message: its FtInput (utime = the record's sample_utime) and the device's
// numbers a reader may count by.
struct FtRecord {
  FtInput in;
  int64_t rdt_sequence = 0;
  int64_t ft_sequence = 0;  // the device's internal sample counter (ftcal-doctor's clock)
  int64_t status = 0;
  int32_t gap = 0;
};
// One ft_batch_t: a datagram's 1..kMaxFtRecords records, oldest first. Fixed storage, so a
// reader decodes into one it keeps and allocates nothing per message.
inline constexpr int kMaxFtRecords = ft_batch_t::MAX_N;
struct FtBatch {
  int leg = 0;
  int64_t receipt_utime = 0;
  int n = 0;
  std::array<FtRecord, kMaxFtRecords> records;
  const FtRecord* begin() const { return records.data(); }
  const FtRecord* end() const { return records.data() + n; }
};
// `leg` is the channel's leg; the message must name the same one and hold 1..kMaxFtRecords
// records with every array of its count (BadInput naming what is wrong otherwise).
void FromLcm(const ft_batch_t& msg, int leg, FtBatch* out);
// Every field from the batch (counts zero: FtRecord does not carry them).
ft_batch_t ToLcm(const FtBatch& batch);
// A batch of one record: the sample as a test or the twin's log writer makes it.
FtBatch BatchOf(const FtInput& in, int64_t receipt_utime);
// The Peek* functions below read an encoded device message in place, giving what wire::Decode
// and FromLcm would give, bit for bit, when the bytes are exactly what lcm-gen's encoder writes
// for a message they accept (the wire guard's rules, wire_guard.h, and FromLcm's). That is the
// only case they read; false/nullopt for anything else (another fingerprint or leg name, a size
// that is not the layout's, ...), which the caller then decodes through wire::Decode and
// FromLcm, and they name what is wrong. Why by hand: LCM's generated decoder costs a function
// call per scalar field and a string copy per name, after the wire guard's walk of the same
// bytes; for the few fields a stage takes, that was a quarter of the calibrator's reading
// thread in perf on the report-scale log (its four hanging series: 182 ms before, 71-115 ms
// after).
//
// An ft_batch_t on leg `leg`'s channel into *out.
bool PeekFtBatch(const void* data, int size, int leg, FtBatch* out);
// An ft_batch_t's record count and each record's rdt_sequence, read in place: a reader that
// only counts records (the calibrator over a span it does not align) need not read the rest.
// nullopt when `data` is not the layout of an ft_batch_t of leg `leg`, as PeekFtBatch.
// `sequences` gets n values.
std::optional<int> PeekRdtSequences(const void* data, int size, int leg,
                                    std::array<int64_t, kMaxFtRecords>* sequences);

// ---- SERVO_STATE: servo_state_t <-> ServoInput ----
// Every leg exactly once, by name, in any order (BadInput otherwise).
ServoInput FromLcm(const servo_state_t& msg);
// The legs in config order; ids, velocities, currents and ticks zero.
servo_state_t ToLcm(const ServoInput& in);
// A servo_state_t read in place (Peek*, above).
std::optional<ServoInput> PeekServoState(const void* data, int size);

// ---- MOCAP_BODY: mocap_body_t <-> MocapInput ----
// markers_ok: tracked, at least `chassis_markers` markers, every one tracked. A tracked q_wc
// that is finite but not a unit quaternion is a BadInput; a non-finite one stays non-finite.
MocapInput FromLcm(const mocap_body_t& msg, int chassis_markers);
// A mocap_body_t of rigid body `body` read in place (Peek*, above); nullopt also for another
// body's frame (the caller's decode then tells the two apart) and for more than 16 markers.
std::optional<MocapInput> PeekMocapBody(const void* data, int size, std::string_view body,
                                        int chassis_markers);
// `chassis_markers` markers, tracked when in.markers_ok, positions NaN; q_gc = q_wc.
mocap_body_t ToLcm(const MocapInput& in, const std::string& body, int chassis_markers);
// The mocap bridges' side: the chassis pose X^G_C (m) into q_gc, its heading-free q_wc, yaw_rad
// and position_m, with `residual_m`; with no pose (nullptr: untracked) every one of them NaN,
// never zeros and never the last pose, so a consumer that ignores `tracked` still sees no number.
void SetBodyPose(const Pose3* X_GC, double residual_m, mocap_body_t* msg);

// ---- SYNC_SAMPLE: sync_sample_t <-> AlignedSample ----
AlignedSample FromLcm(const sync_sample_t& msg);
sync_sample_t ToLcm(const AlignedSample& in);
// The same into a message already sized for six legs (the segmenter's hot path: no allocation).
void ToLcm(const AlignedSample& in, sync_sample_t* out);

// ---- STEADY_POSE: steady_pose_t <-> SteadyPoseOut ----
// What the message carries besides the pose.
struct SteadyPoseHeader {
  int64_t utime = 0;  // publish time
  std::string session_id;
  int32_t pose_index = 0;
};
// Legs by name, any order (BadInput for another count or an unknown leg); pose.t_s is the
// centre of [start_utime, end_utime]. The within-pose scatter travels with the medians when it
// was taken over the same samples (pose.samples == num_samples), else as NaN; a message with
// any NaN in it gives pose.samples = 0 (no scatter).
SteadyPoseOut FromLcm(const steady_pose_t& msg, SteadyPoseHeader* header = nullptr);
steady_pose_t ToLcm(const SteadyPoseOut& pose, const SteadyPoseHeader& header);

// ---- CALIBRATION: calibration_t <-> calibration::Calibration ----
struct CalibrationMessage {
  calibration::Calibration proto;
  int64_t version = 0;
  int64_t utime = 0;
  std::string sha256;  // hex SHA-256 of the binary proto: the calibration's identity
};
// Checks the size field, the SHA-256 and the protobuf; throws std::runtime_error naming which.
CalibrationMessage FromLcm(const calibration_t& msg);
calibration_t ToLcm(const calibration::Calibration& proto, int64_t version, int64_t utime);

// ---- CONTACT_WRENCH: contact_wrench_t <-> LegWrench (leg-samples) ----
// A leg index outside the legs, a count outside 1..MAX_N or an array of another length is a
// BadInput. Ages travel as float seconds (-1: none).
std::vector<LegWrench> FromLcm(const contact_wrench_t& msg);
// The message's sample i (no checks: for a message FromLcm took, or one this process made).
LegWrench LegWrenchAt(const contact_wrench_t& msg, int i);
// Starts a message of leg `leg` for the samples of the FT message received at receipt_utime,
// and appends one leg-sample (the corrector's hot path: the vectors keep their capacity).
void ClearLcm(int leg, int64_t receipt_utime, contact_wrench_t* msg);
void AppendLcm(const LegWrench& in, contact_wrench_t* msg);

// ---- CONTACT_WRENCH_SUM: contact_wrench_sum_t <-> WrenchSum ----
std::vector<WrenchSum> FromLcm(const contact_wrench_sum_t& msg);
WrenchSum WrenchSumAt(const contact_wrench_sum_t& msg, int i);
void ClearLcm(int64_t calibration_version, contact_wrench_sum_t* msg);
void AppendLcm(const WrenchSum& in, contact_wrench_sum_t* msg);

// ---- EXPERIMENT phases ----
// The hanging series of a HANG_* phase, nullopt for any other phase.
std::optional<HangSeries> HangSeriesOfPhase(int phase);
int8_t PhaseOfHangSeries(HangSeries series);
// "HANG_X_POS" ... "TRIPOD", or "phase N" for a code no lcmtypes constant names.
std::string PhaseName(int phase);

// ---- device inputs: what every stage reads from the bridges ----
// The config's FT channels, chassis body and marker count, and the subscriptions to FT_<LEG>,
// SERVO_STATE and MOCAP_BODY that hand libcal inputs to a stage.
class DeviceInputs {
 public:
  // Throws std::invalid_argument when the config's legs are not kLegNames in order.
  explicit DeviceInputs(const config::Config& config);

  // FT_<LEG> channel name of leg k.
  const std::string& FtChannel(int k) const { return ft_channel_[k]; }
  void FromFt(int leg, const ft_batch_t& msg, FtBatch* out) const { FromLcm(msg, leg, out); }
  // One FT message's batch: read in place when it can be (PeekFtBatch), else decoded into
  // *scratch as a typed subscription decodes (BadInput naming what is wrong).
  void FtOf(int leg, const MessageInfo& info, const void* data, int size, ft_batch_t* scratch,
            FtBatch* out) const;
  // nullopt for another rigid body than the config's chassis body.
  std::optional<MocapInput> FromMocap(const mocap_body_t& msg) const;
  // One message's input: read in place when it can be (Peek*), else decoded into *scratch as a
  // typed subscription decodes (BadInput naming what is wrong). nullopt: another body's frame.
  ServoInput ServoOf(const MessageInfo& info, const void* data, int size,
                     servo_state_t* scratch) const;
  std::optional<MocapInput> MocapOf(const MessageInfo& info, const void* data, int size,
                                    mocap_body_t* scratch) const;

  // A null handler is not subscribed. Mocap frames of another body are not handed on.
  struct Handlers {
    std::function<void(const FtBatch&)> ft;  // one FT_<LEG> message
    std::function<void(const ServoInput&)> servo;
    std::function<void(const MocapInput&)> mocap;
  };
  void Subscribe(Bus& bus, const Handlers& handlers) const;

 private:
  const config::Channels channels_;
  std::array<std::string, kNumLegs> ft_channel_;
  std::string body_name_;
  int chassis_markers_;
};

// The aligner's freshness limits: the corrector's (corrector.max_servo_age_s,
// max_mocap_age_s), so every stage calls the same input stale.
AlignerOptions AlignerOptionsFromConfig(const config::Config& config);
// The segmenter's options (config section segmenter), as the segmenter and calibrator use them.
SegmenterOptions SegmenterOptionsFromConfig(const config::Segmenter& segmenter);

}  // namespace ftcal
