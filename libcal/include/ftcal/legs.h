// Leg names and their order (docs/method.md: HL ML FL HR MR FR everywhere).
#pragma once

#include <array>
#include <optional>
#include <string_view>

namespace ftcal {

inline constexpr int kNumLegs = 6;
inline constexpr std::array<std::string_view, kNumLegs> kLegNames = {"HL", "ML", "FL",
                                                                     "HR", "MR", "FR"};

// Index of a leg name in kLegNames, or nullopt for an unknown name.
inline std::optional<int> LegIndex(std::string_view name) {
  for (int i = 0; i < kNumLegs; ++i) {
    if (kLegNames[i] == name) return i;
  }
  return std::nullopt;
}

}  // namespace ftcal
