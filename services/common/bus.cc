#include "common/bus.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <thread>

#include "common/shutdown.h"

namespace ftcal {
namespace {

int64_t WallClockUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// Size of one event in LCM's log format: sync word, event number, timestamp, channel length,
// data length, then the channel and the data.
int64_t LoggedEventBytes(const lcm::LogEvent& event) {
  return 4 + 8 + 8 + 4 + 4 + static_cast<int64_t>(event.channel.size()) + event.datalen;
}

// Reads the header of the event at `at` (its sync word already found there) and leaves `file`
// positioned at `at` when the lengths it claims are possible for this file.
bool PlausibleHeader(FILE* file, int64_t at, int64_t file_bytes) {
  uint8_t header[28];
  if (::fseeko(file, at, SEEK_SET) != 0 || std::fread(header, 1, 28, file) != 28) return false;
  auto be32 = [&header](int offset) {
    return static_cast<int32_t>(uint32_t{header[offset]} << 24 | uint32_t{header[offset + 1]} << 16 |
                                uint32_t{header[offset + 2]} << 8 | uint32_t{header[offset + 3]});
  };
  const int64_t channel_bytes = be32(20);
  const int64_t data_bytes = be32(24);
  return channel_bytes > 0 && data_bytes >= 0 &&
         at + 28 + channel_bytes + data_bytes <= file_bytes &&
         ::fseeko(file, at, SEEK_SET) == 0;
}

// Positions `file` at the next sync word of LCM's log format at or after `from` and returns
// its offset, or -1 when there is none before the end.
int64_t FindSyncWord(FILE* file, int64_t from) {
  constexpr uint32_t kSyncWord = 0xEDA1DA01;  // big-endian on disk
  if (::fseeko(file, from, SEEK_SET) != 0) return -1;
  uint32_t window = 0;
  int64_t bytes = 0;
  for (int c = std::fgetc(file); c != EOF; c = std::fgetc(file)) {
    window = (window << 8) | static_cast<uint32_t>(c);
    if (++bytes >= 4 && window == kSyncWord) {
      const int64_t at = from + bytes - 4;
      return ::fseeko(file, at, SEEK_SET) == 0 ? at : -1;
    }
  }
  return -1;
}

}  // namespace

// ---- Bus ----

void Bus::SubscribeRaw(const std::string& channel, RawHandler handler) {
  std::regex pattern;
  try {
    pattern = std::regex(channel, std::regex::extended);
  } catch (const std::regex_error& e) {
    throw std::invalid_argument("channel pattern '" + channel + "' is not a valid regular "
                                "expression: " + e.what());
  }
  subscriptions_.push_back({channel, std::move(pattern), std::move(handler)});
  TransportSubscribe(subscriptions_.size() - 1, channel);
}

void Bus::PublishRaw(const std::string& channel, const void* data, int size, bool count) {
  TransportPublish(channel, data, size);
  if (count) stats_.CountOut();
}

void Bus::Guarded(const std::string& what, const std::function<void()>& fn) {
  try {
    fn();
  } catch (const BadInput& e) {
    stats_.Drop(e.kind(), e.what());
  } catch (const std::exception& e) {
    stats_.Error(what, e.what());
  } catch (...) {
    stats_.Error(what, "unknown exception");
  }
}

void Bus::Dispatch(size_t subscription, const std::string& channel, int64_t recv_utime,
                   const void* data, int size) {
  stats_.CountIn();
  const Subscription& sub = subscriptions_.at(subscription);
  const MessageInfo info{channel, recv_utime};
  Guarded("handler for " + sub.channel, [&] { sub.handler(info, data, size); });
}

// ---- LcmBus ----

LcmBus::LcmBus(const std::string& url, ServiceStats& stats) : Bus(stats), lcm_(url) {
  if (!lcm_.good()) {
    throw std::runtime_error("cannot open LCM at '" + url +
                             "' (bad URL, or no multicast route: see scripts/netns-exec)");
  }
}

int64_t LcmBus::NowUtime() const { return WallClockUtime(); }

void LcmBus::Trampoline::OnMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
  bus->Dispatch(subscription, channel, rbuf->recv_utime, rbuf->data,
                static_cast<int>(rbuf->data_size));
}

void LcmBus::TransportSubscribe(size_t subscription, const std::string& channel) {
  trampolines_.push_back(std::make_unique<Trampoline>(Trampoline{this, subscription}));
  if (lcm_.subscribe(channel, &Trampoline::OnMessage, trampolines_.back().get()) == nullptr) {
    throw std::runtime_error("LCM refused the subscription to '" + channel + "'");
  }
}

void LcmBus::TransportPublish(const std::string& channel, const void* data, int size) {
  if (lcm_.publish(channel, data, static_cast<unsigned int>(size)) != 0) {
    throw std::runtime_error("LCM publish on " + channel + " failed");
  }
}

int LcmBus::HandleOnce(int timeout_ms) { return lcm_.handleTimeout(timeout_ms); }

void LcmBus::Run(const std::function<void()>& tick, int64_t tick_us) {
  using Clock = std::chrono::steady_clock;
  constexpr int kMaxWaitMs = 100;  // the shutdown flag is checked at least this often
  const auto period = std::chrono::microseconds(tick_us);
  auto next_tick = Clock::now() + period;
  while (!ShutdownRequested()) {
    const auto until_tick =
        std::chrono::duration_cast<std::chrono::milliseconds>(next_tick - Clock::now()).count();
    const int wait_ms = static_cast<int>(std::clamp<int64_t>(until_tick + 1, 0, kMaxWaitMs));
    errno = 0;
    if (lcm_.handleTimeout(wait_ms) < 0 && !ShutdownRequested() && errno != EINTR) {
      stats_.Error("lcm", std::string("handleTimeout failed: ") + std::strerror(errno));
      // Don't spin on a persistent failure.
      std::this_thread::sleep_for(std::chrono::milliseconds(kMaxWaitMs));
    }
    const auto now = Clock::now();
    if (now >= next_tick) {
      Guarded("periodic work", tick);
      next_tick += period;
      if (next_tick <= now) next_tick = now + period;  // late: skip, don't burst
    }
  }
}

// ---- LogReplayBus ----

LogReplayBus::LogReplayBus(const std::string& in_path, const std::string& out_path,
                           ServiceStats& stats)
    : Bus(stats),
      in_path_(in_path) {
  struct stat st {};
  if (::stat(in_path.c_str(), &st) != 0) {
    throw std::runtime_error("replay input '" + in_path + "': " + std::strerror(errno));
  }
  if (!S_ISREG(st.st_mode)) {
    throw std::runtime_error("replay input '" + in_path + "' is not a regular file");
  }
  in_ = std::make_unique<lcm::LogFile>(in_path, "r");
  if (!in_->good()) {
    throw std::runtime_error("replay input '" + in_path + "': cannot open: " +
                             std::strerror(errno));
  }
  out_ = std::make_unique<AtomicLogFile>(out_path, "replay output");
}

// The output's temporary file goes with out_ unless Commit() ran.
LogReplayBus::~LogReplayBus() = default;

void LogReplayBus::TransportSubscribe(size_t /*subscription*/, const std::string& /*channel*/) {}

void LogReplayBus::TransportPublish(const std::string& channel, const void* data, int size) {
  out_->Write(now_utime_, channel, data, size);
}

void LogReplayBus::Run(const std::function<void()>& tick, int64_t tick_us) {
  FILE* file = in_->getFilePtr();
  struct stat st {};
  if (::fstat(::fileno(file), &st) != 0) {
    throw std::runtime_error("replay input '" + in_path_ + "': " + std::strerror(errno));
  }
  const int64_t file_bytes = st.st_size;
  // LCM's reader skips to the next sync word without saying so, refuses an event that is not
  // followed by a sync word or the end, and allocates whatever length a damaged header claims.
  // So each event's sync word and header are checked here first, and every byte not returned
  // as an event is reported (as the span it covers) instead of silently lost.
  int64_t damage_from = -1;
  auto damaged = [&](int64_t at) {
    if (damage_from < 0) damage_from = at;
  };
  auto report_damage = [&](int64_t to) {
    if (damage_from < 0) return;
    stats_.Error("replay input damaged",
                 in_path_ + ": skipped " + std::to_string(to - damage_from) +
                     " unreadable bytes at offset " + std::to_string(damage_from));
    damage_from = -1;
  };
  bool ticking = false;
  int64_t next_tick = 0;
  int64_t pos = 0;
  while (true) {
    if (ShutdownRequested()) {
      stats_.log().warn("replay interrupted after {} events; output not written", events_read_);
      return;
    }
    const int64_t sync = FindSyncWord(file, pos);
    if (sync < 0) {
      if (pos < file_bytes) damaged(pos);
      break;
    }
    if (sync > pos) damaged(pos);
    const lcm::LogEvent* event =
        PlausibleHeader(file, sync, file_bytes) ? in_->readNextEvent() : nullptr;
    if (event == nullptr) {
      damaged(sync);
      pos = sync + 1;
      continue;
    }
    report_damage(sync);
    pos = sync + LoggedEventBytes(*event);
    ++events_read_;

    // Periodic work on the log's clock, as it would have run live between these events; the
    // first tick is at the first event, as a live loop's is at its start.
    if (!ticking) {
      ticking = true;
      next_tick = event->timestamp;
    } else if (event->timestamp - next_tick > 1000 * tick_us) {
      next_tick = event->timestamp - (event->timestamp - next_tick) % tick_us;  // a long gap
    }
    while (event->timestamp >= next_tick) {
      now_utime_ = next_tick;
      Guarded("periodic work", tick);
      next_tick += tick_us;
    }
    now_utime_ = event->timestamp;
    for (size_t i = 0; i < subscriptions_.size(); ++i) {
      if (std::regex_match(event->channel, subscriptions_[i].pattern)) {
        Dispatch(i, event->channel, event->timestamp, event->data, event->datalen);
      }
    }
  }
  report_damage(file_bytes);
  if (events_read_ == 0 && file_bytes > 0) {
    stats_.Error("replay input", in_path_ + ": no LCM log events in " +
                                     std::to_string(file_bytes) + " bytes (not an LCM log?)");
  }
  finished_ = true;
}

void LogReplayBus::Commit() { out_->Commit(); }

}  // namespace ftcal
