// SERVO_STATE as the bridge publishes it: the last good values of each servo, its flags, and
// the read's instant on the host clock.
#include <array>
#include <limits>

#include "dynamixel_bridge.h"

namespace ftcal {

void DynamixelBridge::Publish(std::int64_t utime, const std::vector<bool>& fresh) {
  servo_state_t msg;
  msg.utime = utime;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (std::size_t i = 0; i < servos_.size(); ++i) {  // six: checked at construction
    const ServoSlot& s = servos_[i];
    msg.leg[i] = s.leg;
    msg.id[i] = s.id;
    msg.angle_rad[i] = s.ever_read ? s.angle_rad : nan;
    msg.velocity_rad_s[i] = s.ever_read ? s.velocity_rad_s : nan;
    msg.current_a[i] = s.ever_read ? s.current_a : nan;
    msg.hardware_error[i] = s.hardware_error;
    msg.device_tick_ms[i] = s.tick_ms;
    int32_t flags = 0;
    if (!fresh[i]) flags |= servo_state_t::FLAG_STALE;
    if (s.lost) flags |= servo_state_t::FLAG_LOST;
    if (s.hardware_error != 0 || s.alert) flags |= servo_state_t::FLAG_HW_ERROR;
    if (s.torque_enable == 0) flags |= servo_state_t::FLAG_TORQUE_OFF;
    msg.flags[i] = flags;
  }
  // The read's instant from the ticks of the servos that answered it: a stale servo's tick is
  // of an earlier read.
  std::array<std::int64_t, kNumLegs> ticks{};
  std::array<bool, kNumLegs> answered{};
  for (std::size_t i = 0; i < servos_.size(); ++i) {
    ticks[i] = servos_[i].tick_ms;
    answered[i] = fresh[i];
  }
  msg.sample_utime =
      sample_clock_.Observe(ticks.data(), answered.data(), utime, read_request_utime_);
  publish_(msg);
}

}  // namespace ftcal
