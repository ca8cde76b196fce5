// LCM's wire and log formats store integers big-endian: read in place from a byte pointer (no
// alignment needed).
#pragma once

#include <endian.h>

#include <cstdint>
#include <cstring>

namespace ftcal {

inline uint16_t Be16(const uint8_t* p) {
  uint16_t v;
  std::memcpy(&v, p, sizeof v);
  return be16toh(v);
}
inline uint32_t Be32(const uint8_t* p) {
  uint32_t v;
  std::memcpy(&v, p, sizeof v);
  return be32toh(v);
}
inline uint64_t Be64(const uint8_t* p) {
  uint64_t v;
  std::memcpy(&v, p, sizeof v);
  return be64toh(v);
}

}  // namespace ftcal
