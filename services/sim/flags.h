// Parsing the colon-separated fault flags of ftcal-sim and the device emulators, header-only so
// that an emulator built without the twin (and so without ftcal_sim_live) reads its flags the
// same way as ftcal-sim live.
#pragma once

#include <cmath>
#include <cstddef>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace ftcal::sim {

// "A:B:C" -> {"A", "B", "C"}.
inline std::vector<std::string> SplitFlag(const std::string& text, char sep) {
  std::vector<std::string> out;
  std::stringstream ss(text);
  for (std::string item; std::getline(ss, item, sep);) out.push_back(item);
  return out;
}

// A number in a flag's text, or std::invalid_argument naming the flag.
inline double ParseFlagNumber(const std::string& text, const std::string& flag) {
  try {
    std::size_t used = 0;
    const double v = std::stod(text, &used);
    if (used != text.size() || !std::isfinite(v)) throw std::invalid_argument(text);
    return v;
  } catch (const std::exception&) {
    throw std::invalid_argument(flag + ": '" + text + "' is not a number");
  }
}

}  // namespace ftcal::sim
