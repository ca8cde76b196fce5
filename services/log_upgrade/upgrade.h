// ftcal-log-upgrade's work: an LCM log of older message versions rewritten into the current ones.
//
// A log recorded before a change of ftcal's message types carries the older versions
// (lcmtypes/legacy/, README there), which every current reader refuses as a wrong fingerprint.
// UpgradeLog() reads OLD event by event (lcm::LogFile) and writes NEW atomically
// (AtomicLogFile: a temporary file beside it, renamed when complete):
//   - an event whose fingerprint is an older version is checked with that version's wire
//     schema (a log is untrusted input: bad bytes are refused naming the event and channel,
//     never decoded), decoded, converted by the FromLegacy() below and encoded as the current
//     type; same channel, same timestamp, same place;
//   - every other event (current types, other programs' types, anything undecodable as ftcal's)
//     is copied byte for byte;
//   - a signed envelope (signed_envelope_t) whose inner message is an older version is copied
//     too: re-encoding its inside would break its signature, and none of the signed channels'
//     older versions is read offline (only SEQUENCER_CONTROL's changed, which only the live
//     sequencer reads). They are counted.
// A refused event leaves no NEW behind.
#pragma once

#include <cstdint>
#include <map>
#include <stdexcept>
#include <string>
#include <vector>

#include "ftcal/contact_wrench_sum_t.hpp"
#include "ftcal/contact_wrench_t.hpp"
#include "ftcal/ft_batch_t.hpp"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/sequencer_control_t.hpp"
#include "ftcal/servo_state_t.hpp"
#include "ftcal/steady_pose_t.hpp"
#include "ftcal/sync_sample_t.hpp"
#include "ftcal_pre_batch/contact_wrench_sum_t.hpp"
#include "ftcal_pre_batch/contact_wrench_t.hpp"
#include "ftcal_pre_batch/ft_sample_t.hpp"
#include "ftcal_pre_fixed6/servo_state_t.hpp"
#include "ftcal_pre_fixed6/steady_pose_t.hpp"
#include "ftcal_pre_fixed6/sync_sample_t.hpp"
#include "ftcal_pre_nonce/sequencer_control_t.hpp"
#include "ftcal_pre_sample_time/mocap_body_t.hpp"
#include "ftcal_pre_sample_time/servo_state_t.hpp"
#include "ftcal_pre_scatter/steady_pose_t.hpp"

namespace ftcal::log_upgrade {

// An older message that cannot be converted: its bytes fail its version's checks, or its
// content has no current form (a servo state of five servos). what() names the event number
// in OLD, the channel and the reason. Also an OLD with bytes but no event (not an LCM log).
// Exit code 2.
class RefusedEvent : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The conversions, one per older version. Each copies every field the current type has a place
// for, unit for unit. Those that throw std::invalid_argument (caught and named with the event
// by UpgradeLog) do so for content the current type cannot hold.
//
// One record becomes a batch of one: receipt_utime = sample_utime[0] = the old utime (the old
// stamp was the receipt, or, for an earlier record of a buffered datagram, the receipt less its
// distance on the box's counter: the nearest there is to each).
ftcal::ft_batch_t FromLegacy(const ftcal_pre_batch::ft_sample_t& old);
// One leg-sample becomes a batch of one: receipt_utime = utime[0] = the old utime.
ftcal::contact_wrench_t FromLegacy(const ftcal_pre_batch::contact_wrench_t& old);
// One sum becomes a batch of one.
ftcal::contact_wrench_sum_t FromLegacy(const ftcal_pre_batch::contact_wrench_sum_t& old);
// num_servos / num_legs must be six (the current arrays are fixed at six): else
// std::invalid_argument naming the count.
ftcal::servo_state_t FromLegacy(const ftcal_pre_fixed6::servo_state_t& old);
// Before the mapped sample times: sample_utime = the old utime (the completion of the sync
// read, the receipt of the mocap frame), what every reader aligned by then, so an upgraded log
// calibrates as it did.
ftcal::servo_state_t FromLegacy(const ftcal_pre_sample_time::servo_state_t& old);
ftcal::mocap_body_t FromLegacy(const ftcal_pre_sample_time::mocap_body_t& old);
ftcal::sync_sample_t FromLegacy(const ftcal_pre_fixed6::sync_sample_t& old);
// Without the within-pose scatter: wrench_sem and attitude_sem_rad NaN ("not computed", the
// current definition's word for it; the calibrator then takes the pose without its scatter).
ftcal::steady_pose_t FromLegacy(const ftcal_pre_fixed6::steady_pose_t& old);
ftcal::steady_pose_t FromLegacy(const ftcal_pre_scatter::steady_pose_t& old);
// A bare (unsigned) control message: nonce 0, which is what a STOP carries and which no prompt
// has, so an old CONFIRM stays one a current sequencer refuses (it answered no prompt's nonce).
ftcal::sequencer_control_t FromLegacy(const ftcal_pre_nonce::sequencer_control_t& old);

struct ChannelCounts {
  int64_t converted = 0;   // older versions written as the current type
  int64_t copied = 0;      // written byte for byte
  int64_t old_signed = 0;  // of `copied`: signed envelopes with an older inner type
};

struct Summary {
  std::map<std::string, ChannelCounts> channels;
  // Converted events per older version: "ftcal.ft_sample_t (one record a message, ...)".
  std::map<std::string, int64_t> versions;
  int64_t events = 0;
  int64_t converted = 0;
  int64_t old_signed = 0;
  // Bytes of OLD that LCM's reader skipped (not in any event: damage between events, or a
  // last event cut short).
  int64_t skipped_bytes = 0;
};

// The encoded current form of one event's `data`, when its fingerprint is an older version
// (`*version` then names it); empty when the event is to be copied. Throws
// std::invalid_argument with the reason for bytes its version's checks refuse or content the
// current type cannot hold.
std::vector<uint8_t> ConvertMessage(const void* data, int size, std::string* version);

// Reads OLD and writes NEW (atomically; nothing under NEW unless it completes). Throws
// RefusedEvent (nothing written), std::runtime_error for a file that cannot be read or written,
// std::invalid_argument when NEW is OLD.
Summary UpgradeLog(const std::string& old_path, const std::string& new_path);

// The summary as the program prints it: per channel converted and copied, per older version
// converted, and "nothing to convert" for a log that is already current.
std::string Render(const Summary& summary, const std::string& old_path,
                   const std::string& new_path);

}  // namespace ftcal::log_upgrade
