// What the files of step 1 share and the public header does not show: the slots of the four
// series, the matched samples of one leg, the half-differences and half-sums of a pair, and the
// functions one file calls in another (hanging.cc runs the step; hanging_match.cc puts the four
// series on a common phase grid; hanging_pair.cc solves eq. 4-7 of one pair; leg_com.cc turns
// the pairs' torques into the leg CoM curve). Internal to libcal: tests use only hanging.h.
#pragma once

#include <array>
#include <cmath>
#include <string>
#include <utility>
#include <vector>

#include "ftcal/hanging.h"

namespace ftcal {
namespace hanging_detail {

constexpr double kTwoPi = 2.0 * M_PI;
constexpr double kRadToDeg = 180.0 / M_PI;
// Slots of the four series per leg: gravity along +x, -x, +z, -z of the transducer.
constexpr int kSlotXDown = 0, kSlotXUp = 1, kSlotZDown = 2, kSlotZUp = 3;

// "hanging series <SERIES>, leg <LEG>: ", the start of every message about one series of a leg.
std::string Where(HangSeries series, int leg);
// "hanging, leg <LEG>: ".
std::string LegWhere(int leg);
[[noreturn]] void Fail(const std::string& what);

// To [-pi, pi] (std::remainder is exact but several times slower, and this runs per sample).
inline double WrapPi(double angle) { return angle - kTwoPi * std::nearbyint(angle / kTwoPi); }

// Two unit vectors completing unit n to an orthonormal basis.
inline void OrthonormalComplement(const Vec3& n, Vec3* u, Vec3* v) {
  const Vec3 seed = std::abs(n.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  *u = n.cross(seed).normalized();
  *v = n.cross(*u);
}

// R(s) v for the first-order (I + [s]) or exact (exp([s])) model (hanging_pair.cc).
Vec3 RotApply(const Vec3& s, const Vec3& v, bool exact);

// The matched samples of one leg: index i runs over cycles j (major) and bins (minor).
struct LegMatched {
  std::array<std::vector<Vec6>, 4> w;  // per slot
  std::vector<double> phase;
  std::vector<int> bin;
  std::vector<std::pair<int, int>> cycles;  // [begin, end) of each full cycle
  int num_cycles_total = 0;
};

// The four series of one leg binned on the phase grid and matched bin by bin, cycle by cycle
// (hanging_match.cc). series_of_slot[slot] indexes by_series. Throws, naming the series, when a
// series is malformed or the match covers too little phase or too few cycles.
LegMatched MatchLeg(const std::array<const HangingRecording*, kNumHangSeries>& by_series,
                    const std::array<int, 4>& series_of_slot, int leg,
                    const HangingOptions& options);

// Half-differences and half-sums of one pair.
struct PairData {
  Vec3 axis = Vec3::UnitX();
  int axis_index = 0;
  std::vector<Vec3> f_minus, tau_minus, f_plus, tau_plus;
};

PairData MakePair(const LegMatched& m, int slot_down, int slot_up, int axis_index);

// One pair's estimate on a range of matched samples.
struct PairEstimate {
  Vec3 s_plus = Vec3::Zero(), s_minus = Vec3::Zero();
  Vec3 s_down = Vec3::Zero(), s_up = Vec3::Zero();
  double weight_n = 0.0;
  Vec3 d = Vec3::Zero();
  Vec3 force_offset = Vec3::Zero(), torque_offset = Vec3::Zero();
};

// How a pair is solved: with or without the mounting rotation s (the two variants model
// selection compares), first-order or exact rotations, and whether s+ is refined by least
// squares after its closed form.
struct PairSolve {
  bool use_s = true;
  bool exact_rotations = true;
  bool refine_s_plus = true;
};

// The pair on all matched samples (into *full) and, for the sigmas, on each full cycle alone.
// r_fit: the fitted CoM curve at each matched sample's phase. where: the start of messages.
HangingPairResult PairResult(const PairData& pair, const std::vector<Vec3>& r_fit,
                             const LegMatched& m, const PairSolve& how, const std::string& where,
                             PairEstimate* full);

// Inverse-variance weighting of the two pairs' estimates.
ScalarSigma Combine(const ScalarSigma& a, const ScalarSigma& b);
Vec3Sigma Combine(const Vec3Sigma& a, const Vec3Sigma& b);

// t(0.975, n-1) / z(0.975), for a sigma taken from the spread of n values: with that spread the
// only measure of the noise, +-1.96 of the widened sigmas is the Student-t 95 % interval
// (docs/method.md, step 1). 1.31 for six values, 1.15 for ten, 1.02 for fifty.
double StudentWidening(int n);

// Standard error of the mean of per-cycle values (NaN for fewer than two), per component,
// widened by StudentWidening(n).
double StdError(const std::vector<double>& v);
Vec3 StdError3(const std::vector<Vec3>& v);

// Leg CoM per matched sample (leg_com.cc): each pair's smoother, the null space resolved
// between the two pairs.
std::vector<Vec3> ResolveLegCom(const PairData& px, const PairData& pz,
                                const HangingOptions& options);
// The sinusoid fit of the resolved CoM and its sigmas from the per-cycle fits.
ComFitResult FitLegCom(const LegMatched& m, const std::vector<Vec3>& r);
// Per phase bin, the median and spread over cycles of the resolved CoM (report Fig. 4/7).
ComBins BinLegCom(const LegMatched& m, const std::vector<Vec3>& r, int bins);

}  // namespace hanging_detail
}  // namespace ftcal
