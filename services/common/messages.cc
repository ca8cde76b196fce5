// One file over 600 lines: every LCM <-> libcal conversion in one place (messages.h).
#include "common/messages.h"

#include <cmath>
#include <cstring>
#include <limits>
#include <memory>
#include <stdexcept>

#include "common/big_endian.h"
#include "ftcal/config.h"
#include "ftcal/hanging.h"

namespace ftcal {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

void QuaternionOf(const Mat3& R, double q_wxyz[4]) {
  const Eigen::Vector4d q = RotationToQuaternion(R);
  for (int i = 0; i < 4; ++i) q_wxyz[i] = q[i];
}

Mat3 RotationOf(const double q_wxyz[4]) {
  return QuaternionToRotation(Eigen::Vector4d(q_wxyz[0], q_wxyz[1], q_wxyz[2], q_wxyz[3]));
}

}  // namespace

// ---- FT_<LEG> ----

namespace {

// LCM's scalars, read in place.
int64_t Int64At(const uint8_t* p) { return static_cast<int64_t>(Be64(p)); }
int32_t Int32At(const uint8_t* p) { return static_cast<int32_t>(Be32(p)); }
double DoubleAt(const uint8_t* p) {
  const uint64_t bits = Be64(p);
  double d;
  std::memcpy(&d, &bits, sizeof d);
  return d;
}

}  // namespace

// LCM's encoding of ft_batch_t (lcm-gen's rules): the 8-byte fingerprint, then the fields in
// their .lcm order, big-endian; a string is its int32 length (with the NUL) and its bytes and
// NUL; an array of n is its n elements, row by row. So after receipt_utime, the name and n
// come the per-record arrays, each n long, at fixed multiples of n. messages_test checks this
// against the generated encoder, and the fingerprint check refuses any other layout.
namespace {

constexpr int kFtAfterNamePerRecord = 4 * 8 + 6 * 4 + 6 * 8 + 4 + 4;  // bytes per record

// Where the arrays start and how many records, or nullopt when `data` is not the layout of an
// ft_batch_t with leg `leg`'s name.
struct FtLayout {
  const uint8_t* arrays;
  int n;
};
std::optional<FtLayout> FtLayoutOf(const void* data, int size, int leg) {
  constexpr int kNameLength = 16, kName = 20;
  const auto* p = static_cast<const uint8_t*>(data);
  if (size < kName || Int64At(p) != ft_batch_t::getHash()) return std::nullopt;
  const int32_t length = Int32At(p + kNameLength);
  if (length < 1 || length > size - kName - 2) return std::nullopt;
  if (leg < 0 || leg >= kNumLegs) return std::nullopt;
  const std::string_view name = kLegNames[leg];
  if (length != static_cast<int>(name.size()) + 1 ||
      std::memcmp(p + kName, name.data(), name.size()) != 0) {
    return std::nullopt;
  }
  if (p[kName + length - 1] != 0) return std::nullopt;
  const uint8_t* after = p + kName + length;
  const int n = static_cast<int16_t>(Be16(after));
  if (n < 1 || n > kMaxFtRecords || size != kName + length + 2 + n * kFtAfterNamePerRecord) {
    return std::nullopt;
  }
  return FtLayout{after + 2, n};
}

}  // namespace

bool PeekFtBatch(const void* data, int size, int leg, FtBatch* out) {
  const std::optional<FtLayout> layout = FtLayoutOf(data, size, leg);
  if (!layout) return false;
  const uint8_t* a = layout->arrays;
  const int n = layout->n;
  const uint8_t* utime = a;
  const uint8_t* rdt = a + 8 * n;
  const uint8_t* ft = a + 16 * n;
  const uint8_t* status = a + 24 * n;
  const uint8_t* wrench = a + 32 * n + 24 * n;
  const uint8_t* gap = wrench + 48 * n;
  const uint8_t* flags = gap + 4 * n;
  out->leg = leg;
  out->receipt_utime = Int64At(static_cast<const uint8_t*>(data) + 8);
  out->n = n;
  for (int i = 0; i < n; ++i) {
    FtRecord& r = out->records[static_cast<size_t>(i)];
    r.in.utime = Int64At(utime + 8 * i);
    r.in.leg = leg;
    for (int j = 0; j < 6; ++j) r.in.wrench[j] = DoubleAt(wrench + 48 * i + 8 * j);
    r.in.flags = Int32At(flags + 4 * i);
    r.rdt_sequence = Int64At(rdt + 8 * i);
    r.ft_sequence = Int64At(ft + 8 * i);
    r.status = Int64At(status + 8 * i);
    r.gap = Int32At(gap + 4 * i);
  }
  return true;
}

std::optional<int> PeekRdtSequences(const void* data, int size, int leg,
                                    std::array<int64_t, kMaxFtRecords>* sequences) {
  if (leg < 0) return std::nullopt;
  const std::optional<FtLayout> layout = FtLayoutOf(data, size, leg);
  if (!layout) return std::nullopt;
  const uint8_t* rdt = layout->arrays + 8 * layout->n;
  for (int i = 0; i < layout->n; ++i) (*sequences)[static_cast<size_t>(i)] = Int64At(rdt + 8 * i);
  return layout->n;
}

void FromLcm(const ft_batch_t& msg, int leg, FtBatch* out) {
  if (leg < 0 || leg >= kNumLegs || msg.leg != kLegNames[leg]) {
    throw BadInput(
        "leg name not the channel's",
        "message names leg '" + msg.leg + "' on the channel of leg " +
            (leg >= 0 && leg < kNumLegs ? std::string(kLegNames[leg]) : std::to_string(leg)));
  }
  if (msg.n < 1 || msg.n > kMaxFtRecords) {
    throw BadInput("FT record count", "ft_batch_t on leg " + msg.leg + " holds " +
                                          std::to_string(msg.n) + " records, not 1.." +
                                          std::to_string(kMaxFtRecords));
  }
  // lcm-gen's decoder sizes every array by n: a message it decoded has them all n long.
  out->leg = leg;
  out->receipt_utime = msg.receipt_utime;
  out->n = msg.n;
  for (int i = 0; i < msg.n; ++i) {
    FtRecord& r = out->records[static_cast<size_t>(i)];
    r.in.utime = msg.sample_utime[i];
    r.in.leg = leg;
    for (int j = 0; j < 6; ++j) r.in.wrench[j] = msg.wrench[i][j];
    r.in.flags = msg.flags[i];
    r.rdt_sequence = msg.rdt_sequence[i];
    r.ft_sequence = msg.ft_sequence[i];
    r.status = msg.status[i];
    r.gap = msg.gap[i];
  }
}

ft_batch_t ToLcm(const FtBatch& batch) {
  ft_batch_t msg{};
  msg.receipt_utime = batch.receipt_utime;
  msg.leg = std::string(kLegNames.at(static_cast<size_t>(batch.leg)));
  msg.n = static_cast<int16_t>(batch.n);
  const auto n = static_cast<size_t>(batch.n);
  msg.sample_utime.resize(n);
  msg.rdt_sequence.resize(n);
  msg.ft_sequence.resize(n);
  msg.status.resize(n);
  msg.counts.assign(n, std::vector<int32_t>(6, 0));
  msg.wrench.assign(n, std::vector<double>(6, 0.0));
  msg.gap.resize(n);
  msg.flags.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const FtRecord& r = batch.records[i];
    msg.sample_utime[i] = r.in.utime;
    msg.rdt_sequence[i] = r.rdt_sequence;
    msg.ft_sequence[i] = r.ft_sequence;
    msg.status[i] = r.status;
    for (size_t j = 0; j < 6; ++j) msg.wrench[i][j] = r.in.wrench[static_cast<int>(j)];
    msg.gap[i] = r.gap;
    msg.flags[i] = r.in.flags;
  }
  return msg;
}

FtBatch BatchOf(const FtInput& in, int64_t receipt_utime) {
  FtBatch b;
  b.leg = in.leg;
  b.receipt_utime = receipt_utime;
  b.n = 1;
  b.records[0].in = in;
  return b;
}

// ---- SERVO_STATE ----

ServoInput FromLcm(const servo_state_t& msg) {
  ServoInput in;
  // The sampling instant, not the completion: a reply can wait a USB adapter's latency timer.
  in.utime = msg.sample_utime;
  std::array<bool, kNumLegs> seen{};
  for (int i = 0; i < kNumLegs; ++i) {
    const auto k = LegIndex(msg.leg[i]);
    if (!k) {
      throw BadInput("unknown leg in servo state", "servo " + std::to_string(i) + " (id " +
                                                       std::to_string(msg.id[i]) + ") names leg '" +
                                                       msg.leg[i] + "'");
    }
    if (seen[*k]) {
      throw BadInput("duplicate leg in servo state", "leg " + msg.leg[i] + " twice");
    }
    seen[*k] = true;
    in.angle_rad[*k] = msg.angle_rad[i];
  }
  for (int k = 0; k < kNumLegs; ++k) {
    if (!seen[k]) {
      throw BadInput("servo state without every leg",
                     "no servo for leg " + std::string(kLegNames[k]));
    }
  }
  return in;
}

std::optional<ServoInput> PeekServoState(const void* data, int size) {
  // After the six names: id[6] (int32), angle_rad, velocity_rad_s, current_a (double[6]),
  // hardware_error[6] (int32), device_tick_ms[6] (int64), flags[6] (int32), sample_utime (int64).
  constexpr int kAfterLegs = 6 * 4 + 3 * 6 * 8 + 6 * 4 + 6 * 8 + 6 * 4 + 8, kAngles = 6 * 4;
  const auto* p = static_cast<const uint8_t*>(data);
  if (size < 16 || Int64At(p) != servo_state_t::getHash()) return std::nullopt;
  std::array<int, kNumLegs> leg_of{};
  std::array<bool, kNumLegs> seen{};
  int at = 16;
  for (int i = 0; i < kNumLegs; ++i) {
    if (at + 4 > size) return std::nullopt;
    const int32_t length = Int32At(p + at);  // with its NUL
    at += 4;
    if (length < 2 || length > size - at || p[at + length - 1] != 0) return std::nullopt;
    const auto k = LegIndex(
        std::string_view(reinterpret_cast<const char*>(p + at), static_cast<size_t>(length - 1)));
    // A leg name holds no NUL, so a match is also what the wire guard asks of a string.
    if (!k || seen[*k]) return std::nullopt;
    seen[*k] = true;
    leg_of[i] = *k;
    at += length;
  }
  if (size != at + kAfterLegs) return std::nullopt;
  ServoInput in;
  in.utime = Int64At(p + size - 8);  // sample_utime, the last member
  for (int i = 0; i < kNumLegs; ++i) in.angle_rad[leg_of[i]] = DoubleAt(p + at + kAngles + 8 * i);
  return in;
}

servo_state_t ToLcm(const ServoInput& in) {
  servo_state_t msg{};
  msg.utime = msg.sample_utime = in.utime;
  for (int k = 0; k < kNumLegs; ++k) {
    msg.leg[k] = kLegNames[k];
    msg.angle_rad[k] = in.angle_rad[k];
  }
  return msg;
}

// ---- MOCAP_BODY ----

namespace {

MocapInput MocapInputOf(int64_t utime, bool tracked, const double q_wc[4], bool markers_ok) {
  MocapInput in;
  in.utime = utime;
  in.tracked = tracked;
  if (tracked) {
    const Eigen::Vector4d q(q_wc[0], q_wc[1], q_wc[2], q_wc[3]);
    if (q.allFinite() && std::abs(q.norm() - 1.0) > 1e-3) {
      throw BadInput("mocap q_wc not a unit quaternion",
                     "|q_wc| = " + std::to_string(q.norm()) + " at utime " + std::to_string(utime));
    }
    // A non-finite quaternion stays non-finite: the aligner/corrector count and drop it.
    in.R_WC = q.allFinite() ? QuaternionToRotation(q) : Mat3::Constant(kNaN);
  }
  in.markers_ok = markers_ok;
  return in;
}

}  // namespace

MocapInput FromLcm(const mocap_body_t& msg, int chassis_markers) {
  bool all = msg.tracked && msg.num_markers >= chassis_markers;
  for (int i = 0; all && i < msg.num_markers; ++i) all = msg.marker_tracked[i];
  return MocapInputOf(msg.sample_utime, msg.tracked, msg.q_wc, all);
}

std::optional<MocapInput> PeekMocapBody(const void* data, int size, std::string_view body,
                                        int chassis_markers) {
  // The body's name is at 32, after utime, frame_number, device_utime; after it: tracked
  // (boolean), q_wc[4], q_gc[4], position_m[3], yaw_rad, residual_m (double), num_markers
  // (int32), marker_m[n][3] (double), marker_tracked[n] (boolean), sample_utime (int64).
  constexpr int kName = 32, kQwc = 1, kMarkers = 1 + 8 * (4 + 4 + 3 + 1 + 1);
  constexpr int kAfterName = kMarkers + 4 + 8;
  // Few markers only: the wire guard's bound on the decoded size then cannot refuse it.
  constexpr int kMaxMarkers = 16;
  const auto* p = static_cast<const uint8_t*>(data);
  const auto length = static_cast<int>(body.size()) + 1;
  if (size < kName + 4 + length + kAfterName || Int64At(p) != mocap_body_t::getHash() ||
      Int32At(p + kName) != length || body.find('\0') != std::string_view::npos ||
      std::memcmp(p + kName + 4, body.data(), body.size()) != 0 ||
      p[kName + 4 + body.size()] != 0) {
    return std::nullopt;
  }
  const uint8_t* after = p + kName + 4 + length;
  const int32_t n = Int32At(after + kMarkers);
  if (n < 0 || n > kMaxMarkers || size != kName + 4 + length + kAfterName + 25 * n ||
      after[0] > 1) {
    return std::nullopt;
  }
  const uint8_t* marker_tracked = after + kMarkers + 4 + 24 * n;
  bool all = after[0] == 1 && n >= chassis_markers;
  for (int i = 0; i < n; ++i) {
    if (marker_tracked[i] > 1) return std::nullopt;
    all = all && marker_tracked[i] == 1;
  }
  double q_wc[4];
  for (int i = 0; i < 4; ++i) q_wc[i] = DoubleAt(after + kQwc + 8 * i);
  return MocapInputOf(Int64At(p + size - 8), after[0] == 1, q_wc, all);
}

mocap_body_t ToLcm(const MocapInput& in, const std::string& body, int chassis_markers) {
  mocap_body_t msg{};
  msg.utime = msg.sample_utime = in.utime;
  msg.body = body;
  msg.tracked = in.tracked;
  if (in.tracked) {
    QuaternionOf(in.R_WC, msg.q_wc);
  } else {
    for (double& q : msg.q_wc) q = kNaN;
  }
  for (int i = 0; i < 4; ++i) msg.q_gc[i] = msg.q_wc[i];
  for (double& p : msg.position_m) p = kNaN;
  msg.residual_m = kNaN;
  msg.num_markers = chassis_markers;
  msg.marker_m.assign(static_cast<size_t>(chassis_markers), std::vector<double>(3, kNaN));
  msg.marker_tracked.assign(static_cast<size_t>(chassis_markers), in.markers_ok);
  return msg;
}

void SetBodyPose(const Pose3* X_GC, double residual_m, mocap_body_t* msg) {
  if (X_GC == nullptr) {
    for (int i = 0; i < 4; ++i) msg->q_gc[i] = msg->q_wc[i] = kNaN;
    for (double& p : msg->position_m) p = kNaN;
    msg->yaw_rad = kNaN;
    msg->residual_m = kNaN;
    return;
  }
  QuaternionOf(X_GC->R, msg->q_gc);
  QuaternionOf(RemoveHeading(X_GC->R), msg->q_wc);
  msg->yaw_rad = HeadingYaw(X_GC->R);
  for (int i = 0; i < 3; ++i) msg->position_m[i] = X_GC->p(i);
  msg->residual_m = residual_m;
}

// ---- SYNC_SAMPLE ----

AlignedSample FromLcm(const sync_sample_t& msg) {
  AlignedSample a;
  SyncSample& s = a.sample;
  s.utime = msg.utime;
  for (int i = 0; i < kNumLegs; ++i) {
    if (msg.leg[i] != kLegNames[i]) {
      throw BadInput("SYNC_SAMPLE legs not in config order",
                     "leg " + std::to_string(i) + " is '" + msg.leg[i] + "'");
    }
    for (int c = 0; c < 6; ++c) s.wrench[i][c] = msg.wrench[i][c];
    s.angle_rad[i] = msg.angle_rad[i];
  }
  s.R_WC = RotationOf(msg.q_wc);
  s.attitude_ok = msg.attitude_ok;
  s.markers_ok = msg.markers_ok;
  a.flags = msg.flags;
  return a;
}

void ToLcm(const AlignedSample& a, sync_sample_t* out) {
  const SyncSample& s = a.sample;
  sync_sample_t& msg = *out;
  msg.utime = s.utime;
  for (int k = 0; k < kNumLegs; ++k) {
    if (msg.leg[k] != kLegNames[k]) msg.leg[k] = kLegNames[k];  // once: the message is reused
    for (int i = 0; i < 6; ++i) msg.wrench[k][i] = s.wrench[k][i];
    msg.angle_rad[k] = s.angle_rad[k];
  }
  QuaternionOf(s.R_WC, msg.q_wc);
  msg.attitude_ok = s.attitude_ok;
  msg.markers_ok = s.markers_ok;
  msg.flags = a.flags;
}

sync_sample_t ToLcm(const AlignedSample& a) {
  sync_sample_t msg{};
  ToLcm(a, &msg);
  return msg;
}

// ---- STEADY_POSE ----

SteadyPoseOut FromLcm(const steady_pose_t& msg, SteadyPoseHeader* header) {
  SteadyPoseOut p;
  std::array<bool, kNumLegs> seen{};
  for (int i = 0; i < kNumLegs; ++i) {
    const auto k = LegIndex(msg.leg[i]);
    if (!k) throw BadInput("STEADY_POSE unknown leg", "leg '" + msg.leg[i] + "'");
    if (seen[*k]) throw BadInput("STEADY_POSE duplicate leg", "leg " + msg.leg[i] + " twice");
    seen[*k] = true;
    for (int c = 0; c < 6; ++c) {
      p.pose.wrench[*k][c] = msg.wrench[i][c];
      p.pose.wrench_sem[*k][c] = msg.wrench_sem[i][c];
    }
    p.pose.angle_rad[*k] = msg.angle_rad[i];
  }
  p.pose.R_WC = RotationOf(msg.q_wc);
  for (int c = 0; c < 3; ++c) p.pose.attitude_sem_rad[c] = msg.attitude_sem_rad[c];
  // The scatter is over the medians' samples; one NaN (a publisher that computed none) and the
  // pose has no noise floor, rather than a floor with a hole in it.
  bool scatter = msg.num_samples > 0 && p.pose.attitude_sem_rad.allFinite();
  for (int k = 0; k < kNumLegs && scatter; ++k) scatter = p.pose.wrench_sem[k].allFinite();
  p.pose.samples = scatter ? msg.num_samples : 0;
  p.pose.t_s = 0.5e-6 * static_cast<double>(msg.start_utime + msg.end_utime);
  p.start_utime = msg.start_utime;
  p.end_utime = msg.end_utime;
  p.num_samples = msg.num_samples;
  p.markers_ok = msg.markers_ok;
  if (header) *header = {msg.utime, msg.session_id, msg.pose_index};
  return p;
}

steady_pose_t ToLcm(const SteadyPoseOut& p, const SteadyPoseHeader& header) {
  steady_pose_t msg{};
  msg.utime = header.utime;
  msg.session_id = header.session_id;
  msg.pose_index = header.pose_index;
  msg.start_utime = p.start_utime;
  msg.end_utime = p.end_utime;
  msg.num_samples = p.num_samples;
  // The scatter travels only when it is over the same samples as the medians.
  const bool scatter = p.pose.samples > 0 && p.pose.samples == p.num_samples;
  for (int k = 0; k < kNumLegs; ++k) {
    msg.leg[k] = kLegNames[k];
    for (int i = 0; i < 6; ++i) {
      msg.wrench[k][i] = p.pose.wrench[k][i];
      msg.wrench_sem[k][i] = scatter ? p.pose.wrench_sem[k][i] : kNaN;
    }
    msg.angle_rad[k] = p.pose.angle_rad[k];
  }
  QuaternionOf(p.pose.R_WC, msg.q_wc);
  for (int c = 0; c < 3; ++c) msg.attitude_sem_rad[c] = scatter ? p.pose.attitude_sem_rad[c] : kNaN;
  msg.markers_ok = p.markers_ok;
  return msg;
}

// ---- CALIBRATION ----

CalibrationMessage FromLcm(const calibration_t& msg) {
  if (msg.size != static_cast<int32_t>(msg.data.size())) {
    throw std::runtime_error("size field " + std::to_string(msg.size) + " but " +
                             std::to_string(msg.data.size()) + " bytes");
  }
  const std::string bytes(msg.data.begin(), msg.data.end());
  CalibrationMessage out;
  out.sha256 = Sha256Hex(bytes);
  if (out.sha256 != msg.content_sha256) {
    throw std::runtime_error("content_sha256 " + msg.content_sha256 +
                             " does not match the data's " + out.sha256);
  }
  if (!out.proto.ParseFromString(bytes)) {
    throw std::runtime_error("data is not a binary ftcal.calibration.Calibration");
  }
  out.version = msg.version;
  out.utime = msg.utime;
  return out;
}

calibration_t ToLcm(const calibration::Calibration& proto, int64_t version, int64_t utime) {
  std::string bytes;
  proto.SerializeToString(&bytes);
  calibration_t msg{};
  msg.utime = utime;
  msg.version = version;
  msg.content_sha256 = Sha256Hex(bytes);
  msg.data.assign(bytes.begin(), bytes.end());
  msg.size = static_cast<int32_t>(msg.data.size());
  return msg;
}

// ---- CONTACT_WRENCH, CONTACT_WRENCH_SUM ----

namespace {

template <class Msg>
void CheckBatchCount(const char* what, const Msg& msg, size_t arrays_of_n) {
  if (msg.n < 1 || msg.n > Msg::MAX_N || arrays_of_n < static_cast<size_t>(msg.n)) {
    throw BadInput(std::string(what) + " count", std::to_string(msg.n) + " entries (arrays of " +
                                                     std::to_string(arrays_of_n) + "), not 1.." +
                                                     std::to_string(Msg::MAX_N));
  }
}

}  // namespace

LegWrench LegWrenchAt(const contact_wrench_t& msg, int i) {
  const auto at = static_cast<size_t>(i);
  LegWrench w;
  w.utime = msg.utime[at];
  w.leg = msg.leg;
  for (size_t j = 0; j < 6; ++j) w.wrench_W[static_cast<int>(j)] = msg.wrench_w[at][j];
  w.servo_age_s = msg.servo_age_s[at];
  w.mocap_age_s = msg.mocap_age_s[at];
  w.flags = static_cast<uint8_t>(msg.flags[at]);  // a bit mask: no sign extension
  return w;
}

std::vector<LegWrench> FromLcm(const contact_wrench_t& msg) {
  if (msg.leg < 0 || msg.leg >= kNumLegs) {
    throw BadInput("CONTACT_WRENCH leg index", "leg " + std::to_string(msg.leg) + " outside [0, " +
                                                   std::to_string(kNumLegs) + ")");
  }
  CheckBatchCount("CONTACT_WRENCH", msg, msg.utime.size());
  std::vector<LegWrench> out;
  out.reserve(static_cast<size_t>(msg.n));
  for (int i = 0; i < msg.n; ++i) out.push_back(LegWrenchAt(msg, i));
  return out;
}

// lcm-gen's encoder and size walk `n` elements of each array, not the vectors' sizes: a cleared
// message keeps its vectors (and their rows), and the next appends write over them, so a
// publisher that reuses one message allocates nothing once it has held its largest batch.
namespace {

template <class T>
T& Slot(std::vector<T>& v, size_t i) {
  if (v.size() <= i) v.resize(i + 1);
  return v[i];
}
std::vector<double>& Row6(std::vector<std::vector<double>>& v, size_t i) {
  std::vector<double>& row = Slot(v, i);
  row.resize(6);
  return row;
}

}  // namespace

void ClearLcm(int leg, int64_t receipt_utime, contact_wrench_t* msg) {
  msg->receipt_utime = receipt_utime;
  msg->leg = static_cast<int8_t>(leg);
  msg->n = 0;
}

void AppendLcm(const LegWrench& w, contact_wrench_t* msg) {
  const auto i = static_cast<size_t>(msg->n);
  ++msg->n;
  Slot(msg->utime, i) = w.utime;
  std::vector<double>& row = Row6(msg->wrench_w, i);
  for (size_t j = 0; j < 6; ++j) row[j] = w.wrench_W[static_cast<int>(j)];
  Slot(msg->servo_age_s, i) = static_cast<float>(w.servo_age_s);
  Slot(msg->mocap_age_s, i) = static_cast<float>(w.mocap_age_s);
  Slot(msg->flags, i) = static_cast<int8_t>(w.flags);
}

WrenchSum WrenchSumAt(const contact_wrench_sum_t& msg, int i) {
  const auto at = static_cast<size_t>(i);
  WrenchSum s;
  s.utime = msg.utime[at];
  for (size_t j = 0; j < 6; ++j) {
    s.total_W[static_cast<int>(j)] = msg.total_w[at][j];
    s.residual_W[static_cast<int>(j)] = msg.residual_w[at][j];
  }
  s.calibration_version = msg.calibration_version;
  s.oldest_ft_age_s = msg.oldest_ft_age_s[at];
  s.flags = static_cast<uint8_t>(msg.flags[at]);  // a bit mask: no sign extension
  return s;
}

std::vector<WrenchSum> FromLcm(const contact_wrench_sum_t& msg) {
  CheckBatchCount("CONTACT_WRENCH_SUM", msg, msg.utime.size());
  std::vector<WrenchSum> out;
  out.reserve(static_cast<size_t>(msg.n));
  for (int i = 0; i < msg.n; ++i) out.push_back(WrenchSumAt(msg, i));
  return out;
}

void ClearLcm(int64_t calibration_version, contact_wrench_sum_t* msg) {
  msg->calibration_version = calibration_version;
  msg->n = 0;
}

void AppendLcm(const WrenchSum& s, contact_wrench_sum_t* msg) {
  const auto i = static_cast<size_t>(msg->n);
  ++msg->n;
  Slot(msg->utime, i) = s.utime;
  std::vector<double>& total = Row6(msg->total_w, i);
  std::vector<double>& residual = Row6(msg->residual_w, i);
  for (size_t j = 0; j < 6; ++j) {
    total[j] = s.total_W[static_cast<int>(j)];
    residual[j] = s.residual_W[static_cast<int>(j)];
  }
  Slot(msg->oldest_ft_age_s, i) = static_cast<float>(s.oldest_ft_age_s);
  Slot(msg->flags, i) = static_cast<int8_t>(s.flags);
}

// ---- EXPERIMENT phases ----

std::optional<HangSeries> HangSeriesOfPhase(int phase) {
  if (phase < experiment_marker_t::HANG_X_POS || phase > experiment_marker_t::HANG_Z_NEG) {
    return std::nullopt;
  }
  return static_cast<HangSeries>(phase - experiment_marker_t::HANG_X_POS);
}

int8_t PhaseOfHangSeries(HangSeries series) {
  return static_cast<int8_t>(experiment_marker_t::HANG_X_POS + static_cast<int>(series));
}

std::string PhaseName(int phase) {
  if (const auto series = HangSeriesOfPhase(phase)) return HangSeriesName(*series);
  switch (phase) {
    case experiment_marker_t::IDLE:
      return "IDLE";
    case experiment_marker_t::STANDING:
      return "STANDING";
    case experiment_marker_t::WALKING:
      return "WALKING";
    case experiment_marker_t::TRIPOD:
      return "TRIPOD";
    case experiment_marker_t::TARE:
      return "TARE";
    default:
      return "phase " + std::to_string(phase);
  }
}

// ---- device inputs ----

DeviceInputs::DeviceInputs(const config::Config& config)
    : channels_(config.channels()),
      body_name_(config.mocap().body_name()),
      chassis_markers_(static_cast<int>(config.robot().chassis_marker_count())) {
  if (config.robot().leg_size() != kNumLegs) {
    throw std::invalid_argument("config: robot.leg: " + std::to_string(kNumLegs) +
                                " legs expected, got " + std::to_string(config.robot().leg_size()));
  }
  for (int k = 0; k < kNumLegs; ++k) {
    if (config.robot().leg(k).name() != kLegNames[k]) {
      throw std::invalid_argument("config: robot.leg[" + std::to_string(k) + "].name: '" +
                                  config.robot().leg(k).name() + "', expected '" +
                                  std::string(kLegNames[k]) + "'");
    }
    ft_channel_[k] = config.channels().ft_prefix() + std::string(kLegNames[k]);
  }
}

std::optional<MocapInput> DeviceInputs::FromMocap(const mocap_body_t& msg) const {
  if (msg.body != body_name_) return std::nullopt;
  return FromLcm(msg, chassis_markers_);
}

// Each message read in place when it can be (Peek*), else decoded as a typed subscription
// would (one message object per subscription, decoded into again).
void DeviceInputs::Subscribe(Bus& bus, const Handlers& h) const {
  if (h.ft) {
    for (int k = 0; k < kNumLegs; ++k) {
      bus.SubscribeRaw(ft_channel_[k], [this, k, f = h.ft, scratch = std::make_shared<ft_batch_t>(),
                                        batch = std::make_shared<FtBatch>()](
                                           const MessageInfo& info, const void* data, int size) {
        FtOf(k, info, data, size, scratch.get(), batch.get());
        f(*batch);
      });
    }
  }
  if (h.servo) {
    bus.SubscribeRaw(channels_.servo_state(),
                     [this, f = h.servo, scratch = std::make_shared<servo_state_t>()](
                         const MessageInfo& info, const void* data, int size) {
                       f(ServoOf(info, data, size, scratch.get()));
                     });
  }
  if (h.mocap) {
    bus.SubscribeRaw(channels_.mocap_body(),
                     [this, f = h.mocap, scratch = std::make_shared<mocap_body_t>()](
                         const MessageInfo& info, const void* data, int size) {
                       if (const auto in = MocapOf(info, data, size, scratch.get())) f(*in);
                     });
  }
}

void DeviceInputs::FtOf(int leg, const MessageInfo& info, const void* data, int size,
                        ft_batch_t* scratch, FtBatch* out) const {
  if (PeekFtBatch(data, size, leg, out)) return;
  DecodeOrThrow(info, data, size, scratch);
  FromLcm(*scratch, leg, out);
}

ServoInput DeviceInputs::ServoOf(const MessageInfo& info, const void* data, int size,
                                 servo_state_t* scratch) const {
  if (std::optional<ServoInput> peek = PeekServoState(data, size)) return *peek;
  DecodeOrThrow(info, data, size, scratch);
  return FromLcm(*scratch);
}

std::optional<MocapInput> DeviceInputs::MocapOf(const MessageInfo& info, const void* data, int size,
                                                mocap_body_t* scratch) const {
  if (std::optional<MocapInput> peek = PeekMocapBody(data, size, body_name_, chassis_markers_)) {
    return peek;
  }
  DecodeOrThrow(info, data, size, scratch);
  return FromMocap(*scratch);
}

AlignerOptions AlignerOptionsFromConfig(const config::Config& config) {
  AlignerOptions o;
  o.max_servo_age_s = config.corrector().max_servo_age_s();
  o.max_mocap_age_s = config.corrector().max_mocap_age_s();
  return o;
}

SegmenterOptions SegmenterOptionsFromConfig(const config::Segmenter& s) {
  SegmenterOptions o;
  o.sample_rate_hz = s.sample_rate_hz();
  o.savgol_window = static_cast<int>(s.savgol_window());
  o.savgol_order = static_cast<int>(s.savgol_order());
  o.max_force_rate_n_s = s.max_force_rate_n_s();
  o.min_steady_s = s.min_steady_s();
  o.require_all_markers = s.require_all_markers();
  return o;
}

}  // namespace ftcal
