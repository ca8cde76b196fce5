#!/usr/bin/env bash
# scripts/setup beside another apt or dpkg (a fresh Debian machine runs unattended upgrades at
# boot): it waits for the package manager's lock and says so, installs once the lock is
# released, and gives up with a clear message after FTCAL_DPKG_LOCK_WAIT_S.
#   setup_lock_test.sh <source dir>
# The machine's own apt is never touched: the lock is a file of this test's (FTCAL_DPKG_LOCKS),
# held with flock(1) by a helper process; apt-get, dpkg-query, sudo and cmake are stubs on PATH
# that record their calls (one package reads as missing, so setup reaches its install step).
# Event-driven: the test waits for setup's line saying it waits, then releases the lock.
set -euo pipefail
root="$1"
tmp="$(mktemp -d)"
holder=""
cleanup() {
  [ -z "$holder" ] || kill "$holder" 2>/dev/null || true
  rm -rf "$tmp"
}
trap cleanup EXIT
fail() {
  echo "FAIL: $*" >&2
  for f in "$tmp"/*.out "$tmp"/*.err "$tmp"/calls; do
    [ -f "$f" ] && { echo "--- $f" >&2; cat "$f" >&2; }
  done
  exit 1
}

mkdir "$tmp/bin"
cat >"$tmp/bin/dpkg-query" <<'EOF'
#!/bin/sh
# Every package installed but libsodium-dev.
for last; do :; done
[ "$last" = libsodium-dev ] && { printf 'deinstall ok config-files'; exit 0; }
printf 'install ok installed'
EOF
for tool in apt-get cmake; do
  printf '#!/bin/sh\necho "%s $*" >>"%s/calls"\n' "$tool" "$tmp" >"$tmp/bin/$tool"
done
printf '#!/bin/sh\nexec "$@"\n' >"$tmp/bin/sudo"
chmod +x "$tmp/bin/"*
export PATH="$tmp/bin:$PATH" FTCAL_DPKG_LOCKS="$tmp/lock-frontend" FTCAL_BUILD_DIR="$tmp/build"
unset FTCAL_NO_INSTALL FTCAL_SETUP_LOG FTCAL_TARGETS
: >"$tmp/lock-frontend"
mkfifo "$tmp/held" "$tmp/release" "$tmp/setup.pipe"

# Holds the lock until a line arrives on `release`; says "held" once it has it.
hold_lock() {
  flock -x "$tmp/lock-frontend" sh -c 'echo held >"$1"; read -r _ <"$2"' _ "$tmp/held" \
    "$tmp/release" &
  holder=$!
  read -r -t 10 line <"$tmp/held" || fail "the helper did not take the lock"
}
release_lock() {
  echo go >"$tmp/release"
  wait "$holder" || true
  holder=""
}

# 1. Waits while the lock is held, says so naming the file and its holder, then installs.
hold_lock
"$root/scripts/setup" >"$tmp/setup.pipe" 2>"$tmp/wait.err" &
setup=$!
exec {out}<"$tmp/setup.pipe"
said=""
while IFS= read -r -t 30 line <&"$out"; do
  echo "$line" >>"$tmp/wait.out"
  case "$line" in
    "setup: waiting for another apt or dpkg to finish: $tmp/lock-frontend is held by process"*)
      said=$line
      break
      ;;
  esac
done
[ -n "$said" ] || fail "setup did not say it waits for the lock"
[ ! -s "$tmp/calls" ] || fail "apt-get ran while the lock was held"
release_lock
cat <&"$out" >>"$tmp/wait.out"
exec {out}<&-
rc=0
wait "$setup" || rc=$?
[ "$rc" -eq 0 ] || fail "setup exited $rc after the lock was released"
grep -q "^apt-get -o DPkg::Lock::Timeout=300 update" "$tmp/calls" ||
  fail "apt-get update did not run (with apt's own lock timeout) after the release"
grep -q "^apt-get -o DPkg::Lock::Timeout=300 install .*libsodium-dev" "$tmp/calls" ||
  fail "the missing package was not installed after the release"
[ "$(grep -c 'setup: waiting' "$tmp/wait.out")" -eq 1 ] || fail "the wait was not said once"

# 2. Gives up after FTCAL_DPKG_LOCK_WAIT_S with a message naming the lock and what to do.
: >"$tmp/calls"
hold_lock
rc=0
FTCAL_DPKG_LOCK_WAIT_S=1 "$root/scripts/setup" >"$tmp/timeout.out" 2>"$tmp/timeout.err" || rc=$?
release_lock
[ "$rc" -ne 0 ] || fail "setup succeeded with the lock held past its wait"
grep -q "setup: failed: another apt or dpkg is still running after 1 s: $tmp/lock-frontend is held by process" \
  "$tmp/timeout.err" || fail "no clear message after the wait"
grep -q "FTCAL_DPKG_LOCK_WAIT_S" "$tmp/timeout.err" || fail "the message does not name the setting"
[ ! -s "$tmp/calls" ] || fail "apt-get ran although the lock was never released"
echo "setup waited for the held lock, installed after its release, and gave up after its bound"
