// The twin's operator, for `ftcal-sim live --scenario commanded --control PATH`: what a lab
// operator does with their hands between the sequencer's phases (hang the robot in an
// orientation, lift it upright, set it down), given as text lines on a named pipe (FIFO), so a
// test or a script can drive it:
//
//   hang HANG_X_POS | hang HANG_X_NEG | hang HANG_Z_POS | hang HANG_Z_NEG
//   lift      upright and level, every foot in the air (the tare)
//   stand     on its six feet
//
// A pipe and not an LCM channel: the operator's hands are not a network service, the twin
// alone has them (a channel would need its own signing rules, and would let any host on the
// network "hang" the robot). After each applied line the twin writes PATH.state atomically:
// "<n> <support>\n" with n the number of lines applied so far and support one of STANDING,
// LIFTED, HANG_X_POS ... , so a driver knows when the twin's devices report the new support.
// A bad line is logged with its text and the accepted forms, and ignored.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "sim/twin.h"

namespace ftcal::sim {

struct OperatorCommand {
  BigAntTwin::Driven::Support support = BigAntTwin::Driven::Support::kStanding;
  HangSeries series = HangSeries::kXPos;  // kHanging only
};

// One line (surrounding blanks ignored). Returns nullopt and says why in *error for anything
// else; an empty line is an error too.
std::optional<OperatorCommand> ParseOperatorLine(const std::string& line, std::string* error);
// "STANDING", "LIFTED", "HANG_X_POS", ...
std::string SupportName(const OperatorCommand& command);

class OperatorFifo {
 public:
  // Creates the FIFO at `path` (an existing FIFO there is reused, anything else is refused)
  // and opens it without blocking. Throws std::runtime_error naming the path and the step.
  explicit OperatorFifo(std::string path);
  ~OperatorFifo();  // closes and removes the FIFO and its state file
  OperatorFifo(const OperatorFifo&) = delete;
  OperatorFifo& operator=(const OperatorFifo&) = delete;

  // Complete lines received since the last call (never blocks).
  std::vector<std::string> ReadLines();
  // Writes PATH.state: "<applied> <support>\n", atomically.
  void WriteState(std::int64_t applied, const std::string& support) const;
  const std::string& path() const { return path_; }
  int fd() const { return fd_; }

 private:
  std::string path_;
  int fd_ = -1;
  std::string partial_;
};

}  // namespace ftcal::sim
