// The pipeline's processes over the full report-scale experiment, each timed as a whole process
// (wall, and user + system CPU from wait4), as a lab runs them after an experiment:
//   ftcal-sim log            the twin's experiment (729 poses by default, ~86 min of robot time)
//   ftcal-pose-segmenter     --replay of that log: x real time
//   ftcal-calibrator         --log session --log poses: the whole process as users run it
//                            (reading, aligning, segmenting, the default profile's eight
//                            model-selection candidates, the calibration file and the residual
//                            CSVs written), wall time, median (and min, max) of --runs runs;
//                            three times: as the first calibration of the logs finds them
//                            (their digests handed to the digest cache, a directory of the
//                            bench's own, by ftcal-sim and the segmenter as they wrote them,
//                            and the span index the segmenter's replay left beside the
//                            session's digest: the STANDING span is not read), as it finds a
//                            session log the segmenter did not replay (no span index: read
//                            whole), and with no digest cache (each log hashed for the
//                            provenance)
//   ftcal-corrector          --replay with the calibration: leg-samples/s (one FT_<LEG> sample
//                            in, one CONTACT_WRENCH out, and a CONTACT_WRENCH_SUM per six)
// The logs (~3 GB) go to a temporary directory under --dir (default /tmp), removed at the end
// unless --keep. --dir /dev/shm shows what the stages do without the disk: the corrector writes
// ~145 bytes per leg-sample (568 before CONTACT_WRENCH carried one leg), so on a slow disk its
// rate is the disk's write rate.
//   <build>/tests/bench/pipeline_bench [--poses N] [--dir DIR] [--keep] [--runs N]
#include <fcntl.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <functional>
#include <filesystem>
#include <algorithm>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

namespace {

struct Timing {
  double wall_s = 0.0;
  double user_s = 0.0;
  double sys_s = 0.0;
  std::string out;  // stdout + stderr
};

std::string ReadAll(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  std::ostringstream s;
  s << f.rdbuf();
  return s.str();
}

// Runs argv to its end with stdout and stderr into `log`; exits the bench if it fails (a figure
// from a failed run would be meaningless).
Timing Run(const std::vector<std::string>& argv, const std::string& log) {
  std::vector<char*> cargv;
  for (const std::string& a : argv) cargv.push_back(const_cast<char*>(a.c_str()));
  cargv.push_back(nullptr);
  const auto t0 = std::chrono::steady_clock::now();
  const pid_t pid = ::fork();
  if (pid < 0) {
    std::perror("fork");
    std::exit(1);
  }
  if (pid == 0) {
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd < 0) ::_exit(126);
    ::dup2(fd, 1);
    ::dup2(fd, 2);
    ::execv(cargv[0], cargv.data());
    std::perror(cargv[0]);
    ::_exit(127);
  }
  int status = 0;
  rusage ru{};
  if (::wait4(pid, &status, 0, &ru) < 0) {
    std::perror("wait4");
    std::exit(1);
  }
  Timing t;
  t.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  t.user_s = ru.ru_utime.tv_sec + 1e-6 * ru.ru_utime.tv_usec;
  t.sys_s = ru.ru_stime.tv_sec + 1e-6 * ru.ru_stime.tv_usec;
  t.out = ReadAll(log);
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    std::fprintf(stderr, "pipeline_bench: %s failed (status %d):\n%s\n", argv[0].c_str(), status,
                 t.out.c_str());
    std::exit(1);
  }
  return t;
}

// The number after `pattern`'s group in `text`, or exits naming what was not found.
double Capture(const std::string& text, const std::string& pattern, const char* what) {
  std::smatch m;
  if (!std::regex_search(text, m, std::regex(pattern))) {
    std::fprintf(stderr, "pipeline_bench: no %s in the output:\n%s\n", what, text.c_str());
    std::exit(1);
  }
  return std::stod(m[1]);
}

void Print(const char* stage, const Timing& t, const std::string& figure) {
  std::printf("%-22s wall %7.3f s  cpu %7.3f s (user %6.3f, sys %6.3f)  %s\n", stage, t.wall_s,
              t.user_s + t.sys_s, t.user_s, t.sys_s, figure.c_str());
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  std::string poses = "729";
  std::string base = "/tmp";
  bool keep = false;
  int runs = 5;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--poses" && i + 1 < argc) {
      poses = argv[++i];
    } else if (a == "--runs" && i + 1 < argc) {
      runs = std::max(1, std::atoi(argv[++i]));
    } else if (a == "--dir" && i + 1 < argc) {
      base = argv[++i];
    } else if (a == "--keep") {
      keep = true;
    } else {
      std::fprintf(stderr, "usage: pipeline_bench [--poses N] [--dir DIR] [--keep] [--runs N]\n");
      return 2;
    }
  }
  std::string tmpl = base + "/ftcal-pipeline-bench.XXXXXX";
  if (::mkdtemp(tmpl.data()) == nullptr) {
    std::fprintf(stderr, "pipeline_bench: cannot create a directory under %s: %s\n", base.c_str(),
                 std::strerror(errno));
    return 1;
  }
  const std::string dir = tmpl;
  const std::string config = std::string(FTCAL_SOURCE_DIR) + "/config/sim.pbtxt";
  std::printf("pipeline_bench: %s poses, logs in %s\n", poses.c_str(), dir.c_str());
  // The writers (ftcal-sim log, the segmenter) hand their logs' digests to this cache, as they
  // do to a user's ~/.cache/ftcal.
  const std::string cache = dir + "/digest-cache";
  ::setenv("FTCAL_CACHE_DIR", cache.c_str(), 1);

  const Timing sim = Run({FTCAL_SIM, "log", "--out", dir + "/session.lcmlog", "--truth",
                          dir + "/truth.pbtxt", "--poses", poses},
                         dir + "/sim.out");
  const double robot_s = Capture(sim.out, "([0-9.]+) s of robot time", "robot time");
  const double events = Capture(sim.out, "robot time, ([0-9]+) events", "event count");
  char fig[256];
  std::snprintf(fig, sizeof fig, "%.0f s of robot time, %.0f events (%.2f M events/s)", robot_s,
                events, 1e-6 * events / sim.wall_s);
  Print("ftcal-sim log", sim, fig);

  const Timing seg = Run({FTCAL_POSE_SEGMENTER, "--config", config, "--replay",
                          dir + "/session.lcmlog", "--out", dir + "/poses.lcmlog"},
                         dir + "/seg.out");
  const bool seg_indexed =
      seg.out.find("span index for the calibrator in the digest cache") != std::string::npos;
  std::snprintf(fig, sizeof fig, "%.0fx real time (wall), %.0fx (cpu)%s", robot_s / seg.wall_s,
                robot_s / (seg.user_s + seg.sys_s),
                seg_indexed ? ", span index of the session stored" : ", NO span index stored");
  Print("ftcal-pose-segmenter", seg, fig);
  // The segmenter's span index, put back before each first run (a run that reads a log whole
  // stores its own).
  const std::string spans_dir = cache + "/spans", saved_spans = dir + "/spans-from-segmenter";
  // (None when the segmenter stored none: the row then says so, and times a whole reading.)
  std::error_code no_spans;
  std::filesystem::copy(spans_dir, saved_spans, std::filesystem::copy_options::recursive, no_spans);

  // The logs are in the page cache after the segmenter's pass, as after a lab's recording; the
  // first run is a warm-up, not counted. The poses log first, as scripts/demo gives it: its
  // poses carry their scatter, so the STANDING phase is not segmented again.
  const std::vector<std::string> cal_argv = {FTCAL_CALIBRATOR,
                                             "--config",
                                             config,
                                             "--log",
                                             dir + "/poses.lcmlog",
                                             "--log",
                                             dir + "/session.lcmlog",
                                             "--out",
                                             dir + "/cal.pbtxt"};
  auto time_calibrator = [&](const char* name, const char* what,
                             const std::function<void()>& before_each) {
    before_each();
    Run(cal_argv, dir + "/cal.out");
    std::vector<Timing> cals;
    for (int r = 0; r < runs; ++r) {
      before_each();
      cals.push_back(Run(cal_argv, dir + "/cal.out"));
    }
    std::sort(cals.begin(), cals.end(),
              [](const Timing& a, const Timing& b) { return a.wall_s < b.wall_s; });
    const Timing& cal = cals[cals.size() / 2];
    const double used =
        Capture(cal.out, "calibrating: 4 hanging series, ([0-9]+) standing poses", "pose count");
    const double candidates =
        Capture(cal.out, "calibration done: ([0-9]+) candidates", "candidate count");
    const bool cached = cal.out.find("SHA-256 from the digest cache") != std::string::npos;
    const bool skipped = cal.out.find("not read: their records were counted") != std::string::npos;
    std::snprintf(fig, sizeof fig,
                  "whole process, %s: %.0f poses, %.0f candidates; median of %d runs (wall min "
                  "%.3f, max %.3f s)%s%s",
                  what, used, candidates, runs, cals.front().wall_s, cals.back().wall_s,
                  cached ? "" : ", no digest from the cache",
                  skipped ? ", STANDING span skipped (span index)" : "");
    Print(name, cal, fig);
  };
  // The first run on a new log, as a lab's first calibration after the twin or ftcal-record
  // wrote the session and the segmenter replayed it: the writers handed the digests over, the
  // segmenter the session's span index, and no calibrator has read the logs yet.
  const auto segmenter_index = [&] {
    std::filesystem::remove_all(spans_dir);
    std::error_code ec;
    std::filesystem::copy(saved_spans, spans_dir, std::filesystem::copy_options::recursive, ec);
  };
  time_calibrator("ftcal-calibrator", "digests from their writers, span index from the segmenter",
                  segmenter_index);
  // A session log the segmenter did not replay (its poses came live, or from elsewhere): no
  // span index, so the STANDING span is read (the span index a run leaves is removed before
  // the next).
  const auto no_index = [&] { std::filesystem::remove_all(spans_dir); };
  time_calibrator("ftcal-calibrator unindexed", "no span index", no_index);
  ::setenv("FTCAL_CACHE_DIR", "", 1);  // set and empty: no digest cache
  time_calibrator("ftcal-calibrator hash", "logs hashed (no digest cache)", [] {});
  ::setenv("FTCAL_CACHE_DIR", cache.c_str(), 1);

  const Timing cor = Run({FTCAL_CORRECTOR, "--config", config, "--calibration", dir + "/cal.pbtxt",
                          "--replay", dir + "/session.lcmlog", "--out", dir + "/contact.lcmlog"},
                         dir + "/cor.out");
  const double out = Capture(cor.out, "([0-9]+) leg-samples corrected", "leg-sample count");
  std::error_code ec;
  const double bytes = static_cast<double>(std::filesystem::file_size(dir + "/contact.lcmlog", ec));
  std::snprintf(fig, sizeof fig,
                "%.0f leg-samples: %.0f k/s (wall), %.0f k/s (cpu); %.2f GB written (%.0f B each)",
                out, 1e-3 * out / cor.wall_s, 1e-3 * out / (cor.user_s + cor.sys_s), 1e-9 * bytes,
                bytes / out);
  Print("ftcal-corrector", cor, fig);

  if (keep) {
    std::printf("kept %s\n", dir.c_str());
  } else {
    std::filesystem::remove_all(dir, ec);
  }
  return 0;
}
