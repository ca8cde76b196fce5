#include "common/lcm_bus.h"

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <optional>
#include <regex>
#include <thread>

#include "common/shutdown.h"

namespace ftcal {
namespace {

int64_t WallClockUtime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// A subscription pattern that is a plain channel name goes to the one transport that carries
// that channel; a regular expression may match channels of any of them.
bool IsPlainName(const std::string& pattern) {
  return pattern.find_first_of(".*+?()[]{}|^$\\") == std::string::npos;
}

}  // namespace

struct LcmBus::Transport {
  std::string url;
  std::optional<std::regex> channels;  // none: the default (lcm_url)
  lcm::LCM lcm;
  bool subscribed = false;
  Transport(const std::string& u, std::optional<std::regex> c)
      : url(u), channels(std::move(c)), lcm(u) {}
};

LcmBus::LcmBus(const std::string& url, ServiceStats& stats, const std::vector<Route>& routes)
    : Bus(stats) {
  auto open = [&](const std::string& u, std::optional<std::regex> channels) {
    transports_.push_back(std::make_unique<Transport>(u, std::move(channels)));
    if (!transports_.back()->lcm.good()) {
      throw std::runtime_error("cannot open LCM at '" + u +
                               "' (bad URL, or no multicast route: see scripts/netns-exec)");
    }
  };
  open(url, std::nullopt);
  for (const Route& r : routes) {
    std::optional<std::regex> re;
    try {
      re.emplace(r.channels);
    } catch (const std::regex_error& e) {
      throw std::runtime_error("lcm_route '" + r.channels +
                               "' is not a regular expression: " + e.what());
    }
    open(r.url, std::move(re));
  }
}

LcmBus::~LcmBus() = default;

int64_t LcmBus::NowUtime() const { return WallClockUtime(); }

size_t LcmBus::TransportOf(const std::string& channel) {
  const auto it = transport_of_.find(channel);
  if (it != transport_of_.end()) return it->second;
  size_t index = 0;
  for (size_t i = 1; i < transports_.size(); ++i) {
    if (std::regex_match(channel, *transports_[i]->channels)) {
      index = i;
      break;
    }
  }
  transport_of_.emplace(channel, index);
  return index;
}

const std::string& LcmBus::UrlOf(const std::string& channel) {
  return transports_[TransportOf(channel)]->url;
}

void LcmBus::Trampoline::OnMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
  if (bus->ShedIfLate(subscription, rbuf->recv_utime, WallClockUtime())) return;
  bus->Dispatch(subscription, channel, rbuf->recv_utime, rbuf->data,
                static_cast<int>(rbuf->data_size));
}

void LcmBus::TransportSubscribe(size_t subscription, const std::string& channel) {
  std::vector<size_t> where;
  if (IsPlainName(channel)) {
    where.push_back(TransportOf(channel));
  } else {
    for (size_t i = 0; i < transports_.size(); ++i) where.push_back(i);
  }
  trampolines_.push_back(std::make_unique<Trampoline>(Trampoline{this, subscription}));
  for (size_t i : where) {
    Transport& t = *transports_[i];
    lcm::Subscription* sub =
        t.lcm.subscribe(channel, &Trampoline::OnMessage, trampolines_.back().get());
    if (sub == nullptr) {
      throw std::runtime_error("LCM refused the subscription to '" + channel + "' on " + t.url);
    }
    // LCM queues at most 30 received messages per subscription by default and silently drops
    // the rest: a regex subscription over the six FT_<LEG> channels (2400 messages/s with a log
    // played at 4x) overflowed whenever the process was descheduled for ~12 ms, and the live
    // calibrator lost 1-6 % of each hanging series. Every stage outruns its input on average,
    // so a deep queue only absorbs stalls (~4 s of all six transducers at 600 Hz); LCM keeps
    // the messages beyond its ring buffer on the heap.
    sub->setQueueCapacity(kSubscriptionQueueCapacity);
    if (!t.subscribed) {
      // Subscribed now, so asking for the descriptor joins no group it would not anyway.
      t.subscribed = true;
      listening_.push_back(&t);
      fds_.push_back(t.lcm.getFileno());
      pollfds_.push_back({fds_.back(), POLLIN, 0});
    }
  }
}

void LcmBus::TransportPublish(const std::string& channel, const void* data, int size) {
  Transport& t = *transports_[TransportOf(channel)];
  if (t.lcm.publish(channel, data, static_cast<unsigned int>(size)) != 0) {
    throw std::runtime_error("LCM publish on " + channel + " (" + t.url + ") failed");
  }
}

int LcmBus::HandleOnce(int timeout_ms) {
  if (listening_.empty()) {
    std::this_thread::sleep_for(std::chrono::milliseconds(timeout_ms));
    return 0;
  }
  if (listening_.size() == 1) return listening_[0]->lcm.handleTimeout(timeout_ms);
  const int n = ::poll(pollfds_.data(), pollfds_.size(), timeout_ms);
  if (n <= 0) return n;
  int handled = 0;
  for (size_t i = 0; i < pollfds_.size(); ++i) {
    if ((pollfds_[i].revents & POLLIN) == 0) continue;
    const int r = listening_[i]->lcm.handleTimeout(0);
    if (r < 0) return r;
    handled += r;
  }
  return handled;
}

std::vector<LcmBus::Route> RoutesOf(const config::Config& config) {
  std::vector<LcmBus::Route> routes;
  for (const auto& r : config.lcm_route()) routes.push_back({r.channels(), r.url()});
  return routes;
}

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
    const int handled = HandleOnce(wait_ms);
    if (handled < 0 && !ShutdownRequested() && errno != EINTR) {
      stats_.Error("lcm", std::string("handleTimeout failed: ") + std::strerror(errno));
      // Don't spin on a persistent failure.
      std::this_thread::sleep_for(std::chrono::milliseconds(kMaxWaitMs));
    } else if (handled > 0 && gather_us_ > 0) {
      // LCM's receive thread queues what comes meanwhile (kSubscriptionQueueCapacity per
      // subscription); then all of it is handled without waiting.
      // Drained whatever the shutdown flag says: what was gathered was received, and a
      // recorder stopping must not drop it.
      std::this_thread::sleep_for(std::chrono::microseconds(gather_us_));
      while (HandleOnce(0) > 0) {
      }
    }
    const auto now = Clock::now();
    if (now >= next_tick) {
      Guarded("periodic work", tick);
      next_tick += period;
      if (next_tick <= now) next_tick = now + period;  // late: skip, don't burst
    }
  }
  if (gather_us_ > 0) {
    while (HandleOnce(0) > 0) {
    }
  }
}

}  // namespace ftcal
