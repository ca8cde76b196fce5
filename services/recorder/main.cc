// ftcal-record: every channel of the LCM group into an LCM event log, the format lcm-logger
// writes and lcm-logplayer, the calibrator and the segmenter read.
//
// Written here rather than using Debian's lcm-logger (LCM 1.3.1) because that one subscribes with
// LCM's default queue of 30 messages and has no option to change it: when its dispatch falls
// ~20 ms behind six transducers at 7 kHz, LCM drops what does not fit, however large the socket
// buffer and whatever its priority (seen: 271-3007 records lost in a two-host experiment whose
// kernel counted no drop). This recorder is LCM's own pieces: the subscription through
// services/common's bus (a queue of kSubscriptionQueueCapacity), the events written with
// lcm::LogFile; the file is the same format.
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <string>

#include <lcm/lcm-cpp.hpp>

#include "common/atomic_log.h"
#include "common/exit_codes.h"
#include "common/scheduling.h"
#include "common/service.h"
#include "common/shutdown.h"
#include "common/written_digest.h"

namespace {

// FILE, or with `increment` the first of FILE.00, FILE.01, ... that does not exist (lcm-logger
// -i's names, so that a restarted recorder never overwrites what its predecessor wrote).
std::string OutputPath(const std::string& path, bool increment) {
  std::error_code ec;
  if (!increment) return path;
  for (int i = 0; i < 10000; ++i) {
    char suffix[8];
    std::snprintf(suffix, sizeof(suffix), ".%02d", i);
    const std::string candidate = path + suffix;
    if (!std::filesystem::exists(candidate, ec)) return candidate;
  }
  return "";
}

}  // namespace

int main(int argc, char** argv) {
  ftcal::ServiceApp app(
      {"ftcal-record",
       "Records every channel of the LCM URL (the config's lcm_url, or --lcm-url) into an LCM "
       "event log (lcm-logger's format) until SIGINT/SIGTERM, with LCM's receive queue deep "
       "enough to ride out a stall (lcm-logger's holds 30 messages), flushed once a second. "
       "Refuses an existing OUT unless --increment (then OUT.00, OUT.01, ...).",
       /*replayable=*/false});
  std::string out;
  bool increment = false;
  bool lock_memory = false;
  double gather_ms = 10.0;
  app.cli().add_option("out", out, "the log file to write")->required();
  app.cli().add_flag("-i,--increment", increment,
                     "write to the first of OUT.00, OUT.01, ... that does not exist");
  app.cli().add_flag("--lock-memory", lock_memory,
                     "mlockall: no page fault stalls the recorder (needs CAP_IPC_LOCK or root)");
  app.cli()
      .add_option("--gather-ms", gather_ms,
                  "once a message comes, wait this long for more and write them together "
                  "(LCM queues them meanwhile): one wake-up a batch instead of one a message; "
                  "0: every message at once")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 100.0));
  if (auto rc = app.Init(argc, argv)) return *rc;
  app.bus().SetGatherUs(static_cast<int64_t>(gather_ms * 1000));

  const std::string path = OutputPath(out, increment);
  std::error_code ec;
  if (path.empty()) {
    app.log().critical("{}: no free name among {}.00 ... {}.9999", out, out, out);
    return ftcal::kExitDeviceIo;
  }
  if (std::filesystem::exists(path, ec)) {
    app.log().critical("{} exists: refusing to overwrite a recording (--increment writes {}.NN)",
                       path, path);
    return ftcal::kExitRefused;
  }
  lcm::LogFile log(path, "w");
  if (!log.good()) {
    app.log().critical("cannot open {} for writing", path);
    return ftcal::kExitDeviceIo;
  }
  if (lock_memory && !ftcal::LockMemory()) {
    app.log().warn(
        "--lock-memory: mlockall refused (needs CAP_IPC_LOCK or root); recording anyway");
  }

  int64_t events = 0, bytes = 0, file_bytes = 0;
  bool failed = false;
  // The recording's SHA-256, taken from the bytes as they are written: handed to the digest
  // cache at the end, so that the first calibration of the recording need not hash it.
  ftcal::WrittenDigest digest;
  app.bus().SubscribeRaw(".*", [&](const ftcal::MessageInfo& info, const void* data, int size) {
    if (failed) return;
    lcm::LogEvent e;
    e.eventnum = events;
    e.timestamp = info.recv_utime;
    e.channel = info.channel;
    e.datalen = size;
    e.data = const_cast<void*>(data);  // LogFile::writeEvent only reads it
    if (log.writeEvent(&e) != 0) {
      // A full disk or a vanished directory: stop at once, keep what was written.
      failed = true;
      app.stats().Error("write", "writing " + path + " failed; recording stopped");
      ftcal::RequestShutdown();
      return;
    }
    // The bytes lcm_eventlog_write_event() has just written (its event number is the count of
    // events before); the byte count is checked against the file at the end.
    char head[ftcal::kLcmEventHeaderBytes];
    ftcal::EncodeLcmEventHeader(head, events, info.recv_utime,
                                static_cast<uint32_t>(info.channel.size()),
                                static_cast<uint32_t>(size));
    digest.Update(head, sizeof head);
    digest.Update(info.channel.data(), info.channel.size());
    digest.Update(data, static_cast<size_t>(size));
    file_bytes += static_cast<int64_t>(sizeof head + info.channel.size()) + size;
    ++events;
    bytes += size;
  });
  app.AddPeriodic(1.0, [&] {
    if (std::fflush(log.getFilePtr()) != 0 && !failed) {
      failed = true;
      app.stats().Error("write", "flushing " + path + " failed; recording stopped");
      ftcal::RequestShutdown();
    }
  });
  app.log().info("recording into {}", path);
  const int rc = app.Run();
  const bool flushed = std::fflush(log.getFilePtr()) == 0;
  app.log().info("{}: {} events, {} bytes of payload", path, events, bytes);
  if (failed || !flushed) return ftcal::kExitDeviceIo;
  struct stat written {};
  if (::fstat(::fileno(log.getFilePtr()), &written) != 0) written = {};
  if (written.st_size != file_bytes) {
    // Bytes this process did not hash: the digest would be wrong, so it is not handed over.
    app.log().warn("{}: {} bytes in the file, {} hashed; its SHA-256 is not cached", path,
                   static_cast<long long>(written.st_size), static_cast<long long>(file_bytes));
  } else if (const std::string hex = digest.HandOver(path, written); !hex.empty()) {
    app.log().info("{}: SHA-256 {} handed to the digest cache", path, hex);
  }
  return rc;
}
