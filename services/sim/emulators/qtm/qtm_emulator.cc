#include "qtm_emulator.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <pugixml.hpp>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <sstream>
#include <stdexcept>

namespace ftcal::sim {
namespace {

constexpr size_t kMaxClientBacklogBytes = 4u << 20;  // a client this far behind is dropped
constexpr char kWelcome[] = "QTM RT Interface connected";

std::string Lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

std::vector<std::string> Words(const std::string& text) {
  std::istringstream in(text);
  std::vector<std::string> out;
  for (std::string w; in >> w;) out.push_back(w);
  return out;
}

void SetNonBlocking(int fd) {
  const int flags = ::fcntl(fd, F_GETFL, 0);
  ::fcntl(fd, F_SETFL, flags | O_NONBLOCK);
}

std::vector<uint8_t> EventPacket(uint8_t event) {
  return qtm::EncodePacket(static_cast<int32_t>(qtm::PacketType::kEvent), {event});
}

}  // namespace

std::vector<std::string> DefaultQtmLabels(int n) {
  std::vector<std::string> out;
  for (int i = 1; i <= n; ++i) {
    char name[32];
    std::snprintf(name, sizeof name, "chassis_m%02d", i);
    out.emplace_back(name);
  }
  return out;
}

struct QtmEmulator::Client {
  int fd = -1;
  qtm::Deframer deframer;
  std::vector<uint8_t> out;
  size_t out_at = 0;
  int minor = 1;  // protocol 1.1 until the client sends Version
  bool streaming = false;
  int64_t divisor = 1;
  bool markers = false, markers_res = false, bodies = false, bodies_res = false;
  bool dead = false;
};

QtmEmulator::QtmEmulator(QtmEmulatorOptions options, QtmFrameSource source)
    : options_(std::move(options)), source_(std::move(source)), rng_(options_.faults.seed) {
  if (!(options_.rate_hz > 0) || options_.rate_hz > 100000) {
    throw std::invalid_argument("QtmEmulator: rate_hz " + std::to_string(options_.rate_hz) +
                                " outside (0, 100000]");
  }
  if (!source_) throw std::invalid_argument("QtmEmulator: no frame source");
  if (options_.labels.empty()) options_.labels = DefaultQtmLabels(12);
  if (!options_.body_points_m.empty() && options_.body_points_m.size() != options_.labels.size()) {
    throw std::invalid_argument("QtmEmulator: " + std::to_string(options_.body_points_m.size()) +
                                " body points for " + std::to_string(options_.labels.size()) +
                                " labels");
  }
  if (options_.max_clients < 1) throw std::invalid_argument("QtmEmulator: max_clients < 1");
  marker_dropout_until_.assign(options_.labels.size(), -1);
  decoy_first_ = options_.decoy_body_first;
  Listen();
}

QtmEmulator::~QtmEmulator() {
  for (auto& c : clients_) ::close(c->fd);
  CloseListener();
}

void QtmEmulator::Listen() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) throw std::runtime_error(std::string("QtmEmulator: socket: ") + std::strerror(errno));
  const int one = 1;
  ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(port_ != 0 ? port_ : options_.port);  // a restart keeps its port
  if (::inet_pton(AF_INET, options_.address.c_str(), &addr.sin_addr) != 1) {
    ::close(fd);
    throw std::invalid_argument("QtmEmulator: address '" + options_.address + "' is not IPv4");
  }
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0 || ::listen(fd, 16) != 0) {
    const std::string why = std::strerror(errno);
    ::close(fd);
    throw std::runtime_error("QtmEmulator: cannot listen on " + options_.address + ":" +
                             std::to_string(ntohs(addr.sin_port)) + ": " + why);
  }
  socklen_t len = sizeof addr;
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
  port_ = ntohs(addr.sin_port);
  SetNonBlocking(fd);
  listen_fd_ = fd;
}

void QtmEmulator::CloseListener() {
  if (listen_fd_ >= 0) ::close(listen_fd_);
  listen_fd_ = -1;
}

void QtmEmulator::Accept() {
  for (;;) {
    const int fd = ::accept4(listen_fd_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) return;  // EAGAIN: all taken
    const int one = 1;
    ::setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
    auto client = std::make_unique<Client>();
    client->fd = fd;
    if (static_cast<int>(clients_.size()) >= options_.max_clients) {
      ++counters_.refused_clients;
      Send(*client, qtm::EncodeText(qtm::PacketType::kError,
                                    "Connection refused. Max number of clients reached."));
      ::close(fd);
      continue;
    }
    ++counters_.connections;
    Send(*client, qtm::EncodeCommand(kWelcome));
    clients_.push_back(std::move(client));
  }
}

void QtmEmulator::Send(Client& c, const std::vector<uint8_t>& bytes) {
  if (c.dead) return;
  c.out.insert(c.out.end(), bytes.begin(), bytes.end());
  Flush(c);
}

void QtmEmulator::Flush(Client& c) {
  while (!c.dead && c.out_at < c.out.size()) {
    const ssize_t n = ::send(c.fd, c.out.data() + c.out_at, c.out.size() - c.out_at, MSG_NOSIGNAL);
    if (n > 0) {
      c.out_at += static_cast<size_t>(n);
    } else if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
      break;
    } else if (n < 0 && errno == EINTR) {
      continue;
    } else {
      c.dead = true;
    }
  }
  if (c.out_at == c.out.size()) {
    c.out.clear();
    c.out_at = 0;
  } else if (c.out.size() - c.out_at > kMaxClientBacklogBytes) {
    c.dead = true;  // QTM drops a client that does not keep up; so do we
  }
}

void QtmEmulator::ReadClient(Client& c) {
  uint8_t buf[4096];
  for (;;) {
    const ssize_t n = ::recv(c.fd, buf, sizeof buf, 0);
    if (n > 0) {
      c.deframer.Feed(buf, static_cast<size_t>(n));
      continue;
    }
    if (n < 0 && errno == EINTR) continue;
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) break;
    c.dead = true;  // closed or failed
    break;
  }
  try {
    while (auto packet = c.deframer.Next()) {
      if (packet->is(qtm::PacketType::kCommand)) HandleCommand(c, qtm::DecodeText(*packet));
    }
  } catch (const qtm::QtmError&) {
    c.dead = true;  // the client's stream is out of step: nothing to resynchronise on
  }
}

void QtmEmulator::HandleCommand(Client& c, const std::string& text) {
  const std::vector<std::string> words = Words(text);
  const auto error = [&](const std::string& what) {
    Send(c, qtm::EncodeText(qtm::PacketType::kError, what));
  };
  if (words.empty()) return error("Parse Error");
  const std::string verb = Lower(words[0]);
  if (verb == "version") {
    if (words.size() == 1) {
      return Send(c, qtm::EncodeCommand("Version is 1." + std::to_string(c.minor)));
    }
    int major = 0, minor = 0;
    char dot = 0, extra = 0;
    std::istringstream v(words[1]);
    const bool parsed = (v >> major >> dot >> minor) && dot == '.' && !(v >> extra);
    if (parsed && major == 1 && minor >= 21 && minor <= 28) {
      c.minor = minor;
      return Send(c, qtm::EncodeCommand("Version set to " + words[1]));
    }
    ++counters_.versions_refused;
    return Send(c, qtm::EncodeCommand("Version NOT supported"));
  }
  if (verb == "getparameters") {
    if (words.size() < 2) return error("Parse Error");
    ++counters_.parameters_sent;
    return Send(c, qtm::EncodeText(qtm::PacketType::kXml,
                                   ParametersXml({words.begin() + 1, words.end()}, c.minor)));
  }
  if (verb == "streamframes") {
    if (words.size() < 2) return error("Parse Error");
    const std::string rate = Lower(words[1]);
    if (rate == "stop") {
      c.streaming = false;
      return;
    }
    int64_t divisor = 0;
    if (rate == "allframes") {
      divisor = 1;
    } else if (rate.rfind("frequencydivisor:", 0) == 0) {
      divisor = std::atoll(rate.c_str() + 17);
    } else if (rate.rfind("frequency:", 0) == 0) {
      const double hz = std::atof(rate.c_str() + 10);
      if (hz > 0) divisor = std::max<int64_t>(1, std::llround(options_.rate_hz / hz));
    }
    if (divisor < 1) return error("Parse Error");
    bool m = false, mr = false, b = false, br = false;
    for (size_t i = 2; i < words.size(); ++i) {
      const std::string comp = Lower(words[i]);
      if (comp == "3d")
        m = true;
      else if (comp == "3dres")
        mr = true;
      else if (comp == "6d")
        b = true;
      else if (comp == "6dres")
        br = true;
      else
        return error("Parse Error");  // UDP and components the twin has no data for
    }
    if ((m && mr) || (b && br) || !(m || mr || b || br)) return error("Parse Error");
    c.streaming = true;
    c.divisor = divisor;
    c.markers = m || mr;
    c.markers_res = mr;
    c.bodies = b || br;
    c.bodies_res = br;
    return;  // no reply: the first frame is the answer (§3.5)
  }
  if (verb == "qtmversion") return Send(c, qtm::EncodeCommand("QTM Version is ftcal twin"));
  if (verb == "byteorder") return Send(c, qtm::EncodeCommand("Byte order is little endian"));
  if (verb == "getstate") {
    return Send(c, EventPacket(InAny(options_.faults.no_more_data, tick_) ? 4 : 3));
  }
  return error("Parse Error");
}

std::string QtmEmulator::ParametersXml(const std::vector<std::string>& sections, int minor) const {
  bool general = false, three = false, six = false;
  for (const std::string& s : sections) {
    const std::string l = Lower(s);
    general |= l == "general" || l == "all";
    three |= l == "3d" || l == "all";
    six |= l == "6d" || l == "all";
  }
  pugi::xml_document doc;
  pugi::xml_node root = doc.append_child(("QTM_Parameters_Ver_1." + std::to_string(minor)).c_str());
  const auto text = [](pugi::xml_node parent, const char* name, const std::string& value) {
    parent.append_child(name).text().set(value.c_str());
  };
  if (general) {
    pugi::xml_node g = root.append_child("General");
    std::ostringstream hz;
    hz << options_.rate_hz;
    text(g, "Frequency", hz.str());
    text(g, "Capture_Time", "3600");
    text(g, "Start_On_External_Trigger", "false");
    pugi::xml_node euler = g.append_child("EulerAngles");
    euler.append_attribute("First") = "Roll";
    euler.append_attribute("Second") = "Pitch";
    euler.append_attribute("Third") = "Yaw";
  }
  if (three) {
    pugi::xml_node t = root.append_child("The_3D");
    text(t, "AxisUpwards", "+Z");
    text(t, "CalibrationTime", "2026-11-22 00:00:00");
    text(t, "Labels", std::to_string(options_.labels.size()));
    for (const std::string& name : options_.labels) {
      pugi::xml_node l = t.append_child("Label");
      text(l, "Name", name);
      text(l, "RGBColor", "65280");
      text(l, "Trajectory_Type", "Measured");
    }
    t.append_child("Bones");
  }
  if (six) {
    pugi::xml_node s = root.append_child("The_6D");
    const auto body = [&](const std::string& name, const std::vector<Eigen::Vector3d>& points,
                          const std::vector<std::string>& point_names) {
      pugi::xml_node b = s.append_child("Body");
      text(b, "Name", name);
      text(b, "Enabled", "true");
      pugi::xml_node color = b.append_child("Color");
      color.append_attribute("R") = 0;
      color.append_attribute("G") = 128;
      color.append_attribute("B") = 255;
      text(b, "MaximumResidual", "10");
      text(b, "MinimumMarkersInBody", "3");
      text(b, "BoneLengthTolerance", "5");
      b.append_child("Filter").append_attribute("Preset") = "No filter";
      pugi::xml_node pts = b.append_child("Points");
      for (size_t i = 0; i < points.size(); ++i) {
        pugi::xml_node p = pts.append_child("Point");
        p.append_attribute("X") = points[i].x() * 1000.0;
        p.append_attribute("Y") = points[i].y() * 1000.0;
        p.append_attribute("Z") = points[i].z() * 1000.0;
        p.append_attribute("Virtual") = 0;
        p.append_attribute("PhysicalId") = 0;
        p.append_attribute("Name") = point_names[i].c_str();
      }
      pugi::xml_node origin = b.append_child("Data_origin");
      origin.append_attribute("X") = 0;
      origin.append_attribute("Y") = 0;
      origin.append_attribute("Z") = 0;
      origin.append_attribute("Relative_body") = -1;
      origin.text().set("0");
      pugi::xml_node orient = b.append_child("Data_orientation");
      for (const char* r : {"R11", "R12", "R13", "R21", "R22", "R23", "R31", "R32", "R33"}) {
        orient.append_attribute(r) = (r[1] == r[2]) ? 1 : 0;
      }
      orient.append_attribute("Relative_body") = -1;
      orient.text().set("0");
    };
    const auto wand = [&] {
      body("wand", {{0, 0, 0}, {0.25, 0, 0}, {0.5, 0, 0}}, {"wand_1", "wand_2", "wand_3"});
    };
    if (options_.decoy_body_first && decoy_first_) wand();
    body(options_.body_name, options_.body_points_m,
         options_.body_points_m.empty() ? std::vector<std::string>{} : options_.labels);
    if (options_.decoy_body_first && !decoy_first_) wand();
  }
  std::ostringstream out;
  doc.save(out, "  ", pugi::format_default, pugi::encoding_utf8);
  return out.str();
}

void QtmEmulator::Broadcast(const std::vector<uint8_t>& bytes) {
  for (auto& c : clients_) Send(*c, bytes);
}

bool QtmEmulator::InAny(const std::vector<TickWindow>& windows, int64_t tick) const {
  return std::any_of(windows.begin(), windows.end(),
                     [tick](const TickWindow& w) { return w.Contains(tick); });
}

bool QtmEmulator::StartsAny(const std::vector<TickWindow>& windows, int64_t tick) const {
  return std::any_of(windows.begin(), windows.end(), [tick](const TickWindow& w) {
    return w.num_ticks > 0 && w.first_tick == tick;
  });
}

void QtmEmulator::Tick() {
  const QtmFaults& f = options_.faults;
  const int64_t k = tick_;

  // Connection-level faults first: they decide who hears this tick.
  const bool disconnected = InAny(f.disconnected, k);
  if (StartsAny(f.disconnected, k)) {
    ++counters_.disconnects;
    if (options_.reorder_bodies_on_change) decoy_first_ = !decoy_first_;
    Broadcast(EventPacket(qtm::kEventQtmShuttingDown));
    for (auto& c : clients_) ::close(c->fd);
    clients_.clear();
    CloseListener();
  }
  if (!disconnected && listen_fd_ < 0) Listen();
  if (std::find(f.settings_changed.begin(), f.settings_changed.end(), k) !=
      f.settings_changed.end()) {
    ++counters_.events_sent;
    if (options_.reorder_bodies_on_change) decoy_first_ = !decoy_first_;
    Broadcast(EventPacket(qtm::kEventCameraSettingsChanged));
  }
  const bool no_data = InAny(f.no_more_data, k);
  if (StartsAny(f.no_more_data, k)) {
    for (auto& c : clients_) {
      if (c->streaming) Send(*c, qtm::EncodePacket(int32_t(qtm::PacketType::kNoMoreData), {}));
    }
    ++counters_.no_more_data_sent;
  }
  if (k > 0 && !no_data && InAny(f.no_more_data, k - 1)) {  // a new measurement begins
    frame_base_ = static_cast<int32_t>(k);
    skipped_ = 0;
    ++counters_.events_sent;
    Broadcast(EventPacket(qtm::kEventCaptureStarted));
  }

  std::optional<QtmPose> pose = source_(k);
  if (!pose) {
    source_ended_ = true;
    return;
  }
  ++counters_.ticks;

  // Random draws happen every tick whatever is sent, so a seed gives the same faults however
  // the clients behave.
  std::uniform_real_distribution<double> u(0.0, 1.0);
  if (u(rng_) < f.gap_probability) {
    const int g = std::uniform_int_distribution<int>(1, std::max(1, f.max_gap_frames))(rng_);
    skipped_ += g;
    ++counters_.gaps;
    counters_.frames_skipped += g;
  }
  for (auto& until : marker_dropout_until_) {
    if (u(rng_) < f.marker_dropout_probability) until = k + f.marker_dropout_ticks;
  }
  const bool corrupt = u(rng_) < f.corrupt_probability;

  qtm::DataFrame frame;
  frame.frame_number = static_cast<int32_t>(k - frame_base_ + 1 + skipped_);
  frame.timestamp_us =
      std::llround(1e6 * options_.clock_offset_s + (1.0 + 1e-6 * options_.clock_rate_ppm) *
                                                       static_cast<double>(frame.frame_number - 1) *
                                                       1e6 / options_.rate_hz);
  frame.has_markers = true;
  frame.markers.resize(options_.labels.size());
  for (size_t i = 0; i < frame.markers.size(); ++i) {
    if (i < pose->markers_G_m.size() && k >= marker_dropout_until_[i]) {
      frame.markers[i].p_GoM_G_mm = pose->markers_G_m[i] * 1000.0;  // NaN stays NaN
    }
  }
  frame.has_bodies = true;
  frame.bodies_have_residuals = true;
  qtm::Body wand;  // lying on the floor, never moving
  wand.p_GoBo_G_mm = {1500.0, -800.0, 5.0};
  wand.R_GB.setIdentity();
  wand.residual_mm = 0.3;
  const bool with_wand = options_.decoy_body_first;
  if (with_wand && decoy_first_) frame.bodies.push_back(wand);
  const size_t chassis_index = frame.bodies.size();
  qtm::Body chassis;
  const bool untracked = !pose->body_tracked || InAny(f.untracked, k);
  if (!untracked) {
    chassis.p_GoBo_G_mm = pose->p_GoCo_G_m * 1000.0;
    chassis.R_GB = pose->R_GC;
    chassis.residual_mm = pose->residual_m * 1000.0;
  }
  frame.bodies.push_back(chassis);
  if (with_wand && !decoy_first_) frame.bodies.push_back(wand);

  if (!(no_data || disconnected || InAny(f.silent, k))) {
    // Encoded once per component set the clients asked for.
    std::map<int, std::vector<uint8_t>> packets;
    int sent_to = 0;
    for (auto& c : clients_) {
      if (!c->streaming || k % c->divisor != 0) continue;
      const int key = c->markers * 1 + c->markers_res * 2 + c->bodies * 4 + c->bodies_res * 8;
      auto it = packets.find(key);
      if (it == packets.end()) {
        qtm::DataFrame f_c = frame;
        f_c.has_markers = c->markers;
        f_c.markers_have_residuals = c->markers_res;
        f_c.has_bodies = c->bodies;
        f_c.bodies_have_residuals = c->bodies_res;
        std::vector<uint8_t> bytes = qtm::EncodeData(f_c);
        // Byte 24 is the first component's size field (§3.6): +4 makes it disagree with its
        // item count while the packet's own size still frames it.
        if (corrupt) bytes[24] = static_cast<uint8_t>(bytes[24] + 4);
        it = packets.emplace(key, std::move(bytes)).first;
      }
      Send(*c, it->second);
      ++sent_to;
    }
    if (sent_to > 0) {
      ++counters_.frames_sent;
      counters_.frames_corrupt += corrupt;
      counters_.frames_untracked += untracked;
      if (observer_) {
        // The truth is what the wire carries: decode the uncorrupted full frame.
        const std::vector<uint8_t> full = qtm::EncodeData(frame);
        qtm::Packet packet;
        packet.type = static_cast<int32_t>(qtm::PacketType::kData);
        packet.payload.assign(full.begin() + qtm::kPacketHeaderBytes, full.end());
        const qtm::DataFrame wire = qtm::DecodeData(packet);
        QtmSentFrame sent;
        sent.tick = k;
        sent.frame_number = wire.frame_number;
        sent.timestamp_us = wire.timestamp_us;
        sent.corrupt = corrupt;
        sent.body = wire.bodies[chassis_index];
        sent.markers = wire.markers;
        sent.clients = sent_to;
        observer_(sent);
      }
    }
  }
  ++tick_;
}

void QtmEmulator::Run(int64_t max_ticks, const std::function<bool()>& keep_going) {
  using Clock = std::chrono::steady_clock;
  const auto t0 = Clock::now();
  const int64_t start_tick = tick_;
  const double period_ns = 1e9 / options_.rate_hz;
  std::vector<pollfd> fds;
  while (!stop_.load() && !source_ended_) {
    if (max_ticks >= 0 && tick_ - start_tick >= max_ticks) break;
    if (keep_going && !keep_going()) break;
    const auto deadline =
        t0 + std::chrono::nanoseconds(std::llround(period_ns * double(tick_ - start_tick)));

    fds.clear();
    if (listen_fd_ >= 0) fds.push_back({listen_fd_, POLLIN, 0});
    for (auto& c : clients_) {
      fds.push_back({c->fd, static_cast<short>(POLLIN | (c->out.empty() ? 0 : POLLOUT)), 0});
    }
    const auto wait = std::clamp<int64_t>(
        std::chrono::duration_cast<std::chrono::nanoseconds>(deadline - Clock::now()).count(), 0,
        100'000'000);
    const timespec ts{static_cast<time_t>(wait / 1'000'000'000),
                      static_cast<long>(wait % 1'000'000'000)};
    const int ready = ::ppoll(fds.data(), fds.size(), &ts, nullptr);
    if (ready > 0) {
      size_t i = 0;
      if (listen_fd_ >= 0 && fds[i++].revents & POLLIN) Accept();
      for (; i < fds.size(); ++i) {
        auto it = std::find_if(clients_.begin(), clients_.end(),
                               [&](const auto& c) { return c->fd == fds[i].fd; });
        if (it == clients_.end()) continue;
        Client& c = **it;
        if (fds[i].revents & POLLOUT) Flush(c);
        if (fds[i].revents & (POLLIN | POLLHUP | POLLERR)) ReadClient(c);
      }
    }
    if (Clock::now() >= deadline) Tick();
    for (auto it = clients_.begin(); it != clients_.end();) {
      if ((*it)->dead) {
        ::close((*it)->fd);
        it = clients_.erase(it);
      } else {
        ++it;
      }
    }
  }
}

}  // namespace ftcal::sim
