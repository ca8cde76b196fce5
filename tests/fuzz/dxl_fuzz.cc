// libFuzzer target: an arbitrary byte stream through the Dynamixel status parser, fed in
// pieces whose sizes come from the input. Invariants: every packet it returns re-encodes to
// a packet that parses back to the same fields; nothing is held beyond one packet's length.
#include "protocol2.h"

#include <cstdlib>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ftcal::dxl;
  if (size < 1) return 0;
  // First byte: chunk size for feeding (1-16), so split packets are exercised.
  const std::size_t chunk = (data[0] & 0x0F) + 1;
  ++data;
  --size;
  PacketParser parser(256);
  for (std::size_t at = 0; at < size; at += chunk) {
    parser.Feed(data + at, std::min(chunk, size - at));
    while (auto s = parser.NextStatus()) {
      const std::vector<std::uint8_t> again = BuildStatus(s->id, s->error, s->params);
      PacketParser check;
      check.Feed(again.data(), again.size());
      const auto t = check.NextStatus();
      if (!t || t->id != s->id || t->error != s->error || t->params != s->params) std::abort();
      if (s->params.size() == kPresentBlockBytes) {
        const PresentState p = DecodePresentBlock(s->params.data(), s->params.size());
        PositionToRad(p.present_position, 2048, 1);
        VelocityToRadPerS(p.present_velocity);
        CurrentToA(p.present_current);
      }
      DescribeStatusError(s->error);
    }
    // 7 header bytes + max length 256: anything longer is a parser that forgot to resync.
    if (parser.buffered() > 7 + 256 + chunk) std::abort();
  }
  parser.Timeout();
  if (parser.buffered() != 0) std::abort();
  return 0;
}
