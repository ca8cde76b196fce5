// BatchMemory (common/batch_memory.h): what UseForProcess says it granted, checked against glibc's
// own accounting (mallinfo2) and the kernel's view of the mappings (/proc/self/smaps); the room
// Reserve and FaultInAhead give.
#include "common/batch_memory.h"

#include <malloc.h>

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

namespace ftcal {
namespace {

// The smaps entry of the mapping that holds `p`: its header line and fields, "" when none does.
std::string SmapsOf(const void* p) {
  const auto at = reinterpret_cast<uintptr_t>(p);
  std::ifstream in("/proc/self/smaps");
  std::string line, entry;
  bool inside = false;
  while (std::getline(in, line)) {
    unsigned long lo = 0, hi = 0;
    char dash = 0;
    std::istringstream head(line);
    // A header line starts with "lo-hi " in hex; a field line with its name and a colon.
    if (head >> std::hex >> lo >> dash >> hi && dash == '-' && line.find(':') > line.find(' ')) {
      if (inside) return entry;
      inside = at >= lo && at < hi;
      entry.clear();
    }
    if (inside) entry += line + "\n";
  }
  return inside ? entry : "";
}

bool TransparentHugePagesOn() {
  std::ifstream in("/sys/kernel/mm/transparent_hugepage/enabled");
  std::string modes;
  std::getline(in, modes);
  return !modes.empty() && modes.find("[never]") == std::string::npos;
}

TEST(BatchMemory, LargeBlocksComeFromTheAdvisedHeapAndStayThere) {
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  GTEST_SKIP() << "the sanitizer's allocator, not glibc's, serves malloc here";
#endif
  const BatchMemory::Granted granted = BatchMemory::UseForProcess();
  ASSERT_TRUE(granted.thresholds);
  // 4 MiB is far above malloc's default 128 KiB mmap threshold: its own mapping, unless the
  // thresholds took.
  const size_t mapped_before = mallinfo2().hblks;
  void* volatile block = std::malloc(size_t{4} << 20);
  ASSERT_NE(block, nullptr);
  EXPECT_EQ(mallinfo2().hblks, mapped_before) << "a 4 MiB block got a mapping of its own";
  std::memset(block, 1, size_t{4} << 20);
  const size_t heap_before_free = mallinfo2().arena;
  std::free(block);
  // Freed, it stays with the heap (no trim): the heap is as large as before.
  EXPECT_EQ(mallinfo2().arena, heap_before_free);

  if (!TransparentHugePagesOn()) GTEST_SKIP() << "transparent huge pages are off here";
  ASSERT_GE(granted.huge_bytes, (size_t{256} << 20) - (size_t{4} << 20));
  // The block may begin below the advised growth (the top chunk's old part, under the first
  // 2 MiB boundary); its end is inside it.
  constexpr size_t kBytes = size_t{8} << 20;
  void* volatile again = std::malloc(kBytes);
  const std::string smaps = SmapsOf(static_cast<char*>(again) + kBytes - 1);
  std::free(again);
  ASSERT_FALSE(smaps.empty());
  EXPECT_TRUE(std::regex_search(smaps, std::regex("THPeligible:\\s+1\\n"))) << smaps;
  EXPECT_NE(smaps.find(" hg"), std::string::npos) << "VmFlags without hg (MADV_HUGEPAGE):\n"
                                                  << smaps;
}

// The pages faulted in ahead are the vectors' own, written while the thread runs: what the
// caller writes is what it reads back.
TEST(BatchMemory, RoomFaultedInAheadHoldsWhatIsWritten) {
  std::vector<double> a;
  std::vector<int64_t> b;
  constexpr size_t kN = size_t{1} << 18;  // 2 MiB of doubles: many pages, several slices
  {
    BatchMemory memory;
    memory.Reserve(a, kN);
    memory.Reserve(b, kN / 2);
    ASSERT_GE(a.capacity(), kN);
    ASSERT_GE(b.capacity(), kN / 2);
    const double* const a_room = a.data();
    memory.FaultInAhead();
    for (size_t i = 0; i < kN; ++i) a.push_back(0.5 * static_cast<double>(i));
    for (size_t i = 0; i < kN / 2; ++i) b.push_back(static_cast<int64_t>(i) - 7);
    memory.Wait();
    EXPECT_EQ(a.data(), a_room) << "the reserved room was not enough: the vector moved";
  }
  for (size_t i = 0; i < kN; ++i) ASSERT_EQ(a[i], 0.5 * static_cast<double>(i)) << i;
  for (size_t i = 0; i < kN / 2; ++i) ASSERT_EQ(b[i], static_cast<int64_t>(i) - 7) << i;
}

}  // namespace
}  // namespace ftcal
