// The replay bus: a recorded LCM log in, read at full speed with a read-ahead thread, its
// events handed to the handlers in log order; a log out (common/bus.h says what every bus
// does).
#pragma once

#include <sys/stat.h>

#include <array>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/atomic_log.h"
#include "common/bus.h"

namespace ftcal {

// The channels of the first events of the LCM log at `path` (at most `max_events`, read from
// its first `max_bytes`), in order; empty when the file cannot be read. Reading stops at the
// first bytes that are not a whole event (a damaged header's lengths are never trusted), so
// this tells what a log holds, cheaply, and decides nothing about its integrity.
std::vector<std::string> LogChannelsAtStart(const std::string& path, int max_events,
                                            int64_t max_bytes = 1 << 20);

// A recorded log in, a log out. The output is written to a temporary file beside `out_path`
// and renamed onto it by Commit() (after fsync), so a failed or interrupted replay never leaves
// a partial log under the final name.
class LogReplayBus : public Bus {
 public:
  // Throws std::runtime_error naming the file when the input cannot be opened or the output
  // cannot be created.
  LogReplayBus(const std::string& in_path, const std::string& out_path, ServiceStats& stats);
  ~LogReplayBus() override;
  int64_t NowUtime() const override { return now_utime_; }
  // Feeds every event in log order; ticks on the log's clock at the first event and then every
  // `tick_us`, before the first event at or after each tick time (stamped with that time).
  // Unreadable bytes in the input (a damaged event) are skipped and counted as an error.
  // Stops early, leaving the output uncommitted, when shutdown is requested.
  void Run(const std::function<void()>& tick, int64_t tick_us) override;
  bool IsReplay() const override { return true; }
  // Makes the output visible under its final name. Throws std::runtime_error on I/O failure.
  void Commit();
  // Gives `tap` every byte of the output as it is written (AtomicLogFile::SetTap); before Run().
  void TapOutput(std::function<void(const char* data, size_t size)> tap);
  // The output's status after Commit() (AtomicLogFile::committed_stat()).
  const struct stat& output_stat() const;
  // True when Run() read the whole input.
  bool finished() const { return finished_; }
  // Hands `consume` every byte of the input, in order from the first, each once, as Run()
  // reads it: a caller that wants a digest of the log as well as its events (the calibrator's
  // provenance hash) reads the file once. It runs on the read-ahead thread, so it must touch
  // nothing the handlers do; an exception from it ends the consuming, not the replay. Call
  // before Run().
  void ConsumeInput(std::function<void(const uint8_t* data, size_t size)> consume);
  // True when `consume` has had the whole input, from its first byte to the size it had when
  // Run() began (Run() finished, nothing skipped, no exception), and is not running any more.
  bool InputConsumedWhole();
  int64_t events_read() const { return events_read_; }
  // When reading reaches the event at input offset `from` (MessageInfo::log_offset), calls
  // `at_from` and, when it returns true, reads on at offset `to` (> from), the events between
  // unread. One skip at a time; a new one replaces it. The caller vouches that those events
  // would have changed nothing it cannot account for (the calibrator's span index). False when
  // the bus cannot skip: while the whole input must be read (ConsumeInput).
  bool SkipAt(int64_t from, int64_t to, std::function<bool()> at_from);
  // Bytes of the input not read because of SkipAt().
  int64_t skipped_bytes() const { return skipped_bytes_; }

 protected:
  void TransportSubscribe(size_t subscription, const std::string& channel) override;
  void TransportPublish(const std::string& channel, const void* data, int size) override;

 private:
  // The input, read in large chunks by pread(): LCM's reader allocates every event twice and
  // the old sync-word checks cost two lseek()s per event. A chunk holds whole events; one
  // larger than kChunkBytes grows it.
  // Makes bytes [at, at + n) of the input contiguous in chunk_; nullptr when they are not all
  // there (past the size the file had at the start, or a read error).
  const uint8_t* InputBytes(int64_t at, int64_t n);
  // Offset of the next sync word of LCM's log format at or after `from`, or -1.
  int64_t FindSyncWord(int64_t from);

  // Run()'s steps, in the order it takes them for each event.
  // One event of the input, its bytes in chunk_ (valid until the next read).
  struct Event {
    int64_t offset, end;  // [offset, end) in the input
    int64_t timestamp;    // us, as logged
    const char* channel;
    size_t channel_bytes;
    const uint8_t* data;
    int data_bytes;
  };
  enum class Read { kEvent, kDamaged, kEnd };
  // Readies the input for a reading from its first byte (its size now is where it ends).
  void StartReading();
  // The armed skip (SkipAt) when reading has reached its offset: moves *pos to its end when it
  // is at that event and its caller agrees.
  void SkipIfAt(int64_t* pos);
  // The next event from *pos under the rules of LCM's reader, *pos moved past it: kEvent, or
  // kDamaged when the bytes at the next sync word are not one (*pos moved one past it), or
  // kEnd. Unreadable bytes are noted and reported (NoteDamage, ReportDamage).
  Read ReadEvent(int64_t* pos, Event* event);
  void NoteDamage(int64_t at);
  void ReportDamage(int64_t to);
  // The periodic work due on the log's clock before an event stamped `timestamp`.
  void TickBefore(int64_t timestamp, const std::function<void()>& tick, int64_t tick_us);
  // The event to its channel's handlers, in subscription order.
  void Deliver(const Event& event);

  std::string in_path_;
  int in_fd_ = -1;
  int64_t in_bytes_ = 0;  // the input's size when opened
  std::vector<uint8_t> chunk_;
  size_t chunk_base_ = 0;    // index in chunk_ of the byte at chunk_at_
  int64_t chunk_at_ = 0;     // input offset of chunk_[chunk_base_]
  int64_t chunk_bytes_ = 0;  // valid bytes from there
  // The next chunk, read on a thread of its own while this one is handled (ReadAhead in
  // log_replay_bus.cc): the copy out of the page cache was a seventh of a replay's main thread.
  class ReadAhead;
  // ConsumeInput()'s consumer and how far it has had the input; used by the thread that
  // reads, which the read-ahead's hand-over orders.
  struct InputTap;
  std::unique_ptr<InputTap> tap_;
  std::unique_ptr<ReadAhead> read_ahead_;
  std::vector<uint8_t> tail_;  // the straddling event's bytes on their way to the next chunk
  struct Skip {
    int64_t from, to;
    std::function<bool()> at_from;
  };
  std::optional<Skip> skip_;
  int64_t skipped_bytes_ = 0;
  int64_t damage_from_ = -1;  // the first unreadable byte not yet reported; -1: none
  bool ticking_ = false;      // the log's clock is known (a first plausible timestamp)
  int64_t next_tick_ = 0;
  // The channels seen so far with their handlers, found through a small table indexed by a
  // cheap hash of the name (its length and last two bytes, where FT_HL .. FT_FR differ): an
  // event's channel costs one compare instead of a copy into a string and a hash lookup,
  // whatever order the channels come in (six transducers' records arrive in any order within
  // a frame, which defeated guessing the next channel). At most kMaxKnownChannels; channels
  // beyond them take that slower path.
  struct KnownChannel {
    std::string name;
    const std::vector<size_t>* handlers = nullptr;  // HandlersFor(name) at `generation`
    uint64_t generation = 0;
  };
  static constexpr size_t kMaxKnownChannels = 64;
  static constexpr size_t kChannelSlots = 256;
  static size_t ChannelSlot(const char* channel, size_t size) {
    const auto last = static_cast<unsigned char>(channel[size - 1]);
    const auto before = size > 1 ? static_cast<unsigned char>(channel[size - 2]) : 0u;
    return (size * 131 + last * 31 + before) % kChannelSlots;
  }
  // The entry of `channel` (size > 0; its handlers current), or nullptr when it is not one and
  // the table is full.
  KnownChannel* FindChannel(const char* channel, size_t size);
  // known_channels_ index + 1 of the channel last found in each slot; 0: none.
  std::array<uint8_t, kChannelSlots> channel_slots_{};
  std::vector<KnownChannel> known_channels_;
  std::string channel_;  // the current event's channel when not a known one (reused)
  std::unique_ptr<AtomicLogFile> out_;
  int64_t now_utime_ = 0;
  int64_t events_read_ = 0;
  bool finished_ = false;
};

}  // namespace ftcal
