// How an offline (batch) run asks glibc's malloc for memory: a process that reads a log,
// computes and exits, as opposed to a live service that runs for days.
//
// On the paravirtualised VMs we measure on, the first touch of every 4 KiB page traps to the
// hypervisor (microseconds each), and malloc's defaults make an offline run touch fresh pages
// again and again: every block over 128 KiB is its own mmap(), given back by munmap() when freed
// and faulted in afresh on the next allocation; freed heap tops are trimmed the same way. The
// calibrator on the report-scale logs took ~21,000 minor faults for a 72 MiB peak.
#pragma once

#include <cstddef>

namespace ftcal {

struct BatchMemoryGranted {
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
BatchMemoryGranted UseBatchMemory(size_t heap_bytes = size_t{256} << 20);

}  // namespace ftcal
