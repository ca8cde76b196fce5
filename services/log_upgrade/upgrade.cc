#include "log_upgrade/upgrade.h"

#include <sys/stat.h>

#include <cinttypes>
#include <cmath>
#include <cstdio>
#include <limits>
#include <mutex>
#include <sstream>

#include <lcm/lcm-cpp.hpp>

#include "common/atomic_log.h"
#include "common/wire_guard.h"
#include "ftcal/signed_envelope_t.hpp"

namespace ftcal::wire {
// The older versions' own schemas (cmake/LcmTypes.cmake: ftcal_wire_schemas(LegacySchemas ...)).
const std::vector<const Schema*>& LegacySchemas();
}  // namespace ftcal::wire

namespace ftcal::log_upgrade {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

// wire::Decode finds a type's schema by its fingerprint among the registered ones: the older
// versions are registered once, before the first decode.
void RegisterLegacySchemas() {
  static std::once_flag once;
  std::call_once(once, [] { wire::Register(wire::LegacySchemas()); });
}

uint64_t Fingerprint(const void* data, int size) {
  if (size < 8) return 0;
  const auto* b = static_cast<const uint8_t*>(data);
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v = v << 8 | b[i];
  return v;
}

template <class Current>
std::vector<uint8_t> Encode(const Current& msg) {
  std::vector<uint8_t> out(static_cast<size_t>(msg.getEncodedSize()));
  const int used = msg.encode(out.data(), 0, static_cast<int>(out.size()));
  // An invariant: what a conversion made must be what a current reader takes.
  const wire::Schema* schema = wire::FindSchema(static_cast<uint64_t>(Current::getHash()));
  if (used != static_cast<int>(out.size()) || schema == nullptr ||
      wire::Check(*schema, out.data(), used)) {
    throw std::logic_error(std::string("converted ") + Current::getTypeName() +
                           " does not pass the current wire checks");
  }
  return out;
}

// Guard, decode as the older version, convert, encode as the current type.
template <class Old>
std::vector<uint8_t> Convert(const void* data, int size) {
  Old old;
  if (auto refused = wire::Decode(data, size, &old)) {
    throw std::invalid_argument(refused->kind + ": " + refused->detail);
  }
  return Encode(FromLegacy(old));
}

template <class T, size_t N>
void CopyExactly(const std::vector<T>& from, T (&to)[N], const char* field) {
  if (from.size() != N) {
    throw std::invalid_argument(std::string(field) + " has " + std::to_string(from.size()) +
                                " elements, not " + std::to_string(N));
  }
  for (size_t i = 0; i < N; ++i) to[i] = from[i];
}

void RequireSix(int32_t count, const char* field) {
  if (count != 6) {
    throw std::invalid_argument(std::string(field) + " is " + std::to_string(count) +
                                ": the current type holds exactly six (one per leg); a log of "
                                "another robot shape has no current form");
  }
}

template <size_t N>
void FillNaN(double (&a)[N]) {
  for (double& v : a) v = kNaN;
}

template <class Old>
ftcal::steady_pose_t PoseHead(const Old& old) {
  ftcal::steady_pose_t pose{};
  pose.utime = old.utime;
  pose.session_id = old.session_id;
  pose.pose_index = old.pose_index;
  pose.start_utime = old.start_utime;
  pose.end_utime = old.end_utime;
  pose.num_samples = old.num_samples;
  for (int k = 0; k < 4; ++k) pose.q_wc[k] = old.q_wc[k];
  pose.markers_ok = old.markers_ok;
  for (auto& row : pose.wrench_sem) FillNaN(row);
  FillNaN(pose.attitude_sem_rad);
  return pose;
}

}  // namespace

ftcal::ft_batch_t FromLegacy(const ftcal_pre_batch::ft_sample_t& old) {
  ftcal::ft_batch_t batch{};
  batch.receipt_utime = old.utime;
  batch.leg = old.leg;
  batch.n = 1;
  batch.sample_utime = {old.utime};
  batch.rdt_sequence = {old.rdt_sequence};
  batch.ft_sequence = {old.ft_sequence};
  batch.status = {old.status};
  batch.counts = {std::vector<int32_t>(std::begin(old.counts), std::end(old.counts))};
  batch.wrench = {std::vector<double>(std::begin(old.wrench), std::end(old.wrench))};
  batch.gap = {old.gap};
  batch.flags = {old.flags};
  return batch;
}

ftcal::contact_wrench_t FromLegacy(const ftcal_pre_batch::contact_wrench_t& old) {
  ftcal::contact_wrench_t w{};
  w.receipt_utime = old.utime;
  w.leg = old.leg;
  w.n = 1;
  w.utime = {old.utime};
  w.wrench_w = {std::vector<double>(std::begin(old.wrench_w), std::end(old.wrench_w))};
  w.servo_age_s = {old.servo_age_s};
  w.mocap_age_s = {old.mocap_age_s};
  w.flags = {old.flags};
  return w;
}

ftcal::contact_wrench_sum_t FromLegacy(const ftcal_pre_batch::contact_wrench_sum_t& old) {
  ftcal::contact_wrench_sum_t sum{};
  sum.calibration_version = old.calibration_version;
  sum.n = 1;
  sum.utime = {old.utime};
  sum.total_w = {std::vector<double>(std::begin(old.total_w), std::end(old.total_w))};
  sum.residual_w = {std::vector<double>(std::begin(old.residual_w), std::end(old.residual_w))};
  sum.oldest_ft_age_s = {old.oldest_ft_age_s};
  sum.flags = {old.flags};
  return sum;
}

ftcal::servo_state_t FromLegacy(const ftcal_pre_fixed6::servo_state_t& old) {
  RequireSix(old.num_servos, "num_servos");
  ftcal::servo_state_t s{};
  s.utime = old.utime;
  CopyExactly(old.leg, s.leg, "leg");
  CopyExactly(old.id, s.id, "id");
  CopyExactly(old.angle_rad, s.angle_rad, "angle_rad");
  CopyExactly(old.velocity_rad_s, s.velocity_rad_s, "velocity_rad_s");
  CopyExactly(old.current_a, s.current_a, "current_a");
  CopyExactly(old.hardware_error, s.hardware_error, "hardware_error");
  CopyExactly(old.device_tick_ms, s.device_tick_ms, "device_tick_ms");
  CopyExactly(old.flags, s.flags, "flags");
  s.sample_utime = old.utime;  // what every reader aligned by then
  return s;
}

ftcal::servo_state_t FromLegacy(const ftcal_pre_sample_time::servo_state_t& old) {
  ftcal::servo_state_t s{};
  s.utime = old.utime;
  for (int i = 0; i < 6; ++i) {
    s.leg[i] = old.leg[i];
    s.id[i] = old.id[i];
    s.angle_rad[i] = old.angle_rad[i];
    s.velocity_rad_s[i] = old.velocity_rad_s[i];
    s.current_a[i] = old.current_a[i];
    s.hardware_error[i] = old.hardware_error[i];
    s.device_tick_ms[i] = old.device_tick_ms[i];
    s.flags[i] = old.flags[i];
  }
  // The completion time stood for the sample's then; mapping the ticks afresh would change
  // what an older log calibrates to.
  s.sample_utime = old.utime;
  return s;
}

ftcal::mocap_body_t FromLegacy(const ftcal_pre_sample_time::mocap_body_t& old) {
  ftcal::mocap_body_t m{};
  m.utime = old.utime;
  m.frame_number = old.frame_number;
  m.device_utime = old.device_utime;
  m.body = old.body;
  m.tracked = old.tracked;
  for (int i = 0; i < 4; ++i) {
    m.q_wc[i] = old.q_wc[i];
    m.q_gc[i] = old.q_gc[i];
  }
  for (int i = 0; i < 3; ++i) m.position_m[i] = old.position_m[i];
  m.yaw_rad = old.yaw_rad;
  m.residual_m = old.residual_m;
  m.num_markers = old.num_markers;
  m.marker_m = old.marker_m;
  m.marker_tracked = old.marker_tracked;
  m.sample_utime = old.utime;  // the receipt stood for the frame's instant then
  return m;
}

ftcal::sync_sample_t FromLegacy(const ftcal_pre_fixed6::sync_sample_t& old) {
  RequireSix(old.num_legs, "num_legs");
  ftcal::sync_sample_t s{};
  s.utime = old.utime;
  CopyExactly(old.leg, s.leg, "leg");
  for (int i = 0; i < 6; ++i) CopyExactly(old.wrench.at(i), s.wrench[i], "wrench");
  CopyExactly(old.angle_rad, s.angle_rad, "angle_rad");
  for (int k = 0; k < 4; ++k) s.q_wc[k] = old.q_wc[k];
  s.attitude_ok = old.attitude_ok;
  s.markers_ok = old.markers_ok;
  s.flags = old.flags;
  return s;
}

ftcal::steady_pose_t FromLegacy(const ftcal_pre_fixed6::steady_pose_t& old) {
  RequireSix(old.num_legs, "num_legs");
  ftcal::steady_pose_t pose = PoseHead(old);
  CopyExactly(old.leg, pose.leg, "leg");
  for (int i = 0; i < 6; ++i) CopyExactly(old.wrench.at(i), pose.wrench[i], "wrench");
  CopyExactly(old.angle_rad, pose.angle_rad, "angle_rad");
  return pose;
}

ftcal::steady_pose_t FromLegacy(const ftcal_pre_scatter::steady_pose_t& old) {
  ftcal::steady_pose_t pose = PoseHead(old);
  for (int i = 0; i < 6; ++i) {
    pose.leg[i] = old.leg[i];
    for (int k = 0; k < 6; ++k) pose.wrench[i][k] = old.wrench[i][k];
    pose.angle_rad[i] = old.angle_rad[i];
  }
  return pose;
}

ftcal::sequencer_control_t FromLegacy(const ftcal_pre_nonce::sequencer_control_t& old) {
  ftcal::sequencer_control_t c{};
  c.utime = old.utime;
  c.action = old.action;
  c.step = old.step;
  c.nonce = 0;
  c.note = old.note;
  return c;
}

std::vector<uint8_t> ConvertMessage(const void* data, int size, std::string* version) {
  RegisterLegacySchemas();
  const wire::LegacyVersion* legacy = wire::FindLegacyVersion(Fingerprint(data, size));
  if (legacy == nullptr) return {};
  if (version != nullptr) *version = std::string(legacy->name) + " (" + legacy->what + ")";
  const auto fp = static_cast<int64_t>(legacy->fingerprint);
  // One branch per older version (lcmtypes/legacy/README.md).
  if (fp == ftcal_pre_batch::ft_sample_t::getHash()) {
    return Convert<ftcal_pre_batch::ft_sample_t>(data, size);
  }
  if (fp == ftcal_pre_batch::contact_wrench_t::getHash()) {
    return Convert<ftcal_pre_batch::contact_wrench_t>(data, size);
  }
  if (fp == ftcal_pre_batch::contact_wrench_sum_t::getHash()) {
    return Convert<ftcal_pre_batch::contact_wrench_sum_t>(data, size);
  }
  if (fp == ftcal_pre_fixed6::servo_state_t::getHash()) {
    return Convert<ftcal_pre_fixed6::servo_state_t>(data, size);
  }
  if (fp == ftcal_pre_sample_time::servo_state_t::getHash()) {
    return Convert<ftcal_pre_sample_time::servo_state_t>(data, size);
  }
  if (fp == ftcal_pre_sample_time::mocap_body_t::getHash()) {
    return Convert<ftcal_pre_sample_time::mocap_body_t>(data, size);
  }
  if (fp == ftcal_pre_fixed6::sync_sample_t::getHash()) {
    return Convert<ftcal_pre_fixed6::sync_sample_t>(data, size);
  }
  if (fp == ftcal_pre_fixed6::steady_pose_t::getHash()) {
    return Convert<ftcal_pre_fixed6::steady_pose_t>(data, size);
  }
  if (fp == ftcal_pre_scatter::steady_pose_t::getHash()) {
    return Convert<ftcal_pre_scatter::steady_pose_t>(data, size);
  }
  if (fp == ftcal_pre_nonce::sequencer_control_t::getHash()) {
    return Convert<ftcal_pre_nonce::sequencer_control_t>(data, size);
  }
  // A version in lcmtypes/legacy/ without a conversion here: a bug of this program.
  throw std::logic_error(std::string("no conversion for ") + legacy->name + " (" + legacy->what +
                         ")");
}

Summary UpgradeLog(const std::string& old_path, const std::string& new_path) {
  RegisterLegacySchemas();
  struct stat old_stat {};
  if (::stat(old_path.c_str(), &old_stat) != 0 || !S_ISREG(old_stat.st_mode)) {
    throw std::runtime_error("cannot read '" + old_path + "': not a readable file");
  }
  struct stat new_stat {};
  if (::stat(new_path.c_str(), &new_stat) == 0 && new_stat.st_dev == old_stat.st_dev &&
      new_stat.st_ino == old_stat.st_ino) {
    throw std::invalid_argument(
        "NEW '" + new_path + "' is OLD '" + old_path +
        "': write the upgraded log beside it (the older log is the record)");
  }
  lcm::LogFile in(old_path, "r");
  if (!in.good()) throw std::runtime_error("cannot open '" + old_path + "' as an LCM log");
  AtomicLogFile out(new_path, "upgraded log");
  const int64_t envelope_hash = ftcal::signed_envelope_t::getHash();
  Summary summary;
  int64_t event_bytes = 0;
  while (const lcm::LogEvent* e = in.readNextEvent()) {
    ++summary.events;
    event_bytes += static_cast<int64_t>(kLcmEventHeaderBytes + e->channel.size()) + e->datalen;
    ChannelCounts& counts = summary.channels[e->channel];
    std::string version;
    std::vector<uint8_t> converted;
    try {
      converted = ConvertMessage(e->data, e->datalen, &version);
    } catch (const std::invalid_argument& refused) {
      throw RefusedEvent("'" + old_path + "' event " + std::to_string(e->eventnum) + " on " +
                         e->channel + ", an older " + version + ", refused: " + refused.what() +
                         "; nothing written to '" + new_path + "'");
    }
    if (!converted.empty()) {
      out.Write(e->timestamp, e->channel, converted.data(), static_cast<int>(converted.size()));
      ++counts.converted;
      ++summary.converted;
      ++summary.versions[version];
      continue;
    }
    out.Write(e->timestamp, e->channel, e->data, e->datalen);
    ++counts.copied;
    if (static_cast<int64_t>(Fingerprint(e->data, e->datalen)) == envelope_hash) {
      ftcal::signed_envelope_t envelope;
      if (!wire::Decode(e->data, e->datalen, &envelope) &&
          wire::FindLegacyVersion(static_cast<uint64_t>(envelope.inner_fingerprint)) != nullptr) {
        ++counts.old_signed;
        ++summary.old_signed;
      }
    }
  }
  summary.skipped_bytes = static_cast<int64_t>(old_stat.st_size) - event_bytes;
  if (summary.events == 0 && old_stat.st_size > 0) {
    throw RefusedEvent("'" + old_path + "' holds no LCM event in its " +
                       std::to_string(old_stat.st_size) +
                       " bytes: not an LCM log; nothing written to '" + new_path + "'");
  }
  out.Commit();
  return summary;
}

std::string Render(const Summary& summary, const std::string& old_path,
                   const std::string& new_path) {
  std::ostringstream s;
  if (summary.converted == 0) {
    s << "'" << old_path << "' is already current: nothing to convert; '" << new_path
      << "' is a copy of its " << summary.events << " events\n";
  } else {
    s << "'" << old_path << "' -> '" << new_path << "': " << summary.converted << " of "
      << summary.events << " events converted, the rest copied byte for byte\n";
  }
  char line[160];
  std::snprintf(line, sizeof line, "  %-24s %10s %10s\n", "channel", "converted", "copied");
  s << line;
  for (const auto& [channel, c] : summary.channels) {
    std::snprintf(line, sizeof line, "  %-24s %10" PRId64 " %10" PRId64 "\n", channel.c_str(),
                  c.converted, c.copied);
    s << line;
  }
  for (const auto& [version, n] : summary.versions) {
    s << "  converted " << n << " x " << version << "\n";
  }
  if (summary.old_signed > 0) {
    s << "  kept " << summary.old_signed
      << " signed envelope(s) whose inner message is an older version, as signed (converting "
         "it would break the signature; no offline reader takes them)\n";
  }
  if (summary.skipped_bytes != 0) {
    s << "  note: " << summary.skipped_bytes
      << " bytes of the old log were in no event (damage between events, or a last event cut "
         "short): LCM's reader skipped them\n";
  }
  return s.str();
}

}  // namespace ftcal::log_upgrade
