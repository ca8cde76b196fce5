// The ATI bridge's receive path (ati_bridge.h): each socket drained with recvmmsg, every record
// checked (length, sequence) and converted, and each datagram's records published as one
// ft_batch_t with their sample times mapped from the box's counter.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <cstring>

#include "ati_bridge.h"
#include "ati_transducer.h"

namespace ftcal {

using namespace ati_internal;

void AtiBridge::HandleSocket(Transducer& t) {
  // A bounded number of batches per call: a bridge that has fallen behind serves its sockets in
  // turn (poll() returns at once while any has data) instead of draining the first one while
  // the last one's buffer overflows.
  for (int batches = 0; batches < kMaxBatchesPerCall; ++batches) {
    for (int i = 0; i < kBatch; ++i) {
      msghdr& h = t.headers[i].msg_hdr;
      h.msg_name = &t.sources[i];
      h.msg_namelen = sizeof(sockaddr_in);
      h.msg_iov = &t.iovs[i];
      h.msg_iovlen = 1;
      h.msg_control = t.controls[i].data();
      h.msg_controllen = t.controls[i].size();
      h.msg_flags = 0;
    }
    const std::int64_t asked_ns = RealtimeNs();
    const int n = ::recvmmsg(t.fd, t.headers.data(), kBatch, MSG_DONTWAIT, nullptr);
    if (n < 0) {
      if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
        // ECONNREFUSED after an ICMP "port unreachable" for our request (the box is down).
        ++t.c.recv_errors;
        if (!t.logged_recv) {
          t.logged_recv = true;
          log_->warn("{}: receive error: {} (counted from now on)", t.leg, std::strerror(errno));
        }
        continue;
      }
      if (errno != EINTR) t.drained_at_ns = std::max(t.drained_at_ns, asked_ns);
      return;
    }
    const std::int64_t user_ns = RealtimeNs();
    const auto batch_time = Clock::now();
    const std::uint64_t accepted_before = t.tracker.accepted();
    for (int i = 0; i < n; ++i) {
      ++t.c.datagrams;
      const msghdr& h = t.headers[i].msg_hdr;
      std::int64_t kernel_ns = user_ns;
      for (cmsghdr* cm = CMSG_FIRSTHDR(&h); cm != nullptr;
           cm = CMSG_NXTHDR(const_cast<msghdr*>(&h), cm)) {
        if (cm->cmsg_level == SOL_SOCKET && cm->cmsg_type == SCM_TIMESTAMPNS) {
          timespec ts;
          std::memcpy(&ts, CMSG_DATA(cm), sizeof ts);
          kernel_ns = std::int64_t{ts.tv_sec} * 1'000'000'000 + ts.tv_nsec;
        }
      }
      const sockaddr_in& from = t.sources[i];
      if (from.sin_addr.s_addr != t.device.sin_addr.s_addr || from.sin_port != t.device.sin_port) {
        if (!t.logged_foreign) {
          t.logged_foreign = true;
          log_->warn("{}: datagram from {}:{}, not the box: dropped (counted from now on)", t.leg,
                     inet_ntoa(from.sin_addr), ntohs(from.sin_port));
        }
        ++t.c.foreign;
        continue;
      }
      const std::size_t len = t.headers[i].msg_len;
      if (len == 0 || len % rdt::kRecordBytes != 0 || (h.msg_flags & MSG_TRUNC) != 0) {
        ++t.c.wrong_length;
        if (!t.logged_wrong_length) {
          t.logged_wrong_length = true;
          log_->warn(
              "{}: a {}-byte datagram is not a whole number of 36-byte records: dropped "
              "(counted from now on)",
              t.leg, len);
        }
        continue;
      }
      const std::uint8_t* data = t.slots.data() + static_cast<std::size_t>(i) * kSlotBytes;
      // A socket queue is first in, first out: a datagram stamped before the last look that
      // emptied the queue was not in it then.
      const bool held = kernel_ns < t.drained_at_ns;
      // The records of a (buffered) datagram travel on as one message (at most MAX_N, the
      // protocol's largest buffer, so one message unless a box sends more than it may).
      for (std::size_t off = 0; off < len; off += rdt::kRecordBytes) {
        HandleRecord(t, data + off);
        if (t.msg.n == ft_batch_t::MAX_N) PublishBatch(t, kernel_ns, user_ns, held);
      }
      PublishBatch(t, kernel_ns, user_ns, held);
    }
    if (t.tracker.accepted() != accepted_before) {
      t.last_record = batch_time;
      t.backoff_s = SilenceTimeoutS(t);
      t.unanswered = 0;
      if (!t.up || t.silent) LogState(t, "streaming", spdlog::level::info, "streaming again");
      t.silent = false;
      t.up = t.calibrated;
      if (t.up) t.problem.clear();
    }
    if (n < kBatch) {
      t.drained_at_ns = std::max(t.drained_at_ns, asked_ns);
      return;
    }
  }
}

void AtiBridge::HandleRecord(Transducer& t, const std::uint8_t* bytes) {
  const rdt::Record rec = rdt::DecodeRecord(bytes);
  ++t.c.received;
  using V = rdt::SequenceTracker::Verdict;
  // kRestart: two start commands were in flight (a re-send while the box was slow to answer the
  // first) and the tracker had locked onto the stream of the first; the box serves the last.
  const rdt::SequenceTracker::Result r = t.tracker.Update(rec.rdt_sequence, rec.ft_sequence);
  if (!r.accept()) {
    switch (r.verdict) {
      case V::kDuplicate:
        ++t.c.duplicates;
        if (!t.logged_duplicate) {
          t.logged_duplicate = true;
          log_->warn("{}: duplicated record (rdt_sequence {}) dropped (counted from now on)", t.leg,
                     rec.rdt_sequence);
        }
        break;
      case V::kLate:
        ++t.c.late;
        if (!t.logged_late) {
          t.logged_late = true;
          log_->warn("{}: late (reordered) record (rdt_sequence {}) dropped (counted from now on)",
                     t.leg, rec.rdt_sequence);
        }
        break;
      default:
        ++t.c.stale;
        // No earlier re-send for these: the box may simply not have served our start yet, and
        // every re-send begins yet another stream; the back-off paces them.
        if (!t.logged_stale) {
          t.logged_stale = true;
          log_->info(
              "{}: record of a previous stream (rdt_sequence {}) dropped (counted from now "
              "on)",
              t.leg, rec.rdt_sequence);
        }
        break;
    }
    return;
  }
  t.c.lost += r.lost;
  if (r.verdict == V::kStart || r.verdict == V::kRestart) ++t.c.restarts;
  if (r.verdict == V::kRestart) t.restart_pending = true;

  // A box that rebooted restarts ft_sequence near 0 (§1.7): its configuration may have changed.
  if (t.have_ft && static_cast<std::int32_t>(rec.ft_sequence - t.last_ft) < 0) {
    ++t.c.reboots;
    log_->warn(
        "{}: ft_sequence went back from {} to {}: the box restarted; reading its "
        "calibration page again",
        t.leg, t.last_ft, rec.ft_sequence);
    if (t.page_needed) {
      try {
        ReadCalibration(t);
      } catch (const AtiBridgeError& e) {
        t.calibrated = false;
        t.up = false;
        t.calibration_backoff = kCalibrationRetry;
        t.next_calibration_try = Clock::now() + t.calibration_backoff;
        t.problem = std::string(e.what()) + " (not publishing until it can be read)";
        LogState(t, "calibration", spdlog::level::err, t.problem);
      }
    }
  }
  t.ft_unwrapped = t.have_ft
                       ? t.ft_unwrapped + static_cast<std::int32_t>(rec.ft_sequence - t.last_ft)
                       : rec.ft_sequence;
  t.have_ft = true;
  t.last_ft = rec.ft_sequence;

  if (!t.calibrated) {
    ++t.c.uncalibrated;
    t.pending_gap += 1 + r.lost;
    return;
  }

  const rdt::Vector6d w =
      rdt::CountsToWrench(rec.counts, t.counts_per_force, t.counts_per_torque, t.sign);
  std::int32_t flags = 0;
  const bool saturated =
      rdt::StatusSaturated(rec.status) || rdt::ExceedsRatedRange(w, t.rated_range);
  if (saturated) {
    flags |= ft_batch_t::FLAG_SATURATED;
    ++t.c.saturated;
    if (!t.logged_saturated) {
      t.logged_saturated = true;
      log_->warn(
          "{}: saturated sample (status bit 17 or beyond the rated range), published "
          "flagged (counted from now on)",
          t.leg);
    }
  }
  if (rec.status != 0) {
    flags |= ft_batch_t::FLAG_STATUS_ERROR;
    ++t.c.status_nonzero;
    if (!t.logged_status) {
      t.logged_status = true;
      std::string bits;
      for (const auto& s : rdt::DescribeStatus(rec.status)) bits += (bits.empty() ? "" : "; ") + s;
      log_->warn("{}: status word 0x{:08x} ({}), published flagged (counted from now on)", t.leg,
                 rec.status, bits);
    }
  }
  const std::int64_t gap = t.pending_gap + r.lost;
  t.pending_gap = 0;
  if (gap > 0) flags |= ft_batch_t::FLAG_GAP;
  if (t.restart_pending) {
    flags |= ft_batch_t::FLAG_RESTARTED;
    t.restart_pending = false;
  }

  ft_batch_t& m = t.msg;
  const auto i = static_cast<std::size_t>(m.n);
  t.ticks[i] = t.ft_unwrapped;
  m.rdt_sequence[i] = rec.rdt_sequence;
  m.ft_sequence[i] = rec.ft_sequence;
  m.status[i] = rec.status;
  for (std::size_t j = 0; j < 6; ++j) {
    m.counts[i][j] = rec.counts[j];
    m.wrench[i][j] = w(static_cast<int>(j));
  }
  m.gap[i] = static_cast<std::int32_t>(std::min<std::int64_t>(gap, INT32_MAX));
  m.flags[i] = flags;
  ++m.n;
}

void AtiBridge::PublishBatch(Transducer& t, std::int64_t kernel_ns, std::int64_t user_ns,
                             bool held) {
  ft_batch_t& m = t.msg;
  if (m.n == 0) return;
  const auto n = static_cast<std::size_t>(m.n);
  // The box sends a datagram as soon as its last record is taken: the receipt bounds that
  // record's time from above (plus the least transport delay, which the map keeps), and the
  // clock map of many datagrams gives each record its instant on the counter's own rate, so
  // a reader that orders by time (the corrector, the aligner) sees the samples 1/7000 s apart
  // however the datagrams queued. Never after the receipt, never at or before the previous
  // record's time: the stream's times only rise.
  const std::int64_t receipt_us = kernel_ns / 1000;
  t.clock.Observe(t.ticks[n - 1], receipt_us);
  // The last record is capped MAX_N us before the receipt, not at it: the next datagram, if
  // its receipt is within a few us of this one's (two queued by a stall and read back to back,
  // while the map still runs late at the stream's start), must find room for its own records
  // after this one's and before its receipt, or the rising rule pushed them past it (seen:
  // +1..+5 us, CI 2026-12-07). No record is taken that close to its receipt anyway (the box's
  // transport alone takes longer), so the cap binds only on a map that runs late.
  constexpr auto kRoomUs = static_cast<std::int64_t>(ft_batch_t::MAX_N);
  for (std::size_t i = 0; i < n; ++i) {
    // Each record capped so as to leave the later ones of the datagram 1 us each before that:
    // when several map at or after it (a datagram less delayed than the map's line, between
    // two refits), capping them all at one time let the rising rule push the later ones past.
    const auto later = static_cast<std::int64_t>(n - 1 - i);
    const std::int64_t mapped = std::min(t.clock.Map(t.ticks[i]), receipt_us - kRoomUs - later);
    m.sample_utime[i] = std::max(mapped, t.last_utime + 1);
    t.last_utime = m.sample_utime[i];
  }
  m.receipt_utime = receipt_us;
  const int size = m.getEncodedSize();
  const bool encoded = m.encode(t.encoded.data(), 0, size) == size;
  m.n = 0;
  if (!encoded) {
    ++t.c.publish_errors;
    return;
  }
  try {
    publish_(t.channel, t.encoded.data(), size);
    t.c.published += n;
  } catch (const std::exception& e) {
    ++t.c.publish_errors;
    if (!t.logged_publish) {
      t.logged_publish = true;
      log_->error("{}: publish failed: {} (counted from now on)", t.leg, e.what());
    }
    return;
  }
  const std::int64_t done_ns = RealtimeNs();
  for (std::size_t i = 0; i < n; ++i) {
    kernel_latency_.Add(done_ns - kernel_ns);
    user_latency_.Add(done_ns - user_ns);
    if (held) {
      ++t.c.held_in_stack;
      held_latency_.Add(done_ns - kernel_ns);
    }
  }
}

}  // namespace ftcal
