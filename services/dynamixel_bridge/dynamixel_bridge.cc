#include "dynamixel_bridge.h"

#include <poll.h>

#include <algorithm>
#include <type_traits>
#include <cmath>
#include <limits>
#include <stdexcept>

#include <spdlog/fmt/fmt.h>

#include "common/bus.h"

namespace ftcal {
namespace {

// Addresses 64-98 in one SYNC READ: Torque Enable (64), Hardware Error Status (70) ... Bus
// Watchdog (98), whose expiry is as much a reason to look as a hardware error.
constexpr std::uint16_t kErrorBlockAddress = dxl::kAddrTorqueEnable;
constexpr std::uint16_t kErrorBlockBytes = dxl::kAddrBusWatchdog - dxl::kAddrTorqueEnable + 1;
// Past half a wrap of the 15-bit tick the direction of a change is ambiguous: the next tick
// is taken as it comes and the unwrapper starts again.
constexpr double kTickUnwrapMaxGapS = 16.0;
// A tick change of less than half a wrap is forward (§2.9: the tick wraps at 32768 ms).
constexpr std::uint16_t kTickHalfWrap = 0x4000;
}  // namespace

DynamixelBridge::DynamixelBridge(const config::Config& config, DynamixelBridgeOptions options,
                                 ServiceStats& stats, Publisher publish,
                                 std::function<int64_t()> now_utime)
    : config_(config),
      options_(std::move(options)),
      stats_(stats),
      publish_(std::move(publish)),
      now_utime_(std::move(now_utime)),
      parser_(1024),
      reopen_delay_s_(options_.reopen_min_s) {
  if (!config_.has_dynamixel()) throw std::invalid_argument("the config has no dynamixel section");
  device_ = options_.device.empty() ? config_.dynamixel().device() : options_.device;
  if (device_.empty()) throw std::invalid_argument("dynamixel.device is empty");
  baud_ = config_.dynamixel().baud();
  reply_timeout_s_ = config_.dynamixel().reply_timeout_s();
  if (!(reply_timeout_s_ > 0 && reply_timeout_s_ < 1)) {
    throw std::invalid_argument("dynamixel.reply_timeout_s must be in (0, 1) s");
  }
  if (options_.hardware_error_every < 1) {
    throw std::invalid_argument("hardware_error_every must be >= 1");
  }
  if (options_.lost_after_misses < 1) throw std::invalid_argument("lost_after_misses must be >= 1");
  if (!(options_.reprobe_every_s > 0)) throw std::invalid_argument("reprobe_every_s must be > 0");
  if (baud_ == 0) throw std::invalid_argument("dynamixel.baud is 0");
  // Throws for a bad operating mode or watchdog.
  setup_.emplace(config_, stats_, static_cast<ServoSetup::Link&>(*this));
  for (SetupServo& who : ServosFromConfig(config_)) servos_.emplace_back(std::move(who));
  // SERVO_STATE carries exactly six servos (lcmtypes/servo_state_t.lcm: one per leg).
  constexpr std::size_t kServos = std::extent_v<decltype(servo_state_t::id)>;
  if (servos_.size() != kServos) {
    throw std::invalid_argument("the config's legs: " + std::to_string(servos_.size()) +
                                " have servos; SERVO_STATE carries exactly " +
                                std::to_string(kServos));
  }
}

std::vector<std::size_t> DynamixelBridge::ActiveSlots() const {
  std::vector<std::size_t> slots;
  for (std::size_t i = 0; i < servos_.size(); ++i) {
    if (!servos_[i].lost) slots.push_back(i);
  }
  return slots;
}

std::vector<std::uint8_t> DynamixelBridge::IdsOf(const std::vector<std::size_t>& slots) const {
  std::vector<std::uint8_t> ids;
  ids.reserve(slots.size());
  for (const std::size_t i : slots) ids.push_back(servos_[i].id);
  return ids;
}

std::vector<std::uint8_t> DynamixelBridge::lost() const {
  std::vector<std::uint8_t> ids;
  for (const auto& s : servos_) {
    if (s.lost) ids.push_back(s.id);
  }
  return ids;
}

DynamixelBridge::ServoSlot* DynamixelBridge::FindId(std::uint8_t id) {
  for (auto& s : servos_) {
    if (s.id == id) return &s;
  }
  return nullptr;
}

bool DynamixelBridge::Connect() {
  try {
    port_ = std::make_unique<dxl::SerialPort>(device_, baud_);
  } catch (const dxl::SerialError& e) {
    stats_.Error("serial port cannot be opened", e.what());
    down_reason_ = e.what();
    next_reopen_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(reopen_delay_s_));
    reopen_delay_s_ = std::min(options_.reopen_max_s, 2 * reopen_delay_s_);
    return false;
  }
  ++stats_.Counter("port_opens");
  reopen_delay_s_ = options_.reopen_min_s;
  down_reason_.clear();
  parser_ = dxl::PacketParser(1024);
  synced_ = {};
  stats_.log().info("opened {} at {} bit/s", device_, baud_);

  missing_at_start_.clear();
  for (std::size_t i = 0; i < servos_.size(); ++i) {
    ServoSlot& s = servos_[i];
    // A new port session: the ticks seen before it say nothing about the next one (the outage
    // may have been longer than a wrap, or the servos rebooted).
    s.ticks.Reset();
    sample_clock_.Reset(static_cast<int>(i));
    s.tick_known = false;
    s.lost = false;
    s.probe_outstanding = false;
    s.consecutive_misses = 0;
    const bool got = Request(i, dxl::BuildPing(s.id), kPingParams, [&](const dxl::StatusPacket& p) {
      return setup_->PingAnswered(i, p);
    });
    if (!port_) return false;
    if (!got) {
      missing_at_start_.push_back(s.id);
      stats_.Error(ServoName(s.id, s.leg) + " missing",
                   ServoName(s.id, s.leg) + " does not answer PING on " + device_);
      // Not read each cycle until a PING finds it.
      s.lost = true;
      s.next_probe = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                        std::chrono::duration<double>(options_.reprobe_every_s));
    }
  }
  setup_->ReadReturnDelays(ActiveSlots());
  if (!port_) return false;
  for (auto& s : servos_) {  // a new session: what was read may be old
    s.mode_checked = false;
    s.limits_checked = false;
  }
  setup_->CheckFound();
  if (!port_) return false;
  if (missing_at_start_.empty()) {
    stats_.log().info("all {} servos answer PING", servos_.size());
  }
  return true;
}

void DynamixelBridge::PortLost(const std::string& why) {
  port_.reset();
  ++stats_.Counter("port_lost");
  stats_.Error("serial port lost", why);
  down_reason_ = why;
  next_reopen_ = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                    std::chrono::duration<double>(reopen_delay_s_));
}

void DynamixelBridge::SyncParserStats() {
  const auto& now = parser_.stats();
  for (auto n = synced_.crc_errors; n < now.crc_errors; ++n) {
    stats_.Drop("CRC error", "a status packet failed its CRC");
  }
  for (auto n = synced_.malformed; n < now.malformed; ++n) {
    stats_.Drop("malformed packet", "bad length, id or stuffing, or not a status packet");
  }
  stats_.Counter("crc_errors") += static_cast<std::int64_t>(now.crc_errors - synced_.crc_errors);
  stats_.Counter("malformed") += static_cast<std::int64_t>(now.malformed - synced_.malformed);
  stats_.Counter("noise_bytes") += static_cast<std::int64_t>(now.noise_bytes - synced_.noise_bytes);
  stats_.Counter("timeouts") += static_cast<std::int64_t>(now.timeouts - synced_.timeouts);
  synced_ = now;
}

std::vector<bool> DynamixelBridge::Transact(
    const std::vector<std::uint8_t>& packet, const std::vector<std::size_t>& slots,
    std::size_t reply_params,
    const std::function<bool(std::size_t, const dxl::StatusPacket&)>& on_reply) {
  std::vector<bool> got(slots.size(), false);
  if (!port_ || slots.empty()) return got;
  // The replies follow one another on the bus, each after its servo's return delay: waiting
  // longer only lets one silent servo eat the other servos' cycle (§2.9).
  double budget_s = dxl::WireSeconds(packet.size(), baud_) + reply_timeout_s_;
  for (const std::size_t i : slots) {
    budget_s += dxl::WireSeconds(dxl::MaxStatusPacketBytes(reply_params), baud_) +
                servos_[i].return_delay_s;
  }
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                           std::chrono::duration<double>(budget_s));
  try {
    // A reply that missed its deadline must not pass for the answer to this request.
    DrainLate();
    port_->WriteAll(packet.data(), packet.size(), 100);
    last_traffic_ = Clock::now();
    std::size_t remaining = slots.size();
    std::uint8_t buf[1024];
    while (remaining > 0) {
      const auto left = deadline - Clock::now();
      if (left <= Clock::duration::zero()) break;
      const auto ns = std::chrono::duration_cast<std::chrono::nanoseconds>(left).count();
      timespec ts{static_cast<time_t>(ns / 1'000'000'000), static_cast<long>(ns % 1'000'000'000)};
      pollfd p{port_->fd(), POLLIN, 0};
      if (::ppoll(&p, 1, &ts, nullptr) <= 0) continue;
      const std::size_t n = port_->ReadSome(buf, sizeof buf);
      parser_.Feed(buf, n);
      while (auto status = parser_.NextStatus()) {
        std::size_t k = 0;
        while (k < slots.size() && servos_[slots[k]].id != status->id) ++k;
        if (k == slots.size() || got[k]) {
          if (ProbeAnswered(*status)) continue;
          ++stats_.Counter("unexpected_replies");
          stats_.Drop("unexpected status packet",
                      "status from id " + std::to_string(status->id) + " that was not asked");
          continue;
        }
        if (status->error_number() == 0 && status->params.size() != reply_params) {
          // Protocol 2.0 replies carry no request number: the size tells which request a
          // reply answers, and this one answers an earlier one.
          ++stats_.Counter("mismatched_replies");
          stats_.Drop("status packet of another request",
                      "status from id " + std::to_string(status->id) + " with " +
                          std::to_string(status->params.size()) + " bytes, expected " +
                          std::to_string(reply_params) + ": a late reply to an earlier request");
          continue;
        }
        if (on_reply(k, *status)) {
          got[k] = true;
          --remaining;
        }
      }
    }
    if (remaining > 0) parser_.Timeout();
  } catch (const dxl::SerialError& e) {
    PortLost(e.what());
  }
  SyncParserStats();
  return got;
}

void DynamixelBridge::Reprobe() {
  const auto now = Clock::now();
  for (std::size_t i = 0; i < servos_.size(); ++i) {
    ServoSlot& s = servos_[i];
    if (!s.lost || now < s.next_probe) continue;
    // Sent, not waited for: the answer is picked up between cycles (OnDeviceReadable) or at
    // the start of the next read, so a probe of a silent servo costs the others nothing.
    const auto ping = dxl::BuildPing(s.id);
    try {
      DrainLate();
      port_->WriteAll(ping.data(), ping.size(), 100);
      last_traffic_ = Clock::now();
    } catch (const dxl::SerialError& e) {
      PortLost(e.what());
      return;
    }
    ++stats_.Counter("reprobes");
    s.probe_outstanding = true;
    s.next_probe = now + std::chrono::duration_cast<Clock::duration>(
                             std::chrono::duration<double>(options_.reprobe_every_s));
    return;  // one probe per cycle: their replies must not collide on the bus
  }
}

bool DynamixelBridge::ProbeAnswered(const dxl::StatusPacket& status) {
  ServoSlot* s = FindId(status.id);
  if (s == nullptr || !s->lost || !s->probe_outstanding || status.error_number() != 0 ||
      status.params.size() != kPingParams) {
    return false;
  }
  s->lost = false;
  s->probe_outstanding = false;
  s->consecutive_misses = 0;
  // Its tick goes on from where it was unless it was gone too long to tell (ReadPresent).
  s->tick_known = false;
  // It may have been swapped, reflashed or power-cycled while it was gone: its mode and limits
  // are read again.
  s->mode_checked = false;
  s->limits_checked = false;
  force_error_read_ = true;
  ++stats_.Counter("servos_found");
  stats_.log().info("{} answers again: read each cycle", ServoName(s->id, s->leg));
  return true;
}

void DynamixelBridge::SendPendingWrites() {
  std::vector<std::pair<std::uint8_t, std::vector<std::uint8_t>>> torque;
  std::vector<std::pair<std::uint8_t, std::int32_t>> goals;
  for (auto& s : servos_) {
    if (s.pending_torque) {
      torque.push_back({s.id, {static_cast<std::uint8_t>(*s.pending_torque ? 1 : 0)}});
      s.pending_torque.reset();
    }
    if (s.goal_count) {
      goals.emplace_back(s.id, *s.goal_count);
      s.goal_count.reset();
    }
  }
  if (!port_ || (torque.empty() && goals.empty())) return;
  try {
    // Torque first: a goal written before the enable would be ignored by a servo still off.
    if (!torque.empty()) {
      const auto p = dxl::BuildSyncWrite(dxl::kAddrTorqueEnable, 1, torque);
      port_->WriteAll(p.data(), p.size(), 100);
      stats_.Counter("torque_writes") += static_cast<std::int64_t>(torque.size());
      force_error_read_ = true;
    }
    if (!goals.empty()) {
      const auto p = dxl::BuildSyncWriteGoalPosition(goals);
      port_->WriteAll(p.data(), p.size(), 100);
      last_traffic_ = Clock::now();
      stats_.Counter("goal_writes") += static_cast<std::int64_t>(goals.size());
    }
  } catch (const dxl::SerialError& e) {
    PortLost(e.what());
  }
}

bool DynamixelBridge::Request(std::size_t i, const std::vector<std::uint8_t>& packet,
                              std::size_t reply_params,
                              const std::function<bool(const dxl::StatusPacket&)>& on_reply) {
  return Transact(packet, {i}, reply_params,
                  [&](std::size_t, const dxl::StatusPacket& p) { return on_reply(p); })[0];
}

void DynamixelBridge::ReadPresent(std::vector<bool>* fresh) {
  const auto now = Clock::now();
  fresh->assign(servos_.size(), false);
  const std::vector<std::size_t> slots = ActiveSlots();
  std::vector<bool> repeated(servos_.size(), false);
  // The servos sample a constant bus time after the request: the read's instant (Publish).
  read_request_utime_ = now_utime_();
  const std::vector<bool> got =
      slots.empty()
          ? std::vector<bool>{}
          : Transact(
                dxl::BuildSyncRead(dxl::kAddrPresentBlock, dxl::kPresentBlockBytes, IdsOf(slots)),
                slots, dxl::kPresentBlockBytes, [&](std::size_t k, const dxl::StatusPacket& p) {
                  const std::size_t i = slots[k];
                  ServoSlot& s = servos_[i];
                  if (p.error_number() != 0) {
                    ++stats_.Counter("status_errors");
                    stats_.Drop(ServoName(s.id, s.leg) + ": " + dxl::DescribeStatusError(p.error),
                                "the reply to the present-block read carries an error; its data is "
                                "not used");
                    return false;
                  }
                  const dxl::PresentState st =
                      dxl::DecodePresentBlock(p.params.data(), p.params.size());
                  if (s.ever_read &&
                      now - s.last_read > std::chrono::duration_cast<Clock::duration>(
                                              std::chrono::duration<double>(kTickUnwrapMaxGapS))) {
                    s.ticks.Reset();
                    sample_clock_.Reset(static_cast<int>(i));
                    s.tick_known = false;
                  }
                  // Protocol 2.0 has no sequence number: under load a reply that missed its
                  // deadline can arrive during the next request and look like its answer. The
                  // Realtime Tick is the only witness: a block whose tick is not after the last one
                  // accepted is that late reply (or a second read within one ms, which says nothing
                  // new either): this cycle publishes that servo STALE rather than an old sample as
                  // new.
                  const std::uint16_t forward =
                      static_cast<std::uint16_t>((st.realtime_tick_ms - s.last_raw_tick) & 0x7FFF);
                  if (s.tick_known && (forward == 0 || forward >= kTickHalfWrap)) {
                    const bool same = forward == 0;
                    ++stats_.Counter(same ? "repeated_tick" : "backward_tick");
                    stats_.Drop(same ? "repeated Realtime Tick" : "Realtime Tick went backwards",
                                ServoName(s.id, s.leg) + " sent a present block with tick " +
                                    std::to_string(st.realtime_tick_ms) + " after " +
                                    std::to_string(s.last_raw_tick) +
                                    " (a late reply); not published as new");
                    repeated[i] = true;
                    return true;
                  }
                  s.last_raw_tick = st.realtime_tick_ms;
                  s.tick_known = true;
                  s.ever_read = true;
                  s.last_read = now;
                  s.angle_rad = dxl::PositionToRad(st.present_position, s.zero_count, s.direction);
                  s.velocity_rad_s = s.direction * dxl::VelocityToRadPerS(st.present_velocity);
                  s.current_a = s.direction * dxl::CurrentToA(st.present_current);
                  s.tick_ms = s.ticks.Update(st.realtime_tick_ms);
                  if (p.alert() && !s.alert) {
                    ++stats_.Counter("hw_error_alerts");
                    stats_.Error(ServoName(s.id, s.leg) + " hardware error",
                                 ServoName(s.id, s.leg) + " raised its Alert bit");
                    force_error_read_ = true;  // what the error is: read it this cycle
                  }
                  s.alert = p.alert();
                  s.consecutive_misses = 0;
                  stats_.CountIn();
                  return true;
                });
  std::vector<bool> asked(servos_.size(), false);
  for (std::size_t k = 0; k < slots.size(); ++k) {
    asked[slots[k]] = true;
    (*fresh)[slots[k]] = got[k] && !repeated[slots[k]];
  }
  for (std::size_t i = 0; i < servos_.size(); ++i) {
    ServoSlot& s = servos_[i];
    if ((*fresh)[i]) continue;
    ++stats_.Counter("stale");
    // Left out of this read because it was lost when the read was sent: a lost cycle, not a
    // miss, even when a late answer to its PING found it again during the read (Transact drains
    // and hands such answers to ProbeAnswered); counted as a miss it was a STALE that no reply
    // accounted for, and a step towards losing a servo that had just come back.
    if (!asked[i]) {
      ++stats_.Counter("lost_cycles");
      continue;
    }
    ++s.consecutive_misses;
    stats_.Drop(ServoName(s.id, s.leg) + " no valid reply",
                "no valid reply this cycle: published STALE with its last good values");
    if (s.consecutive_misses >= options_.lost_after_misses && port_) {
      s.lost = true;
      s.next_probe = now + std::chrono::duration_cast<Clock::duration>(
                               std::chrono::duration<double>(options_.reprobe_every_s));
      ++stats_.Counter("servos_lost");
      stats_.Error(ServoName(s.id, s.leg) + " lost",
                   ServoName(s.id, s.leg) + " gave no valid reply in " +
                       std::to_string(s.consecutive_misses) +
                       fmt::format(" cycles: left out of the reads, PINGed every {} s",
                                   options_.reprobe_every_s));
    }
  }
}

void DynamixelBridge::ReadHardwareErrors() {
  const std::vector<std::size_t> slots = ActiveSlots();
  if (slots.empty()) return;
  Transact(dxl::BuildSyncRead(kErrorBlockAddress, kErrorBlockBytes, IdsOf(slots)), slots,
           kErrorBlockBytes, [&](std::size_t k, const dxl::StatusPacket& p) {
             ServoSlot& s = servos_[slots[k]];
             if (p.error_number() != 0) {
               ++stats_.Counter("status_errors");
               stats_.Drop(ServoName(s.id, s.leg) + " bad hardware-error reply",
                           "error '" + dxl::DescribeStatusError(p.error) + "'");
               return false;
             }
             s.torque_enable = p.params[0];
             const int hw = p.params[dxl::kAddrHardwareErrorStatus - kErrorBlockAddress];
             if (p.params[dxl::kAddrBusWatchdog - kErrorBlockAddress] == dxl::kBusWatchdogExpired) {
               s.watchdog_expired = true;
             }
             if (hw != 0 && hw != s.hardware_error) {
               stats_.Error(ServoName(s.id, s.leg) + " hardware error status",
                            ServoName(s.id, s.leg) + " reports Hardware Error Status " +
                                std::to_string(hw) +
                                " (bit 0 voltage, 2 overheating, 3 encoder, "
                                "4 electrical shock, 5 overload)");
             }
             s.hardware_error = hw;
             s.alert = p.alert();
             return true;
           });
}

void DynamixelBridge::Cycle() {
  if (!port_) {
    if (Clock::now() < next_reopen_) return;
    if (!Connect()) return;
    ++stats_.Counter("reopens");
  }
  ++cycles_;
  ++stats_.Counter("cycles");
  // Before any goal: a servo found again must not take a goal in a mode not checked.
  setup_->CheckFound();
  if (!port_) return;
  // A gap in the bridge's own traffic (it was stopped, or a cycle stalled) long enough for a
  // watchdog to have run out: look now, not at the next scheduled error read, so that the gate
  // hears of it before it takes another command.
  if (Clock::now() - last_traffic_ > std::chrono::duration_cast<Clock::duration>(
                                         std::chrono::duration<double>(setup_->watchdog_s() / 2))) {
    force_error_read_ = true;
  }
  SendPendingWrites();
  std::vector<bool> fresh;
  ReadPresent(&fresh);
  // Torque Enable and Hardware Error Status change rarely and the Alert bit of every present
  // reply says when to look: a low rate, not every cycle, even while a servo is in error.
  const bool want_errors = force_error_read_ || cycles_ % options_.hardware_error_every == 1 ||
                           options_.hardware_error_every == 1;
  if (port_ && want_errors) {
    force_error_read_ = false;
    ReadHardwareErrors();
  }
  for (std::size_t i = 0; port_ && i < servos_.size(); ++i) {
    if (!servos_[i].watchdog_expired) continue;
    servos_[i].watchdog_expired = false;
    setup_->ClearExpiredWatchdog(i);
  }
  if (port_) Reprobe();
  if (!port_) return;  // lost during the cycle: nothing trustworthy to publish
  last_fresh_ = fresh;
  Publish(now_utime_(), fresh);
}

void DynamixelBridge::DrainLate() {
  std::uint8_t buf[1024];
  while (const std::size_t n = port_->ReadSome(buf, sizeof buf)) {
    // Nobody is being asked: whatever comes is a late reply or noise.
    parser_.Feed(buf, n);
    while (auto status = parser_.NextStatus()) {
      if (ProbeAnswered(*status)) continue;
      ++stats_.Counter("late_replies");
      stats_.Drop("late status packet",
                  "status from id " + std::to_string(status->id) + " after its deadline");
    }
  }
}

void DynamixelBridge::OnDeviceReadable() {
  if (!port_) return;
  try {
    DrainLate();
  } catch (const dxl::SerialError& e) {
    PortLost(e.what());
  }
  SyncParserStats();
}

void DynamixelBridge::OnCommand(const servo_command_t& cmd) {
  if (cmd.num_servos < 0 || static_cast<std::size_t>(cmd.num_servos) != cmd.id.size()) {
    throw BadInput("servo_command_t inconsistent", "num_servos does not match the arrays");
  }
  // Validate everything before applying anything: a command is taken whole or not at all.
  std::vector<std::pair<ServoSlot*, std::optional<std::int32_t>>> plan;
  for (std::size_t i = 0; i < cmd.id.size(); ++i) {
    const int id = cmd.id[i];
    ServoSlot* s = (id >= 0 && id <= dxl::kMaxId) ? FindId(static_cast<std::uint8_t>(id)) : nullptr;
    if (s == nullptr) {
      throw BadInput("servo_command_t unknown id",
                     "SERVO_CMD names servo id " + std::to_string(id) + ", not in the config");
    }
    std::optional<std::int32_t> count;
    if (cmd.torque_enable) {
      const double goal = cmd.goal_angle_rad[i];
      if (!std::isfinite(goal)) {
        throw BadInput("servo_command_t non-finite goal",
                       "SERVO_CMD goal for " + ServoName(s->id, s->leg) + " is not finite");
      }
      count = setup_->Goal(*s, goal);
    }
    plan.emplace_back(s, count);
  }
  for (auto& [s, count] : plan) {
    s->pending_torque = cmd.torque_enable;
    s->goal_count = count;
  }
  ++stats_.Counter("commands");
}

bool DynamixelBridge::Degraded(std::string* why) const {
  std::string reason;
  if (!port_) {
    reason = "port " + device_ + " down" + (down_reason_.empty() ? "" : ": " + down_reason_);
  } else {
    for (std::size_t i = 0; i < servos_.size(); ++i) {
      const ServoSlot& s = servos_[i];
      if (s.lost) {
        reason += (reason.empty() ? "" : "; ") + ServoName(s.id, s.leg) +
                  fmt::format(" lost (PINGed every {} s)", options_.reprobe_every_s);
      } else if (i < last_fresh_.size() && !last_fresh_[i]) {
        reason += (reason.empty() ? "" : "; ") + ServoName(s.id, s.leg) + " not answering";
      } else if (s.hardware_error != 0 || s.alert) {
        reason += (reason.empty() ? "" : "; ") + ServoName(s.id, s.leg) + " hardware error";
      } else if (s.mode_checked && !s.mode_ok) {
        reason += (reason.empty() ? "" : "; ") + ServoName(s.id, s.leg) + " in Operating Mode " +
                  std::to_string(s.mode) + ", not " + std::to_string(setup_->operating_mode());
      } else if (!s.limits_error.empty()) {
        reason += (reason.empty() ? "" : "; ") + s.limits_error;
      }
    }
  }
  if (why) *why = reason;
  return !reason.empty();
}

}  // namespace ftcal
