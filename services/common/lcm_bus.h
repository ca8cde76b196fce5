// The live bus: LCM, one instance per URL of the config's channel routes (common/bus.h says
// what every bus does).
#pragma once

#include <poll.h>

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include <lcm/lcm-cpp.hpp>

#include "common/bus.h"
#include "proto/config.pb.h"

namespace ftcal {

// Live LCM. The loop wakes at least every 100 ms (handleTimeout) to check the shutdown flag and
// run the tick, so a quiet bus never delays shutdown.
class LcmBus : public Bus {
 public:
  // Messages LCM may hold per subscription before it drops (lcm_bus.cc says why not LCM's 30).
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

}  // namespace ftcal
