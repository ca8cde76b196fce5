// libFuzzer target, one executable per message type (FTCAL_FUZZ_TYPE): arbitrary bytes after
// the type's fingerprint through the wire guard and LCM's decoder (wire::Decode), as every
// typed subscription receives them. The fingerprint is prepended so the fuzzer explores the
// fields rather than a 2^-64 chance. Invariants: the decoder never throws nor disagrees with
// the guard on the size; a message the guard accepts re-encodes to exactly the bytes received
// (nothing was read but what was there); its decoded size stays within the guard's bound
// (ASan's -rss_limit_mb catches the rest).
#include <cstdlib>
#include <cstring>
#include <vector>

#include "common/wire_guard.h"
#include FTCAL_FUZZ_HEADER

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  using Msg = ftcal::FTCAL_FUZZ_TYPE;
  std::vector<std::uint8_t> bytes(8 + size);
  const auto fingerprint = static_cast<std::uint64_t>(Msg::getHash());
  for (int i = 0; i < 8; ++i) bytes[i] = static_cast<std::uint8_t>(fingerprint >> (56 - 8 * i));
  if (size > 0) std::memcpy(bytes.data() + 8, data, size);
  Msg msg;
  const auto refused = ftcal::wire::Decode(bytes.data(), static_cast<int>(bytes.size()), &msg);
  if (refused) {
    if (refused->kind == "decoder threw" || refused->kind == "decoder disagrees") std::abort();
    return 0;
  }
  const int n = msg.getEncodedSize();
  if (n != static_cast<int>(bytes.size())) std::abort();
  std::vector<std::uint8_t> again(static_cast<std::size_t>(n));
  if (msg.encode(again.data(), 0, n) != n || again != bytes) std::abort();
  return 0;
}
