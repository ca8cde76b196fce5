#include "common/log_replay_bus.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <condition_variable>
#include <cstring>
#include <mutex>
#include <thread>

#include "common/big_endian.h"
#include "common/shutdown.h"

namespace ftcal {
namespace {

constexpr uint32_t kSyncWord = 0xEDA1DA01;  // LCM log format, big-endian on disk
constexpr int64_t kHeaderBytes = 28;        // sync, event number, timestamp, two lengths
constexpr int64_t kChunkBytes = 1 << 20;
// Room before a read-ahead chunk for the tail of the event that straddles the chunks, so that
// it is copied there instead of read again. An event longer than this is read again whole.
constexpr int64_t kHeadroomBytes = 64 << 10;

// pread until `len` bytes or the end of the file (or an error); the bytes read.
int64_t PreadFully(int fd, uint8_t* into, int64_t len, int64_t offset) {
  int64_t got = 0;
  while (got < len) {
    const ssize_t r = ::pread(fd, into + got, static_cast<size_t>(len - got), offset + got);
    if (r < 0 && errno == EINTR) continue;
    if (r <= 0) break;  // an error, or the file shrank since it was opened
    got += r;
  }
  return got;
}

}  // namespace

std::vector<std::string> LogChannelsAtStart(const std::string& path, int max_events,
                                            int64_t max_bytes) {
  std::vector<std::string> channels;
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return channels;
  // Read as far as the events need, a piece at a time: a few hundred events are tens of kB, not
  // the whole allowance (1 MB by default) zeroed, faulted in and filled.
  constexpr int64_t kPieceBytes = 64 << 10;
  const int64_t limit = std::max<int64_t>(max_bytes, 0);
  std::vector<uint8_t> bytes;
  int64_t n = 0;  // bytes read
  bool eof = false;
  // Makes bytes [0, want) present when the file and the allowance have them.
  auto have = [&](int64_t want) {
    while (n < want && !eof && n < limit) {
      const int64_t piece = std::min(limit - n, std::max(kPieceBytes, want - n));
      bytes.resize(static_cast<size_t>(n + piece));
      const int64_t got = PreadFully(fd, bytes.data() + n, piece, n);
      if (got <= 0) {
        eof = true;
        break;
      }
      eof = got < piece;
      n += got;
    }
    return n >= want;
  };
  for (int64_t at = 0; static_cast<int>(channels.size()) < max_events && have(at + kHeaderBytes);) {
    const uint8_t* header = bytes.data() + at;
    if (Be32(header) != kSyncWord) break;
    const int64_t channel_bytes = static_cast<int32_t>(Be32(header + 20));
    const int64_t data_bytes = static_cast<int32_t>(Be32(header + 24));
    if (channel_bytes <= 0 || data_bytes < 0 || !have(at + kHeaderBytes + channel_bytes)) break;
    header = bytes.data() + at;  // the buffer may have moved
    channels.emplace_back(reinterpret_cast<const char*>(header + kHeaderBytes),
                          static_cast<size_t>(channel_bytes));
    at += kHeaderBytes + channel_bytes + data_bytes;
  }
  ::close(fd);
  return channels;
}

// ---- LogReplayBus ----

struct LogReplayBus::InputTap {
  std::function<void(const uint8_t*, size_t)> consume;
  int64_t upto = 0;  // bytes [0, upto) consumed; -1: an exception ended the consuming
  // Bytes [offset, offset + got) were read: what of them extends the consumed prefix goes in.
  void Add(int64_t offset, const uint8_t* data, int64_t got) {
    if (upto < 0 || offset > upto || offset + got <= upto) return;
    try {
      consume(data + (upto - offset), static_cast<size_t>(offset + got - upto));
      upto = offset + got;
    } catch (...) {
      upto = -1;
    }
  }
};

// One read at a time on a thread of its own, into a buffer the caller takes when it needs it.
// (No library in Debian does this for a plain file; io_uring would, at the cost of a
// dependency for one pread.)
class LogReplayBus::ReadAhead {
 public:
  ReadAhead(int fd, InputTap* tap) : fd_(fd), tap_(tap), thread_([this] { Loop(); }) {}
  ~ReadAhead() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      quit_ = true;
    }
    cv_.notify_all();
    thread_.join();
  }

  // Starts reading [offset, offset + len) into the spare buffer, after kHeadroomBytes.
  void Request(int64_t offset, int64_t len) {
    std::lock_guard<std::mutex> lock(mu_);
    offset_ = offset;
    len_ = len;
    state_ = State::kRequested;
    cv_.notify_all();
  }
  // The request's offset, or -1 when there is none.
  int64_t pending_offset() {
    std::lock_guard<std::mutex> lock(mu_);
    return state_ == State::kIdle ? -1 : offset_;
  }
  // Waits for the request and swaps its buffer into *buf (the data start at kHeadroomBytes);
  // the bytes read. The old *buf becomes the next spare.
  int64_t Take(std::vector<uint8_t>* buf) {
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [this] { return state_ == State::kDone; });
    buf->swap(spare_);
    state_ = State::kIdle;
    return got_;
  }
  // Lets a request finish and forgets it.
  void Drop() {
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [this] { return state_ != State::kRequested; });
    state_ = State::kIdle;
  }

 private:
  enum class State { kIdle, kRequested, kDone };
  void Loop() {
    std::unique_lock<std::mutex> lock(mu_);
    while (true) {
      cv_.wait(lock, [this] { return quit_ || state_ == State::kRequested; });
      if (quit_) return;
      const int64_t offset = offset_, len = len_;
      const auto need = static_cast<size_t>(kHeadroomBytes + len);
      lock.unlock();  // the buffer is this thread's while kRequested
      if (spare_.size() < need) spare_.resize(need);
      const int64_t got = PreadFully(fd_, spare_.data() + kHeadroomBytes, len, offset);
      // Here, not on the replay's thread: a digest there would lengthen the replay's own work.
      if (tap_ != nullptr) tap_->Add(offset, spare_.data() + kHeadroomBytes, got);
      lock.lock();
      got_ = got;
      state_ = State::kDone;
      cv_.notify_all();
    }
  }

  int fd_;
  InputTap* tap_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::vector<uint8_t> spare_;
  int64_t offset_ = 0, len_ = 0, got_ = 0;
  State state_ = State::kIdle;
  bool quit_ = false;
  std::thread thread_;  // last: starts once the members it uses are built
};

LogReplayBus::LogReplayBus(const std::string& in_path, const std::string& out_path,
                           ServiceStats& stats)
    : Bus(stats), in_path_(in_path) {
  struct stat st {};
  if (::stat(in_path.c_str(), &st) != 0) {
    throw std::runtime_error("replay input '" + in_path + "': " + std::strerror(errno));
  }
  if (!S_ISREG(st.st_mode)) {
    throw std::runtime_error("replay input '" + in_path + "' is not a regular file");
  }
  in_fd_ = ::open(in_path.c_str(), O_RDONLY | O_CLOEXEC);
  if (in_fd_ < 0) {
    throw std::runtime_error("replay input '" + in_path +
                             "': cannot open: " + std::strerror(errno));
  }
  try {
    out_ = std::make_unique<AtomicLogFile>(out_path, "replay output");
  } catch (...) {
    ::close(in_fd_);
    throw;
  }
}

// The output's temporary file goes with out_ unless Commit() ran.
LogReplayBus::~LogReplayBus() {
  read_ahead_.reset();  // before the descriptor it reads
  ::close(in_fd_);
}

const uint8_t* LogReplayBus::InputBytes(int64_t at, int64_t n) {
  if (at < 0 || n < 0 || at + n > in_bytes_) return nullptr;
  const int64_t chunk_end = chunk_at_ + chunk_bytes_;
  if (at >= chunk_at_ && at + n <= chunk_end) return chunk_.data() + chunk_base_ + (at - chunk_at_);
  if (!read_ahead_) read_ahead_ = std::make_unique<ReadAhead>(in_fd_, tap_.get());
  // Reading is sequential: the next chunk was asked for at this one's end. The last bytes of
  // this one go in front of it, where the event that straddles the two begins.
  const int64_t keep = std::min(kHeadroomBytes, chunk_bytes_);
  const int64_t ahead = std::min(kChunkBytes, in_bytes_ - chunk_end);  // what was asked for
  if (chunk_bytes_ > 0 && read_ahead_->pending_offset() == chunk_end && at >= chunk_end - keep &&
      at + n <= chunk_end + ahead) {
    const uint8_t* from = chunk_.data() + chunk_base_ + (chunk_bytes_ - keep);
    tail_.assign(from, from + keep);
    const int64_t got = read_ahead_->Take(&chunk_);  // the old chunk is the reader's spare now
    const size_t base = static_cast<size_t>(kHeadroomBytes - keep);
    if (keep > 0) std::memcpy(chunk_.data() + base, tail_.data(), static_cast<size_t>(keep));
    chunk_base_ = base;
    chunk_at_ = chunk_end - keep;
    chunk_bytes_ = keep + got;
  } else {
    read_ahead_->Drop();
    // Refill from `at` (a jump, or an event longer than what is read ahead).
    const int64_t want = std::min(std::max(n, kChunkBytes), in_bytes_ - at);
    if (static_cast<int64_t>(chunk_.size()) < want) chunk_.resize(static_cast<size_t>(want));
    chunk_base_ = 0;
    chunk_at_ = at;
    chunk_bytes_ = PreadFully(in_fd_, chunk_.data(), want, at);
    if (tap_) tap_->Add(at, chunk_.data(), chunk_bytes_);
  }
  const int64_t next = chunk_at_ + chunk_bytes_;
  if (next < in_bytes_) read_ahead_->Request(next, std::min(kChunkBytes, in_bytes_ - next));
  if (at < chunk_at_ || at + n > chunk_at_ + chunk_bytes_) return nullptr;  // short: see above
  return chunk_.data() + chunk_base_ + (at - chunk_at_);
}

int64_t LogReplayBus::FindSyncWord(int64_t from) {
  for (int64_t at = from; at + 4 <= in_bytes_;) {
    const uint8_t* p = InputBytes(at, 4);
    if (p == nullptr) return -1;
    const int64_t span = chunk_at_ + chunk_bytes_ - at;  // whatever the chunk holds from `at`
    for (int64_t i = 0; i + 4 <= span; ++i) {
      if (p[i] == 0xED && Be32(p + i) == kSyncWord) return at + i;
    }
    at += span - 3;
  }
  return -1;
}

LogReplayBus::KnownChannel* LogReplayBus::FindChannel(const char* channel, size_t size) {
  auto is = [&](const KnownChannel& c) {
    return c.name.size() == size && std::memcmp(c.name.data(), channel, size) == 0;
  };
  KnownChannel* found = nullptr;
  uint8_t& slot = channel_slots_[ChannelSlot(channel, size)];
  if (slot > 0 && is(known_channels_[slot - 1])) {
    found = &known_channels_[slot - 1];
  } else {
    for (KnownChannel& c : known_channels_) {
      if (is(c)) {
        found = &c;
        break;
      }
    }
  }
  if (found == nullptr) {
    if (known_channels_.size() >= kMaxKnownChannels) return nullptr;
    found = &known_channels_.emplace_back();
    found->name.assign(channel, size);
    found->handlers = &HandlersFor(found->name);
    found->generation = subscription_generation();
  }
  static_assert(kMaxKnownChannels < 256, "slots hold an index + 1 in a byte");
  slot = static_cast<uint8_t>(found - known_channels_.data() + 1);
  if (found->generation != subscription_generation()) {  // a handler subscribed since
    found->handlers = &HandlersFor(found->name);
    found->generation = subscription_generation();
  }
  return found;
}

void LogReplayBus::TransportSubscribe(size_t /*subscription*/, const std::string& /*channel*/) {}

void LogReplayBus::TransportPublish(const std::string& channel, const void* data, int size) {
  out_->Write(now_utime_, channel, data, size);
}

void LogReplayBus::Run(const std::function<void()>& tick, int64_t tick_us) {
  StartReading();
  for (int64_t pos = 0;;) {
    if (ShutdownRequested()) {
      stats_.log().warn("replay interrupted after {} events; output not written", events_read_);
      return;
    }
    SkipIfAt(&pos);
    Event event;
    const Read read = ReadEvent(&pos, &event);
    if (read == Read::kEnd) break;
    if (read == Read::kDamaged) continue;
    TickBefore(event.timestamp, tick, tick_us);
    Deliver(event);
  }
  ReportDamage(in_bytes_);
  if (events_read_ == 0 && in_bytes_ > 0) {
    stats_.Error("replay input", in_path_ + ": no LCM log events in " + std::to_string(in_bytes_) +
                                     " bytes (not an LCM log?)");
  }
  finished_ = true;
}

void LogReplayBus::StartReading() {
  struct stat st {};
  if (::fstat(in_fd_, &st) != 0) {
    throw std::runtime_error("replay input '" + in_path_ + "': " + std::strerror(errno));
  }
  in_bytes_ = st.st_size;
  chunk_bytes_ = 0;
  damage_from_ = -1;
  ticking_ = false;
  next_tick_ = 0;
}

void LogReplayBus::SkipIfAt(int64_t* pos) {
  if (!skip_ || *pos < skip_->from) return;
  Skip skip = std::move(*skip_);
  skip_.reset();
  // Only at the event it names, forward, and inside what the file had when Run() began.
  if (*pos == skip.from && skip.to > *pos && skip.to <= in_bytes_ && skip.at_from()) {
    skipped_bytes_ += skip.to - *pos;
    *pos = skip.to;
    ticking_ = false;  // no periodic work for the skipped time: one tick, at the next event
  }
}

// The rules of LCM's reader (lcm_eventlog_read_next_event), kept so a log reads as it always
// did: an event starts at a sync word, and is followed by another sync word or by fewer than
// four bytes before the end. LCM's reader skips to the next sync word without saying so and
// allocates whatever length a damaged header claims; here each header's lengths are checked
// against the file first, and every byte not returned as an event is reported (as the span it
// covers) instead of silently lost.
LogReplayBus::Read LogReplayBus::ReadEvent(int64_t* pos, Event* event) {
  const int64_t sync = FindSyncWord(*pos);
  if (sync < 0) {
    if (*pos < in_bytes_) NoteDamage(*pos);
    return Read::kEnd;
  }
  if (sync > *pos) NoteDamage(*pos);
  const uint8_t* header = InputBytes(sync, kHeaderBytes);
  const int64_t channel_bytes = header ? static_cast<int32_t>(Be32(header + 20)) : -1;
  const int64_t data_bytes = header ? static_cast<int32_t>(Be32(header + 24)) : -1;
  const int64_t end = sync + kHeaderBytes + channel_bytes + data_bytes;
  bool good = header != nullptr && channel_bytes > 0 && data_bytes >= 0 && end <= in_bytes_;
  if (good && in_bytes_ - end >= 4) {
    const uint8_t* next = InputBytes(end, 4);
    good = next != nullptr && Be32(next) == kSyncWord;
  }
  const uint8_t* bytes = good ? InputBytes(sync, end - sync) : nullptr;
  if (bytes == nullptr) {
    NoteDamage(sync);
    *pos = sync + 1;
    return Read::kDamaged;
  }
  ReportDamage(sync);
  *pos = end;
  ++events_read_;
  event->offset = sync;
  event->end = end;
  event->timestamp = static_cast<int64_t>(Be64(bytes + 12));
  event->channel = reinterpret_cast<const char*>(bytes + kHeaderBytes);
  event->channel_bytes = static_cast<size_t>(channel_bytes);
  event->data = bytes + kHeaderBytes + channel_bytes;
  event->data_bytes = static_cast<int>(data_bytes);
  return Read::kEvent;
}

void LogReplayBus::NoteDamage(int64_t at) {
  if (damage_from_ < 0) damage_from_ = at;
}

void LogReplayBus::ReportDamage(int64_t to) {
  if (damage_from_ < 0) return;
  stats_.Error("replay input damaged", in_path_ + ": skipped " + std::to_string(to - damage_from_) +
                                           " unreadable bytes at offset " +
                                           std::to_string(damage_from_));
  damage_from_ = -1;
}

// Periodic work on the log's clock, as it would have run live between these events; the first
// tick is at the first event, as a live loop's is at its start. Only on a plausible clock: a
// damaged or forged event's timestamp near the int64 limits overflowed the arithmetic below
// (found by logreader_fuzz); such an event is delivered but runs no periodic work. [0, 2^62) us
// is the epoch to the year 148 000.
void LogReplayBus::TickBefore(int64_t timestamp, const std::function<void()>& tick,
                              int64_t tick_us) {
  constexpr int64_t kMaxPlausibleUtime = int64_t{1} << 62;
  if (timestamp < 0 || timestamp >= kMaxPlausibleUtime) return;
  if (!ticking_) {
    ticking_ = true;
    next_tick_ = timestamp;
  } else if (timestamp - next_tick_ > 1000 * tick_us) {
    next_tick_ = timestamp - (timestamp - next_tick_) % tick_us;  // a long gap
  }
  while (timestamp >= next_tick_) {
    now_utime_ = next_tick_;
    Guarded("periodic work", tick);
    next_tick_ += tick_us;
  }
}

// In subscription order, as a regex match per subscription would give; a handler that
// subscribes (the cached list goes stale) sees its new subscription from this event on. (After
// the ticks: periodic work may subscribe.)
void LogReplayBus::Deliver(const Event& event) {
  now_utime_ = event.timestamp;
  const KnownChannel* known = FindChannel(event.channel, event.channel_bytes);
  if (known == nullptr) channel_.assign(event.channel, event.channel_bytes);
  const std::string& channel = known != nullptr ? known->name : channel_;
  const int channel_id = known != nullptr ? static_cast<int>(known - known_channels_.data()) : -1;
  const std::vector<size_t>* handlers = known != nullptr ? known->handlers : &HandlersFor(channel);
  for (size_t j = 0; j < handlers->size(); ++j) {
    const size_t i = (*handlers)[j];
    const uint64_t generation = subscription_generation();
    Dispatch(i, channel, event.timestamp, event.data, event.data_bytes, channel_id, event.offset,
             event.end);
    if (subscription_generation() != generation) {
      handlers = &HandlersFor(channel);
      j = static_cast<size_t>(std::upper_bound(handlers->begin(), handlers->end(), i) -
                              handlers->begin()) -
          1;
    }
  }
}

void LogReplayBus::Commit() { out_->Commit(); }

void LogReplayBus::TapOutput(std::function<void(const char* data, size_t size)> tap) {
  out_->SetTap(std::move(tap));
}

const struct stat& LogReplayBus::output_stat() const { return out_->committed_stat(); }

void LogReplayBus::ConsumeInput(std::function<void(const uint8_t* data, size_t size)> consume) {
  tap_ = std::make_unique<InputTap>();
  tap_->consume = std::move(consume);
}

bool LogReplayBus::SkipAt(int64_t from, int64_t to, std::function<bool()> at_from) {
  if (tap_ || from < 0 || to <= from || !at_from) return false;
  skip_ = Skip{from, to, std::move(at_from)};
  return true;
}

bool LogReplayBus::InputConsumedWhole() {
  if (!tap_ || !finished_) return false;
  if (read_ahead_) read_ahead_->Drop();  // a read still on its way hands over its bytes first
  return tap_->upto == in_bytes_;
}

}  // namespace ftcal
