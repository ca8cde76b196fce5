#include "launcher/supervisor.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <sstream>
#include <stdexcept>
#include <thread>

#include "launcher/launch_plan.h"

namespace ftcal::launch {
namespace {

using Clock = std::chrono::steady_clock;

// The part of a double-quoted shell word: $VAR still expands, nothing else does.
std::string DoubleQuoteBody(const std::string& s) {
  std::string out;
  for (char c : s) {
    if (c == '"' || c == '\\' || c == '`') out += '\\';
    out += c;
  }
  return out;
}

std::string Trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) return "";
  const auto e = s.find_last_not_of(" \t\r\n");
  return s.substr(b, e - b + 1);
}

}  // namespace

CommandResult RunShell(const std::vector<std::string>& shell, const std::string& line,
                       const std::string& input, double timeout_s) {
  std::vector<std::string> argv = shell;
  if (argv.empty()) argv = {"/bin/sh", "-c"};
  argv.push_back(line);
  std::vector<char*> args;
  args.reserve(argv.size() + 1);
  for (auto& a : argv) args.push_back(a.data());
  args.push_back(nullptr);

  int in_pipe[2], out_pipe[2];
  if (::pipe2(in_pipe, O_CLOEXEC) != 0)
    throw std::runtime_error(std::string("pipe: ") + std::strerror(errno));
  if (::pipe2(out_pipe, O_CLOEXEC) != 0) {
    ::close(in_pipe[0]);
    ::close(in_pipe[1]);
    throw std::runtime_error(std::string("pipe: ") + std::strerror(errno));
  }
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::dup2(in_pipe[0], STDIN_FILENO);
    ::dup2(out_pipe[1], STDOUT_FILENO);
    ::dup2(out_pipe[1], STDERR_FILENO);
    // Its own process group: a timeout kills ssh and whatever it started, nothing of ours.
    ::setpgid(0, 0);
    sigset_t none;
    sigemptyset(&none);
    ::sigprocmask(SIG_SETMASK, &none, nullptr);
    ::signal(SIGPIPE, SIG_DFL);
    ::execvp(args[0], args.data());
    const char msg[] = "ftcal-launch: cannot execute the host's shell\n";
    (void)!::write(STDERR_FILENO, msg, sizeof(msg) - 1);
    ::_exit(127);
  }
  const int fork_errno = errno;
  ::close(in_pipe[0]);
  ::close(out_pipe[1]);
  if (pid < 0) {
    ::close(in_pipe[1]);
    ::close(out_pipe[0]);
    throw std::runtime_error(std::string("fork: ") + std::strerror(fork_errno));
  }
  // A short input (a config file) fits the pipe buffer; write it before reading, then close
  // so the command sees end of input.
  std::size_t written = 0;
  ::signal(SIGPIPE, SIG_IGN);
  while (written < input.size()) {
    const ssize_t n = ::write(in_pipe[1], input.data() + written, input.size() - written);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    written += static_cast<std::size_t>(n);
  }
  ::close(in_pipe[1]);

  CommandResult result;
  const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
  bool timed_out = false;
  char buf[4096];
  while (true) {
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
    if (left <= 0) {
      timed_out = true;
      break;
    }
    pollfd p{out_pipe[0], POLLIN, 0};
    const int r = ::poll(&p, 1, static_cast<int>(std::min<long long>(left, 200)));
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) continue;
    const ssize_t n = ::read(out_pipe[0], buf, sizeof(buf));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    result.output.append(buf, static_cast<std::size_t>(n));
  }
  ::close(out_pipe[0]);
  if (timed_out) ::kill(-pid, SIGKILL);
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (timed_out) {
    throw std::runtime_error("'" + line + "' did not finish within " + std::to_string(timeout_s) +
                             " s (killed)");
  }
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

std::map<std::string, ProgramStatus> ParseStatus(const std::string& output) {
  std::map<std::string, ProgramStatus> out;
  std::istringstream in(output);
  for (std::string line; std::getline(in, line);) {
    std::istringstream words(line);
    std::string name, state;
    if (!(words >> name >> state)) continue;
    static const char* kStates[] = {"STOPPED",  "STARTING", "RUNNING", "BACKOFF",
                                    "STOPPING", "EXITED",   "FATAL",   "UNKNOWN"};
    bool known = false;
    for (const char* s : kStates) known = known || state == s;
    if (!known) continue;  // "unix:///...: no such file" and other complaints
    ProgramStatus ps;
    ps.state = state;
    std::string rest;
    std::getline(words, rest);
    ps.detail = Trim(rest);
    if (state == "RUNNING" && ps.detail.rfind("pid ", 0) == 0) {
      ps.pid = std::stoll(ps.detail.substr(4));
    }
    out[name] = ps;
  }
  return out;
}

HostSupervisor::HostSupervisor(std::string host, std::vector<std::string> shell,
                               std::string run_dir_spec)
    : host_(std::move(host)), shell_(std::move(shell)), run_dir_spec_(std::move(run_dir_spec)) {}

const std::string& HostSupervisor::run_dir() {
  if (!run_dir_.empty()) return run_dir_;
  const std::string q = "\"" + DoubleQuoteBody(run_dir_spec_) + "\"";
  // The run dir holds supervisord's control socket and the config the processes read: made here
  // with mode 0700, and one that exists is used only when it is this user's, closed to group and
  // others, and not a symbolic link (the fallback under /tmp is anyone's to create first).
  const std::string script =
      "umask 077; d=" + q +
      "; [ -e \"$d\" ] || [ -L \"$d\" ] || mkdir -p -m 0700 \"$d\" || exit 1; "
      "if [ -L \"$d\" ] || [ ! -d \"$d\" ]; then "
      "echo \"run dir '$d' is not a directory of its own (a symbolic link or a file)\"; exit 3; "
      "fi; "
      "u=$(stat -c %u \"$d\") && m=$(stat -c %a \"$d\") || exit 1; "
      "if [ \"$u\" != \"$(id -u)\" ] || [ $((0$m & 077)) -ne 0 ]; then "
      "echo \"run dir '$d' is owned by uid $u ($(stat -c %U \"$d\")) with mode $m; ftcal-launch "
      "uses only a directory of its own user (uid $(id -u)) with mode 0700: remove it, or choose "
      "another (--run-dir, launch.host.run_dir)\"; exit 3; fi; "
      "mkdir -p \"$d/groups\" \"$d/logs\" && cd \"$d\" && pwd -P";
  const auto r = RunShell(shell_, script);
  const std::string dir = Trim(r.output);
  if (r.exit_code == 3) {
    throw LaunchError("host '" + host_ + "': refused the run dir '" + run_dir_spec_ +
                      "': " + Trim(r.output));
  }
  if (r.exit_code != 0 || dir.empty() || dir[0] != '/' || dir.find('\n') != std::string::npos) {
    throw std::runtime_error("host '" + host_ + "': cannot make the run dir '" + run_dir_spec_ +
                             "': " + Trim(r.output));
  }
  run_dir_ = dir;
  return run_dir_;
}

void HostSupervisor::WriteFile(const std::string& relative, const std::string& content) {
  const std::string path = run_dir() + "/" + relative;
  // Temporary beside the target, renamed over it: supervisord never reads half a file.
  const std::string tmp = path + ".tmp." + std::to_string(::getpid());
  const auto r = RunShell(shell_,
                          "umask 077 && cat > " + ShellQuote(tmp) + " && mv -f " + ShellQuote(tmp) +
                              " " + ShellQuote(path),
                          content);
  if (r.exit_code != 0) {
    RunShell(shell_, "rm -f " + ShellQuote(tmp));
    throw std::runtime_error("host '" + host_ + "': cannot write " + path + ": " + Trim(r.output));
  }
}

void HostSupervisor::RemoveFile(const std::string& relative) {
  RunShell(shell_, "rm -f " + ShellQuote(run_dir() + "/" + relative));
}

std::string HostSupervisor::Tail(const std::string& relative, int max_bytes) {
  const auto r = RunShell(shell_, "tail -c " + std::to_string(max_bytes) + " " +
                                      ShellQuote(run_dir() + "/" + relative) + " 2>/dev/null");
  return Trim(r.output);
}

CommandResult HostSupervisor::Ctl(const std::vector<std::string>& args, double timeout_s) {
  std::string line = "supervisorctl -c " + ShellQuote(conf_path());
  for (const auto& a : args) line += " " + ShellQuote(a);
  return RunShell(shell_, line, "", timeout_s);
}

bool HostSupervisor::Alive() {
  const auto r = Ctl({"pid"}, 15);
  const std::string out = Trim(r.output);
  return !out.empty() && out.find_first_not_of("0123456789") == std::string::npos;
}

void HostSupervisor::EnsureRunning(double timeout_s) {
  if (Alive()) return;
  // The daemon must not keep our pipe open: its early complaints go to a file we then print.
  const std::string start_log = ShellQuote(run_dir() + "/supervisord.start.log");
  const auto r = RunShell(shell_,
                          "supervisord -c " + ShellQuote(conf_path()) + " </dev/null >" +
                              start_log + " 2>&1; rc=$?; cat " + start_log + "; exit $rc",
                          "", 30);
  if (r.exit_code != 0) {
    throw std::runtime_error("host '" + host_ + "': supervisord -c " + conf_path() +
                             " failed: " + Trim(r.output));
  }
  const auto deadline = Clock::now() + std::chrono::duration<double>(timeout_s);
  while (!Alive()) {
    if (Clock::now() > deadline) {
      throw std::runtime_error("host '" + host_ + "': supervisord did not answer on " + run_dir() +
                               "/supervisor.sock within " + std::to_string(timeout_s) +
                               " s; its log: " + Tail("supervisord.log"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
}

std::map<std::string, ProgramStatus> HostSupervisor::Status() {
  return ParseStatus(Ctl({"status"}, 30).output);
}

pid_t HostSupervisor::SupervisordPid() {
  const std::string out = Trim(Ctl({"pid"}, 15).output);
  if (out.empty() || out.find_first_not_of("0123456789") != std::string::npos) return 0;
  return static_cast<pid_t>(std::stol(out));
}

}  // namespace ftcal::launch
