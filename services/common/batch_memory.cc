#include "common/batch_memory.h"

#include <malloc.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <system_error>
#include <utility>

namespace ftcal {

BatchMemory::Granted BatchMemory::UseForProcess(size_t heap_bytes) {
  Granted granted;
  // glibc's upper bound for the mmap threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX); blocks
  // larger than that are rare here and keep their own mappings.
  constexpr int kMmapThreshold = 32 << 20;
  constexpr int kTrimThreshold = 1 << 30;
  granted.thresholds = ::mallopt(M_MMAP_THRESHOLD, kMmapThreshold) == 1 &&
                       ::mallopt(M_TRIM_THRESHOLD, kTrimThreshold) == 1;
  if (!granted.thresholds || heap_bytes == 0) return granted;
#ifdef MADV_HUGEPAGE
  // The heap grows by the request plus M_TOP_PAD: one request past the top chunk with the pad
  // raised grows it by heap_bytes at once; freed, it stays as the top chunk (trim threshold).
  // The growth is advised from its first 2 MiB boundary to its end (madvise splits the heap's
  // mapping there); a later growth past it is not advised.
  constexpr uintptr_t kHugePage = uintptr_t{2} << 20;
  constexpr size_t kDefaultTopPad = size_t{128} << 10;  // glibc's DEFAULT_TOP_PAD
  const auto before = reinterpret_cast<uintptr_t>(::sbrk(0));
  if (::mallopt(M_TOP_PAD, static_cast<int>(heap_bytes)) != 1) return granted;
  // volatile: a malloc whose block is only freed may be left out by the compiler.
  void* volatile probe = std::malloc(16 << 20);
  const auto after = reinterpret_cast<uintptr_t>(::sbrk(0));
  ::mallopt(M_TOP_PAD, static_cast<int>(kDefaultTopPad));
  std::free(probe);
  const uintptr_t begin = (before + kHugePage - 1) & ~(kHugePage - 1);
  const uintptr_t end = after & ~(kHugePage - 1);
  // No growth (brk refused, malloc fell back to a mapping, or another allocator): nothing to
  // advise.
  // madvise takes page-aligned addresses, computed here as integers.
  // NOLINTNEXTLINE(performance-no-int-to-ptr)
  if (end > begin && ::madvise(reinterpret_cast<void*>(begin), end - begin, MADV_HUGEPAGE) == 0) {
    granted.huge_bytes = end - begin;
  }
#endif
  return granted;
}

void BatchMemory::FaultInAhead() {
  Wait();
  std::vector<Room> rooms = std::move(rooms_);
  rooms_.clear();
  try {
    prefault_ = std::async(std::launch::async, Prefault, std::move(rooms));
  } catch (const std::system_error&) {
    // No thread to spare: the pages are faulted in as they are written.
  }
}

void BatchMemory::Prefault(const std::vector<Room>& rooms) {
#ifdef MADV_POPULATE_WRITE
  constexpr int kSlices = 16;
  const auto page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
  for (int s = 0; s < kSlices; ++s) {
    for (const Room& r : rooms) {
      const auto at = reinterpret_cast<uintptr_t>(r.data);
      const uintptr_t begin = (at + r.bytes * s / kSlices + page - 1) & ~(page - 1);
      const uintptr_t end = (at + r.bytes * (s + 1) / kSlices) & ~(page - 1);
      if (end > begin &&
          ::madvise(reinterpret_cast<void*>(begin),  // NOLINT(performance-no-int-to-ptr)
                    end - begin, MADV_POPULATE_WRITE) != 0) {
        return;
      }
    }
  }
#else
  (void)rooms;
#endif
}

}  // namespace ftcal
