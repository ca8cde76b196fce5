// The Qualisys QTM client behind ftcal-mocap-bridge: one TCP connection to the RT server's
// little-endian port, the handshake of docs/device-protocols.md §3.3-3.5 (welcome, Version,
// GetParameters General 3D 6D, StreamFrames AllFrames 6DRes 3D), and each data frame turned into
// a mocap_body_t for the configured chassis body.
//
// Testable without LCM: the caller passes a publish callback and a clock; the class never
// blocks longer than the wait it is given. Everything it counts goes to ServiceStats counters
// (published in the heartbeat): frames, published, untracked, frame_gaps, frames_lost,
// frame_restarts, duplicates, decode_errors, stream_errors, no_more_data, events,
// parameter_reads, connects, disconnects, timeouts.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "common/device.h"
#include "common/service_stats.h"
#include "ftcal/device_clock.h"
#include "ftcal/mocap_body_t.hpp"
#include "proto/config.pb.h"
#include "qtm_protocol.h"

namespace ftcal {

// A setting the server refuses (the protocol version) or the config gets wrong: the bridge
// cannot do its job with this configuration and must not fall back silently.
class MocapConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct MocapBridgeOptions {
  std::string address;
  uint16_t port = qtm::kLittleEndianPort;
  std::string protocol_version = "1.25";  // at least 1.21: the 6D XML layout the codec reads
  std::string body_name = "chassis";
  double reply_timeout_s = 2.0;      // welcome, Version and GetParameters answers
  double silence_degraded_s = 0.5;   // streaming with no packet this long: DEGRADED
  double silence_reconnect_s = 5.0;  // ... this long: reconnect
  double backoff_min_s = 0.05;
  double backoff_max_s = 1.0;
};

// From the config's mocap section. Throws MocapConfigError naming the field for an empty
// address, a port of 0 or a protocol version that is not 1.N with N >= 21.
MocapBridgeOptions MocapBridgeOptionsFromConfig(const config::Mocap& mocap);

class MocapBridge : public Device {
 public:
  using PublishFn = std::function<void(const mocap_body_t&)>;
  using ClockFn = std::function<int64_t()>;  // host time, us since the epoch

  enum class Link { kDisconnected, kConnecting, kWelcome, kVersion, kParameters, kStreaming };

  MocapBridge(MocapBridgeOptions options, ServiceStats& stats, PublishFn publish,
              ClockFn now_utime);
  ~MocapBridge() override;
  MocapBridge(const MocapBridge&) = delete;
  MocapBridge& operator=(const MocapBridge&) = delete;

  // The Device a ServiceApp's loop waits on (Device::Step is one turn by hand): the server's
  // socket (none while disconnected); the deadline is the timers' (connect when due, timeouts
  // and silence judged on a 20 ms grain); degraded while not healthy(). Throws
  // MocapConfigError when the server refuses the configured protocol version.
  void AddPollFds(std::vector<pollfd>* fds) override;
  void OnPolled(const pollfd* fds, std::size_t n) override;
  Clock::time_point NextDeadline() const override;
  void OnDeadline(Clock::time_point now) override;
  bool Degraded(std::string* why) override;

  // The parts of a turn: the socket (-1 when there is none) and the events to wait for; then
  // OnReady(revents) and OnTimer().
  int fd() const { return fd_; }
  short poll_events() const;
  void OnReady(short revents);
  void OnTimer();
  // Longest the caller may wait before OnTimer() has work to do, ms.
  int TimerDueMs() const;

  Link link() const { return link_; }
  // False while not streaming frames of the configured body: not connected, in the handshake,
  // No More Data, silent, body missing from the parameters, QTM shutting down.
  bool healthy() const;
  // Why not healthy ("" when healthy).
  std::string health_reason() const;
  static std::string LinkName(Link link);

 private:
  void StartConnect();
  void FinishConnect();
  void Disconnect(const std::string& why, bool count_as_failure);
  void SendCommand(const std::string& text);
  void Expect(Link next);
  void HandlePacket(const qtm::Packet& packet);
  void HandleText(const qtm::Packet& packet);
  void HandleParameters(const std::string& xml);
  void HandleEvent(uint8_t event);
  void HandleData(const qtm::Packet& packet);
  void RequestParameters();
  double SecondsSince(Clock::time_point t) const;

  MocapBridgeOptions options_;
  ServiceStats& stats_;
  PublishFn publish_;
  ClockFn now_utime_;
  // QTM's frame timestamp (us) mapped onto the host clock (docs/method.md, "Clocks and delays");
  // a timestamp that falls (a new measurement) starts the map afresh.
  DeviceClock frame_clock_{DeviceClockOptions{1e6}};

  int fd_ = -1;
  bool polled_fd_ = false;        // AddPollFds appended fd_
  Clock::time_point last_timer_;  // OnTimer's last run
  Link link_ = Link::kDisconnected;
  qtm::Deframer deframer_;
  Clock::time_point link_since_;   // when the current link state began
  Clock::time_point last_packet_;  // last packet of any kind from the server
  Clock::time_point next_connect_;
  double backoff_s_;
  bool reconnect_now_ = false;

  // Parameters of the current connection.
  bool have_parameters_ = false;
  bool parameters_pending_ = false;  // a GetParameters is outstanding
  Clock::time_point parameters_requested_at_;
  int num_bodies_ = 0;
  std::optional<Clock::time_point> retry_parameters_at_;
  int body_index_ = -1;
  std::vector<std::string> labels_;
  bool streaming_requested_ = false;

  // Health.
  bool no_more_data_ = false;
  bool shutting_down_ = false;
  bool silent_ = false;
  bool got_frame_ = false;  // a frame arrived on this connection
  std::string parameters_problem_;

  std::optional<int32_t> last_frame_;
  std::vector<uint8_t> read_buffer_;
};

}  // namespace ftcal
