#include "common/bus.h"

#include <algorithm>

#include "common/user_errors.h"

namespace ftcal {

void Bus::SubscribeRaw(const std::string& channel, RawHandler handler) {
  std::regex pattern;
  try {
    pattern = std::regex(channel, std::regex::extended);
  } catch (const std::regex_error& e) {
    throw std::invalid_argument("channel pattern '" + channel +
                                "' is not a valid regular "
                                "expression: " +
                                e.what());
  }
  subscriptions_.push_back({channel, std::move(pattern), std::move(handler), 0, {}, {}});
  handlers_by_channel_.clear();
  ++subscription_generation_;
  TransportSubscribe(subscriptions_.size() - 1, channel);
}

const std::vector<size_t>& Bus::HandlersFor(const std::string& channel) {
  const auto found = handlers_by_channel_.find(channel);
  if (found != handlers_by_channel_.end()) return found->second;
  std::vector<size_t>& list = handlers_by_channel_[channel];
  for (size_t i = 0; i < subscriptions_.size(); ++i) {
    if (std::regex_match(channel, subscriptions_[i].pattern)) list.push_back(i);
  }
  return list;
}

void Bus::ShedLate(const std::string& channel, int64_t max_queue_us) {
  for (Subscription& sub : subscriptions_) {
    if (sub.channel != channel) continue;
    sub.max_queue_us = std::max<int64_t>(0, max_queue_us);
    sub.late_kind = "late " + channel;
    sub.late_reason = "waited over " + std::to_string(max_queue_us / 1000) +
                      " ms in the receive queue: this process is not keeping up with " + channel;
  }
}

bool Bus::ShedIfLate(size_t subscription, int64_t recv_utime, int64_t now_utime) {
  const Subscription& sub = subscriptions_[subscription];
  if (sub.max_queue_us <= 0 || now_utime - recv_utime <= sub.max_queue_us) return false;
  stats_.CountIn();
  stats_.Drop(sub.late_kind, sub.late_reason);
  return true;
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
    stats_.Error(what, UserText(e, what));
  } catch (...) {
    stats_.Error(what, "unknown exception");
  }
}

void Bus::Dispatch(size_t subscription, const std::string& channel, int64_t recv_utime,
                   const void* data, int size, int channel_id, int64_t log_offset,
                   int64_t log_end) {
  stats_.CountIn();
  const Subscription& sub = subscriptions_.at(subscription);
  const MessageInfo info{channel, recv_utime, nullptr, channel_id, log_offset, log_end};
  // Guarded()'s handling inline: its name argument would cost a string per event.
  try {
    sub.handler(info, data, size);
  } catch (const BadInput& e) {
    stats_.Drop(e.kind(), e.what());
  } catch (const std::exception& e) {
    stats_.Error("handler for " + sub.channel, UserText(e, "handling a message on " + channel));
  } catch (...) {
    stats_.Error("handler for " + sub.channel, "unknown exception");
  }
}

}  // namespace ftcal
