#include "mocap_bridge.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <limits>

#include "common/messages.h"
#include "ftcal/geometry.h"

namespace ftcal {
namespace {

constexpr char kStreamCommand[] = "StreamFrames AllFrames 6DRes 3D";
constexpr char kParametersCommand[] = "GetParameters General 3D 6D";
constexpr double kParametersRetryS = 1.0;
// A decoded rotation farther than this from SO(3) is not a pose QTM computed: f32 rounding of
// a rotation leaves ~1e-7.
constexpr double kMaxOrthonormalityError = 1e-3;

// "1.N" with N >= 21, else nullopt.
std::optional<int> MinorVersion(const std::string& v) {
  if (v.size() < 3 || v.compare(0, 2, "1.") != 0) return std::nullopt;
  const std::string minor = v.substr(2);
  if (minor.empty() || minor.size() > 3 ||
      !std::all_of(minor.begin(), minor.end(), [](unsigned char c) { return std::isdigit(c); })) {
    return std::nullopt;
  }
  return std::stoi(minor);
}

bool AllFinite(const Eigen::Vector3d& v) { return v.allFinite(); }

}  // namespace

MocapBridgeOptions MocapBridgeOptionsFromConfig(const config::Mocap& mocap) {
  MocapBridgeOptions o;
  o.address = mocap.server_address();
  if (o.address.empty()) throw MocapConfigError("config mocap.server_address is empty");
  if (mocap.port() == 0 || mocap.port() > 65535) {
    throw MocapConfigError("config mocap.port " + std::to_string(mocap.port()) +
                           " is not a TCP port");
  }
  o.port = static_cast<uint16_t>(mocap.port());
  o.protocol_version = mocap.protocol_version();
  const auto minor = MinorVersion(o.protocol_version);
  if (!minor || *minor < 21) {
    throw MocapConfigError("config mocap.protocol_version '" + o.protocol_version +
                           "': the bridge needs QTM RT protocol 1.21 or later (1.N), whose 6D "
                           "parameters it can read");
  }
  o.body_name = mocap.body_name();
  if (o.body_name.empty()) throw MocapConfigError("config mocap.body_name is empty");
  return o;
}

MocapBridge::MocapBridge(MocapBridgeOptions options, ServiceStats& stats, PublishFn publish,
                         ClockFn now_utime)
    : options_(std::move(options)),
      stats_(stats),
      publish_(std::move(publish)),
      now_utime_(std::move(now_utime)),
      next_connect_(Clock::now()),
      backoff_s_(options_.backoff_min_s) {
  for (const char* name :
       {"frames", "published", "untracked", "frame_gaps", "frames_lost", "frame_restarts",
        "duplicates", "decode_errors", "stream_errors", "no_more_data", "events", "parameter_reads",
        "connects", "disconnects", "timeouts"}) {
    stats_.Counter(name);  // present in the heartbeat from the start, at zero
  }
  read_buffer_.resize(64 * 1024);
}

MocapBridge::~MocapBridge() {
  if (fd_ >= 0) ::close(fd_);
}

std::string MocapBridge::LinkName(Link link) {
  switch (link) {
    case Link::kDisconnected:
      return "disconnected";
    case Link::kConnecting:
      return "connecting";
    case Link::kWelcome:
      return "awaiting welcome";
    case Link::kVersion:
      return "awaiting version";
    case Link::kParameters:
      return "awaiting parameters";
    case Link::kStreaming:
      return "streaming";
  }
  return "?";
}

double MocapBridge::SecondsSince(Clock::time_point t) const {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

short MocapBridge::poll_events() const {
  if (fd_ < 0) return 0;
  return link_ == Link::kConnecting ? POLLOUT : POLLIN;
}

int MocapBridge::TimerDueMs() const {
  if (link_ == Link::kDisconnected) {
    const auto ms =
        std::chrono::duration_cast<std::chrono::milliseconds>(next_connect_ - Clock::now()).count();
    return static_cast<int>(std::clamp<int64_t>(ms + 1, 0, 100));
  }
  return 20;  // timeouts and silence are judged on this grain
}

bool MocapBridge::healthy() const { return health_reason().empty(); }

std::string MocapBridge::health_reason() const {
  if (!parameters_problem_.empty()) return parameters_problem_;
  if (link_ != Link::kStreaming) return "QTM link " + LinkName(link_);
  if (shutting_down_) return "QTM is shutting down";
  if (no_more_data_) return "No More Data: QTM is not capturing";
  if (silent_)
    return "no frame from QTM for more than " + std::to_string(options_.silence_degraded_s) + " s";
  if (!got_frame_) return "no frame yet";
  return "";
}

void MocapBridge::AddPollFds(std::vector<pollfd>* fds) {
  polled_fd_ = fd_ >= 0;
  if (polled_fd_) fds->push_back({fd_, poll_events(), 0});
}

void MocapBridge::OnPolled(const pollfd* fds, std::size_t n) {
  if (polled_fd_ && n == 1 && fds[0].revents != 0) OnReady(fds[0].revents);
}

// Early rather than late: TimerDueMs() counts from now while disconnected.
Device::Clock::time_point MocapBridge::NextDeadline() const {
  return last_timer_ + std::chrono::milliseconds(TimerDueMs());
}

void MocapBridge::OnDeadline(Clock::time_point now) {
  OnTimer();
  last_timer_ = now;
}

bool MocapBridge::Degraded(std::string* why) { return DegradedBecause(health_reason(), why); }

void MocapBridge::StartConnect() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    stats_.Error("qtm socket", std::strerror(errno));
    next_connect_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                       std::chrono::duration<double>(options_.backoff_max_s));
    return;
  }
  // QTM's frames are small and latency matters more than packet count (§3.3).
  const int one = 1;
  ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
  // A QTM that is not capturing is quiet for as long as it likes: a dead peer is found by
  // keepalive probes (about 5 s), not by silence.
  const int idle_s = 2, interval_s = 1, probes = 3;
  ::setsockopt(fd, SOL_SOCKET, SO_KEEPALIVE, &one, sizeof one);
  ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPIDLE, &idle_s, sizeof idle_s);
  ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPINTVL, &interval_s, sizeof interval_s);
  ::setsockopt(fd, IPPROTO_TCP, TCP_KEEPCNT, &probes, sizeof probes);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(options_.port);
  if (::inet_pton(AF_INET, options_.address.c_str(), &addr.sin_addr) != 1) {
    ::close(fd);
    throw MocapConfigError("config mocap.server_address '" + options_.address +
                           "' is not an IPv4 address");
  }
  fd_ = fd;
  deframer_.Reset();
  link_since_ = Clock::now();
  last_packet_ = link_since_;
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) == 0) {
    FinishConnect();
  } else if (errno == EINPROGRESS) {
    link_ = Link::kConnecting;
  } else {
    Disconnect(std::string("connect: ") + std::strerror(errno), true);
  }
}

void MocapBridge::FinishConnect() {
  int err = 0;
  socklen_t len = sizeof err;
  ::getsockopt(fd_, SOL_SOCKET, SO_ERROR, &err, &len);
  if (err != 0) {
    Disconnect(std::string("connect: ") + std::strerror(err), true);
    return;
  }
  ++stats_.Counter("connects");
  stats_.log().info("connected to QTM at {}:{}", options_.address, options_.port);
  Expect(Link::kWelcome);
}

void MocapBridge::Expect(Link next) {
  link_ = next;
  link_since_ = Clock::now();
}

void MocapBridge::Disconnect(const std::string& why, bool count_as_failure) {
  const bool was_connected = link_ != Link::kConnecting && link_ != Link::kDisconnected;
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
  deframer_.Reset();
  if (was_connected) {
    ++stats_.Counter("disconnects");
    if (shutting_down_) {
      stats_.log().info("QTM closed the connection after announcing its shutdown");
    } else if (count_as_failure) {
      stats_.Error("qtm connection lost", why);
    }
  } else if (count_as_failure) {
    stats_.Error("qtm connect failed",
                 options_.address + ":" + std::to_string(options_.port) + ": " + why);
  }
  link_ = Link::kDisconnected;
  have_parameters_ = false;
  parameters_pending_ = false;
  retry_parameters_at_.reset();
  streaming_requested_ = false;
  got_frame_ = false;
  no_more_data_ = false;
  silent_ = false;
  shutting_down_ = false;
  parameters_problem_.clear();
  next_connect_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                     std::chrono::duration<double>(backoff_s_));
  backoff_s_ = std::min(options_.backoff_max_s, backoff_s_ * 2);
}

void MocapBridge::SendCommand(const std::string& text) {
  const std::vector<uint8_t> bytes = qtm::EncodeCommand(text);
  size_t at = 0;
  // Commands are tens of bytes into an idle socket: they go out whole or the link is broken.
  while (at < bytes.size()) {
    const ssize_t n = ::send(fd_, bytes.data() + at, bytes.size() - at, MSG_NOSIGNAL);
    if (n > 0) {
      at += static_cast<size_t>(n);
    } else if (n < 0 && errno == EINTR) {
      continue;
    } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
      pollfd p{fd_, POLLOUT, 0};
      if (::poll(&p, 1, 100) <= 0) {
        Disconnect("command '" + text + "' could not be sent", true);
        return;
      }
    } else {
      Disconnect("sending '" + text + "': " + std::strerror(errno), true);
      return;
    }
  }
}

void MocapBridge::RequestParameters() {
  ++stats_.Counter("parameter_reads");
  parameters_pending_ = true;
  parameters_requested_at_ = Clock::now();
  retry_parameters_at_.reset();
  SendCommand(kParametersCommand);
}

void MocapBridge::OnTimer() {
  const auto now = Clock::now();
  switch (link_) {
    case Link::kDisconnected:
      if (now >= next_connect_) StartConnect();
      return;
    case Link::kConnecting:
    case Link::kWelcome:
    case Link::kVersion:
      if (SecondsSince(link_since_) > options_.reply_timeout_s) {
        ++stats_.Counter("timeouts");
        Disconnect("no answer while " + LinkName(link_), true);
      }
      return;
    case Link::kParameters:
    case Link::kStreaming:
      break;
  }
  if (parameters_pending_ && SecondsSince(parameters_requested_at_) > options_.reply_timeout_s) {
    ++stats_.Counter("timeouts");
    Disconnect("no answer to GetParameters", true);
    return;
  }
  if (retry_parameters_at_ && now >= *retry_parameters_at_) {
    RequestParameters();
    if (fd_ < 0) return;
  }
  if (link_ == Link::kStreaming) {
    const double quiet_s = SecondsSince(last_packet_);
    // Not capturing, QTM sends nothing until the next measurement, whose start it announces
    // (§3.10): the connection is kept; only a lost connection (recv 0 or an error, which TCP
    // keepalive also raises for a peer gone dead) reconnects.
    if (quiet_s > options_.silence_reconnect_s && !no_more_data_) {
      ++stats_.Counter("timeouts");
      Disconnect("no packet from QTM for " + std::to_string(quiet_s) + " s", true);
    } else if (quiet_s > options_.silence_degraded_s && !silent_ && !no_more_data_) {
      silent_ = true;
      ++stats_.Counter("timeouts");
      stats_.log().warn("QTM silent for {:.2f} s", quiet_s);
    }
  }
}

void MocapBridge::OnReady(short revents) {
  if (fd_ < 0) return;
  if (link_ == Link::kConnecting) {
    if (revents & (POLLOUT | POLLERR | POLLHUP)) FinishConnect();
    return;
  }
  if (!(revents & (POLLIN | POLLHUP | POLLERR))) return;
  bool closed = false;
  std::string close_reason;
  for (;;) {
    const ssize_t n = ::recv(fd_, read_buffer_.data(), read_buffer_.size(), 0);
    if (n > 0) {
      deframer_.Feed(read_buffer_.data(), static_cast<size_t>(n));
      if (static_cast<size_t>(n) < read_buffer_.size()) break;
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) break;
    closed = true;
    close_reason =
        n == 0 ? "QTM closed the connection" : std::string("recv: ") + std::strerror(errno);
    break;
  }
  // What arrived before a close still counts (QTM announces its shutdown, then closes).
  try {
    while (fd_ >= 0) {
      std::optional<qtm::Packet> packet = deframer_.Next();
      if (!packet) break;
      last_packet_ = Clock::now();
      silent_ = false;
      HandlePacket(*packet);
    }
  } catch (const qtm::QtmError& e) {
    ++stats_.Counter("stream_errors");
    Disconnect(e.what(), true);
    return;
  }
  if (closed && fd_ >= 0) Disconnect(close_reason, true);
}

void MocapBridge::HandlePacket(const qtm::Packet& packet) {
  switch (static_cast<qtm::PacketType>(packet.type)) {
    case qtm::PacketType::kError:
    case qtm::PacketType::kCommand:
      return HandleText(packet);
    case qtm::PacketType::kXml:
      if (!parameters_pending_) {
        stats_.Drop("unrequested QTM XML", "an XML packet arrived with no GetParameters out");
        return;
      }
      return HandleParameters(qtm::DecodeText(packet));
    case qtm::PacketType::kData:
      return HandleData(packet);
    case qtm::PacketType::kNoMoreData:
      ++stats_.Counter("no_more_data");
      if (!no_more_data_) stats_.log().warn("QTM: No More Data (not capturing)");
      no_more_data_ = true;
      return;
    case qtm::PacketType::kEvent:
      try {
        return HandleEvent(qtm::DecodeEvent(packet));
      } catch (const qtm::QtmError& e) {
        stats_.Drop("malformed QTM event", e.what());
        return;
      }
    default:
      stats_.Drop("unexpected QTM packet type " + std::to_string(packet.type),
                  std::to_string(packet.payload.size()) + " payload bytes skipped");
  }
}

void MocapBridge::HandleText(const qtm::Packet& packet) {
  const std::string text = qtm::DecodeText(packet);
  const bool error = packet.is(qtm::PacketType::kError);
  switch (link_) {
    case Link::kWelcome:
      if (!error && qtm::IsWelcome(text)) {
        Expect(Link::kVersion);
        SendCommand("Version " + options_.protocol_version);
      } else {
        Disconnect("QTM refused the connection: '" + text + "'", true);
      }
      return;
    case Link::kVersion:
      if (!error && qtm::IsVersionAccepted(text, options_.protocol_version)) {
        stats_.log().info("QTM RT protocol {} accepted", options_.protocol_version);
        Expect(Link::kParameters);
        RequestParameters();
        return;
      }
      // No fallback to another version: a different layout would be misread (§3.9).
      throw MocapConfigError("QTM at " + options_.address + ":" + std::to_string(options_.port) +
                             " refused protocol version " + options_.protocol_version + ": '" +
                             text + "' (config mocap.protocol_version)");
    default:
      break;
  }
  if (error && parameters_pending_ && text.find("Parameters not available") != std::string::npos) {
    parameters_pending_ = false;
    parameters_problem_ = "QTM has no parameters to send";
    retry_parameters_at_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>(kParametersRetryS));
    stats_.Error("qtm parameters not available", text);
    return;
  }
  if (error) {
    stats_.Error("qtm error reply", text);
  } else {
    stats_.Drop("unexpected QTM command reply", text);
  }
}

void MocapBridge::HandleParameters(const std::string& xml) {
  parameters_pending_ = false;
  qtm::Parameters params;
  try {
    params = qtm::ParseParameters(xml);
  } catch (const qtm::QtmError& e) {
    parameters_problem_ = std::string("unreadable parameters: ") + e.what();
    stats_.Error("qtm parameters unreadable", e.what());
    retry_parameters_at_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>(kParametersRetryS));
    return;
  }
  const auto it = std::find(params.body_names.begin(), params.body_names.end(), options_.body_name);
  if (it == params.body_names.end()) {
    std::string names;
    for (const auto& n : params.body_names) names += (names.empty() ? "" : ", ") + n;
    parameters_problem_ = "body '" + options_.body_name + "' (config mocap.body_name) is not " +
                          "among QTM's 6D bodies [" + names + "]";
    stats_.Error("qtm body missing", parameters_problem_);
    retry_parameters_at_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>(kParametersRetryS));
    return;
  }
  parameters_problem_.clear();
  body_index_ = static_cast<int>(it - params.body_names.begin());
  num_bodies_ = static_cast<int>(params.body_names.size());
  labels_ = params.labels_3d;
  have_parameters_ = true;
  stats_.log().info("QTM parameters: body '{}' is {} of {}, {} labelled markers",
                    options_.body_name, body_index_ + 1, num_bodies_, labels_.size());
  if (!streaming_requested_) {
    streaming_requested_ = true;
    Expect(Link::kStreaming);
    last_packet_ = Clock::now();
    SendCommand(kStreamCommand);
  }
}

void MocapBridge::HandleEvent(uint8_t event) {
  ++stats_.Counter("events");
  if (event == qtm::kEventCameraSettingsChanged) {
    // The bodies or labels may have changed order: no frame is mapped until they are re-read.
    stats_.log().info("QTM event {}: re-reading parameters", qtm::EventName(event));
    if (link_ == Link::kStreaming && !parameters_pending_) RequestParameters();
  } else if (event == qtm::kEventCaptureStarted || event == qtm::kEventRtFromFileStarted) {
    // A new measurement: its bodies may differ from the last one's (§3.10).
    stats_.log().info("QTM event {}: a new measurement; re-reading parameters",
                      qtm::EventName(event));
    if (link_ == Link::kStreaming && !parameters_pending_) RequestParameters();
  } else if (event == qtm::kEventQtmShuttingDown) {
    stats_.log().warn("QTM event {}: expecting a disconnect", qtm::EventName(event));
    shutting_down_ = true;
  } else {
    stats_.log().debug("QTM event {}", qtm::EventName(event));
  }
}

void MocapBridge::HandleData(const qtm::Packet& packet) {
  // Decoded first so that a damaged packet is counted as such whenever it arrives.
  qtm::DataFrame frame;
  try {
    frame = qtm::DecodeData(packet);
  } catch (const qtm::QtmError& e) {
    ++stats_.Counter("decode_errors");
    stats_.Drop("undecodable QTM data packet", e.what());
    return;
  }
  if (link_ != Link::kStreaming || !have_parameters_ || parameters_pending_) {
    stats_.Drop("QTM frame while parameters are unknown",
                "dropped: the body order is not known until GetParameters is answered");
    return;
  }
  stats_.CountIn();
  ++stats_.Counter("frames");
  no_more_data_ = false;
  if (!got_frame_) backoff_s_ = options_.backoff_min_s;  // the link works: next loss retries fast
  got_frame_ = true;

  if (last_frame_) {
    const int64_t step = int64_t{frame.frame_number} - *last_frame_;
    if (step == 0) {
      ++stats_.Counter("duplicates");
      stats_.Drop("duplicate QTM frame", "frame " + std::to_string(frame.frame_number) + " again");
      return;
    }
    if (step < 0) {
      ++stats_.Counter("frame_restarts");  // frame numbers restart with each measurement
    } else if (step > 1) {
      ++stats_.Counter("frame_gaps");
      stats_.Counter("frames_lost") += step - 1;
    }
  }
  last_frame_ = frame.frame_number;

  const std::string where = "frame " + std::to_string(frame.frame_number);
  if (!frame.has_bodies || static_cast<int>(frame.bodies.size()) != num_bodies_) {
    stats_.Drop("QTM 6D bodies differ from the parameters",
                where + ": " + (frame.has_bodies ? std::to_string(frame.bodies.size()) : "no") +
                    " bodies, parameters list " + std::to_string(num_bodies_));
    if (!parameters_pending_) RequestParameters();
    return;
  }
  if (frame.has_markers && frame.markers.size() != labels_.size()) {
    stats_.Drop("QTM 3D markers differ from the labels",
                where + ": " + std::to_string(frame.markers.size()) + " markers, " +
                    std::to_string(labels_.size()) + " labels");
    if (!parameters_pending_) RequestParameters();
    return;
  }

  const qtm::Body& body = frame.bodies[static_cast<size_t>(body_index_)];
  const bool tracked = body.tracked();
  if (tracked) {
    // Not NaN yet not a pose: the bytes are damaged; never publish them as a value.
    if (!AllFinite(body.p_GoBo_G_mm) || !body.R_GB.allFinite() ||
        OrthonormalityError(body.R_GB) > kMaxOrthonormalityError ||
        !(std::isnan(body.residual_mm) ||
          (std::isfinite(body.residual_mm) && body.residual_mm >= 0))) {
      ++stats_.Counter("decode_errors");
      stats_.Drop("QTM pose not a rigid motion",
                  where + ": non-finite values or a rotation " + "off SO(3) by " +
                      std::to_string(OrthonormalityError(body.R_GB)));
      return;
    }
  }
  for (const qtm::Marker& m : frame.markers) {
    if (m.tracked() && !AllFinite(m.p_GoM_G_mm)) {
      ++stats_.Counter("decode_errors");
      stats_.Drop("QTM marker not finite", where + ": a marker position is infinite");
      return;
    }
  }

  mocap_body_t msg;
  msg.utime = now_utime_();
  msg.frame_number = frame.frame_number;
  msg.device_utime = frame.timestamp_us;
  msg.sample_utime = frame_clock_.Observe(frame.timestamp_us, msg.utime);
  msg.body = options_.body_name;
  msg.tracked = tracked;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  if (tracked) {
    const Pose3 X_GC(body.R_GB, body.p_GoBo_G_mm / 1000.0);
    SetBodyPose(&X_GC, body.residual_mm / 1000.0, &msg);  // a NaN residual stays NaN
  } else {
    SetBodyPose(nullptr, nan, &msg);
    ++stats_.Counter("untracked");
  }
  msg.num_markers = static_cast<int32_t>(frame.markers.size());
  msg.marker_m.assign(frame.markers.size(), std::vector<double>(3, nan));
  msg.marker_tracked.resize(frame.markers.size());
  for (size_t i = 0; i < frame.markers.size(); ++i) {
    const bool seen = frame.markers[i].tracked();
    msg.marker_tracked[i] = seen;
    for (int a = 0; a < 3; ++a) {
      msg.marker_m[i][a] = seen ? frame.markers[i].p_GoM_G_mm(a) / 1000.0 : nan;
    }
  }
  publish_(msg);
  ++stats_.Counter("published");
}

}  // namespace ftcal
