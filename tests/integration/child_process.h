// Starting and stopping real processes from a test: fork/exec with stdout and stderr to files,
// signals, and waits with a deadline. A Child still running when destroyed is SIGKILLed and
// reaped, so a failing test leaves nothing behind.
#pragma once

#include <sys/types.h>

#include <optional>
#include <string>
#include <vector>

namespace ftcal::testing {

class Child {
 public:
  // Throws std::runtime_error when the process cannot be started.
  Child(const std::vector<std::string>& argv, const std::string& stdout_path,
        const std::string& stderr_path);
  ~Child();
  Child(const Child&) = delete;
  Child& operator=(const Child&) = delete;

  pid_t pid() const { return pid_; }
  void Signal(int signo) const;
  // The wait status (see WIFEXITED), or nullopt if still running after `timeout_s`.
  std::optional<int> Wait(double timeout_s);
  bool running() const { return !status_.has_value(); }

 private:
  pid_t pid_ = -1;
  std::optional<int> status_;
};

std::string ReadFile(const std::string& path);
// A fresh directory under $TMPDIR (or /tmp), removed by the caller with RemoveTree.
std::string MakeTempDir();
void RemoveTree(const std::string& dir);
// "exit 3", "signal 9 (Killed)".
std::string DescribeWaitStatus(int status);
// Sleeps for `s` seconds (a test's waits for processes it started).
void SleepS(double s);

// Sets an environment variable (which the children started meanwhile inherit) and puts back
// what it was, or unsets it, when it goes: e.g. FTCAL_CACHE_DIR, which the suite sets.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const std::string& value);
  ~ScopedEnv();
  ScopedEnv(const ScopedEnv&) = delete;
  ScopedEnv& operator=(const ScopedEnv&) = delete;

 private:
  std::string name_;
  std::optional<std::string> before_;
};

}  // namespace ftcal::testing
