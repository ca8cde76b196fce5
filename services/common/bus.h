// One handler code, two transports.
//
// A process registers handlers for channels and publishes through a Bus. Two transports
// implement it, as Drake puts DrakeLcm and DrakeLcmLog behind DrakeLcmInterface: LcmBus
// (common/lcm_bus.h) runs the handlers live on LCM; LogReplayBus (common/log_replay_bus.h)
// feeds them the events of a recorded log in log order, at full speed, and writes every
// publication to an output log stamped with the time of the input event that caused it. A
// replayed result therefore equals the live one, and a test can drive a stage without a
// network. This file is what both share: the subscriptions, the typed publish and subscribe,
// and the decoding behind the wire guard.
//
// Handlers never let an exception escape into LCM's C callback: the Bus catches it and counts
// it (BadInput as a drop, anything else as an error), logging once per kind. Typed
// subscriptions decode the bytes themselves instead of using LCM 1.3.1's typed subscribe, which
// drops a message whose fingerprint does not match with only a line on stderr and whose decoder
// trusts length fields: here the bytes pass the wire guard (common/wire_guard.h) first, and a
// message that does not pass or does not decode is counted as a drop.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <regex>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include "common/envelope.h"
#include "common/service_stats.h"
#include "common/wire_guard.h"

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
