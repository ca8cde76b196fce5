// The twin's OptiTrack Motive server: NatNet 3.1 or 4.1 over UDP on this machine, so
// ftcal-natnet-bridge runs unchanged against it (docs/natnet-protocol.md §7).
//
// A command socket (default port 1510) answers NAT_CONNECT (every variant of §2.3, honouring a
// requested bitstream 3.x/4.x per client), NAT_REQUEST_MODELDEF, NAT_REQUEST (FrameRate,
// UnitsToMillimeters, Bitstream; anything else NAT_UNRECOGNIZED_REQUEST), NAT_ECHOREQUEST,
// NAT_KEEPALIVE and NAT_DISCONNECT. A data socket (default 1511) sends one frame per tick:
// to the multicast group, or to each unicast client's NAT_CONNECT endpoint (a client silent
// for client_timeout_s is forgotten). Frames and descriptions come from the shared codec
// (natnet_protocol.h). Motive's axes (Y-up by default) and its pivot frame are made from the
// source's ftcal-frame poses here, the inverse of what the bridge must do.
//
// Clock: Motive's high-resolution ticks run at clock_hz from the emulator's (re)start; the
// frame's mid-exposure lies system_latency_s before its transmit time, and the truth records
// that instant on the host clock, so a test can measure the bridge's time-stamping residual.
//
// Faults, deterministic for a seed and schedule (ticks count from the first frame): frame
// gaps, duplicated frames, reordered frames (held back and sent after the next 1..3 frames, as
// UDP may deliver them), corrupt frames (a byte after the end tag, the datagram's length
// agreeing: only a decoder that checks it consumed everything refuses it), untracked windows
// (tracked bit clear, the last pose resent), silent windows (Motive up and answering but paused:
// no frames, while its camera frame numbers run on),
// edit-mode windows, down windows (Motive gone: no answers; afterwards it restarts with frame
// numbers and ticks from zero and the body renumbered), model-list changes (bit 1 set, the two
// bodies swap order and ids), mid-exposure 0.
#pragma once

#include <netinet/in.h>

#include <Eigen/Core>

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "natnet_protocol.h"

namespace ftcal::sim {

// What the mocap sees at one tick, in ftcal's z-up global frame G, SI units.
struct NatNetPose {
  bool body_tracked = true;
  Eigen::Matrix3d R_GC = Eigen::Matrix3d::Identity();
  Eigen::Vector3d p_GoCo_G_m = Eigen::Vector3d::Zero();
  double residual_m = 0.0005;
  std::vector<Eigen::Vector3d> markers_G_m;  // in the body's member order; NaN when not seen
};
using NatNetFrameSource = std::function<std::optional<NatNetPose>(int64_t tick)>;

struct NatNetWindow {
  int64_t first_tick = 0;
  int64_t num_ticks = 0;
  bool Contains(int64_t t) const { return t >= first_tick && t < first_tick + num_ticks; }
};

struct NatNetFaults {
  uint64_t seed = 1;
  double gap_probability = 0.0;        // per tick: 1..3 frame numbers skipped
  double duplicate_probability = 0.0;  // per tick: the frame is sent twice
  double reorder_probability = 0.0;    // per tick: held back, sent after the next 1..3 frames
  double corrupt_probability = 0.0;    // per tick: a byte count off (see the header)
  bool mid_exposure_zero = false;      // USB cameras / playback: mid-exposure ticks 0
  std::vector<NatNetWindow> untracked;
  std::vector<NatNetWindow> silent;     // up, answering, no frames (paused; numbers run on)
  std::vector<NatNetWindow> edit_mode;  // frames flagged edit mode
  std::vector<NatNetWindow> down;       // gone; restarts afterwards
  std::vector<int64_t> model_changes;   // bit 1 and a reshuffle at these ticks
};

struct NatNetEmulatorOptions {
  std::string address = "127.0.0.1";
  uint16_t command_port = natnet::kCommandPort;  // 0: any free port
  uint16_t data_port = natnet::kDataPort;        // 0: any free port
  bool multicast = false;
  std::string multicast_group = natnet::kMulticastGroup;
  natnet::Version version{4, 1};  // the server's own bitstream
  double rate_hz = 100.0;
  // Motive's clock: its high-resolution ticks and frame timestamps run this fast, the
  // timestamps start this far into its run.
  double clock_rate_ppm = 0.0;
  double clock_offset_s = 0.0;
  std::string body_name = "chassis";
  int32_t body_id = 3;
  bool decoy_body = true;  // "wand" (id 1) listed first: a client must map by name
  bool z_up = false;       // Motive's Up Axis: Y (default) or Z
  // The chassis frame C in the rigid body's pivot frame P (the bridge's configured X_PC).
  Eigen::Matrix3d R_PC = Eigen::Matrix3d::Identity();
  Eigen::Vector3d p_PoCo_P_m = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector3d> body_points_C_m;  // the chassis markers in C; names m01..
  uint64_t clock_hz = 10'000'000;
  double system_latency_s = 0.002;  // mid-exposure to transmit
  double client_timeout_s = 3.0;    // unicast: forgotten without keep-alive
  NatNetFaults faults;
};

// One frame as it went out, when it went out (values narrowed to f32 as on the wire).
struct NatNetSentFrame {
  int64_t tick = 0;
  int32_t frame_number = 0;
  double timestamp_s = 0;
  int64_t exposure_utime = 0;  // mid-exposure on the host clock, us since the epoch
  bool corrupt = false;
  bool duplicated = false;  // sent twice
  bool late = false;        // sent after a frame with a higher number (reordered)
  bool tracked = true;
  bool edit_mode = false;
  Eigen::Matrix3d R_GC = Eigen::Matrix3d::Identity();  // the source's (truth)
  Eigen::Vector3d p_GoCo_G_m = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector3d> markers_G_m;
  int receivers = 0;  // unicast clients, or 1 for the multicast group
};

struct NatNetEmulatorCounters {
  int64_t ticks = 0;
  int64_t frames_sent = 0;
  int64_t frames_corrupt = 0;
  int64_t frames_untracked = 0;
  int64_t frames_duplicated = 0;
  int64_t frames_reordered = 0;  // sent after a frame with a higher number
  int64_t gaps = 0;
  int64_t frames_skipped = 0;
  int64_t connects = 0;
  int64_t keepalives = 0;
  int64_t descriptions_sent = 0;
  int64_t clients_expired = 0;
  int64_t restarts = 0;
  int64_t restart_utime = 0;  // the host clock when Motive last came back (sockets bound again)
  int64_t model_changes = 0;
  int64_t requests_unrecognized = 0;
};

class NatNetEmulator {
 public:
  using SentObserver = std::function<void(const NatNetSentFrame&)>;

  // Binds both sockets now. Throws std::runtime_error naming the address on failure and
  // std::invalid_argument for options it cannot serve.
  NatNetEmulator(NatNetEmulatorOptions options, NatNetFrameSource source);
  ~NatNetEmulator();
  NatNetEmulator(const NatNetEmulator&) = delete;
  NatNetEmulator& operator=(const NatNetEmulator&) = delete;

  uint16_t command_port() const { return command_port_; }
  uint16_t data_port() const { return data_port_; }
  void SetObserver(SentObserver observer) { observer_ = std::move(observer); }
  // Serves in real time until the source ends, `max_ticks` ticks have run (< 0: no limit),
  // RequestStop() (any thread) or `keep_going` returns false.
  void Run(int64_t max_ticks = -1, const std::function<bool()>& keep_going = {});
  void RequestStop() { stop_.store(true); }
  const NatNetEmulatorCounters& counters() const { return counters_; }
  // The descriptions as the server has them now.
  natnet::Descriptions CurrentDescriptions() const;

 private:
  struct Client {
    natnet::Version version;
    double last_heard_s = 0;
  };
  struct Datagram {
    sockaddr_in to{};
    std::vector<uint8_t> bytes;
  };
  // A frame's datagrams (every copy to every receiver), sent now or held back (reordering).
  struct Outgoing {
    int64_t release_tick = 0;
    std::vector<Datagram> datagrams;
    NatNetSentFrame frame;
  };
  void Bind();
  void Close();
  void ReadCommands();
  void HandleCommand(const natnet::Packet& p, const sockaddr_in& from);
  void Reply(const sockaddr_in& to, uint16_t id, const std::vector<uint8_t>& payload);
  void Tick();
  void Emit(Outgoing& out);
  void ReleaseHeld(int64_t tick);
  double Seconds() const;  // since (re)start
  uint64_t Ticks() const;
  natnet::Version VersionFor(const sockaddr_in& from) const;
  bool InAny(const std::vector<NatNetWindow>& w, int64_t tick) const;

  NatNetEmulatorOptions options_;
  NatNetFrameSource source_;
  SentObserver observer_;
  int command_fd_ = -1;
  int data_fd_ = -1;
  uint16_t command_port_ = 0;
  uint16_t data_port_ = 0;
  std::map<std::pair<uint32_t, uint16_t>, Client> clients_;  // unicast, by endpoint
  std::atomic<bool> stop_{false};
  bool source_ended_ = false;
  bool up_ = true;

  int64_t tick_ = 0;
  int64_t frame_base_ = 0;
  int64_t skipped_ = 0;
  double start_s_ = 0;    // steady seconds at the (re)start: tick origin
  bool swapped_ = false;  // the bodies' order and ids after model changes
  std::optional<NatNetPose> last_tracked_;
  std::vector<Outgoing> held_;   // reordered frames waiting for their release tick
  int32_t max_sent_number_ = 0;  // the highest frame number sent since the (re)start
  std::mt19937_64 rng_;
  NatNetEmulatorCounters counters_;
};

}  // namespace ftcal::sim
