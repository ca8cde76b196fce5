// libFuzzer target: an arbitrary datagram through the NatNet packet, frame, description and
// SERVERINFO parsers, at the version the first byte picks (3.0, 3.1, 4.0, 4.1, 4.2).
// Invariants: a decoded frame re-encodes to exactly the bytes it came from (so the decoder
// consumed every byte, in the layout the encoder writes); descriptions without types the encoder
// does not write re-encode to as many bytes, and that encoding decodes and re-encodes to itself
// (a server may send marker sets, rigid bodies and skeletons in any order; the encoder groups
// them by kind); nothing but NatNetError escapes.
#include "natnet_protocol.h"

#include <cstdlib>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using namespace ftcal::natnet;
  if (size < 1) return 0;
  static const Version kVersions[] = {{3, 0}, {3, 1}, {4, 0}, {4, 1}, {4, 2}};
  const Version v = kVersions[(data[0] & 0x0F) % 5];
  const int kind = data[0] >> 4;
  ++data;
  --size;
  const std::vector<std::uint8_t> payload(data, data + size);
  try {
    switch (kind % 4) {
      case 0: {
        const FrameOfData f = DecodeFrame(payload, v);
        if (EncodeFrame(f, v) != payload) std::abort();
        PeekFrameParams(payload);
        break;
      }
      case 1: {
        const Descriptions d = DecodeDescriptions(payload, v);
        if (d.other == 0) {
          const std::vector<std::uint8_t> grouped = EncodeDescriptions(d, v);
          if (grouped.size() != payload.size()) std::abort();
          if (EncodeDescriptions(DecodeDescriptions(grouped, v), v) != grouped) std::abort();
        }
        break;
      }
      case 2: {
        const Packet p = DecodePacket(data, size);
        if (EncodePacket(p.id, p.payload) != payload) std::abort();
        if (p.id == kServerInfo) DecodeServerInfo(p.payload);
        if (p.id == kEchoResponse) DecodeEchoResponse(p.payload);
        if (p.id == kConnect) DecodeConnectRequest(p.payload);
        break;
      }
      default: {
        const ServerInfo s = DecodeServerInfo(payload);
        if (EncodeServerInfo(s).size() != payload.size()) std::abort();
        break;
      }
    }
  } catch (const NatNetError&) {
  }
  return 0;
}
