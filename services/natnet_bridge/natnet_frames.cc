// The frames' side of NatNetBridge (natnet_bridge.h): Motive's axes and pivot turned into ftcal's
// frames (MotiveFrames), the sample time mapped from Motive's clock, and each frame of data
// checked and published as a mocap_body_t. The session (sockets, handshake, descriptions,
// keep-alives, liveness) is natnet_bridge.cc.
#include <algorithm>
#include <cmath>
#include <limits>

#include "common/messages.h"
#include "ftcal/config.h"
#include "natnet_bridge.h"

namespace ftcal {
namespace {

// f32 rounding leaves a unit quaternion within ~1e-7 of norm 1: farther is not a pose Motive
// computed.
constexpr double kMaxQuaternionNormError = 1e-3;
// A mapped sample time later than its receipt by more, or older by more than a second, is a
// clock we do not understand: the receipt time is used instead (and counted).
constexpr double kMaxFutureUs = 1000.0;
constexpr double kMaxLatencyUs = 1e6;

bool Finite(const natnet::Vec3f& v) {
  return std::isfinite(v[0]) && std::isfinite(v[1]) && std::isfinite(v[2]);
}

}  // namespace

// ---- MotiveFrames ----

MotiveFrames::MotiveFrames(UpAxis up, const Pose3& X_PC) : X_PC_(X_PC) {
  if (up == UpAxis::kY) {
    // Rx(+90°): y_Y -> z_G, z_Y -> -y_G.
    R_GM_ << 1, 0, 0, 0, 0, -1, 0, 1, 0;
  } else {
    R_GM_.setIdentity();
  }
}

MotiveFrames MotiveFrames::FromConfig(const config::NatNet& n) {
  UpAxis up;
  if (n.up_axis() == "Y") {
    up = UpAxis::kY;
  } else if (n.up_axis() == "Z") {
    up = UpAxis::kZ;
  } else {
    throw NatNetConfigError("mocap.natnet.up_axis '" + n.up_axis() + "' is not Y or Z");
  }
  return MotiveFrames(up, n.has_x_pivot_chassis() ? ToPose3(n.x_pivot_chassis()) : Pose3());
}

Vec3 MotiveFrames::Point(const natnet::Vec3f& p) const { return R_GM_ * Vec3(p[0], p[1], p[2]); }

Mat3 MotiveFrames::Rotation(const natnet::Quatf& q) const {
  // Wire order x, y, z, w; QuaternionToRotation takes (w, x, y, z).
  Eigen::Vector4d wxyz(q[3], q[0], q[1], q[2]);
  wxyz.normalize();
  return R_GM_ * QuaternionToRotation(wxyz);
}

Pose3 MotiveFrames::Chassis(const natnet::Vec3f& p, const natnet::Quatf& q) const {
  return Pose3(Rotation(q), Point(p)) * X_PC_;
}

// ---- Frames ----

int64_t NatNetBridge::SampleUtime(const natnet::FrameOfData& f, int64_t receive_us) {
  const double hz = static_cast<double>(server_.clock_frequency_hz);
  if (!(hz > 0) || f.transmit_ticks == 0) {
    ++stats_.Counter("clock_fallbacks");
    return receive_us;
  }
  const auto us = [hz](uint64_t ticks) { return static_cast<double>(ticks) / hz * 1e6; };
  const double transmit_us = us(f.transmit_ticks);
  if (!motive_clock_) motive_clock_ = std::make_unique<DeviceClock>(DeviceClockOptions{hz});
  // The transmit stamp against the receipt: the lower envelope is Motive's clock plus the least
  // transit. A clock beyond int64 ticks is no clock Motive has.
  const auto transmit = static_cast<int64_t>(std::min<uint64_t>(f.transmit_ticks, INT64_MAX));
  const int64_t transmit_host_us = motive_clock_->Observe(transmit, receive_us);
  // Mid-exposure is the sample time (the photons' average age, §5.3); 0 when Motive does not
  // know it (USB cameras, playback): the camera data's arrival, else the transmit time.
  const uint64_t sample_ticks = f.mid_exposure_ticks != 0    ? f.mid_exposure_ticks
                                : f.data_received_ticks != 0 ? f.data_received_ticks
                                                             : f.transmit_ticks;
  const auto sample_us = static_cast<double>(
      motive_clock_->Map(static_cast<int64_t>(std::min<uint64_t>(sample_ticks, INT64_MAX))));
  stats_.Counter("system_latency_us") = std::llround(transmit_us - us(sample_ticks));
  stats_.Counter("transit_us") = receive_us - transmit_host_us;
  const double age = static_cast<double>(receive_us) - sample_us;
  if (!(age > -kMaxFutureUs && age < kMaxLatencyUs)) {
    ++stats_.Counter("clock_fallbacks");
    return receive_us;
  }
  return std::llround(sample_us);
}

void NatNetBridge::HandleFrame(const natnet::Packet& p, int64_t receive_us) {
  if (link_ == Link::kDisconnected || link_ == Link::kAwaitInfo) {
    stats_.Drop("natnet frame before SERVERINFO", "the version is not known yet");
    return;
  }
  const auto params = natnet::PeekFrameParams(p.payload);
  if (params && (*params & natnet::kFrameBitstreamChanged)) {
    ++stats_.Counter("bitstream_changes");
    if (!options_.multicast) SendToServer(natnet::kRequest, natnet::EncodeString("Bitstream"));
  }
  natnet::FrameOfData f;
  try {
    f = natnet::DecodeFrame(p.payload, version_);
  } catch (const natnet::NatNetError& e) {
    ++stats_.Counter("decode_errors");
    stats_.Drop("natnet frame undecodable", e.what());
    return;
  }
  stats_.CountIn();
  ++stats_.Counter("frames");
  const bool after_silence = SecondsSince(last_frame_at_) > options_.silence_s;
  last_frame_at_ = Clock::now();
  probing_ = false;
  if (server_up_not_streaming_) stats_.log().info("Motive streams again");
  server_up_not_streaming_ = false;
  got_frame_ = true;

  const std::string where = "frame " + std::to_string(f.frame_number);
  const std::optional<int32_t> newest = sequence_.last();
  const auto verdict = sequence_.Accept(
      {f.frame_number, f.timestamp_s, f.transmit_ticks, natnet::FrameSequence::Digest(p.payload)},
      after_silence);
  stats_.Counter("frame_gaps") = sequence_.gaps();
  stats_.Counter("frames_lost") = sequence_.lost();
  stats_.Counter("frames_paused") = sequence_.paused();
  stats_.Counter("reordered") = sequence_.late();
  stats_.Counter("duplicates") = sequence_.duplicates();
  stats_.Counter("frame_restarts") = sequence_.restarts();
  switch (verdict) {
    case natnet::FrameSequence::Verdict::kDuplicate:
      stats_.Drop("natnet duplicate frame", where + " again");
      return;
    case natnet::FrameSequence::Verdict::kLate:
      // Published frames stay in order (§6): a late one is dropped, and is not lost.
      stats_.Drop("natnet late frame", where + " after frame " + std::to_string(*newest));
      if (f.model_list_changed() && !descriptions_pending_) RequestDescriptions();
      return;
    case natnet::FrameSequence::Verdict::kRestart:
      // Motive restarted (or a take was rewound): its clock and maybe its ids changed.
      stats_.log().info("Motive restarted: {} after frame {}", where, newest.value_or(0));
      ++stats_.Counter("clock_resyncs");
      motive_clock_.reset();
      if (!descriptions_pending_) RequestDescriptions();
      break;
    case natnet::FrameSequence::Verdict::kNext:
      break;
  }

  if (f.model_list_changed()) {
    ++stats_.Counter("model_changes");
    stats_.log().info("Motive's model list changed ({}): re-reading descriptions", where);
    if (!descriptions_pending_) RequestDescriptions();
  }
  // Bit 2 means edit mode from 4.0 on only (§4.4); a 3.x stream cannot say.
  if (version_.AtLeast(4, 0) && f.edit_mode()) {
    ++stats_.Counter("edit_mode_frames");
    if (!edit_mode_) stats_.log().warn("Motive is in edit mode: its frames are not live");
    edit_mode_ = true;
    stats_.Drop("natnet edit-mode frame", where + ": playback, not live data");
    return;
  }
  edit_mode_ = false;
  if (descriptions_pending_ || !body_id_) {
    stats_.Drop("natnet frame while descriptions are unknown",
                where + ": body ids are mapped by name from NAT_MODELDEF first");
    return;
  }
  const auto body = std::find_if(f.rigid_bodies.begin(), f.rigid_bodies.end(),
                                 [&](const natnet::RigidBodyData& b) { return b.id == *body_id_; });
  if (body == f.rigid_bodies.end()) {
    ++stats_.Counter("body_missing");
    stats_.Drop("natnet body not in frame", where + ": no rigid body with id " +
                                                std::to_string(*body_id_) + " ('" +
                                                options_.body_name + "')");
    if (!descriptions_pending_ && !retry_descriptions_at_) RequestDescriptions();
    return;
  }
  const bool tracked = body->tracked();
  if (tracked) {
    const auto& q = body->orientation;
    const double norm = std::sqrt(double(q[0]) * q[0] + double(q[1]) * q[1] + double(q[2]) * q[2] +
                                  double(q[3]) * q[3]);
    if (!Finite(body->position) || !std::isfinite(norm) ||
        std::abs(norm - 1.0) > kMaxQuaternionNormError || !std::isfinite(body->mean_error) ||
        body->mean_error < 0) {
      ++stats_.Counter("decode_errors");
      stats_.Drop("natnet pose not a rigid motion",
                  where + ": non-finite values or a quaternion of norm " + std::to_string(norm));
      return;
    }
  }

  mocap_body_t msg;
  msg.utime = receive_us;
  msg.sample_utime = SampleUtime(f, receive_us);
  msg.frame_number = f.frame_number;
  msg.device_utime = std::llround(f.timestamp_s * 1e6);
  msg.body = options_.body_name;
  msg.tracked = tracked;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  if (tracked) {
    const Pose3 X_GC = frames_.Chassis(body->position, body->orientation);
    SetBodyPose(&X_GC, body->mean_error, &msg);
  } else {
    // An untracked body's pose is Motive's last one (§4.2): never published as a value.
    SetBodyPose(nullptr, nan, &msg);
    ++stats_.Counter("untracked");
  }
  msg.num_markers = static_cast<int32_t>(marker_ids_.size());
  msg.marker_m.assign(marker_ids_.size(), std::vector<double>(3, nan));
  msg.marker_tracked.assign(marker_ids_.size(), false);
  for (const natnet::LabeledMarker& m : f.labeled_markers) {
    const auto it = std::find(marker_ids_.begin(), marker_ids_.end(), m.id);
    if (it == marker_ids_.end() || m.occluded() || !Finite(m.position)) continue;
    const size_t i = static_cast<size_t>(it - marker_ids_.begin());
    const Vec3 p = frames_.Point(m.position);
    msg.marker_tracked[i] = true;
    for (int a = 0; a < 3; ++a) msg.marker_m[i][a] = p(a);
  }
  publish_(msg);
  ++stats_.Counter("published");
}

}  // namespace ftcal
