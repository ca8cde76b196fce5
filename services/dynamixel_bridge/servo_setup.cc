#include "servo_setup.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include <spdlog/fmt/fmt.h>

#include "common/bus.h"

namespace ftcal {
namespace {

// The limits' read: Acceleration Limit (40) ... Goal Position (116-119), one READ that covers
// every register the bridge sets, and Torque Enable (64).
constexpr std::uint16_t kLimitBlockAddress = dxl::kAddrAccelerationLimit;
constexpr std::uint16_t kLimitBlockBytes = dxl::kAddrGoalPosition + 4 - kLimitBlockAddress;
constexpr std::uint16_t kAddrPresentPosition = 132;

}  // namespace

std::string ServoName(std::uint8_t id, const std::string& leg) {
  return "servo " + std::to_string(id) + " (" + leg + ")";
}

ServoSetup::ServoSetup(const config::Config& config, ServiceStats& stats, Link& link)
    : stats_(stats), link_(link) {
  const config::DynamixelBus& dxl_config = config.dynamixel();
  switch (dxl_config.operating_mode()) {
    case config::POSITION_MODE:
      operating_mode_ = dxl::kPositionMode;
      min_goal_count_ = dxl::kPositionModeMinCount;
      max_goal_count_ = dxl::kPositionModeMaxCount;
      break;
    case config::EXTENDED_POSITION_MODE:
      operating_mode_ = dxl::kExtendedPositionMode;
      min_goal_count_ = -dxl::kExtendedModeMaxCount;
      max_goal_count_ = dxl::kExtendedModeMaxCount;
      break;
    default:
      throw std::invalid_argument("dynamixel.operating_mode " +
                                  std::to_string(dxl_config.operating_mode()) +
                                  " is not POSITION_MODE or EXTENDED_POSITION_MODE");
  }
  mode_name_ = config::DynamixelOperatingMode_Name(dxl_config.operating_mode());
  // Register units (docs/device-protocols.md §2.7), rounded down so that the servo never goes
  // faster than the config says; above a register's range it holds its maximum.
  const double velocity_unit_rad_s = dxl::kVelocityUnitRpm * 2 * M_PI / 60;
  const double acceleration_unit_rad_s2 = dxl::kAccelerationUnitRevPerMin2 * 2 * M_PI / 3600;
  velocity_limit_ = static_cast<std::uint32_t>(
      std::clamp(std::floor(dxl_config.max_velocity_rad_s() / velocity_unit_rad_s + 1e-9), 1.0,
                 static_cast<double>(dxl::kMaxVelocityLimit)));
  acceleration_limit_ = static_cast<std::uint32_t>(
      std::clamp(std::floor(dxl_config.max_acceleration_rad_s2() / acceleration_unit_rad_s2 + 1e-9),
                 1.0, static_cast<double>(dxl::kMaxAccelerationLimit)));
  watchdog_s_ = dxl_config.bus_watchdog_s();
  const double units = std::round(watchdog_s_ / dxl::kBusWatchdogUnitS);
  if (!(units >= 1 && units <= 127)) {
    throw std::invalid_argument("dynamixel.bus_watchdog_s " + std::to_string(watchdog_s_) +
                                " is not 1-127 units of 20 ms");
  }
  watchdog_units_ = static_cast<std::uint8_t>(units);
}

std::vector<SetupServo> ServosFromConfig(const config::Config& config) {
  std::vector<SetupServo> servos;
  for (const auto& leg : config.robot().leg()) {
    SetupServo s;
    s.leg = leg.name();
    s.id = static_cast<std::uint8_t>(leg.servo().id());
    s.zero_count = leg.servo().zero_count();
    s.direction = leg.servo().direction();
    if (s.direction != 1 && s.direction != -1) {
      throw std::invalid_argument("leg " + s.leg + " servo direction must be +1 or -1");
    }
    s.min_angle_rad = leg.servo().min_angle_rad();
    s.max_angle_rad = leg.servo().max_angle_rad();
    servos.push_back(std::move(s));
  }
  return servos;
}

bool ServoSetup::PingAnswered(std::size_t i, const dxl::StatusPacket& p) {
  if (p.params.size() != kPingParams) return false;
  const SetupServo& s = link_.servo(i);
  const int model = p.params[0] | (p.params[1] << 8);
  if (model != 321) {
    stats_.Error(
        ServoName(s.id, s.leg) + " is not an MX-106(2.0)",
        ServoName(s.id, s.leg) + " reports model " + std::to_string(model) + ", expected 321");
  }
  return true;
}

void ServoSetup::ReadReturnDelays(const std::vector<std::size_t>& slots) {
  for (const std::size_t i : slots) {
    SetupServo& s = link_.servo(i);
    link_.Request(i, dxl::BuildRead(s.id, dxl::kAddrReturnDelayTime, 1), 1,
                  [&](const dxl::StatusPacket& p) {
                    if (p.error_number() != 0) return false;
                    s.return_delay_s = p.params[0] * dxl::kReturnDelayUnitS;
                    return true;
                  });
    if (!link_.port_open()) return;
  }
}

void ServoSetup::CheckFound() {
  std::vector<std::size_t> unchecked;
  for (const std::size_t i : link_.active()) {
    if (!link_.servo(i).mode_checked) unchecked.push_back(i);
  }
  if (!unchecked.empty()) CheckOperatingModes(unchecked);
  if (!link_.port_open()) return;
  for (const std::size_t i : link_.active()) {
    const SetupServo& s = link_.servo(i);
    if (s.mode_checked && !s.limits_checked) CheckLimits(i);
    if (!link_.port_open()) return;
  }
}

std::optional<std::uint8_t> ServoSetup::ReadByte(std::size_t i, std::uint16_t address) {
  std::optional<std::uint8_t> value;
  link_.Request(i, dxl::BuildRead(link_.servo(i).id, address, 1), 1,
                [&](const dxl::StatusPacket& p) {
                  if (p.error_number() != 0) return false;
                  value = p.params[0];
                  return true;
                });
  return value;
}

void ServoSetup::CheckOperatingModes(const std::vector<std::size_t>& slots) {
  const std::string want =
      std::to_string(operating_mode_) + " (" + mode_name_ + ", dynamixel.operating_mode)";
  for (const std::size_t i : slots) {
    SetupServo& s = link_.servo(i);
    if (s.mode_checked) continue;
    const std::optional<std::uint8_t> mode = ReadByte(i, dxl::kAddrOperatingMode);
    if (!link_.port_open()) return;
    if (!mode) continue;  // no answer: tried again next cycle
    s.mode_checked = true;
    s.mode = *mode;
    s.mode_ok = *mode == operating_mode_;
    if (s.mode_ok) continue;
    const std::string name = ServoName(s.id, s.leg);
    // Operating Mode is EEPROM, writable only with torque off; switching a servo that holds a
    // leg would drop it, so a servo with torque on is left alone (and not commanded).
    const std::optional<std::uint8_t> torque = ReadByte(i, dxl::kAddrTorqueEnable);
    if (!link_.port_open()) return;
    if (!torque || *torque != 0) {
      ++stats_.Counter("wrong_operating_mode");
      stats_.Error(name + " in the wrong operating mode",
                   name + " is in Operating Mode " + std::to_string(*mode) + ", not " + want +
                       (torque ? ", with torque on: not switched (it would drop the leg); its "
                                 "goals are refused until torque is off and the bridge restarts"
                               : ", and its Torque Enable cannot be read: not switched; its goals "
                                 "are refused"));
      continue;
    }
    bool written = false;
    link_.Request(i, dxl::BuildWrite(s.id, dxl::kAddrOperatingMode, {operating_mode_}), 0,
                  [&](const dxl::StatusPacket& p) {
                    written = p.error_number() == 0;
                    if (!written) {
                      stats_.Error(name + " refused its operating mode",
                                   name + " refused Operating Mode " + want + ": " +
                                       dxl::DescribeStatusError(p.error));
                    }
                    return true;
                  });
    if (!link_.port_open()) return;
    const std::optional<std::uint8_t> now =
        written ? ReadByte(i, dxl::kAddrOperatingMode) : std::nullopt;
    if (!link_.port_open()) return;
    s.mode = now ? *now : -1;
    s.mode_ok = now && *now == operating_mode_;
    if (s.mode_ok) {
      ++stats_.Counter("operating_mode_writes");
      stats_.log().info("{}: Operating Mode {} -> {}", name, *mode, want);
    } else {
      ++stats_.Counter("wrong_operating_mode");
      stats_.Error(name + " in the wrong operating mode",
                   name + " is in Operating Mode " + std::to_string(*mode) +
                       " and could not be set to " + want + ": its goals are refused");
    }
  }
}

std::optional<std::vector<std::uint8_t>> ServoSetup::ReadBlock(std::size_t i, std::uint16_t address,
                                                               std::uint16_t length) {
  std::optional<std::vector<std::uint8_t>> block;
  link_.Request(i, dxl::BuildRead(link_.servo(i).id, address, length), length,
                [&](const dxl::StatusPacket& p) {
                  if (p.error_number() != 0) return false;
                  block = p.params;
                  return true;
                });
  return block;
}

std::optional<std::uint8_t> ServoSetup::WriteItem(std::size_t i, std::uint16_t address,
                                                  std::uint32_t value, int size) {
  std::vector<std::uint8_t> data;
  data.reserve(static_cast<std::size_t>(size));
  for (int k = 0; k < size; ++k) data.push_back(static_cast<std::uint8_t>(value >> (8 * k)));
  std::optional<std::uint8_t> error;
  link_.Request(i, dxl::BuildWrite(link_.servo(i).id, address, data), 0,
                [&](const dxl::StatusPacket& p) {
                  error = p.error_number();
                  return true;
                });
  return error;
}

std::vector<ServoSetup::LimitItem> ServoSetup::LimitsFor(std::size_t i) {
  const SetupServo& s = link_.servo(i);
  std::vector<LimitItem> items = {
      {"Acceleration Limit", dxl::kAddrAccelerationLimit, 4, true, acceleration_limit_},
      {"Velocity Limit", dxl::kAddrVelocityLimit, 4, true, velocity_limit_},
  };
  // Only Position mode uses them; Extended Position mode ignores them (§2.7), so there they
  // are left as they are and the bridge's clamp is the position limit.
  if (operating_mode_ == dxl::kPositionMode) {
    // Angle limits beyond one turn are the mode's range (goals past it are refused anyway).
    const auto count = [&](double rad) {
      return std::clamp(dxl::RadToPosition(rad, s.zero_count, s.direction),
                        dxl::kPositionModeMinCount, dxl::kPositionModeMaxCount);
    };
    const std::int32_t a = count(s.min_angle_rad);
    const std::int32_t b = count(s.max_angle_rad);
    items.push_back({"Max Position Limit", dxl::kAddrMaxPositionLimit, 4, true,
                     static_cast<std::uint32_t>(std::max(a, b))});
    items.push_back({"Min Position Limit", dxl::kAddrMinPositionLimit, 4, true,
                     static_cast<std::uint32_t>(std::min(a, b))});
  }
  items.push_back(
      {"Profile Acceleration", dxl::kAddrProfileAcceleration, 4, false, acceleration_limit_});
  items.push_back({"Profile Velocity", dxl::kAddrProfileVelocity, 4, false, velocity_limit_});
  items.push_back({"Bus Watchdog", dxl::kAddrBusWatchdog, 1, false, watchdog_units_});
  return items;
}

bool ServoSetup::ClearWatchdog(std::size_t i, std::string* why) {
  SetupServo& s = link_.servo(i);
  const std::string name = ServoName(s.id, s.leg);
  auto refused = [&](const std::string& step, const std::optional<std::uint8_t>& e) {
    *why = name + ": " + step +
           (e ? " refused: " + dxl::DescribeStatusError(*e) : " not answered") +
           "; its goals stay refused";
    return false;
  };
  auto e = WriteItem(i, dxl::kAddrBusWatchdog, 0, 1);
  if (!e || *e != 0) return refused("clearing the expired Bus Watchdog (98) with 0", e);
  // Where it stopped, not where it was going: the clear must not set it moving again.
  const auto present = ReadBlock(i, kAddrPresentPosition, 4);
  if (!present) return refused("reading Present Position (132)", std::nullopt);
  const std::uint32_t count = (*present)[0] | ((*present)[1] << 8) | ((*present)[2] << 16) |
                              (static_cast<std::uint32_t>((*present)[3]) << 24);
  e = WriteItem(i, dxl::kAddrGoalPosition, count, 4);
  if (!e || *e != 0) return refused("holding Goal Position (116) at the present position", e);
  e = WriteItem(i, dxl::kAddrBusWatchdog, watchdog_units_, 1);
  if (!e || *e != 0) return refused("re-arming the Bus Watchdog (98)", e);
  ++stats_.Counter("watchdog_expiries");
  const std::string what = name + "'s Bus Watchdog had expired (no instruction for " +
                           fmt::format("{}", watchdog_s_) +
                           " s with torque on): it stopped where it was; cleared, held there, "
                           "and commands wait for a new ARM";
  stats_.Error(name + " Bus Watchdog expired", what);
  watchdog_expiry_ = watchdog_expiry_ ? *watchdog_expiry_ + "; " + what : what;
  return true;
}

void ServoSetup::ClearExpiredWatchdog(std::size_t i) {
  std::string why;
  if (!ClearWatchdog(i, &why) && link_.port_open()) {
    SetupServo& s = link_.servo(i);
    s.limits_error = why;
    stats_.Error(ServoName(s.id, s.leg) + " Bus Watchdog not cleared", why);
  }
}

void ServoSetup::CheckLimits(std::size_t i) {
  SetupServo& s = link_.servo(i);
  const std::string name = ServoName(s.id, s.leg);
  const auto value_of = [](const std::vector<std::uint8_t>& block, const LimitItem& item) {
    std::uint32_t v = 0;
    for (int k = 0; k < item.size; ++k) {
      v |= static_cast<std::uint32_t>(block[item.address - kLimitBlockAddress + k]) << (8 * k);
    }
    return v;
  };
  const auto block = ReadBlock(i, kLimitBlockAddress, kLimitBlockBytes);
  if (!block) return;  // no answer: tried again next cycle
  std::vector<std::string> problems;
  std::vector<std::uint16_t> reported;
  if ((*block)[dxl::kAddrBusWatchdog - kLimitBlockAddress] == dxl::kBusWatchdogExpired) {
    std::string why;
    if (!ClearWatchdog(i, &why)) {
      if (!link_.port_open()) return;
      problems.push_back(why);
      reported.push_back(dxl::kAddrBusWatchdog);
    }
  }
  const bool torque_on = (*block)[dxl::kAddrTorqueEnable - kLimitBlockAddress] != 0;
  const std::vector<LimitItem> items = LimitsFor(i);
  for (const LimitItem& item : items) {
    if (value_of(*block, item) == item.value) continue;
    if (item.eeprom && torque_on) {
      // EEPROM is writable only with torque off (§2.7), and turning it off drops the leg.
      problems.push_back(fmt::format(
          "{}: {} ({}) is {}, the config wants {}, and torque is on (EEPROM is written only with "
          "torque off): not rewritten",
          name, item.name, item.address, value_of(*block, item), item.value));
      reported.push_back(item.address);
      continue;
    }
    const auto e = WriteItem(i, item.address, item.value, item.size);
    if (!link_.port_open()) return;
    if (!e) return;  // no answer: all of it again next cycle
    if (*e != 0) {
      problems.push_back(fmt::format("{}: {} ({}) refused {}: {}", name, item.name, item.address,
                                     item.value, dxl::DescribeStatusError(*e)));
      reported.push_back(item.address);
      continue;
    }
    ++stats_.Counter("limit_writes");
  }
  const auto back = ReadBlock(i, kLimitBlockAddress, kLimitBlockBytes);
  if (!link_.port_open() || !back) return;
  for (const LimitItem& item : items) {
    const std::uint32_t read = value_of(*back, item);
    if (read == item.value ||
        std::find(reported.begin(), reported.end(), item.address) != reported.end()) {
      continue;
    }
    problems.push_back(fmt::format("{}: {} ({}) written {}, read back {}", name, item.name,
                                   item.address, item.value, read));
  }
  s.limits_checked = true;
  s.limits_error.clear();
  for (const std::string& p : problems) s.limits_error += (s.limits_error.empty() ? "" : "; ") + p;
  if (!problems.empty()) {
    ++stats_.Counter("limits_mismatch");
    stats_.Error(name + " limits not as configured", s.limits_error + ": not armed");
  } else {
    stats_.log().info(
        "{}: limits written and read back (velocity {}, acceleration {}, watchdog "
        "{} x 20 ms)",
        name, velocity_limit_, acceleration_limit_, watchdog_units_);
  }
}

std::int32_t ServoSetup::Goal(const SetupServo& s, double goal_rad) {
  const double clamped = std::clamp(goal_rad, s.min_angle_rad, s.max_angle_rad);
  if (clamped != goal_rad) {
    ++stats_.Counter("goals_clamped");
    stats_.log().debug("goal {} rad for {} clamped to {}", goal_rad, ServoName(s.id, s.leg),
                       clamped);
  }
  if (s.mode_checked && !s.mode_ok) {
    throw BadInput("servo_command_t servo in the wrong operating mode",
                   "SERVO_CMD goal for " + ServoName(s.id, s.leg) +
                       ": the servo is in "
                       "Operating Mode " +
                       std::to_string(s.mode) + ", not the configured " +
                       std::to_string(operating_mode_));
  }
  const std::int32_t count = dxl::RadToPosition(clamped, s.zero_count, s.direction);
  if (count < min_goal_count_ || count > max_goal_count_) {
    throw BadInput("servo_command_t goal outside the encoder range",
                   "SERVO_CMD goal for " + ServoName(s.id, s.leg) + " is count " +
                       std::to_string(count) + ", outside " + std::to_string(min_goal_count_) +
                       ".." + std::to_string(max_goal_count_) + " of Operating Mode " +
                       std::to_string(operating_mode_));
  }
  return count;
}

std::string ServoSetup::ArmBlocker() const {
  std::string why;
  for (std::size_t i = 0; i < link_.size(); ++i) {
    const SetupServo& s = link_.servo(i);
    std::string one;
    if (!s.limits_checked) {
      one = ServoName(s.id, s.leg) + ": limits not yet written and read back";
    } else if (!s.limits_error.empty()) {
      one = s.limits_error;
    }
    if (!one.empty()) why += (why.empty() ? "" : "; ") + one;
  }
  return why;
}

std::vector<std::uint8_t> ServoSetup::wrong_mode() const {
  std::vector<std::uint8_t> ids;
  for (std::size_t i = 0; i < link_.size(); ++i) {
    const SetupServo& s = link_.servo(i);
    if (s.mode_checked && !s.mode_ok) ids.push_back(s.id);
  }
  return ids;
}

std::optional<std::string> ServoSetup::TakeWatchdogExpiry() {
  std::optional<std::string> what;
  what.swap(watchdog_expiry_);
  return what;
}

}  // namespace ftcal
