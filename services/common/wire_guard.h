// A received message costs at most its size: the encoded bytes are checked before LCM's
// generated decoder sees them.
//
// LCM 1.3.1's C++ decoders trust length fields: they resize a vector to the length before
// checking that the bytes are there (a 153-byte mocap_body_t claiming 4e8 markers allocated
// 8.8 GB), compute `n * 8 > maxlen` in int and overflow for n = 3e8 (reading past the buffer),
// throw std::length_error out of a string of length 0 or a negative array length, and decode
// `double v[n][m]` with m = 0 into n empty vectors (1.1 GB from 32 bytes). No option of LCM
// changes that, so every typed subscription walks the bytes with the message's schema (one
// table per .lcm file, generated at build time by cmake/lcm_wire_schema.py) and refuses, before
// any allocation, a message whose
//   - fingerprint is not the type's,
//   - length field is negative or above its cap (kMaxLength, or the type's MAX_<MEMBER>),
//   - arrays (multi-dimensional ones multiplied out) need more bytes than remain,
//   - strings have length 0, run past the end, lack their terminating NUL or hold another,
//   - booleans are neither 0 nor 1,
//   - bytes run past the last field (trailing bytes),
//   - decoded form would take more than kMaxDecodedBytesPerByte x its size in memory (empty
//     inner dimensions and strings cost container headers no wire byte pays for).
// Then the decoder runs inside a try, and must consume exactly the received size.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

namespace ftcal::wire {

enum class Prim : uint8_t {
  kInt8,
  kInt16,
  kInt32,
  kInt64,
  kByte,
  kBoolean,
  kFloat,
  kDouble,
  kString
};

struct Dim {
  int64_t fixed;   // the size, when `member` < 0
  int32_t member;  // index of the earlier integer member that holds the size, or -1
};

struct Field {
  const char* name;
  Prim type;
  uint8_t ndims;
  Dim dims[3];
  // For an integer member that sizes arrays: the largest size it may give (the type's
  // `const MAX_<MEMBER>`, e.g. ft_batch_t's MAX_N); 0: kMaxLength.
  int64_t cap = 0;
};

struct Schema {
  const char* name;      // "ftcal.mocap_body_t"
  uint64_t fingerprint;  // the first 8 bytes of every encoded message, as getHash()
  const Field* fields;
  int num_fields;
};

// Caps every length field: no ftcal message has more elements in one dimension (the largest
// is calibration_t's protobuf bytes).
constexpr int64_t kMaxLength = 16 << 20;
// Decoded size allowed per received byte, plus kDecodedSlackBytes: a string element is a
// 32-byte std::string for at least 5 wire bytes, a boolean or byte one for one.
constexpr int64_t kMaxDecodedBytesPerByte = 8;
constexpr int64_t kDecodedSlackBytes = 4096;

struct Refusal {
  std::string kind;    // short and fixed, for counting once per kind ("length over cap")
  std::string detail;  // which field, which value, where
};

// The schemas of lcmtypes/*.lcm (generated).
const std::vector<const Schema*>& FtcalSchemas();

// An older version of one of ftcal's types, as logs recorded before a change carry it
// (lcmtypes/legacy/). Check() names it when it meets its fingerprint, with the command that
// converts the log (ftcal-log-upgrade).
struct LegacyVersion {
  uint64_t fingerprint;
  const char* name;  // the type it is a version of: "ftcal.ft_sample_t"
  const char* what;  // "one record a message, before ft_batch_t (1faf3aa)"
};
// The versions of lcmtypes/legacy/ (generated, beside FtcalSchemas()).
const std::vector<LegacyVersion>& FtcalSchemasLegacy();
// The older version with this fingerprint; nullptr when none is known.
const LegacyVersion* FindLegacyVersion(uint64_t fingerprint);
// Looks up a schema by fingerprint among FtcalSchemas() and those added by Register();
// nullptr when none.
const Schema* FindSchema(uint64_t fingerprint);
// Adds schemas of other message types (tests' own types). Not thread-safe: call at start.
void Register(const std::vector<const Schema*>& schemas);

// Checks `data[0, size)` as an encoded message of `schema`; nullopt when it may be decoded.
std::optional<Refusal> Check(const Schema& schema, const void* data, int size);

// A message that passed Check(), as text: "name=value" per field, arrays in brackets (byte
// arrays as their length). For log tools that print what they cannot link a type for.
std::string Describe(const Schema& schema, const void* data, int size);

// Check() then Msg::decode inside a try; nullopt and `*msg` filled when the message is good.
template <class Msg>
std::optional<Refusal> Decode(const void* data, int size, Msg* msg) {
  static const Schema* const schema = FindSchema(static_cast<uint64_t>(Msg::getHash()));
  if (schema == nullptr) {
    return Refusal{"no wire schema", std::string("no schema for ") + Msg::getTypeName() +
                                         " (not generated from lcmtypes/?)"};
  }
  if (auto refused = Check(*schema, data, size)) return refused;
  int used = -1;
  try {
    used = msg->decode(data, 0, size);
  } catch (const std::exception& e) {
    return Refusal{"decoder threw",
                   std::string("decoder threw after the checks passed: ") + e.what()};
  }
  if (used != size) {
    return Refusal{"decoder disagrees", "decoder used " + std::to_string(used) + " of " +
                                            std::to_string(size) + " bytes the checks passed"};
  }
  return std::nullopt;
}

}  // namespace ftcal::wire
