// The session side of NatNetBridge (natnet_bridge.h): the options from the config, the sockets,
// the handshake (NAT_CONNECT, SERVERINFO, descriptions), keep-alives, probes and liveness. What a
// frame of data becomes (MotiveFrames, the sample time, MOCAP_BODY) is natnet_frames.cc.
#include "natnet_bridge.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <limits>

#include "ftcal/config.h"

namespace ftcal {
namespace {

constexpr double kDescriptionsRetryS = 1.0;
// While Motive answers but sends no frames, ask again this often whether it is still there.
constexpr double kProbeIntervalS = 1.0;
// A unicast client whose frames stop for this long connects again (a restarted Motive has
// forgotten it): ten frame periods at 200 Hz, well below silence_s.
constexpr double kUnicastRejoinS = 0.05;
constexpr char kClientName[] = "ftcal-natnet-bridge";

uint32_t Ipv4(const std::string& text, const std::string& field) {
  in_addr a{};
  if (::inet_pton(AF_INET, text.c_str(), &a) != 1) {
    throw NatNetConfigError(field + " '" + text + "' is not an IPv4 address");
  }
  return a.s_addr;
}

}  // namespace

// ---- Options ----

NatNetBridgeOptions NatNetBridgeOptionsFromConfig(const config::Mocap& mocap) {
  const config::NatNet& n = mocap.natnet();
  NatNetBridgeOptions o;
  if (mocap.system() != config::OPTITRACK) {
    throw NatNetConfigError(
        "mocap.system is not OPTITRACK: this config runs "
        "ftcal-mocap-bridge (Qualisys), not ftcal-natnet-bridge");
  }
  o.address = n.server_address();
  if (o.address.empty()) throw NatNetConfigError("mocap.natnet.server_address is empty");
  Ipv4(o.address, "mocap.natnet.server_address");
  auto port = [](uint32_t p, const std::string& field) {
    if (p == 0 || p > 65535) {
      throw NatNetConfigError(field + " " + std::to_string(p) + " is not a UDP port");
    }
    return static_cast<uint16_t>(p);
  };
  o.command_port = port(n.command_port(), "mocap.natnet.command_port");
  o.data_port = port(n.data_port(), "mocap.natnet.data_port");
  o.multicast = n.multicast();
  o.multicast_group = n.multicast_group();
  o.local_interface = n.local_interface();
  if (o.multicast) {
    const uint32_t group = ntohl(Ipv4(o.multicast_group, "mocap.natnet.multicast_group"));
    if ((group >> 28) != 0xE) {
      throw NatNetConfigError("mocap.natnet.multicast_group '" + o.multicast_group +
                              "' is not a multicast (class D) address");
    }
    Ipv4(o.local_interface, "mocap.natnet.local_interface");
  }
  if (!n.bitstream_version().empty()) {
    const auto v = natnet::ParseVersion(n.bitstream_version());
    if (!v || !natnet::Supported(*v)) {
      throw NatNetConfigError("mocap.natnet.bitstream_version '" + n.bitstream_version() +
                              "': the bridge reads NatNet 3.x and 4.x");
    }
    if (o.multicast) {
      throw NatNetConfigError(
          "mocap.natnet.bitstream_version: only a unicast client can "
          "choose the bitstream (set multicast: false or leave it empty)");
    }
    o.bitstream = v;
  }
  o.body_name = mocap.body_name();
  if (o.body_name.empty()) throw NatNetConfigError("mocap.body_name is empty");
  const MotiveFrames frames = MotiveFrames::FromConfig(n);
  o.up_axis = n.up_axis() == "Z" ? MotiveFrames::UpAxis::kZ : MotiveFrames::UpAxis::kY;
  if (n.has_x_pivot_chassis()) o.X_PC = ToPose3(n.x_pivot_chassis());
  if (!(n.keepalive_s() > 0) || !(n.silence_s() > 0)) {
    throw NatNetConfigError("mocap.natnet.keepalive_s and silence_s must be positive");
  }
  o.keepalive_s = n.keepalive_s();
  o.silence_s = n.silence_s();
  (void)frames;
  return o;
}

// ---- NatNetBridge ----

NatNetBridge::NatNetBridge(NatNetBridgeOptions options, ServiceStats& stats, PublishFn publish,
                           ClockFn now_utime)
    : options_(std::move(options)),
      frames_(options_.up_axis, options_.X_PC),
      stats_(stats),
      publish_(std::move(publish)),
      now_utime_(std::move(now_utime)),
      next_connect_(Clock::now()) {
  for (const char* name : {"frames",          "published",         "untracked",
                           "frame_gaps",      "frames_lost",       "frame_restarts",
                           "duplicates",      "decode_errors",     "edit_mode_frames",
                           "model_changes",   "description_reads", "bitstream_changes",
                           "body_missing",    "connects",          "probes",
                           "server_lost",     "not_streaming",     "keepalives",
                           "timeouts",        "foreign_packets",   "unknown_messages",
                           "clock_fallbacks", "clock_resyncs",     "system_latency_us",
                           "transit_us",      "frames_paused",     "reordered"}) {
    stats_.Counter(name);
  }
  server_ip_ = Ipv4(options_.address, "mocap.natnet.server_address");
  buffer_.resize(65536);
}

NatNetBridge::~NatNetBridge() { CloseSockets(); }

std::string NatNetBridge::LinkName(Link link) {
  switch (link) {
    case Link::kDisconnected:
      return "disconnected";
    case Link::kAwaitInfo:
      return "awaiting SERVERINFO";
    case Link::kAwaitDescriptions:
      return "awaiting descriptions";
    case Link::kStreaming:
      return "streaming";
  }
  return "?";
}

double NatNetBridge::SecondsSince(Clock::time_point t) const {
  return std::chrono::duration<double>(Clock::now() - t).count();
}

NatNetBridge::Clock::time_point NatNetBridge::After(double s) const {
  return Clock::now() +
         std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(s));
}

void NatNetBridge::Open() {
  command_fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (command_fd_ < 0) throw NatNetSocketError(std::string("socket: ") + std::strerror(errno));
  // Unicast frames arrive here too (§2.5): room for a burst of large frames.
  const int rcvbuf = 1 << 20;
  ::setsockopt(command_fd_, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  sockaddr_in any{};
  any.sin_family = AF_INET;
  any.sin_addr.s_addr = htonl(INADDR_ANY);
  if (::bind(command_fd_, reinterpret_cast<sockaddr*>(&any), sizeof any) != 0) {
    throw NatNetSocketError(std::string("binding the command socket: ") + std::strerror(errno));
  }
  if (!options_.multicast) return;
  data_fd_ = ::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (data_fd_ < 0) throw NatNetSocketError(std::string("socket: ") + std::strerror(errno));
  const int one = 1;
  ::setsockopt(data_fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);  // clients share 1511
  ::setsockopt(data_fd_, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
  // Bound to INADDR_ANY, not the interface: on Linux an interface-bound socket never sees the
  // group's datagrams; the interface is chosen in the membership (§2.4).
  sockaddr_in data{};
  data.sin_family = AF_INET;
  data.sin_addr.s_addr = htonl(INADDR_ANY);
  data.sin_port = htons(options_.data_port);
  if (::bind(data_fd_, reinterpret_cast<sockaddr*>(&data), sizeof data) != 0) {
    throw NatNetSocketError("binding the data socket to port " +
                            std::to_string(options_.data_port) + ": " + std::strerror(errno));
  }
  ip_mreq m{};
  m.imr_multiaddr.s_addr = Ipv4(options_.multicast_group, "mocap.natnet.multicast_group");
  m.imr_interface.s_addr = Ipv4(options_.local_interface, "mocap.natnet.local_interface");
  if (::setsockopt(data_fd_, IPPROTO_IP, IP_ADD_MEMBERSHIP, &m, sizeof m) != 0) {
    throw NatNetSocketError("joining " + options_.multicast_group + " on " +
                            options_.local_interface + ": " + std::strerror(errno));
  }
}

void NatNetBridge::CloseSockets() {
  if (command_fd_ >= 0) ::close(command_fd_);
  if (data_fd_ >= 0) ::close(data_fd_);
  command_fd_ = data_fd_ = -1;
}

std::vector<int> NatNetBridge::fds() const {
  std::vector<int> out{command_fd_};
  if (data_fd_ >= 0) out.push_back(data_fd_);
  return out;
}

void NatNetBridge::SendToServer(uint16_t id, const std::vector<uint8_t>& payload) {
  const std::vector<uint8_t> bytes = natnet::EncodePacket(id, payload);
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_addr.s_addr = server_ip_;
  to.sin_port = htons(options_.command_port);
  if (::sendto(command_fd_, bytes.data(), bytes.size(), 0, reinterpret_cast<sockaddr*>(&to),
               sizeof to) < 0) {
    // ECONNREFUSED and friends: Motive's port is closed; the reply timeout handles it.
    stats_.Error("natnet send", "message " + std::to_string(id) + " to " + options_.address + ":" +
                                    std::to_string(options_.command_port) + ": " +
                                    std::strerror(errno));
  }
}

void NatNetBridge::SendConnect() {
  connect_sent_at_ = Clock::now();
  SendToServer(natnet::kConnect, natnet::EncodeConnect(kClientName, options_.bitstream));
}

void NatNetBridge::RequestDescriptions() {
  ++stats_.Counter("description_reads");
  descriptions_pending_ = true;
  retry_descriptions_at_.reset();
  modeldef_sent_at_ = Clock::now();
  SendToServer(natnet::kRequestModelDef, {});
}

void NatNetBridge::StartProbe() {
  ++stats_.Counter("probes");
  probing_ = true;
  connect_since_ = Clock::now();
  SendConnect();
}

int NatNetBridge::TimerDueMs() const {
  if (link_ == Link::kDisconnected) {
    const auto ms =
        std::chrono::duration_cast<std::chrono::milliseconds>(next_connect_ - Clock::now()).count();
    return static_cast<int>(std::clamp<int64_t>(ms + 1, 0, 100));
  }
  // A NAT_CONNECT waiting for its answer is repeated every connect_repeat_s: look often.
  if (link_ == Link::kAwaitInfo || probing_) return 10;
  return 20;
}

void NatNetBridge::AddPollFds(std::vector<pollfd>* fds) {
  for (int fd : this->fds()) fds->push_back({fd, POLLIN, 0});
}

void NatNetBridge::OnPolled(const pollfd* fds, std::size_t n) {
  for (std::size_t i = 0; i < n; ++i) {
    if (fds[i].revents & (POLLIN | POLLERR)) OnReadable(fds[i].fd);
  }
}

// Early rather than late: TimerDueMs() counts from now while disconnected.
Device::Clock::time_point NatNetBridge::NextDeadline() const {
  return last_timer_ + std::chrono::milliseconds(TimerDueMs());
}

void NatNetBridge::OnDeadline(Clock::time_point now) {
  OnTimer();
  last_timer_ = now;
}

bool NatNetBridge::Degraded(std::string* why) { return DegradedBecause(health_reason(), why); }

void NatNetBridge::OnReadable(int fd) { Drain(fd); }

void NatNetBridge::Drain(int fd) {
  for (;;) {
    sockaddr_in from{};
    socklen_t len = sizeof from;
    // MSG_TRUNC: the datagram's real length, so a cut one is seen as such (§6 "truncation").
    const ssize_t n = ::recvfrom(fd, buffer_.data(), buffer_.size(), MSG_TRUNC,
                                 reinterpret_cast<sockaddr*>(&from), &len);
    if (n < 0) {
      if (errno == EINTR) continue;
      if (errno != EAGAIN && errno != EWOULDBLOCK) {
        // An ICMP port-unreachable from a stopped Motive surfaces here on the command socket.
        stats_.Drop("natnet receive error", std::strerror(errno));
        continue;
      }
      return;
    }
    const int64_t receive_us = now_utime_();
    if (static_cast<size_t>(n) > buffer_.size()) {
      ++stats_.Counter("decode_errors");
      stats_.Drop("natnet datagram truncated", std::to_string(n) + " bytes");
      continue;
    }
    const bool from_server = from.sin_addr.s_addr == server_ip_;
    const uint8_t* data = buffer_.data();
    const size_t size = static_cast<size_t>(n);
    natnet::Packet packet;
    if (!from_server) {
      ++stats_.Counter("foreign_packets");
      char ip[INET_ADDRSTRLEN] = {};
      ::inet_ntop(AF_INET, &from.sin_addr, ip, sizeof ip);
      stats_.Drop("natnet datagram from another host",
                  std::string(ip) + " is not " + options_.address);
      continue;
    }
    try {
      packet = natnet::DecodePacket(data, size);
    } catch (const natnet::NatNetError& e) {
      ++stats_.Counter("decode_errors");
      stats_.Drop("natnet datagram malformed", e.what());
      continue;
    }
    switch (packet.id) {
      case natnet::kServerInfo:
        HandleServerInfo(packet);
        break;
      case natnet::kModelDef:
        HandleDescriptions(packet);
        break;
      case natnet::kFrameOfData:
        HandleFrame(packet, receive_us);
        break;
      case natnet::kResponse:
        HandleResponse(packet);
        break;
      case natnet::kMessageString:
        stats_.log().info("Motive says: {}", natnet::DecodeString(packet.payload));
        break;
      case natnet::kEchoResponse:
      case natnet::kUnrecognizedRequest:
      case natnet::kUnrecognizedRequestAlt:
        break;  // replies without transaction ids: nothing to match them to (§6)
      default:
        ++stats_.Counter("unknown_messages");
        stats_.Drop("natnet message unknown", "id " + std::to_string(packet.id));
    }
  }
}

void NatNetBridge::HandleDatagram(const uint8_t* data, size_t size, bool from_server) {
  if (!from_server) {
    ++stats_.Counter("foreign_packets");
    return;
  }
  natnet::Packet packet;
  try {
    packet = natnet::DecodePacket(data, size);
  } catch (const natnet::NatNetError& e) {
    ++stats_.Counter("decode_errors");
    stats_.Drop("natnet datagram malformed", e.what());
    return;
  }
  switch (packet.id) {
    case natnet::kServerInfo:
      return HandleServerInfo(packet);
    case natnet::kModelDef:
      return HandleDescriptions(packet);
    case natnet::kFrameOfData:
      return HandleFrame(packet, now_utime_());
    case natnet::kResponse:
      return HandleResponse(packet);
    default:
      return;
  }
}

void NatNetBridge::HandleServerInfo(const natnet::Packet& p) {
  natnet::ServerInfo info;
  try {
    info = natnet::DecodeServerInfo(p.payload);
  } catch (const natnet::NatNetError& e) {
    ++stats_.Counter("decode_errors");
    stats_.Drop("natnet SERVERINFO malformed", e.what());
    return;
  }
  if (!natnet::Supported(info.version())) {
    throw NatNetConfigError("Motive at " + options_.address + " streams NatNet " +
                            info.version().ToString() + "; ftcal-natnet-bridge reads 3.x and 4.x");
  }
  if (probing_) {
    // Motive answers, so it is up: while it sends no frames the bridge waits, it does not
    // start over (its descriptions still hold). Before silence_s the answer only says that a
    // unicast client's connect reached it.
    probing_ = false;
    server_ = info;
    if (SecondsSince(last_frame_at_) <= options_.silence_s) return;
    if (!server_up_not_streaming_) {
      ++stats_.Counter("not_streaming");
      stats_.log().warn("Motive at {} answers but sends no frames: waiting", options_.address);
    }
    server_up_not_streaming_ = true;
    return;
  }
  if (link_ != Link::kAwaitInfo) return;  // a late duplicate
  server_ = info;
  sequence_.Forget();  // a new session: its frame numbers are its own
  // The version to parse with: the one asked for (unicast), which Motive honours in
  // NAT_CONNECT (§2.3), else the server's; a Bitstream reply overrides both.
  version_ = options_.bitstream.value_or(info.version());
  ++stats_.Counter("connects");
  stats_.log().info("Motive '{}' {}.{} at {}: NatNet {} ({}), clock {} Hz, parsing {}",
                    info.app_name, info.app_version[0], info.app_version[1], options_.address,
                    info.version().ToString(), info.multicast ? "multicast" : "unicast",
                    info.clock_frequency_hz, version_.ToString());
  if (info.multicast != options_.multicast) {
    stats_.log().warn("Motive says it streams {} but the config says {} (mocap.natnet.multicast)",
                      info.multicast ? "multicast" : "unicast",
                      options_.multicast ? "multicast" : "unicast");
  }
  motive_clock_.reset();
  link_ = Link::kAwaitDescriptions;
  next_keepalive_ = After(options_.keepalive_s);
  if (options_.bitstream) SendToServer(natnet::kRequest, natnet::EncodeString("Bitstream"));
  RequestDescriptions();
}

void NatNetBridge::HandleResponse(const natnet::Packet& p) {
  const std::string text = natnet::DecodeString(p.payload);
  if (text.rfind("Bitstream,", 0) != 0) return;
  const auto v = natnet::ParseVersion(text.substr(10));
  if (!v || !natnet::Supported(*v)) {
    stats_.Error("natnet bitstream", "Motive reports '" + text + "', which the bridge cannot read");
    return;
  }
  if (*v != version_) {
    stats_.log().warn("Motive streams bitstream {}, not {}: switching", v->ToString(),
                      version_.ToString());
    version_ = *v;
    if (!descriptions_pending_) RequestDescriptions();
  }
}

void NatNetBridge::HandleDescriptions(const natnet::Packet& p) {
  if (link_ == Link::kDisconnected || link_ == Link::kAwaitInfo) {
    stats_.Drop("natnet descriptions before SERVERINFO", "the version is not known yet");
    return;
  }
  descriptions_pending_ = false;
  natnet::Descriptions d;
  try {
    d = natnet::DecodeDescriptions(p.payload, version_);
  } catch (const natnet::NatNetError& e) {
    ++stats_.Counter("decode_errors");
    descriptions_problem_ = std::string("unreadable descriptions: ") + e.what();
    stats_.Error("natnet descriptions unreadable", e.what());
    retry_descriptions_at_ = After(kDescriptionsRetryS);
    return;
  }
  const auto it = std::find_if(d.rigid_bodies.begin(), d.rigid_bodies.end(),
                               [&](const auto& rb) { return rb.name == options_.body_name; });
  if (it == d.rigid_bodies.end()) {
    std::string names;
    for (const auto& rb : d.rigid_bodies) names += (names.empty() ? "" : ", ") + rb.name;
    descriptions_problem_ = "rigid body '" + options_.body_name + "' (config mocap.body_name) is " +
                            "not among Motive's [" + names + "]";
    ++stats_.Counter("body_missing");
    stats_.Error("natnet body missing", descriptions_problem_);
    body_id_.reset();
    retry_descriptions_at_ = After(kDescriptionsRetryS);
    return;
  }
  descriptions_problem_.clear();
  if (body_id_ != it->id) {
    stats_.log().info("Motive rigid body '{}' is id {} with {} markers", it->name, it->id,
                      it->marker_positions.size());
  }
  body_id_ = it->id;
  // Labeled markers of a rigid body carry its id in the high 16 bits and the 1-based member
  // index in the low 16 (§4.3): the description's order is the published order.
  marker_ids_.clear();
  for (size_t i = 0; i < it->marker_positions.size(); ++i) {
    marker_ids_.push_back(static_cast<int32_t>((static_cast<uint32_t>(it->id) << 16) | (i + 1)));
  }
  if (link_ == Link::kAwaitDescriptions) {
    link_ = Link::kStreaming;
    last_frame_at_ = Clock::now();
  }
}

void NatNetBridge::ServerLost(const std::string& why) {
  ++stats_.Counter("server_lost");
  stats_.Error("natnet server lost", options_.address + ": " + why);
  ResetSession();
  link_ = Link::kDisconnected;
  next_connect_ = Clock::now();  // connect again at once (and every connect_repeat_s)
}

void NatNetBridge::ResetSession() {
  body_id_.reset();
  marker_ids_.clear();
  descriptions_pending_ = false;
  descriptions_problem_.clear();
  retry_descriptions_at_.reset();
  probing_ = false;
  server_up_not_streaming_ = false;
  got_frame_ = false;
  edit_mode_ = false;
  motive_clock_.reset();
}

void NatNetBridge::OnTimer() {
  const auto now = Clock::now();
  if (link_ == Link::kDisconnected) {
    if (now >= next_connect_) {
      link_ = Link::kAwaitInfo;
      connect_since_ = now;
      SendConnect();
    }
    return;
  }
  if (link_ == Link::kAwaitInfo) {
    if (SecondsSince(connect_since_) > options_.reply_timeout_s) {
      ++stats_.Counter("timeouts");
      stats_.Error("natnet no SERVERINFO", "Motive at " + options_.address + ":" +
                                               std::to_string(options_.command_port) +
                                               " did not answer NAT_CONNECT (streaming off, "
                                               "wrong address or interface?)");
      connect_since_ = now;
    }
    // Asked again until it answers: it may come back at any moment.
    if (SecondsSince(connect_sent_at_) >= options_.connect_repeat_s) SendConnect();
    return;
  }
  if (!options_.multicast && now >= next_keepalive_) {
    // Unicast sessions go to sleep without it (§2.5); no reply is expected.
    SendToServer(natnet::kKeepAlive, {});
    ++stats_.Counter("keepalives");
    next_keepalive_ = now + std::chrono::duration_cast<Clock::duration>(
                                std::chrono::duration<double>(options_.keepalive_s));
  }
  if (descriptions_pending_ && SecondsSince(modeldef_sent_at_) > options_.reply_timeout_s) {
    ++stats_.Counter("timeouts");
    if (link_ == Link::kAwaitDescriptions) {
      ServerLost("no answer to NAT_REQUEST_MODELDEF");
      return;
    }
    RequestDescriptions();
  }
  if (retry_descriptions_at_ && now >= *retry_descriptions_at_) RequestDescriptions();
  if (link_ != Link::kStreaming) return;
  const double quiet_s = SecondsSince(last_frame_at_);
  if (probing_) {
    if (quiet_s > options_.silence_s && SecondsSince(connect_since_) > options_.reply_timeout_s) {
      ServerLost("no frame for " + std::to_string(quiet_s) + " s and no answer to NAT_CONNECT");
      return;
    }
    // Until it answers: for a unicast client the CONNECT that reaches a restarted Motive is
    // the one that makes it stream again.
    if (SecondsSince(connect_sent_at_) >= options_.connect_repeat_s) SendConnect();
    return;
  }
  if (server_up_not_streaming_) {
    // It answered and sends nothing (paused): ask again now and then whether it is still there.
    if (SecondsSince(connect_sent_at_) > kProbeIntervalS) StartProbe();
    return;
  }
  // Is Motive gone, or up and not streaming? Only SERVERINFO tells. A unicast client asks
  // early: a Motive that restarted streams to it only once it connects again.
  const double ask_after_s =
      options_.multicast ? options_.silence_s : std::min(options_.silence_s, kUnicastRejoinS);
  if (quiet_s > ask_after_s && SecondsSince(connect_sent_at_) >= options_.connect_repeat_s) {
    StartProbe();
  }
}

std::string NatNetBridge::health_reason() const {
  if (link_ == Link::kDisconnected || link_ == Link::kAwaitInfo) {
    return "no SERVERINFO from Motive at " + options_.address + ":" +
           std::to_string(options_.command_port);
  }
  if (!descriptions_problem_.empty()) return descriptions_problem_;
  if (link_ == Link::kAwaitDescriptions) return "awaiting Motive's data descriptions";
  if (edit_mode_) return "Motive is in edit mode (playback, not live)";
  if (server_up_not_streaming_) return "Motive is up but sends no frames";
  if (SecondsSince(last_frame_at_) > options_.silence_s) {
    return "no frame from Motive for more than " + std::to_string(options_.silence_s) + " s";
  }
  if (!got_frame_) return "no frame yet";
  return "";
}

}  // namespace ftcal
