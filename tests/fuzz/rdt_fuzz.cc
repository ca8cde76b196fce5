// libFuzzer target: an arbitrary datagram through the RDT decoder and the sequence tracker,
// and arbitrary bytes as a calibration page. Invariants checked beyond "no crash":
// a decoded datagram re-encodes to the same bytes; the tracker's counters add up.
#include "rdt_codec.h"

#include <cstdlib>
#include <string_view>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ftcal::rdt;
  std::vector<Record> records;
  try {
    records = DecodeDatagram(data, size);
  } catch (const RdtError&) {
    if (size != 0 && size % kRecordBytes == 0) std::abort();  // a valid length was refused
  }
  if (!records.empty()) {
    const std::vector<std::uint8_t> again = EncodeDatagram(records);
    if (again.size() != size || !std::equal(again.begin(), again.end(), data)) std::abort();
  }
  SequenceTracker tracker;
  std::uint64_t fed = 0;
  for (const Record& r : records) {
    tracker.Update(r.rdt_sequence, r.ft_sequence);
    ++fed;
    StatusSaturated(r.status);
    DescribeStatus(r.status);
    const Vector6d w = CountsToWrench(r.counts, 1e6, 1e6, -1);
    ExceedsRatedRange(w, {1, 1, 1, 1, 1, 1});
  }
  if (tracker.accepted() + tracker.duplicates() + tracker.late() + tracker.stale() != fed) {
    std::abort();
  }
  // The same bytes as an XML page.
  try {
    ParseNetFtXml(std::string_view(reinterpret_cast<const char*>(data), size), "fuzz");
  } catch (const RdtError&) {
  }
  return 0;
}
