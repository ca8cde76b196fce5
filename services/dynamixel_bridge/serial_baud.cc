// Baud rates: kept apart from serial_port.cc because Linux's <asm/termbits.h> (termios2,
// BOTHER) cannot be included together with glibc's <termios.h>.
#include <asm/termbits.h>
#include <sys/ioctl.h>

#include <cerrno>
#include <cstring>

#include "serial_port.h"

namespace ftcal::dxl {
namespace {

// The Dynamixel rates (docs/device-protocols.md §2.1) that have a Bxxx constant.
speed_t StandardSpeed(std::uint32_t baud) {
  switch (baud) {
    case 9600:
      return B9600;
    case 57600:
      return B57600;
    case 115200:
      return B115200;
    case 1000000:
      return B1000000;
    case 2000000:
      return B2000000;
    case 3000000:
      return B3000000;
    case 4000000:
      return B4000000;
    default:
      return 0;
  }
}

}  // namespace

void SetSerialBaud(int fd, std::uint32_t baud, const std::string& path) {
  if (baud == 0) throw SerialError("serial port " + path + ": baud 0");
  termios2 tio{};
  if (::ioctl(fd, TCGETS2, &tio) != 0) {
    throw SerialError("serial port " + path + ": TCGETS2: " + std::strerror(errno));
  }
  tio.c_cflag &= ~static_cast<tcflag_t>(CBAUD | (CBAUD << IBSHIFT));
  const speed_t standard = StandardSpeed(baud);
  if (standard != 0) {
    tio.c_cflag |= standard | (standard << IBSHIFT);
  } else {
    // 4.5 Mbit/s and other rates without a constant: the driver takes the number itself.
    tio.c_cflag |= BOTHER | (BOTHER << IBSHIFT);
  }
  tio.c_ispeed = baud;
  tio.c_ospeed = baud;
  if (::ioctl(fd, TCSETS2, &tio) != 0) {
    throw SerialError("serial port " + path + ": cannot set " + std::to_string(baud) +
                      " bit/s: " + std::strerror(errno));
  }
}

}  // namespace ftcal::dxl
