// One handler code, two transports.
//
// A process registers handlers for channels and publishes through a Bus. LcmBus runs them live
// on LCM; LogReplayBus feeds them the events of a recorded log in log order, at full speed, and
// writes every publication to an output log stamped with the time of the input event that
// caused it. A replayed result therefore equals the live one, and a test can drive a stage
// without a network.
//
// Handlers never let an exception escape into LCM's C callback: the Bus catches it and counts
// it (BadInput as a drop, anything else as an error), logging once per kind. Typed
// subscriptions decode the bytes themselves instead of using LCM 1.3.1's typed subscribe, which
// drops a message whose fingerprint does not match with only a line on stderr and whose decoder
// trusts length fields: here the bytes pass the wire guard (common/wire_guard.h) first, and a
// message that does not pass or does not decode is counted as a drop.
#pragma once

#include <poll.h>
#include <sys/stat.h>

#include <array>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <optional>
#include <memory>
#include <regex>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "common/atomic_log.h"
#include "common/envelope.h"
#include "common/service_stats.h"
#include "common/wire_guard.h"
#include "proto/config.pb.h"

namespace ftcal {

// Where an input came from.
struct MessageInfo {
  const std::string& channel;
  // Live: this host's receive time; replay: the logged event's timestamp. us since the epoch.
  int64_t recv_utime;
  // On a signed channel (Bus::SubscribeSigned), the name of the trusted key whose signature
  // verified; null for an unsigned message (and on other channels).
  const std::string* signer = nullptr;
  // Replay: a small number naming `channel` for the life of the bus (0, 1, ... in the order
  // first read), so a handler on many channels tells them apart without comparing names;
  // -1 live and for channels past the replay's table of known ones.
  int channel_id = -1;
  // Replay: the event's bytes in the input log, [log_offset, log_end); -1 live.
  int64_t log_offset = -1;
  int64_t log_end = -1;
};

// Thrown by a handler that refuses an input (a NaN, an unknown leg, a message from the
// future): counted as a drop under `kind`, logged once per kind with `what()` as the reason.
class BadInput : public std::runtime_error {
 public:
  BadInput(std::string kind, const std::string& reason)
      : std::runtime_error(reason), kind_(std::move(kind)) {}
  const std::string& kind() const { return kind_; }

 private:
  std::string kind_;
};

class Bus {
 public:
  using RawHandler = std::function<void(const MessageInfo& info, const void* data, int size)>;
  template <class Msg>
  using Handler = std::function<void(const MessageInfo& info, const Msg& msg)>;

  explicit Bus(ServiceStats& stats) : stats_(stats) {}
  virtual ~Bus() = default;
  Bus(const Bus&) = delete;
  Bus& operator=(const Bus&) = delete;

  // `channel` is a regular expression matched against the whole channel name (LCM's rule).
  void SubscribeRaw(const std::string& channel, RawHandler handler);
  // Decodes to Msg after the wire guard's checks; a message refused by them or by the decoder
  // (wrong type, a length field past its cap or the bytes, truncated, trailing bytes) is counted
  // as a drop under "undecodable <type> on <channel>: <kind>".
  template <class Msg>
  void Subscribe(const std::string& channel, Handler<Msg> handler);

  // A signed channel (common/envelope.h): the envelope is checked by `verifier` before the
  // inner Msg is decoded (through the wire guard as in Subscribe). `window_us` > 0 refuses
  // envelopes signed further than that from the receive time (live: this host's clock; replay:
  // the logged receive time). With `allow_unsigned`, a bare Msg is accepted too and counted
  // as `unsigned_accepted`. Refusals are drops of kind "<refusal> on <channel>", the refusal
  // naming the sender, so each sender's first one is logged. `verifier` must outlive the bus.
  template <class Msg>
  void SubscribeSigned(const std::string& channel, auth::Verifier* verifier, int64_t window_us,
                       bool allow_unsigned, Handler<Msg> handler);

  // Live only: a message on a subscription whose pattern is exactly `channel` that waited
  // longer than `max_queue_us` between its arrival (LCM's receive stamp) and its handler is
  // dropped undecoded, counted as a drop of kind "late <channel>" (logged as drops are). For a
  // consumer whose output is only worth anything fresh: when it cannot keep up, it sheds the
  // backlog instead of working through seconds of old input. Replay never sheds.
  void ShedLate(const std::string& channel, int64_t max_queue_us);

  // `count` false leaves msgs_out alone (the heartbeat does not count itself).
  void PublishRaw(const std::string& channel, const void* data, int size, bool count = true);
  template <class Msg>
  void Publish(const std::string& channel, const Msg& msg, bool count = true);
  // The same, encoding into `buffer` (grown as needed, never shrunk) instead of the bus's
  // buffer, which is per thread: for a stage that publishes from its hot path and keeps its
  // own (the corrector).
  template <class Msg>
  void Publish(const std::string& channel, const Msg& msg, std::vector<uint8_t>& buffer,
               bool count = true);
  // Msg in an envelope signed by `signer` at NowUtime().
  template <class Msg>
  void PublishSigned(const std::string& channel, const Msg& msg, auth::Signer& signer);

  // Now on the bus's clock (us since the epoch): the wall clock live, the current input
  // event's timestamp on replay. Stamp outputs with this, not with the wall clock.
  virtual int64_t NowUtime() const = 0;
  // Runs until shutdown is requested (live) or the input ends (replay). `tick` runs at least
  // every `tick_us` of bus time (live: also when the bus is quiet).
  virtual void Run(const std::function<void()>& tick, int64_t tick_us) = 0;
  virtual bool IsReplay() const = 0;
  // Live: once a message has come, wait `us` for more to gather before handling them all, so
  // the loop wakes once a batch, not once a message (a recorder, which needs no low latency:
  // each wake-up is a context switch, and they were most of ftcal-record's CPU at 6 x 7 kHz).
  // 0 (the default): every message at once. Replay ignores it.
  virtual void SetGatherUs(int64_t /*us*/) {}
  // For a process that runs its own loop (a bridge paced by its device): the descriptors that
  // are readable when a message waits (none on replay; one per transport route subscribed to),
  // and HandleOnce() to handle what waits.
  virtual const std::vector<int>& Filenos() {
    static const std::vector<int> none;
    return none;
  }
  bool HasSubscriptions() const { return !subscriptions_.empty(); }
  // Handles at most one message per route, waiting up to `timeout_ms` for the first; returns
  // >0 handled, 0 timeout, <0 error (-1 on replay).
  virtual int HandleOnce(int /*timeout_ms*/) { return -1; }
  // Replay: when reading reaches the event at input offset `from` (MessageInfo::log_offset),
  // calls `at_from` and, when it returns true, reads on at offset `to` (> from), the events
  // between unread. One skip at a time; a new one replaces it. The caller vouches that those
  // events would have changed nothing it cannot account for (the calibrator's span index). False
  // when the bus cannot skip: live, or while the whole input must be read (ConsumeInput).
  virtual bool SkipAt(int64_t /*from*/, int64_t /*to*/, std::function<bool()> /*at_from*/) {
    return false;
  }

  ServiceStats& stats() { return stats_; }

  // A live process's marks of what it accepted on signed channels (common/seen_store.h), set by
  // ServiceApp; SubscribeSigned hands it to each verifier that persists. Null on replay and in
  // tests that make their own bus: an offline reader judges a recording afresh each time.
  void SetSeenStore(std::shared_ptr<auth::SeenStore> store) { seen_store_ = std::move(store); }
  const std::shared_ptr<auth::SeenStore>& seen_store() const { return seen_store_; }

 protected:
  // The transports call this for every message a subscription receives.
  void Dispatch(size_t subscription, const std::string& channel, int64_t recv_utime,
                const void* data, int size, int channel_id = -1, int64_t log_offset = -1,
                int64_t log_end = -1);
  // Runs `fn`, counting any exception it throws under `what` instead of propagating it.
  void Guarded(const std::string& what, const std::function<void()>& fn);
  // The subscriptions whose pattern matches `channel`, in subscription order. Cached per
  // channel name (a regex match per subscription per event was most of a replay's time); the
  // cache is dropped by every SubscribeRaw(), which also bumps subscription_generation_ so a
  // caller holding the returned list while calling handlers can tell it went stale.
  const std::vector<size_t>& HandlersFor(const std::string& channel);
  uint64_t subscription_generation() const { return subscription_generation_; }
  virtual void TransportSubscribe(size_t subscription, const std::string& channel) = 0;
  virtual void TransportPublish(const std::string& channel, const void* data, int size) = 0;

  struct Subscription {
    std::string channel;
    std::regex pattern;
    RawHandler handler;
    int64_t max_queue_us = 0;  // ShedLate(); 0: never shed
    std::string late_kind;     // built once: shedding must cost less than handling
    std::string late_reason;
  };
  // True (and the message counted as shed) when a live message waited too long (ShedLate).
  bool ShedIfLate(size_t subscription, int64_t recv_utime, int64_t now_utime);
  std::vector<Subscription> subscriptions_;
  std::shared_ptr<auth::SeenStore> seen_store_;
  ServiceStats& stats_;

 private:
  std::unordered_map<std::string, std::vector<size_t>> handlers_by_channel_;
  uint64_t subscription_generation_ = 0;
};

// Live LCM. The loop wakes at least every 100 ms (handleTimeout) to check the shutdown flag and
// run the tick, so a quiet bus never delays shutdown.
class LcmBus : public Bus {
 public:
  // Messages LCM may hold per subscription before it drops (bus.cc says why not LCM's 30).
  static constexpr int kSubscriptionQueueCapacity = 10000;

  // A channel route (config lcm_route): the channels a pattern matches whole go by `url`.
  struct Route {
    std::string channels;
    std::string url;
  };
  // Throws std::runtime_error naming the URL when LCM cannot open it, or a route's pattern
  // when it is not a regular expression.
  LcmBus(const std::string& url, ServiceStats& stats, const std::vector<Route>& routes = {});
  ~LcmBus() override;
  int64_t NowUtime() const override;
  void Run(const std::function<void()>& tick, int64_t tick_us) override;
  bool IsReplay() const override { return false; }
  const std::vector<int>& Filenos() override { return fds_; }
  int HandleOnce(int timeout_ms) override;
  void SetGatherUs(int64_t us) override { gather_us_ = us; }
  // The URL a channel is published on.
  const std::string& UrlOf(const std::string& channel);

 protected:
  void TransportSubscribe(size_t subscription, const std::string& channel) override;
  void TransportPublish(const std::string& channel, const void* data, int size) override;

 private:
  // LCM 1.3.1 takes member-function pointers, not closures: one small object per subscription.
  struct Trampoline {
    LcmBus* bus;
    size_t subscription;
    void OnMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel);
  };
  // One LCM instance per URL: [0] is lcm_url's, then the routes' in config order. An instance
  // opens its receive socket (joins its group and port) only when subscribed to.
  struct Transport;
  size_t TransportOf(const std::string& channel);
  std::vector<std::unique_ptr<Transport>> transports_;
  std::unordered_map<std::string, size_t> transport_of_;  // channel -> index, as published
  // The transports subscribed to, and their descriptors: kept as they are subscribed, so that
  // waiting for a message allocates nothing.
  std::vector<Transport*> listening_;
  std::vector<int> fds_;
  std::vector<pollfd> pollfds_;
  std::vector<std::unique_ptr<Trampoline>> trampolines_;
  int64_t gather_us_ = 0;
};

// The config's channel routes (lcm_route), for LcmBus.
std::vector<LcmBus::Route> RoutesOf(const config::Config& config);

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
  bool SkipAt(int64_t from, int64_t to, std::function<bool()> at_from) override;
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

  std::string in_path_;
  int in_fd_ = -1;
  int64_t in_bytes_ = 0;  // the input's size when opened
  std::vector<uint8_t> chunk_;
  size_t chunk_base_ = 0;    // index in chunk_ of the byte at chunk_at_
  int64_t chunk_at_ = 0;     // input offset of chunk_[chunk_base_]
  int64_t chunk_bytes_ = 0;  // valid bytes from there
  // The next chunk, read on a thread of its own while this one is handled (ReadAhead in
  // bus.cc): the copy out of the page cache was a seventh of a replay's main thread.
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

// ---- templates ----

// What a typed subscription does with a message's bytes (wire::Decode into *msg), for a raw
// handler that decodes some messages itself: a BadInput naming the type, channel and refusal.
template <class Msg>
void DecodeOrThrow(const MessageInfo& info, const void* data, int size, Msg* msg) {
  if (auto refused = wire::Decode(data, size, msg)) {
    throw BadInput(std::string("undecodable ") + Msg::getTypeName() + " on " + info.channel + ": " +
                       refused->kind,
                   refused->detail);
  }
}

template <class Msg>
void Bus::Subscribe(const std::string& channel, Handler<Msg> handler) {
  // One message object per subscription, decoded into again for every event: LCM's decoders
  // assign every field and reuse the strings' and vectors' storage, so a replay of millions of
  // messages does not allocate and free their strings and arrays each time. Handlers get it by
  // const reference for the call only (dispatch is never re-entrant for one subscription).
  auto scratch = std::make_shared<Msg>();
  SubscribeRaw(channel, [handler = std::move(handler), scratch](const MessageInfo& info,
                                                                const void* data, int size) {
    Msg& msg = *scratch;
    DecodeOrThrow(info, data, size, &msg);
    handler(info, msg);
  });
}

template <class Msg>
void Bus::SubscribeSigned(const std::string& channel, auth::Verifier* verifier, int64_t window_us,
                          bool allow_unsigned, Handler<Msg> handler) {
  if (seen_store_ && verifier->persist() && !verifier->store()) verifier->Persist(seen_store_);
  SubscribeRaw(channel, [this, verifier, window_us, allow_unsigned, handler = std::move(handler)](
                            const MessageInfo& info, const void* data, int size) {
    const auto fingerprint = static_cast<uint64_t>(Msg::getHash());
    auto [opened, refused] =
        verifier->Open(info.channel, data, size, fingerprint, info.recv_utime, window_us);
    Msg msg;
    if (refused && refused->kind == "unsigned" && allow_unsigned) {
      if (auto bad = wire::Decode(data, size, &msg)) {
        throw BadInput(std::string("undecodable ") + Msg::getTypeName() + " on " + info.channel +
                           ": " + bad->kind,
                       bad->detail);
      }
      ++stats_.Counter("unsigned_accepted");
      handler(info, msg);
      return;
    }
    if (refused) throw BadInput(refused->kind + " on " + info.channel, refused->detail);
    if (auto bad = wire::Decode(opened->payload, opened->size, &msg)) {
      throw BadInput(std::string("undecodable ") + Msg::getTypeName() + " on " + info.channel +
                         " from " + *opened->signer + ": " + bad->kind,
                     bad->detail);
    }
    handler(MessageInfo{info.channel, info.recv_utime, opened->signer, info.channel_id}, msg);
  });
}

template <class Msg>
void Bus::PublishSigned(const std::string& channel, const Msg& msg, auth::Signer& signer) {
  const signed_envelope_t envelope = signer.Seal(channel, msg, NowUtime());
  Publish(channel, envelope);
}

template <class Msg>
void Bus::Publish(const std::string& channel, const Msg& msg, std::vector<uint8_t>& buffer,
                  bool count) {
  const int size = msg.getEncodedSize();
  if (buffer.size() < static_cast<size_t>(size)) buffer.resize(static_cast<size_t>(size));
  if (msg.encode(buffer.data(), 0, size) != size) {
    stats_.Error(std::string("encode ") + Msg::getTypeName(), "message did not encode");
    return;
  }
  PublishRaw(channel, buffer.data(), size, count);
}

template <class Msg>
void Bus::Publish(const std::string& channel, const Msg& msg, bool count) {
  // Reused, never shrunk: a replay publishes millions of messages of the same few sizes, and
  // a fresh zero-filled vector per message was a tenth of the corrector's own work.
  thread_local std::vector<uint8_t> buffer;
  Publish(channel, msg, buffer, count);
}

}  // namespace ftcal
