// The OptiTrack Motive NatNet client behind ftcal-natnet-bridge: the handshake of
// docs/natnet-protocol.md §2 (NAT_CONNECT -> NAT_SERVERINFO, NAT_REQUEST_MODELDEF ->
// NAT_MODELDEF), frames over multicast (a data socket joined to the group) or unicast (frames on
// the command socket, a keep-alive every keepalive_s), and each frame turned into the same
// mocap_body_t that ftcal-mocap-bridge publishes for QTM (docs/writing-a-bridge.md).
//
// Testable without LCM: the caller passes a publish callback and a clock; the class never
// blocks longer than the wait it is given. Counters (ServiceStats, in the heartbeat): frames,
// published, untracked, frame_gaps, frames_lost, frames_paused (numbers skipped while Motive sent
// nothing), reordered (late frames, dropped), frame_restarts, duplicates, decode_errors,
// edit_mode_frames, model_changes, description_reads, bitstream_changes, body_missing,
// connects, probes, server_lost, not_streaming, keepalives, timeouts, foreign_packets,
// unknown_messages, clock_fallbacks, and the latest timing in microseconds: system_latency_us
// (Motive's mid-exposure to transmit), transit_us (transmit to receipt, after the clock offset),
// clock_resyncs.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/device.h"
#include "common/service_stats.h"
#include "frame_sequence.h"
#include "ftcal/device_clock.h"
#include "ftcal/geometry.h"
#include "ftcal/mocap_body_t.hpp"
#include "natnet_protocol.h"
#include "proto/config.pb.h"

namespace ftcal {

// A configuration the bridge cannot serve, or a server it must not read (NatNet < 3.0).
class NatNetConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A socket the bridge cannot open, bind or join to its group: the host's network, not the
// config's values (exit 4, docs/exit-codes.md).
class NatNetSocketError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Motive's frames and units -> ftcal's, in one place (docs/natnet-protocol.md §5).
//
// G is ftcal's mocap global frame: right-handed, z up (as QTM's). Motive streams Y-up by
// default: p_G = Rx(+90°) p_Y, i.e. (x, y, z)_G = (x, -z, y)_Y; with Motive's Z-up setting the
// axes already agree. The rigid body's quaternion (x, y, z, w, Hamilton) is R_YP: the pivot
// frame P into Motive's world, so R_GP = Rx(+90°) R_YP (the body frame itself is unchanged).
// The chassis frame C sits in P at X_PC (configured): R_GC = R_GP R_PC, p_GoCo = p_GoPo +
// R_GP p_PoCo. Positions are metres on the wire and stay metres.
class MotiveFrames {
 public:
  enum class UpAxis { kY, kZ };
  MotiveFrames(UpAxis up, const Pose3& X_PC);
  // Throws NatNetConfigError for an up_axis other than "Y"/"Z".
  static MotiveFrames FromConfig(const config::NatNet& n);

  Vec3 Point(const natnet::Vec3f& p_motive) const;   // a position in G
  Mat3 Rotation(const natnet::Quatf& q_xyzw) const;  // R_GP (quaternion normalised)
  // The chassis pose from the rigid body's pose: R_GC and p_GoCo_G.
  Pose3 Chassis(const natnet::Vec3f& p, const natnet::Quatf& q_xyzw) const;
  const Mat3& R_GM() const { return R_GM_; }  // Motive's world axes into G

 private:
  Mat3 R_GM_;
  Pose3 X_PC_;
};

struct NatNetBridgeOptions {
  std::string address;
  uint16_t command_port = natnet::kCommandPort;
  uint16_t data_port = natnet::kDataPort;
  bool multicast = true;
  std::string multicast_group = natnet::kMulticastGroup;
  std::string local_interface = "0.0.0.0";
  std::optional<natnet::Version> bitstream;  // unicast: asked for in NAT_CONNECT
  std::string body_name = "chassis";
  MotiveFrames::UpAxis up_axis = MotiveFrames::UpAxis::kY;
  Pose3 X_PC;  // chassis in the pivot frame
  double keepalive_s = 1.0;
  double reply_timeout_s = 1.0;  // SERVERINFO and MODELDEF answers
  double silence_s = 0.5;        // no frame this long: DEGRADED, and probe the server
  // An unanswered NAT_CONNECT is sent again this often: a restarted Motive streams to a unicast
  // client only once it connects again, so the client must not wait out a reply timeout.
  double connect_repeat_s = 0.05;
};

// From the config's mocap section (body_name, natnet). Throws NatNetConfigError naming the field.
NatNetBridgeOptions NatNetBridgeOptionsFromConfig(const config::Mocap& mocap);

class NatNetBridge : public Device {
 public:
  using PublishFn = std::function<void(const mocap_body_t&)>;
  using ClockFn = std::function<int64_t()>;  // host time, us since the epoch

  enum class Link { kDisconnected, kAwaitInfo, kAwaitDescriptions, kStreaming };

  NatNetBridge(NatNetBridgeOptions options, ServiceStats& stats, PublishFn publish,
               ClockFn now_utime);
  ~NatNetBridge() override;
  NatNetBridge(const NatNetBridge&) = delete;
  NatNetBridge& operator=(const NatNetBridge&) = delete;

  // Opens the command socket and, in multicast, the data socket joined to the group; before
  // any other call. Throws NatNetSocketError when the host refuses one of them.
  void Open();

  // The Device a ServiceApp's loop waits on (Device::Step is one turn by hand): the command
  // socket and, in multicast, the data socket; the deadline is the timers'; degraded while not
  // healthy(). Throws NatNetConfigError for a server older than NatNet 3.0.
  void AddPollFds(std::vector<pollfd>* fds) override;
  void OnPolled(const pollfd* fds, std::size_t n) override;
  Clock::time_point NextDeadline() const override;
  void OnDeadline(Clock::time_point now) override;
  bool Degraded(std::string* why) override;

  // The parts of a turn: the sockets, then OnReadable(fd) for each readable one and OnTimer().
  std::vector<int> fds() const;
  void OnReadable(int fd);
  void OnTimer();
  int TimerDueMs() const;

  Link link() const { return link_; }
  bool healthy() const { return health_reason().empty(); }
  std::string health_reason() const;
  static std::string LinkName(Link link);
  natnet::Version version() const { return version_; }
  // Motive's clock mapped onto the host's (null before the first frame of this session).
  const DeviceClock* motive_clock() const { return motive_clock_.get(); }

  // Handles one datagram as if it had arrived from `from_server` (tests, benchmarks).
  void HandleDatagram(const uint8_t* data, size_t size, bool from_server);

 private:
  void CloseSockets();
  void SendToServer(uint16_t id, const std::vector<uint8_t>& payload);
  void SendConnect();
  void StartProbe();
  void RequestDescriptions();
  void Drain(int fd);
  void HandleServerInfo(const natnet::Packet& p);
  void HandleDescriptions(const natnet::Packet& p);
  void HandleResponse(const natnet::Packet& p);
  void HandleFrame(const natnet::Packet& p, int64_t receive_us);
  void ServerLost(const std::string& why);
  void ResetSession();
  int64_t SampleUtime(const natnet::FrameOfData& f, int64_t receive_us);
  double SecondsSince(Clock::time_point t) const;
  Clock::time_point After(double s) const;

  NatNetBridgeOptions options_;
  MotiveFrames frames_;
  ServiceStats& stats_;
  PublishFn publish_;
  ClockFn now_utime_;

  int command_fd_ = -1;
  Clock::time_point last_timer_;  // OnTimer's last run
  int data_fd_ = -1;
  uint32_t server_ip_ = 0;  // network order
  Link link_ = Link::kDisconnected;
  Clock::time_point next_connect_;
  Clock::time_point connect_since_;    // the first NAT_CONNECT of the unanswered ones
  Clock::time_point connect_sent_at_;  // the latest NAT_CONNECT
  Clock::time_point modeldef_sent_at_;
  Clock::time_point next_keepalive_;
  Clock::time_point last_frame_at_;
  bool probing_ = false;  // silent: a CONNECT is out to see whether Motive is up
  bool server_up_not_streaming_ = false;
  bool descriptions_pending_ = false;
  bool got_frame_ = false;
  bool edit_mode_ = false;

  natnet::ServerInfo server_;
  natnet::Version version_{0, 0};
  std::optional<int32_t> body_id_;
  std::vector<int32_t> marker_ids_;  // labeled-marker ids of the body's members
  std::string descriptions_problem_;
  std::optional<Clock::time_point> retry_descriptions_at_;

  natnet::FrameSequence sequence_;
  // Motive's high-resolution clock mapped onto the host's by the lower envelope of (transmit
  // ticks, receipt) (§5.3; docs/method.md, "Clocks and delays"): its offset plus the smallest
  // transit, and its rate, without echoes. Made afresh with each SERVERINFO (its frequency).
  std::unique_ptr<DeviceClock> motive_clock_;
  std::vector<uint8_t> buffer_;
};

}  // namespace ftcal
