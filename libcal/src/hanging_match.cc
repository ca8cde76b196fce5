// Phase matching of step 1 (docs/method.md "Step 1"): each of a leg's four hanging series is
// averaged onto a grid of phase_bins cells per leg cycle, short gaps are interpolated, and the
// four are matched bin by bin, cycle by cycle, so that every matched sample i has the four
// readings at the same leg phase. The pair equations (hanging_pair.cc) and the CoM smoother
// (leg_com.cc) run on these samples.
#include <algorithm>
#include <cmath>
#include <sstream>

#include "hanging_internal.h"

namespace ftcal {
namespace hanging_detail {
namespace {

// A cycle counts towards the spread when at least this fraction of its bins was matched.
constexpr double kFullCycleFraction = 0.9;

// One series of one leg, averaged into cells of the continuous phase grid (cell n covers
// unwrapped phase [n, n+1) / bins), with the cells listed per bin in cycle order.
struct BinnedSeries {
  double cycles = 0.0;
  std::vector<Vec6> cell_wrench;
  std::vector<double> cell_phase;  // mean leg phase of the cell's samples, in [0, 1)
  std::vector<int> occurrences;    // per bin: how many cycles have it
  std::vector<int> lookup;         // [bin * max_occurrences + j] -> cell
  int max_occurrences = 0;
};

void ValidateSamples(const LegSamples& samples, HangSeries series, int leg) {
  const size_t n = samples.t_s.size();
  if (n == 0) Fail(Where(series, leg) + "no samples");
  if (samples.angle_rad.size() != n || samples.wrench.size() != n) {
    std::ostringstream s;
    s << Where(series, leg) << "mismatched sample vectors: " << n << " times, "
      << samples.angle_rad.size() << " angles, " << samples.wrench.size() << " wrenches";
    Fail(s.str());
  }
  for (size_t i = 0; i < n; ++i) {
    if (!std::isfinite(samples.t_s[i]) || !std::isfinite(samples.angle_rad[i]) ||
        !samples.wrench[i].allFinite()) {
      std::ostringstream s;
      s << Where(series, leg) << "non-finite value in sample " << i << " (t_s " << samples.t_s[i]
        << ", angle_rad " << samples.angle_rad[i] << ", wrench " << samples.wrench[i].transpose()
        << ")";
      Fail(s.str());
    }
    if (i > 0 && samples.t_s[i] < samples.t_s[i - 1]) {
      std::ostringstream s;
      s << Where(series, leg) << "sample " << i << " is earlier than the one before (t_s "
        << samples.t_s[i] << " < " << samples.t_s[i - 1] << ")";
      Fail(s.str());
    }
  }
}

BinnedSeries BinSeries(const LegSamples& samples, HangSeries series, int leg,
                       const HangingOptions& options) {
  const int bins = options.phase_bins;
  const size_t n = samples.t_s.size();
  // Unwrapped angle: consecutive samples are far less than half a turn apart, so the wrap of
  // the shaft angle at +-pi is undone by wrapping each increment.
  double psi = samples.angle_rad[0] / kTwoPi;
  double psi_min = psi, psi_max = psi;
  const double psi_first = psi;
  std::vector<double> psi_all(n);
  psi_all[0] = psi;
  for (size_t i = 1; i < n; ++i) {
    psi += WrapPi(samples.angle_rad[i] - samples.angle_rad[i - 1]) / kTwoPi;
    psi_all[i] = psi;
    psi_min = std::min(psi_min, psi);
    psi_max = std::max(psi_max, psi);
  }
  BinnedSeries out;
  out.cycles = std::abs(psi - psi_first);
  if (out.cycles < options.min_cycles) {
    std::ostringstream s;
    s << Where(series, leg) << "the leg turned " << out.cycles << " cycles, need at least "
      << options.min_cycles;
    Fail(s.str());
  }
  const bool forward = psi > psi_first;
  const long n_min = static_cast<long>(std::floor(psi_min * bins));
  const long n_max = static_cast<long>(std::floor(psi_max * bins));
  const long num_cells = n_max - n_min + 1;
  if (num_cells > 100000000L / bins) {
    Fail(Where(series, leg) + "shaft angle spans an implausible number of turns");
  }
  // Per cell: the samples' wrench is regressed on their position x in the cell and evaluated
  // at the bin centre, so that every series gives its value at the same phase (a plain mean
  // would sit at each series' own mean phase, which differs between series by up to half a
  // bin: ~0.5 mm of CoM on a typical leg). Too few or too clustered samples: their mean.
  out.cell_wrench.assign(num_cells, Vec6::Zero());
  std::vector<double> cell_pos(num_cells, 0.0);  // position of the value inside the cell, [0, 1)
  std::vector<int> count(num_cells, 0);
  std::vector<double> sum_x(num_cells, 0.0), sum_xx(num_cells, 0.0);
  std::vector<Vec6> sum_xw(num_cells, Vec6::Zero());
  for (size_t i = 0; i < n; ++i) {
    const double x = psi_all[i] * bins;
    const long cell = std::min(static_cast<long>(std::floor(x)) - n_min, num_cells - 1);
    const double pos = x - static_cast<double>(cell + n_min);
    out.cell_wrench[cell] += samples.wrench[i];
    sum_x[cell] += pos;
    sum_xx[cell] += pos * pos;
    sum_xw[cell] += pos * samples.wrench[i];
    ++count[cell];
  }
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    const double k = count[c];
    const Vec6 mean_w = out.cell_wrench[c] / k;
    const double mean_x = sum_x[c] / k;
    const double var_x = sum_xx[c] / k - mean_x * mean_x;
    // 1/48: half the spread of samples uniform over the cell.
    if (count[c] >= 3 && var_x >= 1.0 / 48.0) {
      const Vec6 slope = (sum_xw[c] / k - mean_x * mean_w) / var_x;
      out.cell_wrench[c] = mean_w + slope * (0.5 - mean_x);
      cell_pos[c] = 0.5;
    } else {
      out.cell_wrench[c] = mean_w;
      cell_pos[c] = mean_x;
    }
  }
  // Short gaps (a few bins without a sample, e.g. a fast stretch or a dropped packet) are
  // filled by linear interpolation between the neighbouring cells at the bin centre.
  long last = -1;
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    if (last >= 0 && c - last > 1 && c - last - 1 <= options.max_gap_bins) {
      const double x0 = last + cell_pos[last], x1 = c + cell_pos[c];
      for (long g = last + 1; g < c; ++g) {
        const double w = (g + 0.5 - x0) / (x1 - x0);
        out.cell_wrench[g] = (1.0 - w) * out.cell_wrench[last] + w * out.cell_wrench[c];
        cell_pos[g] = 0.5;
        count[g] = -1;  // interpolated
      }
    }
    last = c;
  }
  // Cells per bin in the order the leg passed them.
  out.occurrences.assign(bins, 0);
  out.cell_phase.assign(num_cells, 0.0);
  auto bin_of = [&](long c) {
    const long global = c + n_min;
    return static_cast<int>(((global % bins) + bins) % bins);
  };
  for (long c = 0; c < num_cells; ++c) {
    if (count[c] == 0) continue;
    const int b = bin_of(c);
    out.cell_phase[c] = (b + cell_pos[c]) / bins;
    ++out.occurrences[b];
  }
  out.max_occurrences = *std::max_element(out.occurrences.begin(), out.occurrences.end());
  out.lookup.assign(static_cast<size_t>(bins) * out.max_occurrences, -1);
  std::vector<int> filled(bins, 0);
  for (long k = 0; k < num_cells; ++k) {
    const long c = forward ? k : num_cells - 1 - k;
    if (count[c] == 0) continue;
    const int b = bin_of(c);
    out.lookup[static_cast<size_t>(b) * out.max_occurrences + filled[b]++] = static_cast<int>(c);
  }
  return out;
}

}  // namespace

LegMatched MatchLeg(const std::array<const HangingRecording*, kNumHangSeries>& by_series,
                    const std::array<int, 4>& series_of_slot, int leg,
                    const HangingOptions& options) {
  const int bins = options.phase_bins;
  const std::string leg_where = LegWhere(leg);
  // Bin the four series and match them.
  std::array<BinnedSeries, 4> binned;
  for (int slot = 0; slot < 4; ++slot) {
    const HangingRecording& rec = *by_series[series_of_slot[slot]];
    ValidateSamples(rec.legs[leg], rec.series, leg);
    binned[slot] = BinSeries(rec.legs[leg], rec.series, leg, options);
  }
  std::vector<int> matched_per_bin(bins);
  int covered = 0, cycles_max = 0;
  for (int b = 0; b < bins; ++b) {
    int n_b = binned[0].occurrences[b];
    for (int slot = 1; slot < 4; ++slot) n_b = std::min(n_b, binned[slot].occurrences[b]);
    matched_per_bin[b] = n_b;
    covered += n_b > 0;
    cycles_max = std::max(cycles_max, n_b);
  }
  if (covered < options.min_phase_coverage * bins) {
    int worst = 0, worst_covered = bins + 1;
    for (int slot = 0; slot < 4; ++slot) {
      const int c = static_cast<int>(std::count_if(binned[slot].occurrences.begin(),
                                                   binned[slot].occurrences.end(),
                                                   [](int o) { return o > 0; }));
      if (c < worst_covered) worst_covered = c, worst = slot;
    }
    std::ostringstream s;
    s << Where(by_series[series_of_slot[worst]]->series, leg) << "only " << covered << " of "
      << bins << " phase bins are matched in all four series (this series covers " << worst_covered
      << "): less than one full cycle of phase coverage";
    Fail(s.str());
  }
  LegMatched m;
  {
    size_t total = 0;
    for (int n_b : matched_per_bin) total += n_b;
    for (auto& w : m.w) w.reserve(total);
    m.phase.reserve(total);
    m.bin.reserve(total);
  }
  for (int j = 0; j < cycles_max; ++j) {
    const int begin = static_cast<int>(m.phase.size());
    for (int b = 0; b < bins; ++b) {
      if (j >= matched_per_bin[b]) continue;
      double phase = 0.0;
      for (int slot = 0; slot < 4; ++slot) {
        const BinnedSeries& bs = binned[slot];
        const int cell = bs.lookup[static_cast<size_t>(b) * bs.max_occurrences + j];
        m.w[slot].push_back(bs.cell_wrench[cell]);
        phase += bs.cell_phase[cell];
      }
      m.phase.push_back(phase / 4.0);
      m.bin.push_back(b);
    }
    const int end = static_cast<int>(m.phase.size());
    if (end - begin >= kFullCycleFraction * bins) m.cycles.emplace_back(begin, end);
  }
  if (static_cast<int>(m.cycles.size()) < options.min_cycles) {
    std::ostringstream s;
    s << leg_where << "only " << m.cycles.size()
      << " full cycles are matched across the four series, need at least " << options.min_cycles;
    Fail(s.str());
  }
  return m;
}

}  // namespace hanging_detail
}  // namespace ftcal
