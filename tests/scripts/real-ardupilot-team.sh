#!/usr/bin/env bash
# Three rovers on the real ArduPilot firmware, navigating without GNSS: runs
# tests/scripts/real_ardupilot_team.py for each set-up and method and prints the table of
# docs/real-autopilot.md. It runs an ArduRover SITL binary you built yourself from ArduPilot's
# sources (its SITL rover build); it builds nothing.
#
#   bash tests/scripts/real-ardupilot-team.sh /path/to/ardupilot/build/sitl/bin/ardurover [SETUP...]
#
# SETUP: nognss, gnss-lost (default: both). Each run takes about 4 minutes of real time (three
# SITL instances at 1x, three nodes); results go to $OUT (default /tmp/real-ardupilot-team).
# Needs pymavlink (tests/requirements.txt; COOPLOC_PYTHON names the interpreter) and
# target/release/cooploc (cargo build --release).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
ardurover="${1:?usage: real-ardupilot-team.sh ARDUROVER [SETUP...]}"
shift
setups=("$@")
[ ${#setups[@]} -gt 0 ] || setups=(nognss gnss-lost)
py="${COOPLOC_PYTHON:-python3}"
out="${OUT:-/tmp/real-ardupilot-team}"
mkdir -p "$out"
[ -x "$root/target/release/cooploc" ] || { echo "error: build cooploc first (cargo build --release)" >&2; exit 1; }
"$root/target/release/cooploc" --version 2>/dev/null || true
"$ardurover" --help 2>&1 | head -1 || true
for setup in "${setups[@]}"; do
  for method in dcl dr alone; do
    echo "==> $setup $method"
    "$py" "$here/real_ardupilot_team.py" --ardurover "$ardurover" --setup "$setup" --method "$method" \
      --out "$out/$setup-$method" --json "$out/$setup-$method.json" | grep -E "without GNSS|team RMS|timeout|error" || true
  done
done
"$py" "$here/real_team_common.py" table "$out" ArduPilot "${setups[@]}"
