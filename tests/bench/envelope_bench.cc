// What authentication and the wire guard cost per message: sealing a six-servo SERVO_CMD
// (Ed25519 sign), opening it (envelope guard, signature verify, sequence, window), the inner
// guarded decode, and refusing the 153-byte mocap_body_t that claims 4e8 markers.
#include <benchmark/benchmark.h>
#include <sodium.h>

#include <chrono>

#include "common/envelope.h"
#include "common/wire_guard.h"
#include "ftcal/mocap_body_t.hpp"
#include "ftcal/servo_command_t.hpp"

namespace {

using namespace ftcal;

auth::Signer MakeSigner() {
  std::array<uint8_t, auth::kSeedBytes> seed{};
  randombytes_buf(seed.data(), seed.size());
  return auth::Signer::FromSeed(seed);
}

servo_command_t SixServos() {
  servo_command_t c{};
  c.action = servo_command_t::MOVE;
  c.num_servos = 6;
  c.id = {1, 2, 3, 4, 5, 6};
  c.goal_angle_rad = {0.1, 0.2, 0.3, -0.1, -0.2, -0.3};
  c.torque_enable = true;
  return c;
}

int64_t NowUs() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

template <class Msg>
std::vector<uint8_t> Encode(const Msg& m) {
  std::vector<uint8_t> b(static_cast<size_t>(m.getEncodedSize()));
  m.encode(b.data(), 0, static_cast<int>(b.size()));
  return b;
}

void BM_SealServoCommand(benchmark::State& state) {
  auth::InitSodium();
  auth::Signer signer = MakeSigner();
  const servo_command_t cmd = SixServos();
  for (auto _ : state) {
    auto e = signer.Seal("SERVO_CMD", cmd, NowUs());
    benchmark::DoNotOptimize(Encode(e));
  }
}
BENCHMARK(BM_SealServoCommand);

void BM_OpenServoCommand(benchmark::State& state) {
  auth::InitSodium();
  auth::Signer signer = MakeSigner();
  auth::Verifier verifier({{"op", signer.public_key(), {"SERVO_CMD"}}});
  const servo_command_t cmd = SixServos();
  // Distinct envelopes (rising sequences), sealed beforehand: only the receiver is timed.
  std::vector<std::vector<uint8_t>> envelopes;
  for (int i = 0; i < 4096; ++i)
    envelopes.push_back(Encode(signer.Seal("SERVO_CMD", cmd, NowUs())));
  size_t i = 0;
  for (auto _ : state) {
    if (i == envelopes.size()) {
      state.PauseTiming();
      verifier = auth::Verifier({{"op", signer.public_key(), {"SERVO_CMD"}}});
      i = 0;
      state.ResumeTiming();
    }
    const auto& b = envelopes[i++];
    auto [opened, refused] =
        verifier.Open("SERVO_CMD", b.data(), static_cast<int>(b.size()),
                      static_cast<uint64_t>(servo_command_t::getHash()), NowUs(), /*window_us=*/0);
    if (refused) state.SkipWithError(refused->kind.c_str());
    servo_command_t out;
    benchmark::DoNotOptimize(wire::Decode(opened->payload, opened->size, &out));
  }
}
BENCHMARK(BM_OpenServoCommand);

void BM_GuardedDecodeServoCommand(benchmark::State& state) {
  const auto b = Encode(SixServos());
  for (auto _ : state) {
    servo_command_t out;
    benchmark::DoNotOptimize(wire::Decode(b.data(), static_cast<int>(b.size()), &out));
  }
}
BENCHMARK(BM_GuardedDecodeServoCommand);

void BM_PlainDecodeServoCommand(benchmark::State& state) {
  const auto b = Encode(SixServos());
  for (auto _ : state) {
    servo_command_t out;
    benchmark::DoNotOptimize(out.decode(b.data(), 0, static_cast<int>(b.size())));
  }
}
BENCHMARK(BM_PlainDecodeServoCommand);

void BM_Refuse153ByteMocap(benchmark::State& state) {
  mocap_body_t m{};
  m.body = "chassis";
  auto b = Encode(m);
  const uint32_t n = 400'000'000;
  for (int k = 0; k < 4; ++k) b[b.size() - 4 + k] = static_cast<uint8_t>(n >> (24 - 8 * k));
  for (auto _ : state) {
    mocap_body_t out;
    auto refused = wire::Decode(b.data(), static_cast<int>(b.size()), &out);
    if (!refused) state.SkipWithError("accepted");
    benchmark::DoNotOptimize(refused);
  }
}
BENCHMARK(BM_Refuse153ByteMocap);

}  // namespace

BENCHMARK_MAIN();
