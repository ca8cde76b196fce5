#include "sim/offset_drift.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <stdexcept>

#include "sim/flags.h"

namespace ftcal {
namespace {

const char* ShapeName(OffsetDriftTerm::Shape s) {
  switch (s) {
    case OffsetDriftTerm::Shape::kStep:
      return "step";
    case OffsetDriftTerm::Shape::kRamp:
      return "ramp";
    case OffsetDriftTerm::Shape::kWarmup:
      return "warm-up";
  }
  return "?";
}

}  // namespace

void OffsetDrift::Add(const OffsetDriftTerm& term) {
  const std::string what = std::string("offset drift ") + ShapeName(term.shape) + ": ";
  if (term.leg < 0 || term.leg >= kNumLegs) {
    throw std::invalid_argument(what + "leg index " + std::to_string(term.leg) + " out of range");
  }
  if (!std::isfinite(term.t0_s) || !std::isfinite(term.t1_s) || !term.change.allFinite()) {
    throw std::invalid_argument(what + "times and changes must be finite");
  }
  if (term.shape == OffsetDriftTerm::Shape::kRamp && !(term.t1_s > term.t0_s)) {
    throw std::invalid_argument(what + "must end (" + std::to_string(term.t1_s) +
                                " s) after it starts (" + std::to_string(term.t0_s) + " s)");
  }
  if (term.shape == OffsetDriftTerm::Shape::kWarmup && !(term.t1_s > 0.0)) {
    throw std::invalid_argument(what + "tau must be > 0 s, got " + std::to_string(term.t1_s));
  }
  terms_.push_back(term);
}

void OffsetDrift::AddFlag(OffsetDriftTerm::Shape shape, const std::string& text,
                          const std::string& flag) {
  const std::vector<std::string> parts = sim::SplitFlag(text, ':');
  const size_t times = shape == OffsetDriftTerm::Shape::kStep ? 1 : 2;
  const char* form = shape == OffsetDriftTerm::Shape::kStep ? "LEG:AT_S:fx,fy,fz,tx,ty,tz"
                     : shape == OffsetDriftTerm::Shape::kRamp
                         ? "LEG:FROM_S:UNTIL_S:fx,fy,fz,tx,ty,tz"
                         : "LEG:FROM_S:TAU_S:fx,fy,fz,tx,ty,tz";
  if (parts.size() != times + 2) {
    throw std::invalid_argument(flag + " '" + text + "': expected " + form);
  }
  OffsetDriftTerm term;
  term.shape = shape;
  term.t0_s = sim::ParseFlagNumber(parts[1], flag);
  if (times == 2) term.t1_s = sim::ParseFlagNumber(parts[2], flag);
  const std::vector<std::string> values = sim::SplitFlag(parts.back(), ',');
  if (values.size() != 6) {
    throw std::invalid_argument(flag + " '" + text + "': six changes (N, N*m) expected, got " +
                                std::to_string(values.size()));
  }
  for (int i = 0; i < 6; ++i) term.change[i] = sim::ParseFlagNumber(values[i], flag);
  std::vector<int> legs;
  if (parts[0] == "all") {
    for (int k = 0; k < kNumLegs; ++k) legs.push_back(k);
  } else if (const auto k = LegIndex(parts[0])) {
    legs.push_back(*k);
  } else {
    throw std::invalid_argument(flag + " '" + text + "': unknown leg '" + parts[0] +
                                "' (HL ML FL HR MR FR or all)");
  }
  for (int k : legs) {
    term.leg = k;
    try {
      Add(term);
    } catch (const std::invalid_argument& e) {
      throw std::invalid_argument(flag + " '" + text + "': " + e.what());
    }
  }
}

Vec6 OffsetDrift::OffsetChange(int leg, double t_s) const {
  Vec6 d = Vec6::Zero();
  for (const OffsetDriftTerm& term : terms_) {
    if (term.leg != leg || t_s < term.t0_s) continue;
    switch (term.shape) {
      case OffsetDriftTerm::Shape::kStep:
        d += term.change;
        break;
      case OffsetDriftTerm::Shape::kRamp:
        d += term.change * std::min(1.0, (t_s - term.t0_s) / (term.t1_s - term.t0_s));
        break;
      case OffsetDriftTerm::Shape::kWarmup:
        d += term.change * -std::expm1(-(t_s - term.t0_s) / term.t1_s);
        break;
    }
  }
  return d;
}

std::string DriftTruthCsv(const OffsetDrift& drift, const RobotCalibration& truth,
                          const std::function<const RobotCalibration&(double)>& offsets_at,
                          const std::function<int64_t(double)>& utime_at, double end_s,
                          double period_s) {
  if (!(period_s > 0.0) || !std::isfinite(end_s)) {
    throw std::invalid_argument("drift truth: period must be > 0 and the end finite");
  }
  std::vector<double> times;
  const long n = static_cast<long>(std::floor(end_s / period_s));
  for (long i = 0; i <= n; ++i) times.push_back(i * period_s);
  times.push_back(end_s);
  // Both sides of a step (1 us apart), so that interpolating the file never smears one.
  for (const OffsetDriftTerm& term : drift.terms()) {
    if (term.shape != OffsetDriftTerm::Shape::kStep) continue;
    if (term.t0_s > 0.0 && term.t0_s <= end_s) {
      times.push_back(term.t0_s - 1e-6);
      times.push_back(term.t0_s);
    }
  }
  std::sort(times.begin(), times.end());
  times.erase(std::unique(times.begin(), times.end()), times.end());
  std::string out =
      "t_s,utime,leg,d_fx_n,d_fy_n,d_fz_n,d_tx_nm,d_ty_nm,d_tz_nm,"
      "offset_fx_n,offset_fy_n,offset_fz_n,offset_tx_nm,offset_ty_nm,offset_tz_nm\n";
  char line[512];
  for (double t : times) {
    const RobotCalibration& base = offsets_at(t);
    for (int k = 0; k < kNumLegs; ++k) {
      const Vec6 offset = base.leg[k].offset + drift.OffsetChange(k, t);
      const Vec6 d = offset - truth.leg[k].offset;
      int used =
          std::snprintf(line, sizeof line, "%.6f,%lld,%s", t, static_cast<long long>(utime_at(t)),
                        std::string(kLegNames[k]).c_str());
      for (int i = 0; i < 6; ++i) {
        used += std::snprintf(line + used, sizeof line - used, ",%.9g", d[i]);
      }
      for (int i = 0; i < 6; ++i) {
        used += std::snprintf(line + used, sizeof line - used, ",%.9g", offset[i]);
      }
      out.append(line, static_cast<size_t>(used));
      out += '\n';
    }
  }
  return out;
}

}  // namespace ftcal
