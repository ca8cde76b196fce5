// ftcal-doctor's verdict on an examined recording (LogExaminer::Judge) and its one-screen text.
// The problems are the calibrator's own refusals, found before it runs (collector.cc: missing
// hanging series, config legs with no channel, no markers; calibrate: too few poses, a phase
// over calibrator.max_gap_share); the warnings are what degrades a calibration without stopping
// it.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "common/exit_codes.h"
#include "doctor/log_health.h"
#include "ftcal/experiment_marker_t.hpp"

namespace ftcal::doctor {

namespace {

// Beyond a crystal's tolerance (tens of ppm): a nominal rate that is not the device's, or a
// host clock being slewed.
constexpr double kSkewWarnPpm = 200.0;
// A motion-capture stream untracked, or short of markers, more often than this starves the
// standing poses.
constexpr double kMocapWarnShare = 0.1;

std::string Format(const char* fmt, double a) {
  char b[64];
  std::snprintf(b, sizeof b, fmt, a);
  return b;
}

std::string Seconds(double s) { return Format("%.3f s", s); }

std::string Stretches(const std::vector<Stretch>& v, bool lost) {
  std::string out;
  const size_t shown = std::min<size_t>(v.size(), 3);
  for (size_t i = 0; i < shown; ++i) {
    out += (i ? "; " : "") + Format("at %.3f s", v[i].t_s) + " for " + Seconds(v[i].length_s);
    if (lost) out += " (" + std::to_string(v[i].samples) + " samples)";
  }
  if (v.size() > shown) out += "; " + std::to_string(v.size() - shown) + " more";
  return out;
}

bool IsFt(const StreamHealth& s, const std::string& prefix) { return s.name.rfind(prefix, 0) == 0; }

}  // namespace

void LogExaminer::Judge(HealthReport& r) const {
  const auto& ch = config_.channels();
  for (const StreamHealth& s : r.streams) {
    if (s.samples == 0) {
      r.problems.push_back(s.name + ": no messages in the recording (the calibrator needs " +
                           (IsFt(s, ch.ft_prefix()) ? "every configured leg's transducer" : "it") +
                           ")");
      continue;
    }
    // What a phase lost or waited for is the calibration's concern; between phases (the robot
    // re-hung, the devices idle) it is only worth knowing.
    for (const bool gaps : {true, false}) {
      const std::vector<Stretch>& all = gaps ? s.gaps : s.stalls;
      std::vector<Stretch> in, out;
      for (const Stretch& x : all) (x.phase.empty() ? out : in).push_back(x);
      const char* what = gaps ? " gaps" : " stalls (nothing received, nothing lost)";
      if (!in.empty()) {
        std::string phases;
        for (const Stretch& x : in) {
          if (phases.find(x.phase) == std::string::npos) {
            phases += (phases.empty() ? "" : ", ") + x.phase;
          }
        }
        int64_t lost = 0;
        for (const Stretch& x : in) lost += x.samples;
        r.warnings.push_back(s.name + ": " + std::to_string(in.size()) + what + " in " + phases +
                             (gaps ? ", " + std::to_string(lost) + " samples lost" : "") + ": " +
                             Stretches(in, gaps));
      }
      if (!out.empty()) {
        double total_s = 0;
        for (const Stretch& x : out) total_s += x.length_s;
        r.notes.push_back({s.name, std::to_string(out.size()) + what + " between phases, " +
                                       Format("%.1f s", total_s) + " in all"});
      }
    }
    if (s.duplicates > 0) {
      r.warnings.push_back(s.name + ": " + std::to_string(s.duplicates) + " duplicated samples");
    }
    if (s.counter_restarts > 0) {
      r.warnings.push_back(s.name + ": the device's counter restarted " +
                           std::to_string(s.counter_restarts) + " times (a device reboot?)");
    }
    if (s.has_clock && std::abs(s.skew_ppm) > kSkewWarnPpm) {
      r.warnings.push_back(s.name + ": its clock runs " + Format("%+.0f", s.skew_ppm) +
                           " ppm against the host's, beyond a crystal's tolerance (a nominal "
                           "rate that is not the device's, or the host's clock being slewed)");
    }
    if (s.clock_restarts > 0) {
      r.notes.push_back(
          {s.name, "its clock map started afresh " + std::to_string(s.clock_restarts) +
                       " times (its counter fell or stood still while the host's time went on)"});
    }
    for (const auto& [what, n] : s.flagged) {
      const std::string text =
          std::to_string(n) + " samples " + what +
          Format(" (%.1f %%)", 100.0 * static_cast<double>(n) / static_cast<double>(s.samples));
      // A marker out of view now and then is the motion capture's everyday life: the frames
      // without every marker are left out of the poses (segmenter.require_all_markers).
      const bool everyday =
          (what == "untracked" || what == "markers missing") &&
          static_cast<double>(n) <= kMocapWarnShare * static_cast<double>(s.samples);
      if (everyday) {
        r.notes.push_back({s.name, text});
      } else {
        r.warnings.push_back(s.name + ": " + text);
      }
    }
  }
  if (r.markers == 0) {
    std::string why = "no EXPERIMENT markers accepted (channel '" + ch.experiment() + "')";
    if (r.markers_refused > 0) {
      why += ": " + std::to_string(r.markers_refused) + " refused, the first as '" +
             r.marker_refusal +
             "' (sign them with a key the config's auth trusts on that channel, or set "
             "auth.allow_unsigned for a recording of the twin)";
    }
    r.problems.push_back(why + ": the phases cannot be told apart");
  } else if (r.markers_refused > 0) {
    r.warnings.push_back(std::to_string(r.markers_refused) + " EXPERIMENT markers refused, the " +
                         "first as '" + r.marker_refusal + "'");
  }
  if (r.markers > 0) {
    std::string missing;
    for (int code = experiment_marker_t::HANG_X_POS; code <= experiment_marker_t::HANG_Z_NEG;
         ++code) {
      const bool have = std::any_of(r.phases.begin(), r.phases.end(), [&](const PhaseHealth& p) {
        return p.code == code && p.completed;
      });
      if (!have) missing += (missing.empty() ? "" : ", ") + PhaseName(code);
    }
    if (!missing.empty()) {
      r.problems.push_back("hanging series missing (no completed start..stop): " + missing +
                           ": step 1 needs all four");
    }
    const bool standing = std::any_of(r.phases.begin(), r.phases.end(), [](const PhaseHealth& p) {
      return p.code == experiment_marker_t::STANDING && p.completed;
    });
    if (!standing) {
      r.problems.push_back("no completed STANDING phase: step 2 has no poses");
    } else if (r.steady_poses > 0 &&
               r.steady_poses < static_cast<int64_t>(config_.calibrator().min_poses())) {
      r.problems.push_back(std::to_string(r.steady_poses) + " STEADY_POSE events, fewer than " +
                           "calibrator.min_poses (" +
                           std::to_string(config_.calibrator().min_poses()) + ")");
    } else if (r.steady_poses == 0) {
      r.notes.push_back(
          {"", "no STEADY_POSE events recorded: the calibrator segments the poses itself"});
    }
    std::string optional;
    for (const int8_t code :
         {experiment_marker_t::TARE, experiment_marker_t::TRIPOD, experiment_marker_t::WALKING}) {
      if (std::none_of(r.phases.begin(), r.phases.end(),
                       [&](const PhaseHealth& p) { return p.code == code; })) {
        optional += (optional.empty() ? "" : ", ") + PhaseName(code);
      }
    }
    if (!optional.empty()) r.notes.push_back({"", "not in the recording (optional): " + optional});
  }
  const double max_share = config_.calibrator().max_gap_share();
  for (const PhaseHealth& p : r.phases) {
    if (!p.completed) {
      r.warnings.push_back(PhaseName(p.code) + Format(" started at %.3f s", p.start_s) +
                           " has no stop marker: the calibrator discards it");
    }
    for (int k = 0; k < kNumLegs; ++k) {
      const auto i = static_cast<size_t>(k);
      const int64_t expected = p.ft_received[i] + p.ft_lost[i];
      if (expected == 0) continue;
      const double share = static_cast<double>(p.ft_lost[i]) / static_cast<double>(expected);
      if (share > max_share) {
        r.problems.push_back(PhaseName(p.code) + ": " + std::string(kLegNames[i]) + " lost " +
                             Format("%.1f", 100 * share) + " % of its records, over " +
                             "calibrator.max_gap_share (" + Format("%.1f", 100 * max_share) +
                             " %): the calibrator refuses it unless --allow-gaps");
      }
    }
  }
}

std::string Render(const HealthReport& r) {
  std::string out;
  char line[512];
  std::string logs;
  for (const std::string& l : r.logs) logs += (logs.empty() ? "" : ", ") + l;
  const double span_s =
      r.first_utime >= 0 ? 1e-6 * static_cast<double>(r.last_utime - r.first_utime) : 0;
  std::snprintf(line, sizeof line, "%s: %.0f MB, %lld events, %.1f s of data\n\n", logs.c_str(),
                1e-6 * static_cast<double>(r.bytes), static_cast<long long>(r.events), span_s);
  out += line;
  std::snprintf(line, sizeof line, "%-13s %10s %9s %7s %7s %7s %11s %22s\n", "stream", "rate",
                "samples", "lost", "gaps", "stalls", "clock skew", "queuing p50/p99/max");
  out += line;
  for (const StreamHealth& s : r.streams) {
    const std::string skew = s.has_clock ? Format("%+.1f ppm", s.skew_ppm) : "-";
    const std::string queuing = s.queuing.count() > 0
                                    ? Format("%.2f/", 1e3 * s.queuing.Quantile(0.5)) +
                                          Format("%.2f/", 1e3 * s.queuing.Quantile(0.99)) +
                                          Format("%.1f ms", 1e3 * s.queuing.max_s())
                                    : "-";
    std::snprintf(line, sizeof line, "%-13s %7.1f Hz %9lld %7lld %7zu %7zu %11s %22s\n",
                  s.name.c_str(), s.rate_hz, static_cast<long long>(s.samples),
                  static_cast<long long>(s.lost), s.gaps.size(), s.stalls.size(), skew.c_str(),
                  queuing.c_str());
    out += line;
  }
  std::snprintf(line, sizeof line, "\nphases (EXPERIMENT markers: %lld accepted, %lld refused):\n",
                static_cast<long long>(r.markers), static_cast<long long>(r.markers_refused));
  out += line;
  for (const PhaseHealth& p : r.phases) {
    std::string extra;
    if (p.code == experiment_marker_t::STANDING || p.code == experiment_marker_t::TRIPOD) {
      extra = std::to_string(p.poses) + " poses";
    } else if (p.shaft_turns > 0) {
      extra = Format("shaft travel %.1f turns", p.shaft_turns);
    }
    std::snprintf(line, sizeof line, "  %-11s %9.3f .. %9.3f s %8.1f s  %-13s %s\n",
                  PhaseName(p.code).c_str(), p.start_s, p.end_s, p.end_s - p.start_s,
                  p.completed ? "completed" : "NOT COMPLETED", extra.c_str());
    out += line;
  }
  if (r.phases.empty()) out += "  none\n";
  // The forecast: ftcal-plan's prediction from what the recording holds (sigma_forecast.h).
  const SigmaForecast& f = r.forecast;
  std::snprintf(line, sizeof line,
                "\nsigma forecast (from %d hanging series, %d STEADY_POSE poses; median, worst, "
                "as the calibrator would report them):\n",
                f.hanging_series, f.poses);
  out += line;
  for (const ClassSummary& c : f.classes) {
    std::snprintf(line, sizeof line, "  %-14s %9.3g %-5s worst %9.3g %-5s %s\n", c.klass.c_str(),
                  c.median_reported * c.scale, c.unit.c_str(), c.worst_reported * c.scale,
                  c.unit.c_str(), c.worst_name.c_str());
    out += line;
  }
  if (!f.error.empty()) out += "  none: see the note below\n";
  if (!f.step1_missing.empty()) out += "  step 1 not forecast: see the warning below\n";
  if (!f.step2_missing.empty()) out += "  " + f.step2_missing + "\n";
  const int code = ExitCodeOf(r);
  out += std::string("\nverdict: ") +
         (code == kExitDone      ? "calibratable"
          : code == kExitRefused ? "NOT calibratable"
                                 : "calibratable, with warnings") +
         "\n";
  for (const std::string& p : r.problems) out += "  problem: " + p + "\n";
  for (const std::string& w : r.warnings) out += "  warning: " + w + "\n";
  // The same note of several streams once, naming them all (six transducers alike).
  std::vector<HealthReport::Note> notes;
  for (const HealthReport::Note& n : r.notes) {
    auto same = std::find_if(notes.begin(), notes.end(), [&](const HealthReport::Note& x) {
      return !n.stream.empty() && !x.stream.empty() && x.text == n.text;
    });
    if (same != notes.end()) {
      same->stream += ", " + n.stream;
    } else {
      notes.push_back(n);
    }
  }
  for (const HealthReport::Note& n : notes) {
    out += "  note: " + (n.stream.empty() ? n.text : n.stream + ": " + n.text) + "\n";
  }
  return out;
}

int ExitCodeOf(const HealthReport& r) {
  if (!r.problems.empty()) return kExitRefused;
  if (!r.warnings.empty()) return kExitWarnings;
  return kExitDone;
}

}  // namespace ftcal::doctor
