// libFuzzer target: an arbitrary byte stream through the QTM deframer (fed in pieces whose
// size comes from the input), each packet through the decoder its type calls for.
// Invariants: a decoded data frame re-encodes to a packet of the same size that decodes to
// the same counts; a fatal framing error stays fatal.
#include "qtm_protocol.h"

#include <cstdlib>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ftcal::qtm;
  if (size < 1) return 0;
  const std::size_t chunk = (data[0] & 0x1F) + 1;
  ++data;
  --size;
  Deframer deframer(1 << 16);
  bool failed = false;
  for (std::size_t at = 0; at < size && !failed; at += chunk) {
    deframer.Feed(data + at, std::min(chunk, size - at));
    try {
      while (auto p = deframer.Next()) {
        try {
          if (p->is(PacketType::kData)) {
            const DataFrame f = DecodeData(*p);
            if (f.skipped_component_types.empty()) {
              const std::vector<std::uint8_t> again = EncodeData(f);
              if (again.size() != p->payload.size() + kPacketHeaderBytes) std::abort();
              Deframer d2;
              d2.Feed(again.data(), again.size());
              const DataFrame g = DecodeData(*d2.Next());
              if (g.markers.size() != f.markers.size() || g.bodies.size() != f.bodies.size()) {
                std::abort();
              }
            }
            for (const Body& b : f.bodies) b.tracked();
            for (const Marker& m : f.markers) m.tracked();
          } else if (p->is(PacketType::kEvent)) {
            EventName(DecodeEvent(*p));
          } else if (p->is(PacketType::kXml)) {
            ParseParameters(DecodeText(*p));
          } else if (p->is(PacketType::kCommand) || p->is(PacketType::kError)) {
            IsWelcome(DecodeText(*p));
          }
        } catch (const QtmError&) {
        }
      }
    } catch (const QtmError&) {
      failed = true;
      bool still_failed = false;
      try {
        deframer.Next();
      } catch (const QtmError&) {
        still_failed = true;
      }
      if (!still_failed) std::abort();
    }
  }
  return 0;
}
