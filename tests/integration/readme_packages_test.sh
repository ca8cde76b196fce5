#!/usr/bin/env bash
# The README's by-hand package list ("Building from source") is scripts/setup's list: a
# newcomer who installs by hand gets what the scripts install.
set -euo pipefail
root="$1"
setup_list=$(sed -n '/^packages=(/,/^)/p' "$root/scripts/setup" | sed '1d;$d' | tr -s ' \n' '\n' |
  grep -v '^$' | sort -u)
readme_list=$(sed -n '/^## Building from source/,/^## /p' "$root/README.md" |
  awk '/apt-get install/ {on = 1} on {print; if ($0 !~ /\\$/) exit}' |
  sed 's/sudo apt-get install//; s/\\//g' |
  tr -s ' \n' '\n' | grep -v '^$' | sort -u)
[ -n "$setup_list" ] || { echo "no packages=( ... ) list in scripts/setup" >&2; exit 1; }
[ -n "$readme_list" ] || { echo "no apt-get install list under '## Building from source' in README.md" >&2; exit 1; }
only_setup=$(comm -23 <(echo "$setup_list") <(echo "$readme_list"))
only_readme=$(comm -13 <(echo "$setup_list") <(echo "$readme_list"))
if [ -n "$only_setup$only_readme" ]; then
  [ -z "$only_setup" ] || echo "in scripts/setup, missing from README.md: $(echo $only_setup)"
  [ -z "$only_readme" ] || echo "in README.md, missing from scripts/setup: $(echo $only_readme)"
  exit 1
fi
echo "README.md and scripts/setup list the same $(echo "$setup_list" | wc -l) packages"
