// A row of the truth CSV that the ATI emulator (alone or inside ftcal-sim live) writes, one per
// record it sent: ati_bridge_test and sim_live_test both hold the bridge's output to it, so
// they must read the columns the same way.
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <functional>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace ftcal::testing {

struct AtiTruthRow {
  std::string leg;
  int stream = 0;
  double t_s = 0;
  std::uint32_t rdt_sequence = 0, ft_sequence = 0, status = 0;
  std::array<std::int32_t, 6> counts{};
  std::string fault;           // what was done to the record's datagram
  std::uint32_t datagram = 0;  // the box's datagram the record went out in (or would have)
};

// The comma-separated cells of one line (no quoting: the truth files have none).
inline std::vector<std::string> SplitCsv(const std::string& line) {
  std::vector<std::string> f;
  std::stringstream ss(line);
  for (std::string item; std::getline(ss, item, ',');) f.push_back(item);
  return f;
}

constexpr std::size_t kAtiTruthColumns = 14;

// `f` has kAtiTruthColumns cells: leg, stream, t_s, rdt_sequence, ft_sequence, status, six
// counts, fault, datagram. Throws std::invalid_argument / std::out_of_range on a cell that is no
// number.
inline AtiTruthRow ParseAtiTruthRow(const std::vector<std::string>& f) {
  AtiTruthRow r;
  r.leg = f[0];
  r.stream = std::stoi(f[1]);
  r.t_s = std::stod(f[2]);
  r.rdt_sequence = static_cast<std::uint32_t>(std::stoul(f[3]));
  r.ft_sequence = static_cast<std::uint32_t>(std::stoul(f[4]));
  r.status = static_cast<std::uint32_t>(std::stoul(f[5]));
  for (int i = 0; i < 6; ++i) r.counts[i] = std::stoi(f[6 + i]);
  r.fault = f[12];
  r.datagram = static_cast<std::uint32_t>(std::stoul(f[13]));
  return r;
}

// What the truth says happened to one box's records.
struct AtiLegTally {
  std::map<std::string, std::int64_t> faults;  // records per fault ("none", "drop", ...)
  std::map<std::string, std::set<std::uint32_t>> datagrams;  // datagrams per fault
  std::set<int> streams;
  // Records lost after the last one delivered: they cannot be told from the end of the data.
  std::int64_t lost_at_end = 0;
};

inline AtiLegTally TallyLeg(const std::vector<AtiTruthRow>& truth, const std::string& leg) {
  AtiLegTally t;
  std::uint32_t last_delivered = 0;
  for (const AtiTruthRow& r : truth) {
    if (r.leg != leg) continue;
    ++t.faults[r.fault];
    t.datagrams[r.fault].insert(r.datagram);
    t.streams.insert(r.stream);
    if (r.fault == "none" || r.fault == "duplicate")
      last_delivered = std::max(last_delivered, r.rdt_sequence);
  }
  for (const AtiTruthRow& r : truth) {
    if (r.leg == leg && r.rdt_sequence > last_delivered) ++t.lost_at_end;
  }
  return t;
}

// The bridge's counters for one leg (`counter` of "duplicates", "late", ...) against the truth:
// each kind of fault happened, and was counted as what it is. Faults strike whole datagrams; the
// bridge counts records, but wrong lengths by datagram.
inline void ExpectFaultsCounted(AtiLegTally& t,
                                const std::function<std::int64_t(const std::string&)>& counter) {
  auto& faults = t.faults;
  for (const char* kind : {"drop", "duplicate", "reorder", "corrupt"})
    EXPECT_GT(t.datagrams[kind].size(), 5u) << kind;
  EXPECT_EQ(counter("duplicates"), faults["duplicate"]);
  EXPECT_EQ(counter("late"), faults["reorder"]);
  EXPECT_EQ(counter("wrong_length"), static_cast<std::int64_t>(t.datagrams["corrupt"].size()));
  // A reordered record is first missed (lost), then arrives late and is dropped.
  EXPECT_EQ(counter("lost"),
            faults["drop"] + faults["corrupt"] + faults["reorder"] - t.lost_at_end);
  EXPECT_EQ(counter("received"), faults["none"] + 2 * faults["duplicate"] + faults["reorder"]);
}

}  // namespace ftcal::testing
