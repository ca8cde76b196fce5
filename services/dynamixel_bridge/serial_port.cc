#include "serial_port.h"

#include <fcntl.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>

namespace ftcal::dxl {
namespace {

std::string Errno() { return std::strerror(errno); }

}  // namespace

SerialPort::SerialPort(const std::string& path, std::uint32_t baud) : path_(path) {
  fd_ = ::open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) throw SerialError("serial port " + path + ": open: " + Errno());
  try {
    termios tio{};
    if (::tcgetattr(fd_, &tio) != 0)
      throw SerialError("serial port " + path + ": tcgetattr: " + Errno());
    ::cfmakeraw(&tio);  // 8 data bits, no parity, no echo, no translation
    tio.c_cflag &= ~static_cast<tcflag_t>(CSTOPB | CRTSCTS);  // 1 stop bit, no flow control
    tio.c_cflag |= CLOCAL | CREAD;
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    if (::tcsetattr(fd_, TCSANOW, &tio) != 0) {
      throw SerialError("serial port " + path + ": tcsetattr: " + Errno());
    }
    SetSerialBaud(fd_, baud, path);
    DiscardInput();
  } catch (...) {
    ::close(fd_);
    fd_ = -1;
    throw;
  }
}

SerialPort::~SerialPort() {
  if (fd_ >= 0) ::close(fd_);
}

void SerialPort::WriteAll(const std::uint8_t* data, std::size_t n, int timeout_ms) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(timeout_ms);
  std::size_t done = 0;
  while (done < n) {
    const ssize_t w = ::write(fd_, data + done, n - done);
    if (w > 0) {
      done += static_cast<std::size_t>(w);
      continue;
    }
    if (w < 0 && errno != EAGAIN && errno != EINTR) {
      throw SerialError("serial port " + path_ + ": write: " + Errno());
    }
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
                          deadline - std::chrono::steady_clock::now())
                          .count();
    if (left <= 0) throw SerialError("serial port " + path_ + ": write timed out");
    pollfd p{fd_, POLLOUT, 0};
    ::poll(&p, 1, static_cast<int>(left));
    if (p.revents & (POLLHUP | POLLERR)) {
      throw SerialError("serial port " + path_ + ": hung up while writing");
    }
  }
}

std::size_t SerialPort::ReadSome(std::uint8_t* buf, std::size_t capacity) {
  const ssize_t n = ::read(fd_, buf, capacity);
  if (n > 0) return static_cast<std::size_t>(n);
  if (n == 0 || errno == EAGAIN || errno == EINTR) {
    // With VMIN = VTIME = 0 a tty reads 0 bytes when there is nothing (not EAGAIN), and a
    // hang-up (the pty master or the USB adapter gone) also reads 0: only poll()'s revents tell
    // them apart, and a vanished port must not look like a quiet bus.
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, 0) > 0 && (p.revents & (POLLHUP | POLLERR | POLLNVAL))) {
      throw SerialError("serial port " + path_ + ": hung up (device gone)");
    }
    return 0;
  }
  throw SerialError("serial port " + path_ + ": read: " + Errno());
}

void SerialPort::DiscardInput() { ::tcflush(fd_, TCIFLUSH); }

}  // namespace ftcal::dxl
