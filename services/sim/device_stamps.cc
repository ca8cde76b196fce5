#include "sim/device_stamps.h"

#include <algorithm>
#include <cmath>

namespace ftcal {
namespace {

constexpr double kFtCounterHz = 7000.0;  // the Net F/T's internal sample rate (§1.3)
constexpr double kMocapClockHz = 1e6;    // QTM's and the NatNet bridge's device time: us
// Two stalls are at least this far apart: a stall is a burst, not a slow host.
constexpr double kMinStallSpacingS = 1.0;

}  // namespace

TwinDeviceStamps::TwinDeviceStamps(const SimClocks& clocks, uint64_t seed, int64_t t0_utime,
                                   const std::array<int64_t, kNumLegs>& ft_count0,
                                   const std::array<int64_t, kNumLegs>& tick0_ms)
    : clocks_(clocks),
      t0_utime_(t0_utime),
      rng_(seed ^ 0x57A11ULL),
      ft_count0_(ft_count0),
      tick0_ms_(tick0_ms),
      servo_map_(kNumLegs, DeviceClockOptions{}),
      mocap_map_(DeviceClockOptions{kMocapClockHz}) {
  clocks_.Validate();
  for (auto& m : ft_map_) m = std::make_unique<DeviceClock>(DeviceClockOptions{kFtCounterHz});
  all_answered_.fill(true);
  if (clocks_.stall_every_s > 0 && clocks_.stall_max_s > 0) NextStall(t0_utime);
}

void TwinDeviceStamps::NextStall(int64_t after_utime) {
  const double u = static_cast<double>(rng_() >> 11) * 0x1.0p-53;
  const double v = static_cast<double>(rng_() >> 11) * 0x1.0p-53;
  const double gap_s = std::max(kMinStallSpacingS, -clocks_.stall_every_s * std::log1p(-u));
  stall_begin_ = after_utime + std::llround(gap_s * 1e6);
  stall_end_ = stall_begin_ + std::llround((0.2 + 0.8 * v) * clocks_.stall_max_s * 1e6);
}

int64_t TwinDeviceStamps::HostStamp(int64_t utime) {
  if (stall_end_ <= stall_begin_) return utime;  // no stalls
  // The stamps of one frame come in device order, not time order: a stall is left behind only
  // once a frame well past it (more than kMaxStallS) is stamped.
  while (utime >= stall_end_ + std::llround(kMaxStallS * 1e6)) NextStall(stall_end_);
  if (utime >= stall_begin_ && utime < stall_end_) {
    ++stalls_;
    return stall_end_;
  }
  return utime;
}

TwinDeviceStamps::Ft TwinDeviceStamps::FtSample(int k, double t_s, int64_t receipt_utime) {
  const auto i = static_cast<size_t>(k);
  const auto counter =
      ft_count0_[i] +
      static_cast<int64_t>(std::floor(kFtCounterHz * clocks_.ft[i].DeviceSeconds(t_s)));
  return {counter, ft_map_[i]->Observe(counter, receipt_utime)};
}

const TwinDeviceStamps::Servo& TwinDeviceStamps::ServoSample(double t_s, int64_t completion_utime) {
  for (size_t i = 0; i < kNumLegs; ++i) {
    servo_.tick_ms[i] =
        tick0_ms_[i] + static_cast<int64_t>(std::floor(1e3 * clocks_.servo[i].DeviceSeconds(t_s)));
  }
  const double u = static_cast<double>(rng_() >> 11) * 0x1.0p-53;
  servo_.request_utime = t0_utime_ + std::llround(t_s * 1e6) - kReadLeadUs -
                         std::llround(u * static_cast<double>(kReadJitterUs));
  servo_.sample_utime = servo_map_.Observe(servo_.tick_ms.data(), all_answered_.data(),
                                           completion_utime, servo_.request_utime);
  return servo_;
}

TwinDeviceStamps::Mocap TwinDeviceStamps::MocapSample(double t_s, int64_t receipt_utime) {
  const int64_t device = std::llround(kMocapClockHz * clocks_.mocap.DeviceSeconds(t_s));
  return {device, mocap_map_.Observe(device, receipt_utime)};
}

}  // namespace ftcal
