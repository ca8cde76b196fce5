// Independent tasks 0..n-1 on one worker per core (the calling thread is one of them), each
// worker taking the next task in turn. Not a thread per task: each thread allocates from a
// glibc arena of its own, and fresh arenas are freshly faulted pages (on a paravirtualised VM a
// page's first touch costs microseconds); a worker reuses its arena's pages from one task to
// the next. Step 2's candidates and step 1's legs run this way.
#pragma once

#include <cstddef>
#include <functional>

namespace ftcal {

// Runs task(i) for every i in [0, n) and returns when all have ended. A task's exception does
// not stop the others; the one of the lowest i is rethrown, so the outcome does not depend on
// scheduling. With no thread to spare, the calling thread runs them all.
void ParallelFor(size_t n, const std::function<void(size_t)>& task);

}  // namespace ftcal
