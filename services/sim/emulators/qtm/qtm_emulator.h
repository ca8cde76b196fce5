// The twin's Qualisys QTM real-time server: the little-endian binary protocol (QTM's base port
// + 1, 22223) on this machine, so ftcal-mocap-bridge runs unchanged against it.
//
// One thread, one poll() loop, several clients (QTM allows ten). It answers the commands a
// client of docs/device-protocols.md §3 sends (Version 1.21-1.28, GetParameters, StreamFrames
// with 3D/3DRes/6D/6DRes, QTMVersion, ByteOrder, GetState) and streams one frame per tick at the
// configured rate, from a caller-supplied source (the BigAntTwin in ftcal-emulate-qtm, synthetic
// poses in tests). Packets are built with the shared codec (qtm_protocol.h): the emulator does
// not carry a second encoder.
//
// Faults, deterministic for a given seed and schedule (ticks count from the first frame):
// untracked body (NaN pose) for windows, extra marker dropouts, frame-number gaps (QTM skipped
// real-time frames), corrupt data packets (a component size that disagrees with its count, the
// packet framing intact), silence, No More Data (a measurement ends; numbering restarts after),
// disconnect (QTM Shutting Down, all clients closed, connections refused for the window) and
// Camera Settings Changed events.
#pragma once

#include <Eigen/Core>

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "qtm_protocol.h"

namespace ftcal::sim {

// What the mocap sees at one tick, in QTM's global frame G, SI units.
struct QtmPose {
  bool body_tracked = true;
  Eigen::Matrix3d R_GC = Eigen::Matrix3d::Identity();  // chassis body axes into G
  Eigen::Vector3d p_GoCo_G_m = Eigen::Vector3d::Zero();
  double residual_m = 0.0005;
  std::vector<Eigen::Vector3d> markers_G_m;  // in label order; NaN when not seen
};

// The device state per tick (tick = 0, 1, ...). nullopt: the source has ended (the emulator
// stops streaming and its Run() returns).
using QtmFrameSource = std::function<std::optional<QtmPose>(int64_t tick)>;

struct TickWindow {
  int64_t first_tick = 0;
  int64_t num_ticks = 0;
  bool Contains(int64_t tick) const { return tick >= first_tick && tick < first_tick + num_ticks; }
};

struct QtmFaults {
  uint64_t seed = 1;
  // Per tick: skip 1..max_gap_frames frame numbers (the frame sent carries the later number).
  double gap_probability = 0.0;
  int max_gap_frames = 3;
  // Per tick and marker: that marker drops out for marker_dropout_ticks ticks.
  double marker_dropout_probability = 0.0;
  int marker_dropout_ticks = 20;
  // Per tick: the data packet's 6D component size is off by 4 (framing intact).
  double corrupt_probability = 0.0;
  std::vector<TickWindow> untracked;     // body NaN
  std::vector<TickWindow> silent;        // nothing sent, connections kept
  std::vector<TickWindow> no_more_data;  // one No More Data at the start; frames restart at 1 after
  std::vector<TickWindow> disconnected;  // event 12, all clients closed, refused meanwhile
  std::vector<int64_t> settings_changed;  // event 11 to every client at these ticks
};

struct QtmEmulatorOptions {
  std::string address = "127.0.0.1";
  uint16_t port = qtm::kLittleEndianPort;  // 0: any free port (see port())
  double rate_hz = 100.0;
  // The camera system's clock: its frame timestamps run this fast and start this far into the
  // measurement.
  double clock_rate_ppm = 0.0;
  double clock_offset_s = 0.0;
  std::string body_name = "chassis";
  // A second body listed before the chassis, so a client must map bodies by name.
  bool decoy_body_first = true;
  // With the decoy: swap the two bodies' order at every settings-changed event and every
  // disconnect (a QTM restart), as a changed project would, so a client must re-map.
  bool reorder_bodies_on_change = false;
  std::vector<std::string> labels;  // 3D label names; empty: chassis_m01..chassis_m12
  // The chassis' points in its own frame (mm in the XML), one per label; optional.
  std::vector<Eigen::Vector3d> body_points_m;
  int max_clients = 10;
  QtmFaults faults;
};

// One frame as it went out, values narrowed to f32 as on the wire, for the caller's truth.
struct QtmSentFrame {
  int64_t tick = 0;
  int32_t frame_number = 0;
  int64_t timestamp_us = 0;
  bool corrupt = false;  // sent with a broken component: a client must not use it
  qtm::Body body;        // NaN when untracked
  std::vector<qtm::Marker> markers;
  int clients = 0;  // streaming clients it was written to
};

struct QtmEmulatorCounters {
  int64_t ticks = 0;
  int64_t frames_sent = 0;  // frames written to at least one client
  int64_t frames_corrupt = 0;
  int64_t frames_untracked = 0;
  int64_t gaps = 0;            // frame-number jumps emitted
  int64_t frames_skipped = 0;  // numbers skipped by those jumps
  int64_t connections = 0;
  int64_t refused_clients = 0;  // max clients reached
  int64_t versions_refused = 0;
  int64_t parameters_sent = 0;
  int64_t events_sent = 0;
  int64_t disconnects = 0;  // disconnect windows begun
  int64_t no_more_data_sent = 0;
};

class QtmEmulator {
 public:
  using SentObserver = std::function<void(const QtmSentFrame&)>;

  // Binds and listens now. Throws std::runtime_error naming the address on failure and
  // std::invalid_argument for options it cannot serve.
  QtmEmulator(QtmEmulatorOptions options, QtmFrameSource source);
  ~QtmEmulator();
  QtmEmulator(const QtmEmulator&) = delete;
  QtmEmulator& operator=(const QtmEmulator&) = delete;

  uint16_t port() const { return port_; }
  void SetObserver(SentObserver observer) { observer_ = std::move(observer); }

  // Serves in real time until the source ends, `max_ticks` ticks have run (< 0: no limit),
  // RequestStop() is called (from any thread) or `keep_going` returns false.
  void Run(int64_t max_ticks = -1, const std::function<bool()>& keep_going = {});
  void RequestStop() { stop_.store(true); }

  const QtmEmulatorCounters& counters() const { return counters_; }
  // The GetParameters reply body for `sections` ("General", "3D", "6D", "All").
  std::string ParametersXml(const std::vector<std::string>& sections, int minor) const;

 private:
  struct Client;
  void Listen();
  void CloseListener();
  void Accept();
  void ReadClient(Client& c);
  void HandleCommand(Client& c, const std::string& text);
  void Send(Client& c, const std::vector<uint8_t>& bytes);
  void Flush(Client& c);
  void Tick();
  void Broadcast(const std::vector<uint8_t>& bytes);
  bool InAny(const std::vector<TickWindow>& windows, int64_t tick) const;
  bool StartsAny(const std::vector<TickWindow>& windows, int64_t tick) const;

  QtmEmulatorOptions options_;
  QtmFrameSource source_;
  SentObserver observer_;
  int listen_fd_ = -1;
  uint16_t port_ = 0;
  std::vector<std::unique_ptr<Client>> clients_;
  std::atomic<bool> stop_{false};
  bool source_ended_ = false;

  int64_t tick_ = 0;
  int32_t frame_base_ = 0;  // frame number = tick - frame_base_ + 1 + skipped
  int64_t skipped_ = 0;
  bool decoy_first_ = true;  // current order of the two bodies (with a decoy)
  std::mt19937_64 rng_;
  std::vector<int64_t> marker_dropout_until_;
  QtmEmulatorCounters counters_;
};

// Default label names: chassis_m01 ... chassis_mNN.
std::vector<std::string> DefaultQtmLabels(int n);

}  // namespace ftcal::sim
