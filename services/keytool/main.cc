// ftcal-keygen: makes the signing key of a signed-channel publisher (README, "Signed channels").
//
//   ftcal-keygen --out operator.key     writes a fresh seed (mode 600) and prints the public key
//   ftcal-keygen --public operator.key  prints the public key of an existing seed
//
// The public key goes into the receivers' config (auth.trusted_key); the seed never leaves the
// publisher's host. The seed is written to a temporary file created with mode 600 beside the
// destination and linked into place only when complete, so no one ever sees a partial or a
// readable key, and an existing key is never overwritten.
#include <fcntl.h>
#include <sodium.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <iostream>
#include <string>

#include <CLI/CLI.hpp>

#include "common/envelope.h"
#include "common/exit_codes.h"
#include "common/user_errors.h"

namespace {

int WriteSeed(const std::string& path) {
  std::array<uint8_t, ftcal::auth::kSeedBytes> seed{};
  randombytes_buf(seed.data(), seed.size());
  std::string text = ftcal::auth::ToHex(seed.data(), seed.size()) + "\n";
  const ftcal::auth::Signer signer = ftcal::auth::Signer::FromSeed(seed);
  sodium_memzero(seed.data(), seed.size());

  const std::string tmp = path + ".tmp." + std::to_string(::getpid());
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0600);
  if (fd < 0) {
    std::cerr << "ftcal-keygen: cannot create '" << tmp << "': " << std::strerror(errno) << "\n";
    return 1;
  }
  bool ok = ::fchmod(fd, 0600) == 0 &&  // whatever the umask
            ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size()) &&
            ::fsync(fd) == 0;
  sodium_memzero(text.data(), text.size());
  ok = ::close(fd) == 0 && ok;
  // link() refuses an existing destination, where rename() would replace a key in use.
  if (!ok || ::link(tmp.c_str(), path.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    std::cerr << "ftcal-keygen: cannot write '" << path << "': "
              << (err == EEXIST ? "it exists (a key is never overwritten; remove it first)"
                                : std::strerror(err))
              << "\n";
    return 1;
  }
  ::unlink(tmp.c_str());
  std::cout << ftcal::auth::ToHex(signer.public_key().data(), signer.public_key().size()) << "\n";
  return 0;
}

}  // namespace

int main(int argc, char** argv) try {
  CLI::App cli(
      "Makes an Ed25519 signing key for a publisher of ftcal's signed channels "
      "(SERVO_CMD, EXPERIMENT, CALIBRATION) and prints its public key, 64 hex digits, "
      "for the receivers' config (auth.trusted_key.public_key_hex).",
      "ftcal-keygen");
  std::string out, public_of;
  auto* out_opt = cli.add_option("--out", out, "write a new seed to this file (mode 600)");
  cli.add_option("--public", public_of, "print the public key of this seed file")
      ->excludes(out_opt);
  CLI11_PARSE(cli, argc, argv);
  try {
    ftcal::auth::InitSodium();
    if (!out.empty()) return WriteSeed(out);
    if (!public_of.empty()) {
      const auto signer = ftcal::auth::Signer::FromSeedFile(public_of);
      std::cout << ftcal::auth::ToHex(signer.public_key().data(), signer.public_key().size())
                << "\n";
      return 0;
    }
    std::cerr << "ftcal-keygen: give --out FILE or --public FILE (--help)\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << "ftcal-keygen: " << ftcal::UserText(e, "making the key pair") << "\n";
    return ftcal::ExitCodeFor(e, 2);
  }
} catch (...) {
  return ftcal::ExitOnEscapedException("ftcal-keygen");
}
