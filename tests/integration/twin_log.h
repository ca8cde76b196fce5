// Logs for the multi-process tests, written from the BigAnt twin as the bridges would publish
// them (FT_<LEG>, SERVO_STATE, MOCAP_BODY per 100 Hz frame, EXPERIMENT markers), and read back
// per channel. Header-only: shared by the multi-process tests (pipeline_live, bad_logs,
// calibrator, stages).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <map>
#include <utility>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>

#include "common/messages.h"
#include "ftcal/config.h"
#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/experiment_marker_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "sim/twin.h"

namespace ftcal::twin_log {

// An LCM fixed-size array as a vector, to compare element by element: `a.wrench == b.wrench`
// on the arrays themselves compares two pointers.
template <class T, size_t N>
std::vector<T> Flat(const T (&a)[N]) {
  return std::vector<T>(a, a + N);
}
template <class T, size_t N, size_t M>
std::vector<T> Flat(const T (&a)[N][M]) {
  std::vector<T> out;
  for (const auto& row : a) out.insert(out.end(), row, row + M);
  return out;
}

constexpr int64_t kT0 = 1'700'000'000'000'000;  // us, the log's time origin

inline int64_t Utime(double t_s) { return kT0 + std::llround(t_s * 1e6); }

struct Event {
  int64_t utime;
  std::string channel;
  std::vector<uint8_t> data;
};

template <class Msg>
Event Encode(int64_t utime, const std::string& channel, const Msg& msg) {
  Event e{utime, channel, std::vector<uint8_t>(static_cast<size_t>(msg.getEncodedSize()))};
  msg.encode(e.data.data(), 0, static_cast<int>(e.data.size()));
  return e;
}

inline void WriteLog(const std::string& path, const std::vector<Event>& events) {
  lcm::LogFile log(path, "w");
  ASSERT_TRUE(log.good()) << path;
  int64_t n = 0;
  for (const Event& e : events) {
    lcm::LogEvent ev;
    ev.eventnum = n++;
    ev.timestamp = e.utime;
    ev.channel = e.channel;
    ev.datalen = static_cast<int32_t>(e.data.size());
    ev.data = const_cast<uint8_t*>(e.data.data());
    ASSERT_EQ(log.writeEvent(&ev), 0);
  }
}

// Every event of a log, raw.
inline std::vector<Event> ReadLog(const std::string& path) {
  std::vector<Event> out;
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return out;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    const auto* b = static_cast<const uint8_t*>(e->data);
    out.push_back(Event{e->timestamp, e->channel, std::vector<uint8_t>(b, b + e->datalen)});
  }
  return out;
}

// Every event of `channel` in a log, decoded; a message that does not decode exactly fails
// the test (a recorded output must never be garbage). Streamed: a walk log is a gigabyte, of
// which one channel is a part.
template <class Msg>
std::vector<Msg> ReadChannel(const std::string& path, const std::string& channel) {
  std::vector<Msg> out;
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good()) << path;
  if (!log.good()) return out;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel != channel) continue;
    Msg m;
    EXPECT_EQ(m.decode(e->data, 0, e->datalen), e->datalen)
        << path << " " << channel << " at " << e->timestamp;
    out.push_back(m);
  }
  return out;
}

inline experiment_marker_t Marker(int64_t utime, const std::string& session, int8_t phase,
                                  bool start, const Vec3& gravity_b = Vec3::Zero()) {
  experiment_marker_t m{};
  m.utime = utime;
  m.session_id = session;
  m.phase = phase;
  m.start = start;
  for (int i = 0; i < 3; ++i) m.gravity_b[i] = gravity_b[i];
  m.note = "twin_log";
  return m;
}

// The twin's frame as the bridges would publish it: six FT_<LEG>, one SERVO_STATE, one
// MOCAP_BODY, all stamped with the frame's time.
inline void AppendFrame(const TwinFrame& f, const config::Config& cfg, std::vector<Event>* events) {
  const int64_t t = Utime(f.t_s);
  const auto& ch = cfg.channels();
  for (int k = 0; k < kNumLegs; ++k) {
    FtBatch b;
    b.leg = k;
    b.receipt_utime = t;
    b.n = 1;
    FtRecord& r = b.records[0];
    r.in = {t, k, f.reading[k], 0};
    r.rdt_sequence = std::llround(f.t_s * 100) + 1;
    r.ft_sequence = 70 * r.rdt_sequence;
    ft_batch_t m = ToLcm(b);
    for (size_t i = 0; i < 6; ++i) m.counts[0][i] = f.counts[k][i];
    events->push_back(Encode(t, ch.ft_prefix() + m.leg, m));
  }
  servo_state_t s{};
  s.utime = s.sample_utime = t;
  for (int k = 0; k < kNumLegs; ++k) {
    s.leg[k] = std::string(kLegNames[k]);
    s.id[k] = static_cast<int32_t>(cfg.robot().leg(k).servo().id());
    s.angle_rad[k] = f.angle_rad[k];
    s.velocity_rad_s[k] = 0.0;
    s.current_a[k] = 0.0;
    s.hardware_error[k] = 0;
    s.device_tick_ms[k] = std::llround(f.t_s * 1e3);
    s.flags[k] = 0;
  }
  events->push_back(Encode(t, ch.servo_state(), s));
  mocap_body_t b{};
  b.utime = b.sample_utime = t;
  b.frame_number = std::llround(f.t_s * 100);
  b.device_utime = std::llround(f.t_s * 1e6);
  b.body = cfg.mocap().body_name();
  b.tracked = true;
  const Eigen::Vector4d q_wc = RotationToQuaternion(RemoveHeading(f.R_GC));
  const Eigen::Vector4d q_gc = RotationToQuaternion(f.R_GC);
  for (int i = 0; i < 4; ++i) {
    b.q_wc[i] = q_wc[i];
    b.q_gc[i] = q_gc[i];
  }
  for (int i = 0; i < 3; ++i) b.position_m[i] = f.p_GB_m[i];
  b.yaw_rad = HeadingYaw(f.R_GC);
  b.residual_m = 0.0005;
  b.num_markers = kNumChassisMarkers;
  for (int i = 0; i < kNumChassisMarkers; ++i) {
    b.marker_m.push_back({f.marker_G_m[i].x(), f.marker_G_m[i].y(), f.marker_G_m[i].z()});
    b.marker_tracked.push_back(f.marker_tracked[i]);
  }
  events->push_back(Encode(t, ch.mocap_body(), b));
}

// A whole calibration session: the four hanging series, then `poses` standing poses, each phase
// between its EXPERIMENT start and stop markers, then `walk_s` of tripod walk outside any phase
// (data for the corrector once a calibration is in use). Returns the STANDING stop marker's
// index in `events`.
inline size_t AppendSession(const BigAntTwin& twin, const config::Config& cfg,
                            const std::string& session, int poses, double walk_s,
                            std::vector<Event>* events) {
  const auto& ch = cfg.channels();
  const auto sink = [&](const TwinFrame& f) { AppendFrame(f, cfg, events); };
  auto marker = [&](double t_s, int8_t phase, bool start, const Vec3& g) {
    events->push_back(
        Encode(Utime(t_s), ch.experiment(), Marker(Utime(t_s), session, phase, start, g)));
  };
  double t = 0.0;
  for (int s = 0; s < kNumHangSeries; ++s) {
    const auto series = static_cast<HangSeries>(s);
    const auto phase = static_cast<int8_t>(experiment_marker_t::HANG_X_POS + s);
    const Vec3 g = twin.StatedGravityB(series);
    marker(t, phase, true, g);
    RunOptions run;
    run.t0_s = t + 0.01;
    t = twin.Hanging(series, run, sink);
    marker(t + 0.005, phase, false, g);
    t += 0.5;
  }
  marker(t, experiment_marker_t::STANDING, true, Vec3::Zero());
  RunOptions run;
  run.t0_s = t + 0.01;
  t = twin.Standing(poses, run, sink);
  marker(t + 0.005, experiment_marker_t::STANDING, false, Vec3::Zero());
  const size_t stop = events->size() - 1;
  if (walk_s > 0) {
    run.t0_s = t + 0.01;
    twin.TripodWalk(walk_s, run, sink);
  }
  return stop;
}

// ---- comparing CONTACT_WRENCH streams ----
//
// "Same inputs" is read off the messages themselves. A leg-sample's output depends on that
// sample and on the servo state and attitude of that moment; its ages (servo_age_s,
// mocap_age_s) are its utime minus the stamps of those inputs, so equal ages and flags mean the
// same inputs. The sums (CONTACT_WRENCH_SUM) are checked against the leg-samples before them in
// the same stream (CheckSums).

inline bool SameOrBothNan(double a, double b) { return a == b || (std::isnan(a) && std::isnan(b)); }

// The batched messages of a channel, one element per sample.
inline std::vector<LegWrench> ReadLegWrenches(const std::string& path, const std::string& channel) {
  std::vector<LegWrench> out;
  for (const contact_wrench_t& m : ReadChannel<contact_wrench_t>(path, channel)) {
    for (const LegWrench& w : FromLcm(m)) out.push_back(w);
  }
  return out;
}
inline std::vector<WrenchSum> ReadWrenchSums(const std::string& path, const std::string& channel) {
  std::vector<WrenchSum> out;
  for (const contact_wrench_sum_t& m : ReadChannel<contact_wrench_sum_t>(path, channel)) {
    for (const WrenchSum& s : FromLcm(m)) out.push_back(s);
  }
  return out;
}
inline std::vector<FtRecord> ReadFtRecords(const std::string& path, const std::string& channel,
                                           int leg) {
  std::vector<FtRecord> out;
  FtBatch batch;
  for (const ft_batch_t& m : ReadChannel<ft_batch_t>(path, channel)) {
    FromLcm(m, leg, &batch);
    out.insert(out.end(), batch.begin(), batch.end());
  }
  return out;
}

using WrenchKey = std::pair<int64_t, int32_t>;  // (utime, leg)
using WrenchIndex = std::map<WrenchKey, const LegWrench*>;

inline WrenchIndex IndexWrenches(const std::vector<LegWrench>& v) {
  WrenchIndex index;
  for (const auto& m : v) index[{m.utime, m.leg}] = &m;
  return index;
}

inline bool SameInputs(const LegWrench& a, const LegWrench& b) {
  return a.flags == b.flags && SameOrBothNan(a.servo_age_s, b.servo_age_s) &&
         SameOrBothNan(a.mocap_age_s, b.mocap_age_s);
}

// The largest difference between two numbers; infinite when one is NaN and the other not.
inline void Worst(double x, double y, double* worst) {
  if (std::isnan(x) != std::isnan(y)) {
    *worst = INFINITY;
  } else if (!std::isnan(x)) {
    *worst = std::max(*worst, std::abs(x - y));
  }
}

inline double MaxWrenchDifference(const LegWrench& a, const LegWrench& b) {
  double worst = 0.0;
  for (int i = 0; i < 6; ++i) Worst(a.wrench_W[i], b.wrench_W[i], &worst);
  return worst;
}

struct WrenchComparison {
  size_t outputs = 0;        // in the stream under test
  size_t missing_ref = 0;    // with no reference output for the same (utime, leg)
  size_t duplicate = 0;      // a (utime, leg) published twice
  size_t same_inputs = 0;    // compared number by number
  size_t inputs_differ = 0;  // reordered, lost or unheard inputs: counted, not compared
  double worst = 0.0;        // over same_inputs
  std::vector<int64_t> differ_utimes;
};

inline WrenchComparison CompareWrenches(const std::vector<LegWrench>& test,
                                        const std::vector<LegWrench>& ref) {
  const WrenchIndex r_index = IndexWrenches(ref);
  std::map<WrenchKey, int> seen;
  WrenchComparison c;
  for (const auto& m : test) {
    ++c.outputs;
    if (++seen[{m.utime, m.leg}] > 1) ++c.duplicate;
    const auto it = r_index.find({m.utime, m.leg});
    if (it == r_index.end()) {
      ++c.missing_ref;
      continue;
    }
    if (!SameInputs(m, *it->second)) {
      ++c.inputs_differ;
      c.differ_utimes.push_back(m.utime);
      continue;
    }
    ++c.same_inputs;
    c.worst = std::max(c.worst, MaxWrenchDifference(m, *it->second));
  }
  return c;
}

// Every sum of a log's CONTACT_WRENCH_SUM against the leg-samples published before it in the
// same log: its total is the sum of each leg's sample nearest its instant (the earlier of two
// as near), its residual that total minus (0, 0, weight_n, 0, 0, 0) (not checked when weight_n
// is NaN), its oldest_ft_age_s the largest distance of those samples from the instant. A sum
// while a leg has no sample under the current calibration carries NaN (counted in nan_sums,
// not compared).
struct SumCheck {
  size_t sums = 0;
  size_t nan_sums = 0;
  size_t legs = 0;     // leg-samples read
  double worst = 0.0;  // total and residual against the legs, N or N*m
  double worst_age = 0.0;
};

inline SumCheck CheckSums(const std::string& path, const std::string& leg_channel,
                          const std::string& sum_channel, double weight_n) {
  SumCheck c;
  lcm::LogFile log(path, "r");
  std::array<std::vector<LegWrench>, kNumLegs> seen;
  while (const lcm::LogEvent* e = log.readNextEvent()) {
    if (e->channel == leg_channel) {
      contact_wrench_t m;
      if (m.decode(e->data, 0, e->datalen) != e->datalen || m.leg < 0 || m.leg >= kNumLegs) {
        ADD_FAILURE() << "bad contact_wrench_t in " << path;
        continue;
      }
      for (const LegWrench& w : FromLcm(m)) {
        seen[static_cast<size_t>(w.leg)].push_back(w);
        ++c.legs;
      }
    } else if (e->channel == sum_channel) {
      contact_wrench_sum_t m{};
      if (m.decode(e->data, 0, e->datalen) != e->datalen) {
        ADD_FAILURE() << "bad contact_wrench_sum_t in " << path;
        continue;
      }
      for (const WrenchSum& s : FromLcm(m)) {
        ++c.sums;
        if (std::isnan(s.total_W[0]) ||
            std::any_of(seen.begin(), seen.end(), [](const auto& v) { return v.empty(); })) {
          ++c.nan_sums;
          continue;
        }
        Vec6 total = Vec6::Zero();
        double oldest = 0.0;
        for (const auto& legs : seen) {
          auto it = std::lower_bound(legs.begin(), legs.end(), s.utime,
                                     [](const LegWrench& w, int64_t t) { return w.utime < t; });
          if (it == legs.end() ||
              (it != legs.begin() && s.utime - std::prev(it)->utime <= it->utime - s.utime)) {
            --it;
          }
          total += it->wrench_W;
          oldest = std::max(oldest, 1e-6 * static_cast<double>(std::abs(s.utime - it->utime)));
        }
        for (int i = 0; i < 6; ++i) {
          Worst(s.total_W[i], total[i], &c.worst);
          if (!std::isnan(weight_n)) {
            Worst(s.residual_W[i], total[i] - (i == 2 ? weight_n : 0.0), &c.worst);
          }
        }
        c.worst_age = std::max(c.worst_age, std::abs(s.oldest_ft_age_s - oldest));
      }
    }
  }
  return c;
}

}  // namespace ftcal::twin_log
