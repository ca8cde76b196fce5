#include "parallel.h"

#include <algorithm>
#include <atomic>
#include <exception>
#include <future>
#include <system_error>
#include <thread>
#include <vector>

namespace ftcal {

void ParallelFor(size_t n, const std::function<void(size_t)>& task) {
  std::vector<std::exception_ptr> errors(n);
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t i = next++; i < n; i = next++) {
      try {
        task(i);
      } catch (...) {
        errors[i] = std::current_exception();
      }
    }
  };
  const size_t workers = std::min<size_t>(n, std::max(1u, std::thread::hardware_concurrency()));
  std::vector<std::future<void>> pool;
  for (size_t w = 1; w < workers; ++w) {
    try {
      pool.push_back(std::async(std::launch::async, work));
    } catch (const std::system_error&) {
      break;  // no thread to spare: the workers started take every task
    }
  }
  work();
  for (auto& f : pool) f.get();  // work() catches its tasks' exceptions
  for (const std::exception_ptr& e : errors) {
    if (e) std::rethrow_exception(e);
  }
}

}  // namespace ftcal
