#include "common/wire_guard.h"

#include <algorithm>
#include <cstring>
#include <string>
#include <utility>

namespace ftcal::wire {
namespace {

std::vector<const Schema*>& Registered() {
  static std::vector<const Schema*> schemas;
  return schemas;
}

int64_t WireBytes(Prim p) {
  switch (p) {
    case Prim::kInt8:
    case Prim::kByte:
    case Prim::kBoolean:
      return 1;
    case Prim::kInt16:
      return 2;
    case Prim::kInt32:
    case Prim::kFloat:
      return 4;
    case Prim::kInt64:
    case Prim::kDouble:
      return 8;
    case Prim::kString:
      return 5;  // the shortest: a length of 1 and the NUL
  }
  return 1;
}

// Memory of one decoded element (a string's characters are added per string).
int64_t DecodedBytes(Prim p) {
  return p == Prim::kString ? static_cast<int64_t>(sizeof(std::string)) : WireBytes(p);
}

bool IsInteger(Prim p) {
  return p == Prim::kInt8 || p == Prim::kInt16 || p == Prim::kInt32 || p == Prim::kInt64;
}

// Big-endian, as LCM encodes. The fixed widths are spelled out because this runs for every
// integer member of every message received (a replay decodes millions).
int64_t ReadSigned(const uint8_t* p, int64_t n) {
  switch (n) {
    case 1:
      return static_cast<int8_t>(p[0]);
    case 2: {
      uint16_t v;
      std::memcpy(&v, p, 2);
      return static_cast<int16_t>(__builtin_bswap16(v));
    }
    case 4: {
      uint32_t v;
      std::memcpy(&v, p, 4);
      return static_cast<int32_t>(__builtin_bswap32(v));
    }
    case 8: {
      uint64_t v;
      std::memcpy(&v, p, 8);
      return static_cast<int64_t>(__builtin_bswap64(v));
    }
    default: {
      uint64_t v = 0;
      for (int64_t i = 0; i < n; ++i) v = v << 8 | p[i];
      const int shift = static_cast<int>(64 - 8 * n);
      return static_cast<int64_t>(v << shift) >> shift;  // sign-extends
    }
  }
}

// A field the run below may take: a number or a one-dimensional array of a fixed length, not
// a string (a length and a NUL to check) nor a boolean (each byte to check). For such a field
// Check() only needs the bytes to be there, and its decoded size is its wire size.
bool PlainFixed(const Field& f) {
  if (f.type == Prim::kString || f.type == Prim::kBoolean) return false;
  if (f.ndims == 0) return true;
  return f.ndims == 1 && f.dims[0].member < 0 && f.dims[0].fixed >= 0 &&
         f.dims[0].fixed <= kMaxLength;
}

// Per field i of a schema, the wire bytes of the run of PlainFixed fields starting at i and
// the field after it (run_end[i] == i: not PlainFixed). Check() takes such a run with one
// bounds check instead of one per field: most of a message's fields are fixed-size numbers.
// Only the integers a later field's length refers to are read in a run (most types have none,
// and reading every integer of every message was most of Check()'s time in a replay): `reads`
// lists them for the run starting at each field i (a run that does not fit is walked field by
// field, and the rest of it taken from the next field on), with their offsets from field i.
struct RunRead {
  int field;
  int64_t offset;
  int64_t width;
};
struct Runs {
  std::vector<int64_t> bytes;
  std::vector<int> end;
  std::vector<std::vector<RunRead>> reads;
};

Runs RunsOf(const Schema& schema) {
  const auto n = static_cast<size_t>(schema.num_fields);
  Runs r{std::vector<int64_t>(n + 1, 0), std::vector<int>(n + 1, 0),
         std::vector<std::vector<RunRead>>(n + 1)};
  r.end[n] = schema.num_fields;
  for (int i = schema.num_fields - 1; i >= 0; --i) {
    const Field& f = schema.fields[i];
    if (!PlainFixed(f)) {
      r.end[static_cast<size_t>(i)] = i;
      continue;
    }
    const int64_t elems = f.ndims == 0 ? 1 : f.dims[0].fixed;
    const size_t next = static_cast<size_t>(i) + 1;
    const bool joins = r.end[next] > i + 1;  // the next field starts a run: extend it
    r.end[static_cast<size_t>(i)] = joins ? r.end[next] : i + 1;
    r.bytes[static_cast<size_t>(i)] = elems * WireBytes(f.type) + (joins ? r.bytes[next] : 0);
  }
  std::vector<bool> referenced(n, false);
  for (size_t i = 0; i < n; ++i) {
    const Field& f = schema.fields[i];
    for (int d = 0; d < f.ndims; ++d) {
      const int32_t m = f.dims[d].member;
      if (m >= 0 && static_cast<size_t>(m) < n) referenced[static_cast<size_t>(m)] = true;
    }
  }
  for (int i = 0; i < schema.num_fields; ++i) {
    int64_t offset = 0;
    for (int j = i; j < r.end[static_cast<size_t>(i)]; ++j) {
      const Field& g = schema.fields[j];
      const int64_t elem = WireBytes(g.type);
      if (g.ndims == 0 && IsInteger(g.type) && referenced[static_cast<size_t>(j)]) {
        r.reads[static_cast<size_t>(i)].push_back({j, offset, elem});
      }
      offset += g.ndims == 0 ? elem : g.dims[0].fixed * elem;
    }
  }
  return r;
}

bool IsListed(const Schema* schema);

// The runs of the schemas this thread checked, found by address: a process checks a handful
// of types millions of times. (Thread-local: no lock on the path of every message.) Only the
// generated and registered schemas are kept, which live as long as the process: another
// schema could be a temporary whose address a different one takes later.
const Runs& RunsFor(const Schema& schema) {
  thread_local std::vector<std::pair<const Schema*, Runs>> known;
  thread_local Runs once;
  for (const auto& [s, runs] : known) {
    if (s == &schema) return runs;
  }
  if (!IsListed(&schema)) return once = RunsOf(schema);
  known.emplace_back(&schema, RunsOf(schema));
  return known.back().second;
}

}  // namespace

const Schema* FindSchema(uint64_t fingerprint) {
  for (const Schema* s : FtcalSchemas()) {
    if (s->fingerprint == fingerprint) return s;
  }
  for (const Schema* s : Registered()) {
    if (s->fingerprint == fingerprint) return s;
  }
  return nullptr;
}

const LegacyVersion* FindLegacyVersion(uint64_t fingerprint) {
  for (const LegacyVersion& v : FtcalSchemasLegacy()) {
    if (v.fingerprint == fingerprint) return &v;
  }
  return nullptr;
}

namespace {
bool IsListed(const Schema* schema) {
  const auto& generated = FtcalSchemas();
  const auto& registered = Registered();
  return std::find(generated.begin(), generated.end(), schema) != generated.end() ||
         std::find(registered.begin(), registered.end(), schema) != registered.end();
}
}  // namespace

void Register(const std::vector<const Schema*>& schemas) {
  Registered().insert(Registered().end(), schemas.begin(), schemas.end());
}

std::optional<Refusal> Check(const Schema& schema, const void* data, int size) {
  const auto* bytes = static_cast<const uint8_t*>(data);
  const int64_t total = size;
  if (total < 8) {
    return Refusal{"truncated", std::to_string(total) + " bytes: shorter than a fingerprint"};
  }
  const uint64_t fingerprint = static_cast<uint64_t>(ReadSigned(bytes, 8));
  if (fingerprint != schema.fingerprint) {
    char text[160];
    std::snprintf(text, sizeof text, "fingerprint %016llx, not %s's %016llx",
                  static_cast<unsigned long long>(fingerprint), schema.name,
                  static_cast<unsigned long long>(schema.fingerprint));
    std::string detail = text;
    // A log recorded before a change of ftcal's types: say which version, and what to do.
    if (const LegacyVersion* legacy = FindLegacyVersion(fingerprint)) {
      detail += std::string(": an older ") + legacy->name + " (" + legacy->what +
                "): convert the log with ftcal-log-upgrade OLD NEW";
    }
    return Refusal{"wrong fingerprint", detail};
  }
  const int64_t decoded_bound = kMaxDecodedBytesPerByte * total + kDecodedSlackBytes;
  int64_t pos = 8;
  int64_t decoded = 0;
  // The integer members' values (array sizes), on the stack for every ftcal type (the largest
  // has a few dozen fields): this runs for every message received.
  constexpr int kStackFields = 64;
  // Only the schema's own fields are cleared: clearing all 64 was a fifth of this function.
  int64_t stack_values[kStackFields];
  std::vector<int64_t> heap_values;
  int64_t* values = stack_values;
  if (schema.num_fields > kStackFields) {
    heap_values.assign(static_cast<size_t>(schema.num_fields), 0);
    values = heap_values.data();
  } else {
    std::fill_n(values, schema.num_fields, int64_t{0});
  }
  const Runs& runs = RunsFor(schema);
  for (int i = 0; i < schema.num_fields; ++i) {
    // A run of fixed-size numbers that fits, within the decoded bound: every field in it
    // would pass the checks below (which only grow pos and decoded), so it is taken whole,
    // keeping the integers later lengths may refer to. One that does not fit goes field by
    // field, for the refusal to name the field.
    const auto at = static_cast<size_t>(i);
    if (runs.end[at] > i && runs.bytes[at] <= total - pos &&
        decoded + runs.bytes[at] <= decoded_bound) {
      for (const RunRead& read : runs.reads[at]) {
        values[static_cast<size_t>(read.field)] = ReadSigned(bytes + pos + read.offset, read.width);
      }
      pos += runs.bytes[at];
      decoded += runs.bytes[at];
      i = runs.end[at] - 1;
      continue;
    }
    const Field& f = schema.fields[i];
    auto where = [&] {
      return std::string(schema.name) + "." + f.name + " at byte " + std::to_string(pos);
    };
    auto over_bound = [&] {
      return Refusal{"decoded size over bound", where() + ": would decode into " +
                                                    std::to_string(decoded) + " bytes from " +
                                                    std::to_string(total)};
    };
    // Most members are single numbers: the general path below, with its 128-bit products,
    // was a tenth of a replay's time. Same checks, same refusals.
    if (f.ndims == 0 && f.type != Prim::kString) {
      const int64_t elem = WireBytes(f.type);
      const int64_t remaining = total - pos;
      if (elem > remaining) {
        return Refusal{"array past the end", where() + ": needs at least " + std::to_string(elem) +
                                                 " bytes, " + std::to_string(remaining) +
                                                 " remain"};
      }
      if (f.type == Prim::kBoolean && bytes[pos] > 1) {
        return Refusal{"bad boolean", where() + ": element 0 is " + std::to_string(bytes[pos])};
      }
      if (IsInteger(f.type)) values[static_cast<size_t>(i)] = ReadSigned(bytes + pos, elem);
      pos += elem;
      decoded += DecodedBytes(f.type);
      if (decoded > decoded_bound) return over_bound();
      continue;
    }
    // Elements, and the vector headers of the outer levels, multiplied out level by level;
    // each level is at most kMaxLength (2^24), so three levels fit in 128 bits.
    unsigned __int128 count = 1;
    unsigned __int128 headers = 0;
    for (int d = 0; d < f.ndims; ++d) {
      const Dim& dim = f.dims[d];
      const int64_t n = dim.member < 0 ? dim.fixed : values[static_cast<size_t>(dim.member)];
      if (n < 0) {
        return Refusal{"negative length",
                       where() + ": dimension " + std::to_string(d) + " is " + std::to_string(n)};
      }
      const int64_t member_cap = dim.member < 0 ? 0 : schema.fields[dim.member].cap;
      const int64_t cap = member_cap > 0 ? member_cap : kMaxLength;
      if (n > cap) {
        return Refusal{"length over cap", where() + ": dimension " + std::to_string(d) + " is " +
                                              std::to_string(n) + " (cap " + std::to_string(cap) +
                                              ")"};
      }
      if (d + 1 < f.ndims) headers += count * static_cast<unsigned>(n);
      count *= static_cast<unsigned>(n);
    }
    const int64_t remaining = total - pos;
    const int64_t elem = WireBytes(f.type);
    // (A single string is checked below, with a more precise complaint.)
    if ((f.ndims > 0 || f.type != Prim::kString) &&
        count * static_cast<unsigned>(elem) > static_cast<unsigned __int128>(remaining)) {
      return Refusal{
          "array past the end",
          where() + ": needs at least " +
              std::to_string(static_cast<unsigned long long>(count * static_cast<unsigned>(elem))) +
              " bytes, " + std::to_string(remaining) + " remain"};
    }
    // Both now fit in int64: count <= remaining, headers <= count per level.
    if (headers > static_cast<unsigned __int128>(decoded_bound)) {
      return Refusal{
          "decoded size over bound",
          where() + ": " + std::to_string(static_cast<long long>(headers)) + " empty inner arrays"};
    }
    const int64_t n = static_cast<int64_t>(count);
    decoded += static_cast<int64_t>(headers) * static_cast<int64_t>(sizeof(std::vector<char>)) +
               n * DecodedBytes(f.type);
    if (f.type == Prim::kString) {
      for (int64_t k = 0; k < n; ++k) {
        if (total - pos < 4) return Refusal{"string past the end", where()};
        const int64_t len = ReadSigned(bytes + pos, 4);
        if (len < 1) {
          return Refusal{"bad string length",
                         where() + ": length " + std::to_string(len) + " (at least 1: the NUL)"};
        }
        if (len > total - pos - 4) {
          return Refusal{"string past the end", where() + ": length " + std::to_string(len) + ", " +
                                                    std::to_string(total - pos - 4) +
                                                    " bytes remain"};
        }
        if (bytes[pos + 4 + len - 1] != 0) {
          return Refusal{"string without NUL", where()};
        }
        // LCM decodes the bytes before the last, but encodes up to the first NUL: a string
        // with a NUL inside would mean one thing here and another re-published or logged.
        if (std::memchr(bytes + pos + 4, 0, static_cast<size_t>(len - 1)) != nullptr) {
          return Refusal{"string with a NUL inside", where()};
        }
        pos += 4 + len;
        decoded += len;
      }
    } else {
      if (f.type == Prim::kBoolean) {
        for (int64_t k = 0; k < n; ++k) {
          if (bytes[pos + k] > 1) {
            return Refusal{"bad boolean", where() + ": element " + std::to_string(k) + " is " +
                                              std::to_string(bytes[pos + k])};
          }
        }
      }
      if (f.ndims == 0 && IsInteger(f.type)) {
        values[static_cast<size_t>(i)] = ReadSigned(bytes + pos, elem);
      }
      pos += n * elem;
    }
    if (decoded > decoded_bound) return over_bound();
  }
  if (pos != total) {
    return Refusal{"trailing bytes", std::to_string(total - pos) + " bytes after a " +
                                         std::to_string(pos) + "-byte " + schema.name};
  }
  return std::nullopt;
}

std::string Describe(const Schema& schema, const void* data, int size) {
  if (auto refused = Check(schema, data, size)) return "<" + refused->kind + ">";
  const auto* bytes = static_cast<const uint8_t*>(data);
  int64_t pos = 8;
  std::vector<int64_t> values(static_cast<size_t>(schema.num_fields), 0);
  std::string out;
  auto element = [&](Prim type) {
    char text[64];
    const int64_t n = WireBytes(type);
    switch (type) {
      case Prim::kString: {
        const int64_t len = ReadSigned(bytes + pos, 4);
        std::string s = "\"" +
                        std::string(reinterpret_cast<const char*>(bytes + pos + 4),
                                    static_cast<size_t>(len - 1)) +
                        "\"";
        pos += 4 + len;
        return s;
      }
      case Prim::kFloat:
      case Prim::kDouble: {
        const uint64_t bits = static_cast<uint64_t>(ReadSigned(bytes + pos, n));
        double v;
        if (type == Prim::kFloat) {
          float f;
          const auto b32 = static_cast<uint32_t>(bits);
          std::memcpy(&f, &b32, 4);
          v = f;
        } else {
          std::memcpy(&v, &bits, 8);
        }
        std::snprintf(text, sizeof text, "%.9g", v);
        break;
      }
      default:
        std::snprintf(text, sizeof text, "%lld",
                      static_cast<long long>(ReadSigned(bytes + pos, n)));
    }
    pos += n;
    return std::string(text);
  };
  for (int i = 0; i < schema.num_fields; ++i) {
    const Field& f = schema.fields[i];
    if (i > 0) out += " ";
    out += f.name;
    out += "=";
    if (f.ndims == 0) {
      if (IsInteger(f.type))
        values[static_cast<size_t>(i)] = ReadSigned(bytes + pos, WireBytes(f.type));
      out += element(f.type);
      continue;
    }
    int64_t count = 1;
    for (int d = 0; d < f.ndims; ++d) {
      const Dim& dim = f.dims[d];
      count *= dim.member < 0 ? dim.fixed : values[static_cast<size_t>(dim.member)];
    }
    if (f.type == Prim::kByte) {
      out += "<" + std::to_string(count) + " bytes>";
      pos += count;
      continue;
    }
    out += "[";
    for (int64_t k = 0; k < count; ++k) out += (k ? "," : "") + element(f.type);
    out += "]";
  }
  return out;
}

}  // namespace ftcal::wire
