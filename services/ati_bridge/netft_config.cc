#include "netft_config.h"

#include <httplib.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <mutex>
#include <thread>

#include <spdlog/fmt/fmt.h>

namespace ftcal {

void NetFtSettings::FromConfig(const std::string& leg, const config::AtiTransducer& ati) {
  const std::string& name = leg;
  if (ati.has_counts_per_force() != ati.has_counts_per_torque()) {
    throw AtiBridgeError("leg " + name +
                         ": give both counts_per_force and counts_per_torque, or neither");
  }
  if (ati.has_counts_per_force()) {
    if (!(ati.counts_per_force() > 0 && ati.counts_per_torque() > 0 &&
          std::isfinite(ati.counts_per_force()) && std::isfinite(ati.counts_per_torque()))) {
      throw AtiBridgeError("leg " + name + ": counts per unit must be positive and finite");
    }
    counts_from_config = true;
    calibrated = true;
    counts_per_force = ati.counts_per_force();
    counts_per_torque = ati.counts_per_torque();
  }
  if (ati.rated_range_size() == 6) {
    range_from_config = true;
    for (int i = 0; i < 6; ++i) rated_range[static_cast<std::size_t>(i)] = ati.rated_range(i);
  } else if (ati.rated_range_size() != 0) {
    throw AtiBridgeError("leg " + name + ": rated_range needs 6 values, has " +
                         std::to_string(ati.rated_range_size()));
  }
  if (ati.has_records_per_datagram()) {
    const auto k = ati.records_per_datagram();
    if (k < 1 || k > static_cast<unsigned>(rdt::kMaxRecordsPerDatagram)) {
      throw AtiBridgeError("leg " + name + ": records_per_datagram " + std::to_string(k) +
                           " outside 1.." + std::to_string(rdt::kMaxRecordsPerDatagram));
    }
    k_from_config = true;
    records_per_datagram = static_cast<int>(k);
  }
  page_needed =
      !counts_from_config || !range_from_config || !k_from_config || records_per_datagram > 1;
  if (counts_from_config && !range_from_config) {
    // Counts from the config but no range: the page still supplies cfgmr.
    calibrated = false;
  }
  if (counts_from_config && range_from_config) {
    try {
      rdt::CheckCountsPerUnit(counts_per_force, counts_per_torque, rated_range,
                              "leg " + name + " (config)");
    } catch (const rdt::RdtError& e) {
      throw AtiBridgeError(e.what());
    }
  }
}

rdt::NetFtConfig FetchNetFtPage(const std::string& leg, const std::string& address,
                                std::uint16_t http_port, const std::string& url, double timeout_s,
                                std::size_t max_bytes) {
  using Clock = std::chrono::steady_clock;
  // One deadline on the whole fetch: httplib's timeouts are per read, so a page trickling a
  // byte at a time would hold start-up for as long as it likes. A watchdog stops the client at
  // the deadline whatever it is doing (connecting, reading headers or body).
  const auto timeout = std::chrono::duration<double>(timeout_s);
  const auto deadline = Clock::now() + std::chrono::duration_cast<Clock::duration>(timeout);
  httplib::Client client(address, http_port);
  client.set_connection_timeout(std::chrono::duration_cast<std::chrono::microseconds>(timeout));
  client.set_read_timeout(std::chrono::duration_cast<std::chrono::microseconds>(timeout));
  std::mutex mu;
  std::condition_variable cv;
  bool done = false;
  std::atomic<bool> too_slow{false};
  std::thread watchdog([&] {
    std::unique_lock<std::mutex> lock(mu);
    if (!cv.wait_until(lock, deadline, [&] { return done; })) {
      too_slow = true;
      client.stop();
    }
  });
  // The page is a few kB; a bigger one is not a Net F/T page and is not held in memory.
  std::string body;
  bool too_big = false;
  auto res = client.Get("/netftapi2.xml", [&](const char* data, std::size_t n) {
    if (body.size() + n > max_bytes) {
      too_big = true;
      return false;
    }
    body.append(data, n);
    return !too_slow.load();
  });
  {
    std::lock_guard<std::mutex> lock(mu);
    done = true;
  }
  cv.notify_one();
  watchdog.join();
  if (too_big) {
    throw AtiBridgeError("leg " + leg + ": calibration page " + url + " is larger than " +
                         std::to_string(max_bytes) + " bytes: not a Net F/T page; refused");
  }
  if (too_slow) {
    throw AtiBridgeError(
        "leg " + leg + ": calibration page " + url +
        fmt::format(" not read within {} s ({} bytes came): refused", timeout_s, body.size()));
  }
  if (!res) {
    throw AtiBridgeError("leg " + leg + ": cannot read the calibration page " + url + ": " +
                         httplib::to_string(res.error()));
  }
  if (res->status != 200) {
    throw AtiBridgeError("leg " + leg + ": calibration page " + url + " answered HTTP " +
                         std::to_string(res->status));
  }
  res->body = std::move(body);
  try {
    return rdt::ParseNetFtXml(res->body, url);
  } catch (const rdt::RdtError& e) {
    throw AtiBridgeError("leg " + leg + ": " + e.what());
  }
}

void NetFtSettings::TakePage(const rdt::NetFtConfig& page, const std::string& leg,
                             const std::string& address, const std::string& url) {
  const std::array<double, 6> range = range_from_config ? rated_range : page.rated_range;
  try {
    // The page's own values were checked by the parser; a mix with the config's is checked
    // here.
    rdt::CheckCountsPerUnit(counts_from_config ? counts_per_force : page.counts_per_force,
                            counts_from_config ? counts_per_torque : page.counts_per_torque, range,
                            "leg " + leg + " (" + url + " and the config)");
  } catch (const rdt::RdtError& e) {
    throw AtiBridgeError(e.what());
  }
  CheckRdtSettings(page, leg, address, url);
  if (!counts_from_config) {
    counts_per_force = page.counts_per_force;
    counts_per_torque = page.counts_per_torque;
  }
  rated_range = range;
  calibrated = true;
}

void NetFtSettings::CheckRdtSettings(const rdt::NetFtConfig& page, const std::string& leg,
                                     const std::string& address, const std::string& url) {
  rdt_rate_hz = page.rdt_rate_hz;
  std::string why = "the config's records_per_datagram";
  if (!k_from_config) {
    why = fmt::format("records_per_datagram by default (comrdtrate {} / 1000, rounded)",
                      page.rdt_rate_hz);
    // Resolved once: the start command's mode depends on it.
    if (records_per_datagram == 0) {
      records_per_datagram = rdt::DefaultRecordsPerDatagram(page.rdt_rate_hz);
    }
  }
  const int k = records_per_datagram;
  // Real-time mode sends one record per datagram whatever the buffer size (§1.2): only buffered
  // mode depends on the box's setting.
  if (k == 1) return;
  const std::string box = fmt::format("leg {}: the box at {} ({})", leg, address, url);
  if (!page.rdt_buffer_size) {
    throw AtiBoxMismatchError(fmt::format(
        "{} does not give its RDT buffer size (comrdtbsiz), and {} is {} (buffered mode): "
        "cannot check it; set records_per_datagram: 1 for real-time mode",
        box, why, k));
  }
  if (*page.rdt_buffer_size != k) {
    throw AtiBoxMismatchError(fmt::format(
        "{} has RDT buffer size (comrdtbsiz) {}, but {} is {}: set the box's buffer size to {} or "
        "the config's records_per_datagram to {} (1: real-time mode)",
        box, *page.rdt_buffer_size, why, k, k, *page.rdt_buffer_size));
  }
}

}  // namespace ftcal
