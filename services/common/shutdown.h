// Shutdown on SIGINT/SIGTERM: the handler only sets a lock-free flag (the one thing a signal
// handler may safely do); every loop polls it at least every 100 ms.
#pragma once

namespace ftcal {

// Installs the SIGINT/SIGTERM handlers (sigaction, no SA_RESTART so a blocking poll returns
// early with EINTR). Idempotent.
void InstallShutdownHandlers();
bool ShutdownRequested();
// Same effect as a signal, from code (a process that decides to end, a test).
void RequestShutdown();
// Clears the flag (tests that run several loops in one process).
void ClearShutdownRequest();

}  // namespace ftcal
