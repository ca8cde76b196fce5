#include "natnet_emulator.h"

#include <arpa/inet.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <Eigen/Geometry>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <stdexcept>

namespace ftcal::sim {
namespace {

using Clock = std::chrono::steady_clock;

double SteadySeconds() {
  return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
}

int64_t WallUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Motive's axes M from ftcal's G: Y-up M has y_M = z_G, z_M = -y_G (the inverse of the
// bridge's Rx(+90°)).
Eigen::Matrix3d R_MG(bool z_up) {
  if (z_up) return Eigen::Matrix3d::Identity();
  Eigen::Matrix3d R;
  R << 1, 0, 0, 0, 0, 1, 0, -1, 0;
  return R;
}

natnet::Vec3f F3(const Eigen::Vector3d& v) {
  return {static_cast<float>(v.x()), static_cast<float>(v.y()), static_cast<float>(v.z())};
}

constexpr char kDecoyName[] = "wand";

}  // namespace

NatNetEmulator::NatNetEmulator(NatNetEmulatorOptions options, NatNetFrameSource source)
    : options_(std::move(options)), source_(std::move(source)), rng_(options_.faults.seed) {
  if (!(options_.rate_hz > 0) || options_.rate_hz > 10000) {
    throw std::invalid_argument("NatNetEmulator: rate_hz " + std::to_string(options_.rate_hz) +
                                " outside (0, 10000]");
  }
  if (!natnet::Supported(options_.version)) {
    throw std::invalid_argument("NatNetEmulator: NatNet " + options_.version.ToString() +
                                " is not 3.x or 4.x");
  }
  if (!source_) throw std::invalid_argument("NatNetEmulator: no frame source");
  if (options_.clock_hz == 0) throw std::invalid_argument("NatNetEmulator: clock_hz 0");
  if (options_.body_id <= 0 || options_.body_id > 0x7FFF) {
    throw std::invalid_argument("NatNetEmulator: body_id must be in 1..32767");
  }
  start_s_ = SteadySeconds();
  Bind();
}

NatNetEmulator::~NatNetEmulator() { Close(); }

void NatNetEmulator::Bind() {
  auto open = [&](uint16_t port, const char* what) {
    const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0)
      throw std::runtime_error(std::string("NatNetEmulator: socket: ") + std::strerror(errno));
    const int one = 1;
    // A bridge on this host binds INADDR_ANY on the data port too (SO_REUSEADDR on both).
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_port = htons(port);
    if (::inet_pton(AF_INET, options_.address.c_str(), &a.sin_addr) != 1) {
      ::close(fd);
      throw std::invalid_argument("NatNetEmulator: address '" + options_.address + "' is not IPv4");
    }
    if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
      const std::string why = std::strerror(errno);
      ::close(fd);
      throw std::runtime_error("NatNetEmulator: cannot bind the " + std::string(what) +
                               " socket to " + options_.address + ":" + std::to_string(port) +
                               ": " + why);
    }
    socklen_t len = sizeof a;
    ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len);
    return std::make_pair(fd, ntohs(a.sin_port));
  };
  // A restart keeps its ports.
  std::tie(command_fd_, command_port_) =
      open(command_port_ != 0 ? command_port_ : options_.command_port, "command");
  std::tie(data_fd_, data_port_) = open(data_port_ != 0 ? data_port_ : options_.data_port, "data");
  if (options_.multicast) {
    in_addr ifc{};
    ::inet_pton(AF_INET, options_.address.c_str(), &ifc);
    ::setsockopt(data_fd_, IPPROTO_IP, IP_MULTICAST_IF, &ifc, sizeof ifc);
    const unsigned char loop = 1, ttl = 0;
    ::setsockopt(data_fd_, IPPROTO_IP, IP_MULTICAST_LOOP, &loop, sizeof loop);
    ::setsockopt(data_fd_, IPPROTO_IP, IP_MULTICAST_TTL, &ttl, sizeof ttl);
  }
}

void NatNetEmulator::Close() {
  if (command_fd_ >= 0) ::close(command_fd_);
  if (data_fd_ >= 0) ::close(data_fd_);
  command_fd_ = data_fd_ = -1;
}

double NatNetEmulator::Seconds() const { return SteadySeconds() - start_s_; }

uint64_t NatNetEmulator::Ticks() const {
  // Motive had been up a second before the first frame: mid-exposure never goes below zero.
  return static_cast<uint64_t>((Seconds() * (1.0 + 1e-6 * options_.clock_rate_ppm) + 1.0) *
                               static_cast<double>(options_.clock_hz));
}

natnet::Version NatNetEmulator::VersionFor(const sockaddr_in& from) const {
  const auto it = clients_.find({from.sin_addr.s_addr, from.sin_port});
  return it == clients_.end() ? options_.version : it->second.version;
}

void NatNetEmulator::Reply(const sockaddr_in& to, uint16_t id,
                           const std::vector<uint8_t>& payload) {
  const std::vector<uint8_t> bytes = natnet::EncodePacket(id, payload);
  ::sendto(command_fd_, bytes.data(), bytes.size(), 0, reinterpret_cast<const sockaddr*>(&to),
           sizeof to);
}

natnet::Descriptions NatNetEmulator::CurrentDescriptions() const {
  natnet::Descriptions d;
  natnet::MarkerSetDescription ms;
  ms.name = options_.body_name;
  natnet::RigidBodyDescription rb;
  rb.name = options_.body_name;
  rb.id = swapped_ ? options_.body_id + 10 : options_.body_id;
  for (size_t i = 0; i < options_.body_points_C_m.size(); ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "%s_m%02zu", options_.body_name.c_str(), i + 1);
    ms.marker_names.push_back(name);
    rb.marker_names.push_back(name);
    // Positions in the body's own (pivot) frame.
    rb.marker_positions.push_back(
        F3(options_.R_PC * options_.body_points_C_m[i] + options_.p_PoCo_P_m));
    rb.marker_required_labels.push_back(0);
  }
  d.marker_sets.push_back(ms);
  natnet::RigidBodyDescription wand;
  wand.name = kDecoyName;
  wand.id = swapped_ ? options_.body_id : 1;
  if (options_.decoy_body && !swapped_) d.rigid_bodies.push_back(wand);
  d.rigid_bodies.push_back(rb);
  if (options_.decoy_body && swapped_) d.rigid_bodies.push_back(wand);
  return d;
}

void NatNetEmulator::ReadCommands() {
  uint8_t buf[65536];
  for (;;) {
    sockaddr_in from{};
    socklen_t len = sizeof from;
    const ssize_t n =
        ::recvfrom(command_fd_, buf, sizeof buf, 0, reinterpret_cast<sockaddr*>(&from), &len);
    if (n < 0) {
      if (errno == EINTR) continue;
      return;
    }
    try {
      HandleCommand(natnet::DecodePacket(buf, static_cast<size_t>(n)), from);
    } catch (const natnet::NatNetError&) {
      // Motive ignores what it cannot read.
    }
  }
}

void NatNetEmulator::HandleCommand(const natnet::Packet& p, const sockaddr_in& from) {
  const auto key = std::make_pair(from.sin_addr.s_addr, from.sin_port);
  switch (p.id) {
    case natnet::kConnect: {
      ++counters_.connects;
      natnet::Version v = options_.version;
      const auto asked = natnet::DecodeConnectRequest(p.payload);
      if (asked && natnet::Supported(*asked)) v = *asked;
      if (!options_.multicast) clients_[key] = Client{v, Seconds()};
      natnet::ServerInfo info;
      info.app_name = "Motive";
      info.app_version = {3, 1, 0, 0};
      info.natnet_version = {static_cast<uint8_t>(v.major), static_cast<uint8_t>(v.minor), 0, 0};
      info.clock_frequency_hz = options_.clock_hz;
      info.data_port = data_port_;
      info.multicast = options_.multicast;
      in_addr g{};
      ::inet_pton(AF_INET, options_.multicast_group.c_str(), &g);
      std::memcpy(info.multicast_group.data(), &g, 4);
      return Reply(from, natnet::kServerInfo, natnet::EncodeServerInfo(info));
    }
    case natnet::kKeepAlive: {
      ++counters_.keepalives;
      const auto it = clients_.find(key);
      if (it != clients_.end()) it->second.last_heard_s = Seconds();
      return;
    }
    case natnet::kDisconnect:
      clients_.erase(key);
      return;
    case natnet::kRequestModelDef:
      ++counters_.descriptions_sent;
      return Reply(from, natnet::kModelDef,
                   natnet::EncodeDescriptions(CurrentDescriptions(), VersionFor(from)));
    case natnet::kEchoRequest: {
      if (p.payload.size() != 8) return;
      natnet::Echo e;
      std::memcpy(&e.request_time, p.payload.data(), 8);
      e.server_ticks = Ticks();
      return Reply(from, natnet::kEchoResponse, natnet::EncodeEchoResponse(e));
    }
    case natnet::kRequest: {
      const std::string cmd = natnet::DecodeString(p.payload);
      std::vector<uint8_t> value(4);
      if (cmd == "FrameRate") {
        const auto hz = static_cast<float>(options_.rate_hz);
        std::memcpy(value.data(), &hz, 4);
        return Reply(from, natnet::kResponse, value);
      }
      if (cmd == "UnitsToMillimeters") {
        const float mm = 1000.0f;
        std::memcpy(value.data(), &mm, 4);
        return Reply(from, natnet::kResponse, value);
      }
      if (cmd == "Bitstream") {
        const natnet::Version v = VersionFor(from);
        return Reply(from, natnet::kResponse,
                     natnet::EncodeString("Bitstream," + v.ToString() + ".0"));
      }
      ++counters_.requests_unrecognized;
      return Reply(from, natnet::kUnrecognizedRequest, {});
    }
    default:
      ++counters_.requests_unrecognized;
      return Reply(from, natnet::kUnrecognizedRequest, {});
  }
}

bool NatNetEmulator::InAny(const std::vector<NatNetWindow>& w, int64_t tick) const {
  return std::any_of(w.begin(), w.end(),
                     [tick](const NatNetWindow& x) { return x.Contains(tick); });
}

void NatNetEmulator::Tick() {
  const NatNetFaults& f = options_.faults;
  const int64_t k = tick_;
  const bool down = InAny(f.down, k);
  if (down && up_) {
    Close();  // Motive is gone: nothing answers, and what it held back is never sent
    clients_.clear();
    held_.clear();
    up_ = false;
  } else if (!down && !up_) {
    // Motive restarts: its clock, frame numbers and (here) the body's id start over.
    Bind();
    up_ = true;
    ++counters_.restarts;
    counters_.restart_utime = WallUtime();
    max_sent_number_ = 0;
    start_s_ = SteadySeconds();
    frame_base_ = k;
    skipped_ = 0;
    swapped_ = !swapped_;
  }
  bool model_changed = false;
  if (std::find(f.model_changes.begin(), f.model_changes.end(), k) != f.model_changes.end()) {
    swapped_ = !swapped_;
    model_changed = true;
    ++counters_.model_changes;
  }
  // Unicast clients that stopped talking are forgotten, as Motive does with sleeping ones.
  for (auto it = clients_.begin(); it != clients_.end();) {
    if (Seconds() - it->second.last_heard_s > options_.client_timeout_s) {
      ++counters_.clients_expired;
      it = clients_.erase(it);
    } else {
      ++it;
    }
  }

  std::optional<NatNetPose> pose = source_(k);
  if (!pose) {
    source_ended_ = true;
    return;
  }
  ++counters_.ticks;
  std::uniform_real_distribution<double> u(0.0, 1.0);
  if (u(rng_) < f.gap_probability) {
    const int g = std::uniform_int_distribution<int>(1, 3)(rng_);
    skipped_ += g;
    ++counters_.gaps;
    counters_.frames_skipped += g;
  }
  const bool duplicate = u(rng_) < f.duplicate_probability;
  const bool corrupt = u(rng_) < f.corrupt_probability;
  // Drawn only when asked for, so that the other faults' sequence for a seed stays as it was.
  int64_t hold_ticks = 0;
  if (f.reorder_probability > 0 && u(rng_) < f.reorder_probability) {
    hold_ticks = std::uniform_int_distribution<int64_t>(1, 3)(rng_);
  }
  ++tick_;
  if (down) return;
  if (InAny(f.silent, k)) return ReleaseHeld(k);

  const bool untracked = !pose->body_tracked || InAny(f.untracked, k);
  const bool edit = InAny(f.edit_mode, k);
  if (!untracked) last_tracked_ = pose;
  // An untracked body keeps Motive's last pose (§4.2): the bridge must not publish it.
  const NatNetPose& shown = untracked && last_tracked_ ? *last_tracked_ : *pose;

  const Eigen::Matrix3d R_MG_ = R_MG(options_.z_up);
  natnet::FrameOfData frame;
  frame.frame_number = static_cast<int32_t>(k - frame_base_ + 1 + skipped_);
  // Motive's own clock, as QTM's (whole us, so both emulations give a frame one device time).
  frame.timestamp_s =
      1e-6 * static_cast<double>(std::llround(1e6 * options_.clock_offset_s +
                                              (1.0 + 1e-6 * options_.clock_rate_ppm) *
                                                  static_cast<double>(frame.frame_number - 1) *
                                                  1e6 / options_.rate_hz));
  // Pivot P from chassis C: X_GP = X_GC X_PC^-1.
  const Eigen::Matrix3d R_GP = shown.R_GC * options_.R_PC.transpose();
  const Eigen::Vector3d p_GoPo = shown.p_GoCo_G_m - R_GP * options_.p_PoCo_P_m;
  const Eigen::Quaterniond q(R_MG_ * R_GP);
  natnet::RigidBodyData chassis;
  chassis.id = swapped_ ? options_.body_id + 10 : options_.body_id;
  chassis.position = F3(R_MG_ * p_GoPo);
  chassis.orientation = {static_cast<float>(q.x()), static_cast<float>(q.y()),
                         static_cast<float>(q.z()), static_cast<float>(q.w())};
  chassis.mean_error = static_cast<float>(shown.residual_m);
  chassis.params = untracked ? 0 : 1;
  natnet::RigidBodyData wand;
  wand.id = swapped_ ? options_.body_id : 1;
  wand.position = {1.5f, 0.005f, 0.8f};
  wand.params = 1;
  if (options_.decoy_body && !swapped_) frame.rigid_bodies.push_back(wand);
  frame.rigid_bodies.push_back(chassis);
  if (options_.decoy_body && swapped_) frame.rigid_bodies.push_back(wand);
  natnet::MarkerSetData set;
  set.name = options_.body_name;
  for (size_t i = 0; i < pose->markers_G_m.size(); ++i) {
    const Eigen::Vector3d& m = pose->markers_G_m[i];
    if (!m.allFinite()) continue;  // not seen: absent from the labeled list
    natnet::LabeledMarker lm;
    lm.id = static_cast<int32_t>((static_cast<uint32_t>(chassis.id) << 16) | (i + 1));
    lm.position = F3(R_MG_ * m);
    lm.size = 0.014f;
    lm.params = untracked ? 0x01 : 0x04;  // occluded, else model-solved
    lm.residual = 0.0002f;
    frame.labeled_markers.push_back(lm);
    set.markers.push_back(lm.position);
  }
  frame.marker_sets.push_back(set);
  frame.params = static_cast<int16_t>((model_changed ? natnet::kFrameModelListChanged : 0));
  const uint64_t transmit = Ticks();
  const auto latency_ticks =
      static_cast<uint64_t>(options_.system_latency_s * static_cast<double>(options_.clock_hz));
  frame.transmit_ticks = transmit;
  frame.data_received_ticks = transmit - latency_ticks / 2;
  frame.mid_exposure_ticks = f.mid_exposure_zero ? 0 : transmit - latency_ticks;
  const int64_t exposure_utime = WallUtime() - std::llround((f.mid_exposure_zero ? 0.5 : 1.0) *
                                                            options_.system_latency_s * 1e6);

  // One encoding per version in use.
  std::map<std::pair<int, int>, std::vector<uint8_t>> packets;
  auto packet_for = [&](natnet::Version v) -> const std::vector<uint8_t>& {
    auto it = packets.find({v.major, v.minor});
    if (it != packets.end()) return it->second;
    natnet::FrameOfData fv = frame;
    if (edit && v.AtLeast(4, 0)) fv.params |= natnet::kFrameEditMode;
    std::vector<uint8_t> payload = natnet::EncodeFrame(fv, v);
    // A damaged frame whose datagram is still whole: the decoder must find bytes left over.
    if (corrupt) payload.push_back(0);
    return packets
        .emplace(std::make_pair(v.major, v.minor),
                 natnet::EncodePacket(natnet::kFrameOfData, payload))
        .first->second;
  };
  Outgoing out;
  const int copies = duplicate ? 2 : 1;
  auto add = [&](const sockaddr_in& to, const std::vector<uint8_t>& bytes) {
    for (int c = 0; c < copies; ++c) out.datagrams.push_back({to, bytes});
  };
  int receivers = 0;
  if (options_.multicast) {
    sockaddr_in to{};
    to.sin_family = AF_INET;
    to.sin_port = htons(data_port_);
    ::inet_pton(AF_INET, options_.multicast_group.c_str(), &to.sin_addr);
    add(to, packet_for(options_.version));
    receivers = 1;
  } else {
    for (const auto& [endpoint, client] : clients_) {
      sockaddr_in to{};
      to.sin_family = AF_INET;
      to.sin_addr.s_addr = endpoint.first;
      to.sin_port = endpoint.second;
      add(to, packet_for(client.version));
      ++receivers;
    }
  }
  if (receivers == 0) return ReleaseHeld(k);
  NatNetSentFrame& s = out.frame;
  s.tick = k;
  s.frame_number = frame.frame_number;
  s.timestamp_s = frame.timestamp_s;
  s.exposure_utime = exposure_utime;
  s.corrupt = corrupt;
  s.duplicated = duplicate;
  s.tracked = !untracked;
  s.edit_mode = edit;
  s.R_GC = pose->R_GC;
  s.p_GoCo_G_m = pose->p_GoCo_G_m;
  s.markers_G_m = pose->markers_G_m;
  s.receivers = receivers;
  if (hold_ticks > 0) {
    // UDP reordering: this frame goes out after the frames of the next hold_ticks ticks.
    out.release_tick = k + hold_ticks;
    held_.push_back(std::move(out));
  } else {
    Emit(out);
  }
  ReleaseHeld(k);
}

void NatNetEmulator::Emit(Outgoing& out) {
  for (const Datagram& d : out.datagrams) {
    ::sendto(data_fd_, d.bytes.data(), d.bytes.size(), 0, reinterpret_cast<const sockaddr*>(&d.to),
             sizeof d.to);
  }
  NatNetSentFrame& s = out.frame;
  s.late = s.frame_number < max_sent_number_;
  max_sent_number_ = std::max(max_sent_number_, s.frame_number);
  ++counters_.frames_sent;
  counters_.frames_corrupt += s.corrupt;
  counters_.frames_untracked += !s.tracked;
  counters_.frames_duplicated += s.duplicated;
  counters_.frames_reordered += s.late;
  if (observer_) observer_(s);
}

void NatNetEmulator::ReleaseHeld(int64_t tick) {
  // In the order they were held back; after this tick's frame, so they arrive late.
  auto due = [tick](const Outgoing& o) { return o.release_tick <= tick; };
  for (Outgoing& o : held_) {
    if (due(o)) Emit(o);
  }
  held_.erase(std::remove_if(held_.begin(), held_.end(), due), held_.end());
}

void NatNetEmulator::Run(int64_t max_ticks, const std::function<bool()>& keep_going) {
  const auto t0 = Clock::now();
  const int64_t start_tick = tick_;
  const double period_ns = 1e9 / options_.rate_hz;
  while (!stop_.load() && !source_ended_) {
    if (max_ticks >= 0 && tick_ - start_tick >= max_ticks) break;
    if (keep_going && !keep_going()) break;
    const auto deadline =
        t0 + std::chrono::nanoseconds(std::llround(period_ns * double(tick_ - start_tick)));
    const auto wait = std::clamp<int64_t>(
        std::chrono::duration_cast<std::chrono::nanoseconds>(deadline - Clock::now()).count(), 0,
        100'000'000);
    const timespec ts{static_cast<time_t>(wait / 1'000'000'000),
                      static_cast<long>(wait % 1'000'000'000)};
    if (command_fd_ >= 0) {
      pollfd p{command_fd_, POLLIN, 0};
      if (::ppoll(&p, 1, &ts, nullptr) > 0) ReadCommands();
    } else {
      ::nanosleep(&ts, nullptr);
    }
    if (Clock::now() >= deadline) Tick();
  }
}

}  // namespace ftcal::sim
