// LogReplayBus reads LCM logs itself (in 1 MiB chunks, the next read ahead on a thread of its
// own) and AtomicLogFile writes them itself;
// both are checked here against LCM's own writer and reader, on logs whose events straddle
// chunk boundaries, with one event larger than a chunk and damaged bytes between events.
#include <unistd.h>

#include <cstdint>
#include <functional>
#include <tuple>
#include <stdexcept>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <lcm/lcm-cpp.hpp>
#include <spdlog/sinks/null_sink.h>
#include <spdlog/spdlog.h>

#include "common/atomic_log.h"
#include "common/bus.h"
#include "common/log_replay_bus.h"
#include "ftcal/config.h"

namespace ftcal {
namespace {

struct Event {
  int64_t utime;
  std::string channel;
  std::vector<uint8_t> data;
  bool operator==(const Event& o) const {
    return utime == o.utime && channel == o.channel && data == o.data;
  }
};

std::vector<uint8_t> Bytes(size_t n, uint32_t seed) {
  std::vector<uint8_t> b(n);
  for (size_t i = 0; i < n; ++i) {
    seed = seed * 1664525u + 1013904223u;
    b[i] = static_cast<uint8_t>(seed >> 24);
  }
  return b;
}

// Events of sizes that put chunk boundaries (every 1 MiB) inside headers, channels and data,
// one of 3 MiB (longer than a chunk), ten of 600 kB (most of them begin further before a chunk's
// end than the bytes the read-ahead carries over), and payloads full of the sync word's bytes.
std::vector<Event> MakeEvents() {
  std::vector<Event> events;
  int64_t t = 1'700'000'000'000'000;
  for (int i = 0; i < 9000; ++i) {
    const size_t size = i == 4000        ? (3u << 20)
                        : i % 900 == 450 ? (600u << 10)
                                         : static_cast<size_t>(37 + (i * 7919) % 900);
    Event e{t += 1000, "CH_" + std::to_string(i % 5), Bytes(size, static_cast<uint32_t>(i))};
    if (i % 97 == 0 && e.data.size() >= 8) {
      const uint8_t sync[4] = {0xED, 0xA1, 0xDA, 0x01};
      for (int k = 0; k < 4; ++k) e.data[k] = e.data[4 + k] = sync[k];
    }
    events.push_back(std::move(e));
  }
  return events;
}

std::vector<Event> ReadWithLcm(const std::string& path) {
  lcm::LogFile log(path, "r");
  EXPECT_TRUE(log.good());
  std::vector<Event> events;
  for (const lcm::LogEvent* e = log.readNextEvent(); e != nullptr; e = log.readNextEvent()) {
    const auto* p = static_cast<const uint8_t*>(e->data);
    events.push_back({e->timestamp, e->channel, std::vector<uint8_t>(p, p + e->datalen)});
  }
  return events;
}

void WriteWithAtomicLogFile(const std::string& path, const std::vector<Event>& events) {
  AtomicLogFile log(path, "test input");
  for (const Event& e : events)
    log.Write(e.utime, e.channel, e.data.data(), static_cast<int>(e.data.size()));
  log.Commit();
}

class ReplayBusTest : public ::testing::Test {
 protected:
  std::string dir_ = "/tmp/ftcal_replay_bus_test_" + std::to_string(::getpid());
  std::shared_ptr<spdlog::logger> log_ = std::make_shared<spdlog::logger>(
      "replay_bus_test", std::make_shared<spdlog::sinks::null_sink_mt>());
  void SetUp() override { ASSERT_EQ(::system(("mkdir -p " + dir_).c_str()), 0); }
  void TearDown() override { (void)::system(("rm -rf " + dir_).c_str()); }
};

// Every event as LCM wrote it reaches the handler unchanged, and the replay output (written by
// AtomicLogFile) reads back through LCM's reader as the events republished.
TEST_F(ReplayBusTest, ReadsAndWritesWhatLcmWritesAndReads) {
  const std::vector<Event> events = MakeEvents();
  const std::string in = dir_ + "/in.lcmlog", out = dir_ + "/out.lcmlog";
  {
    lcm::LogFile log(in, "w");
    int64_t n = 0;
    for (const Event& e : events) {
      lcm::LogEvent le;
      le.eventnum = n++;
      le.timestamp = e.utime;
      le.channel = e.channel;
      le.datalen = static_cast<int32_t>(e.data.size());
      le.data = const_cast<uint8_t*>(e.data.data());
      ASSERT_EQ(log.writeEvent(&le), 0);
    }
  }
  ServiceStats stats(log_);
  std::vector<Event> seen;
  {
    LogReplayBus bus(in, out, stats);
    Sha256 sha;
    bus.ConsumeInput([&](const uint8_t* data, size_t size) { sha.Update(data, size); });
    bus.SubscribeRaw("CH_.*", [&](const MessageInfo& info, const void* data, int size) {
      const auto* p = static_cast<const uint8_t*>(data);
      seen.push_back({info.recv_utime, info.channel, std::vector<uint8_t>(p, p + size)});
      bus.PublishRaw("OUT_" + info.channel, data, size);
    });
    bus.Run([] {}, 100'000);
    ASSERT_TRUE(bus.finished());
    bus.Commit();
    // Every byte, in order, once, through the read-ahead and the refill of the 3 MiB event:
    // the hash is the file's SHA-256 from a separate read of it.
    ASSERT_TRUE(bus.InputConsumedWhole());
    EXPECT_EQ(sha.HexDigest(), Sha256File(in));
  }
  EXPECT_EQ(stats.errors(), 0);
  ASSERT_EQ(seen.size(), events.size());
  for (size_t i = 0; i < events.size(); ++i) ASSERT_TRUE(seen[i] == events[i]) << "event " << i;
  const std::vector<Event> back = ReadWithLcm(out);
  ASSERT_EQ(back.size(), events.size());
  for (size_t i = 0; i < events.size(); ++i) {
    Event want = events[i];
    want.channel = "OUT_" + want.channel;
    ASSERT_TRUE(back[i] == want) << "output event " << i;
  }
}

// Garbage between events (a sync word whose header is impossible) and a truncated last event:
// every whole event is read, each damaged span counted as one error, nothing else lost.
TEST_F(ReplayBusTest, DamageBetweenEventsLosesOnlyTheDamagedBytes) {
  std::vector<Event> events = MakeEvents();
  events.resize(3000);
  const std::string in = dir_ + "/in.lcmlog";
  WriteWithAtomicLogFile(in, events);
  // Insert garbage after event 1500 and cut the last event short, with the raw bytes.
  std::vector<uint8_t> bytes;
  {
    FILE* f = std::fopen(in.c_str(), "rb");
    ASSERT_NE(f, nullptr);
    uint8_t buf[65536];
    for (size_t n; (n = std::fread(buf, 1, sizeof buf, f)) > 0;)
      bytes.insert(bytes.end(), buf, buf + n);
    std::fclose(f);
  }
  size_t at = 0;
  for (size_t i = 0; i < 1500; ++i) at += 28 + events[i].channel.size() + events[i].data.size();
  // LCM's rule: an event must be followed by a sync word (or the end), so the garbage starts
  // with one, then a header whose lengths are impossible (-1).
  std::vector<uint8_t> garbage = {0xED, 0xA1, 0xDA, 0x01};
  garbage.resize(4 + 24 + 3, 0xFF);
  bytes.insert(bytes.begin() + static_cast<long>(at), garbage.begin(), garbage.end());
  bytes.resize(bytes.size() - 5);
  {
    FILE* f = std::fopen(in.c_str(), "wb");
    ASSERT_EQ(std::fwrite(bytes.data(), 1, bytes.size(), f), bytes.size());
    std::fclose(f);
  }
  ServiceStats stats(log_);
  std::vector<Event> seen;
  LogReplayBus bus(in, dir_ + "/out.lcmlog", stats);
  Sha256 sha;
  bus.ConsumeInput([&](const uint8_t* data, size_t size) { sha.Update(data, size); });
  bus.SubscribeRaw(".*", [&](const MessageInfo& info, const void* data, int size) {
    const auto* p = static_cast<const uint8_t*>(data);
    seen.push_back({info.recv_utime, info.channel, std::vector<uint8_t>(p, p + size)});
  });
  bus.Run([] {}, 100'000);
  events.pop_back();  // truncated
  ASSERT_EQ(seen.size(), events.size());
  for (size_t i = 0; i < events.size(); ++i) ASSERT_TRUE(seen[i] == events[i]) << "event " << i;
  EXPECT_EQ(stats.errors(), 2) << stats.last_error();  // the garbage, the truncated tail
  // The damaged bytes too: the consumer has the file as it is.
  ASSERT_TRUE(bus.InputConsumedWhole());
  EXPECT_EQ(sha.HexDigest(), Sha256File(in));
}

// Not whole: nothing asked for, nothing read yet, or a consumer that threw part way (which
// stops the consuming, not the replay).
TEST_F(ReplayBusTest, InputConsumedWholeOnlyWhenEveryByteWent) {
  std::vector<Event> events = MakeEvents();
  events.resize(2000);
  const std::string in = dir_ + "/in.lcmlog";
  WriteWithAtomicLogFile(in, events);
  ServiceStats stats(log_);
  LogReplayBus plain(in, dir_ + "/out1.lcmlog", stats);
  plain.Run([] {}, 100'000);
  ASSERT_TRUE(plain.finished());
  EXPECT_FALSE(plain.InputConsumedWhole());
  LogReplayBus unread(in, dir_ + "/out2.lcmlog", stats);
  unread.ConsumeInput([](const uint8_t*, size_t) {});
  EXPECT_FALSE(unread.InputConsumedWhole());
  LogReplayBus throwing(in, dir_ + "/out3.lcmlog", stats);
  int64_t consumed = 0;
  throwing.ConsumeInput([&](const uint8_t*, size_t size) {
    if (consumed > 0) throw std::runtime_error("consumer failed");
    consumed += static_cast<int64_t>(size);
  });
  int64_t events_seen = 0;
  throwing.SubscribeRaw(".*", [&](const MessageInfo&, const void*, int) { ++events_seen; });
  throwing.Run([] {}, 100'000);
  ASSERT_TRUE(throwing.finished());
  EXPECT_EQ(events_seen, 2000);
  EXPECT_GT(consumed, 0);
  EXPECT_FALSE(throwing.InputConsumedWhole());
}

// Each event comes with its bytes' place in the file (the offsets of LCM's format, computed
// here from the events' sizes), and SkipAt() reads on at the offset it names: from an event
// far into the file (chunks already read ahead) to one several chunks on, the events between
// unread and the rest as written; not when its callback says no, not at an offset that is no
// event's start, and not while every byte must be consumed.
TEST_F(ReplayBusTest, SkipAtReadsOnFromTheOffsetItNames) {
  const std::vector<Event> events = MakeEvents();
  const std::string in = dir_ + "/in.lcmlog";
  WriteWithAtomicLogFile(in, events);
  std::vector<int64_t> offset(events.size() + 1, 0);
  for (size_t i = 0; i < events.size(); ++i) {
    offset[i + 1] =
        offset[i] + 28 + static_cast<int64_t>(events[i].channel.size() + events[i].data.size());
  }
  const size_t from = 2500, to = 6500;  // the 3 MiB event (4000) and 600 kB ones between
  ASSERT_GT(offset[to] - offset[from], int64_t{6} << 20);  // several chunks
  auto run = [&](std::function<bool()> at_from, int64_t from_at, std::vector<size_t>* seen,
                 bool consume = false) {
    ServiceStats stats(log_);
    LogReplayBus bus(in, dir_ + "/out.lcmlog", stats);
    if (consume) bus.ConsumeInput([](const uint8_t*, size_t) {});
    size_t i = 0;
    bool armed = false;
    bus.SubscribeRaw(".*", [&](const MessageInfo& info, const void* data, int size) {
      while (i < events.size() && offset[i] < info.log_offset) ++i;  // the skipped ones
      ASSERT_LT(i, events.size());
      ASSERT_EQ(info.log_offset, offset[i]);
      ASSERT_EQ(info.log_end, offset[i + 1]);
      const auto* p = static_cast<const uint8_t*>(data);
      ASSERT_EQ(std::vector<uint8_t>(p, p + size), events[i].data) << i;
      seen->push_back(i);
      if (i == 100 && !armed) {
        armed = true;
        const bool took = bus.SkipAt(from_at, offset[to], at_from);
        EXPECT_EQ(took, !consume);
      }
    });
    bus.Run([] {}, 100'000);
    EXPECT_TRUE(bus.finished());
    EXPECT_EQ(stats.errors(), 0) << stats.last_error();
    return bus.skipped_bytes();
  };
  std::vector<size_t> seen;
  int calls = 0;
  EXPECT_EQ(run([&] { return ++calls > 0; }, offset[from], &seen), offset[to] - offset[from]);
  EXPECT_EQ(calls, 1);
  ASSERT_EQ(seen.size(), events.size() - (to - from));
  for (size_t j = 0; j < seen.size(); ++j) ASSERT_EQ(seen[j], j < from ? j : j + (to - from));

  for (auto [why, at_from, from_at, consume] :
       {std::make_tuple("declined", std::function<bool()>([] { return false; }), offset[from],
                        false),
        std::make_tuple("not an event's start", std::function<bool()>([] { return true; }),
                        offset[from] + 1, false),
        std::make_tuple("consuming every byte", std::function<bool()>([] { return true; }),
                        offset[from], true)}) {
    SCOPED_TRACE(why);
    seen.clear();
    EXPECT_EQ(run(at_from, from_at, &seen, consume), 0);
    EXPECT_EQ(seen.size(), events.size());
  }
}

// A handler that subscribes sees its new subscription from the same event on, in order, as
// matching every pattern per event did.
TEST_F(ReplayBusTest, ASubscriptionMadeInAHandlerTakesEffectAtOnce) {
  const std::string in = dir_ + "/in.lcmlog";
  {
    AtomicLogFile log(in, "test input");
    const uint8_t b = 7;
    for (int i = 0; i < 3; ++i) log.Write(1000 + i, "A", &b, 1);
    log.Commit();
  }
  ServiceStats stats(log_);
  LogReplayBus bus(in, dir_ + "/out.lcmlog", stats);
  std::vector<std::string> calls;
  bus.SubscribeRaw("A", [&](const MessageInfo& info, const void*, int) {
    calls.push_back("first@" + std::to_string(info.recv_utime));
    if (info.recv_utime == 1001) {
      bus.SubscribeRaw("A|B", [&](const MessageInfo& i2, const void*, int) {
        calls.push_back("second@" + std::to_string(i2.recv_utime));
      });
    }
  });
  bus.Run([] {}, 100'000);
  EXPECT_EQ(calls, (std::vector<std::string>{"first@1000", "first@1001", "second@1001",
                                             "first@1002", "second@1002"}));
}

// What the calibrator looks at to find a poses log among its inputs: the channels of a log's
// first events, as written, and nothing past the first bytes that are not a whole event (a
// header claiming more bytes than the file has is not followed).
TEST_F(ReplayBusTest, ChannelsAtStartAreTheFirstEventsAndStopAtDamage) {
  std::vector<Event> events = MakeEvents();
  events.resize(400);
  const std::string in = dir_ + "/in.lcmlog";
  WriteWithAtomicLogFile(in, events);
  std::vector<std::string> want;
  for (size_t i = 0; i < 300; ++i) want.push_back(events[i].channel);
  EXPECT_EQ(LogChannelsAtStart(in, 300), want);
  // Within the first 64 kB: as many whole events as fit.
  size_t fit = 0;
  for (size_t at = 0; fit < events.size(); ++fit) {
    at += 28 + events[fit].channel.size() + events[fit].data.size();
    if (at - events[fit].data.size() > (64u << 10)) break;
  }
  EXPECT_EQ(LogChannelsAtStart(in, 400, 64 << 10).size(), fit);
  // Event 10's channel length made impossible: events 0-9 only.
  {
    FILE* f = std::fopen(in.c_str(), "r+b");
    ASSERT_NE(f, nullptr);
    long at = 0;
    for (size_t i = 0; i < 10; ++i)
      at += static_cast<long>(28 + events[i].channel.size() + events[i].data.size());
    const uint8_t huge[4] = {0x7F, 0xFF, 0xFF, 0xFF};
    ASSERT_EQ(std::fseek(f, at + 20, SEEK_SET), 0);
    ASSERT_EQ(std::fwrite(huge, 1, 4, f), 4u);
    std::fclose(f);
  }
  want.resize(10);
  EXPECT_EQ(LogChannelsAtStart(in, 300), want);
  EXPECT_TRUE(LogChannelsAtStart(dir_ + "/no-such.lcmlog", 10).empty());
}

}  // namespace
}  // namespace ftcal
