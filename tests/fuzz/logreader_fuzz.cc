// libFuzzer target: arbitrary bytes as an LCM log through LogReplayBus, the reader every
// offline stage and the calibrator use (services/common/log_replay_bus.cc: it frames events
// itself, because LCM's reader allocates whatever length a damaged header claims). Invariants
// beyond "no crash": the events it dispatches, written again with LCM's own log writer
// (lcm_eventlog_write_event) and read back, are the same events, in order, with no damage
// reported; and the events returned never add up to more bytes than the input.
#include <stdlib.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/bus.h"
#include "common/log_replay_bus.h"

namespace {

[[noreturn]] void Fail(const char* why) {
  std::fprintf(stderr, "logreader_fuzz: %s\n", why);
  std::abort();
}

struct Event {
  std::string channel;
  int64_t utime;
  std::vector<std::uint8_t> data;
  bool operator==(const Event& o) const {
    return channel == o.channel && utime == o.utime && data == o.data;
  }
};

const std::string& Dir() {
  static const std::string dir = [] {
    char tmpl[] = "/tmp/ftcal-logreader-fuzz-XXXXXX";
    if (::mkdtemp(tmpl) == nullptr) Fail("mkdtemp");
    return std::string(tmpl);
  }();
  return dir;
}

// Every event of `path`, and the reader's error count (damage is counted as an error).
std::vector<Event> Replay(const std::string& path, int64_t* errors) {
  static auto log =
      std::make_shared<spdlog::logger>("fuzz", std::make_shared<spdlog::sinks::null_sink_mt>());
  ftcal::ServiceStats stats(log);
  std::vector<Event> events;
  {
    ftcal::LogReplayBus bus(path, Dir() + "/out.lcmlog", stats);
    bus.SubscribeRaw(".*", [&](const ftcal::MessageInfo& info, const void* data, int size) {
      if (size < 0 || (size > 0 && data == nullptr)) Fail("an event without its bytes");
      const auto* p = static_cast<const std::uint8_t*>(data);
      events.push_back({info.channel, info.recv_utime, std::vector<std::uint8_t>(p, p + size)});
    });
    bus.Run([] {}, 1000000);
    if (!bus.finished()) Fail("the reader did not read to the end");
    // Fewer may be dispatched than read: a channel name holding a NUL matches no pattern
    // (POSIX regular expressions, as LCM's C strings, end there; no live LCM message has one).
    if (bus.events_read() < static_cast<int64_t>(events.size()))
      Fail("dispatched more events than read");
  }  // the uncommitted output goes with the bus
  *errors = stats.errors();
  return events;
}

void WriteFile(const std::string& path, const std::uint8_t* data, std::size_t size) {
  FILE* f = std::fopen(path.c_str(), "wb");
  if (f == nullptr) Fail("fopen");
  if (size > 0 && std::fwrite(data, 1, size, f) != size) Fail("fwrite");
  std::fclose(f);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string in = Dir() + "/in.lcmlog", again = Dir() + "/again.lcmlog";
  WriteFile(in, data, size);
  int64_t errors = 0;
  const std::vector<Event> events = Replay(in, &errors);
  std::size_t bytes = 0;
  for (const Event& e : events) {
    if (e.channel.empty()) Fail("an event with an empty channel");
    bytes += 28 + e.channel.size() + e.data.size();  // LCM's event header is 28 bytes
  }
  if (bytes > size) Fail("events add up to more bytes than the input");

  ::unlink(again.c_str());
  {
    lcm::LogFile out(again, "w");
    if (!out.good()) Fail("lcm::LogFile for writing");
    int64_t number = 0;
    for (const Event& e : events) {
      lcm::LogEvent le;
      le.eventnum = number++;
      le.timestamp = e.utime;
      le.channel = e.channel;
      le.datalen = static_cast<int32_t>(e.data.size());
      le.data = const_cast<std::uint8_t*>(e.data.data());
      if (out.writeEvent(&le) != 0) Fail("lcm::LogFile::writeEvent");
    }
  }
  int64_t errors_again = 0;
  const std::vector<Event> back = Replay(again, &errors_again);
  if (errors_again != 0) Fail("LCM's writing of the events read back with damage");
  if (!(back == events)) Fail("LCM's writing of the events read back as other events");
  return 0;
}
