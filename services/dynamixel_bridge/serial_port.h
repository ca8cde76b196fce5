// A serial port for the Dynamixel bus: an RS-485 adapter's tty (or the twin's pseudo-terminal)
// in raw mode, 8N1, no flow control, at the bus's baud rate.
#pragma once

#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>

namespace ftcal::dxl {

// Opening or using the port failed; the message names the device and the step.
class SerialError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

class SerialPort {
 public:
  // Opens `path` non-blocking, raw 8N1 at `baud` bit/s (a standard Bxxx rate, else
  // termios2/BOTHER), and discards whatever was waiting in its input. Throws SerialError.
  SerialPort(const std::string& path, std::uint32_t baud);
  ~SerialPort();
  SerialPort(const SerialPort&) = delete;
  SerialPort& operator=(const SerialPort&) = delete;

  int fd() const { return fd_; }
  const std::string& path() const { return path_; }

  // Writes every byte, waiting for the port up to `timeout_ms` in all. Throws SerialError when
  // the port is gone or stays full.
  void WriteAll(const std::uint8_t* data, std::size_t n, int timeout_ms);
  // Reads what is there now (never blocks): the number of bytes, 0 when none. Throws
  // SerialError when the port hung up or failed (an unplugged adapter: EIO, ENXIO, POLLHUP).
  std::size_t ReadSome(std::uint8_t* buf, std::size_t capacity);
  // Drops unread input (stale replies from before a resynchronisation).
  void DiscardInput();

 private:
  std::string path_;
  int fd_ = -1;
};

// Sets `baud` bit/s on an open tty: the Bxxx constant when there is one, else termios2 with
// BOTHER (Linux). Throws SerialError naming `path`.
void SetSerialBaud(int fd, std::uint32_t baud, const std::string& path);

}  // namespace ftcal::dxl
