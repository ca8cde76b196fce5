// The ATI bridge's view of a Net F/T box's configuration: counts per unit, rated range and RDT
// settings, from the config's ati section or else from the box's configuration page
// (GET /netftapi2.xml, docs/device-protocols.md §1; parsed by rdt::ParseNetFtXml). The bridge
// (ati_bridge.h) decides when to read the page (at start, after a reboot, on retry); this
// fetches it, checks it against the config and takes from it what the config does not give.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "proto/config.pb.h"
#include "rdt_codec.h"

namespace ftcal {

// The bridge cannot run as configured (no calibration page, a bad address, a socket error);
// the message names the transducer and the URL or address.
class AtiBridgeError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The box is set up otherwise than the config says (its RDT buffer size is not the config's
// records_per_datagram): a config error (exit 3), the message names the box and both values.
class AtiBoxMismatchError : public AtiBridgeError {
 public:
  using AtiBridgeError::AtiBridgeError;
};

// One transducer's counts per unit, rated range and records per datagram, and where each came
// from.
struct NetFtSettings {
  bool counts_from_config = false;
  bool range_from_config = false;
  // Records per datagram: the config's (k_from_config), else resolved from the page's rate at
  // the first read (0 until then). 1: real-time mode, else buffered.
  bool k_from_config = false;
  int records_per_datagram = 0;
  int rdt_rate_hz = 0;  // comrdtrate, once a page was read
  // The page is read at start (and again after a reboot) when it supplies something: counts per
  // unit, rated range, the default k, or the buffer size a buffered stream must match.
  bool page_needed = true;
  bool calibrated = false;
  double counts_per_force = 0;
  double counts_per_torque = 0;
  std::array<double, 6> rated_range{};

  // Takes what leg `leg`'s ati section gives. Throws AtiBridgeError for counts per unit given
  // half or not positive and finite, a rated range of other than 6 values, a records_per_datagram
  // outside 1..40, or counts per unit implausible for the rated range.
  void FromConfig(const std::string& leg, const config::AtiTransducer& ati);

  // Takes the page of the box at `address` (`url`) for what the config does not give: counts
  // per unit and rated range (checked together with the config's), the default records per
  // datagram; sets `calibrated`. Throws AtiBridgeError for implausible counts per unit, and
  // AtiBoxMismatchError when a buffered stream's k is not the box's RDT buffer size (the page's
  // rate and the default k are taken by then; counts and range only when it does not throw).
  void TakePage(const rdt::NetFtConfig& page, const std::string& leg, const std::string& address,
                const std::string& url);

 private:
  // Resolves the default records per datagram from the page's rate and checks a buffered
  // stream's k against the box's buffer size. Throws AtiBoxMismatchError.
  void CheckRdtSettings(const rdt::NetFtConfig& page, const std::string& leg,
                        const std::string& address, const std::string& url);
};

// GET /netftapi2.xml from `address`:`http_port` (`url` names it in errors) within `timeout_s`
// for the whole fetch, not each read, and at most `max_bytes`; parsed. Throws AtiBridgeError
// naming leg `leg` and the URL when it cannot be read in time, is too big, answers other than
// 200, or is not a Net F/T page.
rdt::NetFtConfig FetchNetFtPage(const std::string& leg, const std::string& address,
                                std::uint16_t http_port, const std::string& url, double timeout_s,
                                std::size_t max_bytes);

}  // namespace ftcal
