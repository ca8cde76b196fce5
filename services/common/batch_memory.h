// The memory tricks in one place: first touches of fresh pages trap to our VMs' hypervisor.
//
// BatchMemory holds them so that the code that reads and calibrates says what room it wants, not
// how its pages come: the process-wide malloc settings of an offline (batch) run
// (UseForProcess), and room reserved for vectors whose pages another thread faults in while this
// one fills them (Reserve, FaultInAhead). On the paravirtualised VMs we measure on, the first
// touch of every 4 KiB page traps to the hypervisor, and malloc's defaults make an offline run
// touch fresh pages again and again: every block over 128 KiB is its own mmap(), given back by
// munmap() when freed and faulted in afresh on the next allocation; freed heap tops are trimmed
// the same way. What each trick saved, measured: docs/performance.md ("Memory").
#pragma once

#include <cstddef>
#include <future>
#include <vector>

namespace ftcal {

class BatchMemory {
 public:
  struct Granted {
    bool thresholds = false;  // mallopt took the thresholds
    size_t huge_bytes = 0;    // heap address space advised for transparent huge pages (0: none)
  };

  // For the rest of the process: blocks up to 32 MiB come from malloc's heaps and stay there once
  // freed (M_MMAP_THRESHOLD, M_TRIM_THRESHOLD), and the main heap is grown once by `heap_bytes`
  // of address space (M_TOP_PAD) advised for transparent huge pages (MADV_HUGEPAGE; a fault then
  // maps 2 MiB). What glibc's tunables glibc.malloc.mmap_threshold, trim_threshold and hugetlb=1
  // do, from inside the process: tunables are read only from the environment at start-up. Only
  // address space until written; freed memory is not given back before exit, which is why live
  // services keep the defaults. Best effort: under another allocator (the sanitizers'), or a
  // kernel without transparent huge pages, whatever is refused stays as it was. Call once, early
  // in main(), before the work allocates.
  static Granted UseForProcess(size_t heap_bytes = size_t{256} << 20);

  BatchMemory() = default;
  BatchMemory(const BatchMemory&) = delete;
  BatchMemory& operator=(const BatchMemory&) = delete;
  // Waits for the thread FaultInAhead() started: declare a BatchMemory after the vectors it
  // reserved, so that it is destroyed (and waited for) before they are freed.
  ~BatchMemory() { Wait(); }

  // Reserves room for `n` elements in `v` (address space until written) and notes that room
  // for the next FaultInAhead().
  template <typename T>
  void Reserve(std::vector<T>& v, size_t n) {
    v.reserve(n);
    rooms_.push_back(Room{v.data(), v.capacity() * sizeof(T)});
  }
  // Faults in the pages of every room reserved since the last call, on another thread, slice by
  // slice across all of them (the caller fills them side by side), with one
  // madvise(MADV_POPULATE_WRITE) per slice instead of a trap per page as each is first written.
  // The pages' contents are unchanged. Best effort: a kernel before 5.14 refuses the advice, and
  // with no thread to spare nothing is started; the pages are then faulted in as they are written.
  void FaultInAhead();
  // Waits for FaultInAhead()'s thread: call before any vector it touches is freed, moved or grown.
  void Wait() {
    if (prefault_.valid()) prefault_.wait();
  }

 private:
  // A vector's room, its whole capacity: [data, data + bytes).
  struct Room {
    const void* data;
    size_t bytes;
  };
  static void Prefault(const std::vector<Room>& rooms);

  std::vector<Room> rooms_;
  std::future<void> prefault_;
};

}  // namespace ftcal
