#!/usr/bin/env bash
# scripts/compare_calibration.py against cases computed by hand: a calibration against itself is
# 0 in every class (its rotation angle once read 1.2e-6 deg for two identical rotations, acos of
# the trace); --equal passes a file against itself and names the one field that moved, by how
# much, when one number changes by 1e-9.
#   compare_calibration_test.sh SOURCE_DIR BUILD_DIR
set -euo pipefail
src="$1"
export FTCAL_BUILD_DIR="$2"
cmp="$src/scripts/compare_calibration.py"
truth="$src/tests/integration/testdata/twin_truth.pbtxt"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }

out="$("$cmp" "$truth" "$truth")" || fail "a file against itself failed: $out"
grep -q "mounting rotations  *0.00000 deg" <<<"$out" || fail "rotation of a file against itself is not 0: $out"
[ "$(grep -c "PASS" <<<"$out")" -eq 6 ] || fail "not six classes passing: $out"

out="$("$cmp" --equal 0 "$truth" "$truth")" || fail "--equal 0 against itself failed: $out"
grep -q "largest difference 0," <<<"$out" || fail "--equal against itself: $out"

# HL's leg weight 6.29031266272432 -> 6.29031266372432 (1e-9 N; relative 1e-9 / 6.29).
sed 's/value: 6.29031266272432$/value: 6.29031266372432/' "$truth" >"$tmp/moved.pbtxt"
! cmp -s "$truth" "$tmp/moved.pbtxt" || fail "the test's edit did not apply"
set +e
out="$("$cmp" --equal 1e-12 "$tmp/moved.pbtxt" "$truth")"
rc=$?
set -e
[ "$rc" -eq 1 ] || fail "--equal 1e-12 with a moved weight exited $rc: $out"
grep -q "leg\[0\].leg_weight_n.value" <<<"$out" || fail "the moved field is not named: $out"
grep -q "1.59e-10" <<<"$out" || fail "the relative difference is not 1e-9 / 6.29: $out"
"$cmp" --equal 1e-9 "$tmp/moved.pbtxt" "$truth" >/dev/null || fail "--equal 1e-9 refused a 1.6e-10 difference"
echo "compare_calibration: every case as computed by hand"
