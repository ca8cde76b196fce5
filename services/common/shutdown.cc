#include "common/shutdown.h"

#include <atomic>
#include <cerrno>
#include <csignal>
#include <cstring>
#include <stdexcept>
#include <string>

namespace ftcal {
namespace {

// std::atomic<bool> is async-signal-safe only when lock-free; checked at compile time.
std::atomic<bool> g_shutdown{false};
static_assert(std::atomic<bool>::is_always_lock_free, "shutdown flag must be lock-free");

extern "C" void OnShutdownSignal(int /*signo*/) {
  g_shutdown.store(true, std::memory_order_relaxed);
}

}  // namespace

void InstallShutdownHandlers() {
  struct sigaction action {};
  action.sa_handler = OnShutdownSignal;
  sigemptyset(&action.sa_mask);
  action.sa_flags = 0;
  for (int signo : {SIGINT, SIGTERM}) {
    if (sigaction(signo, &action, nullptr) != 0) {
      throw std::runtime_error(std::string("sigaction(") + strsignal(signo) +
                               ") failed: " + std::strerror(errno));
    }
  }
}

bool ShutdownRequested() { return g_shutdown.load(std::memory_order_relaxed); }

void RequestShutdown() { g_shutdown.store(true, std::memory_order_relaxed); }

void ClearShutdownRequest() { g_shutdown.store(false, std::memory_order_relaxed); }

}  // namespace ftcal
