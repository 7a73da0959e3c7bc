#!/usr/bin/env bash
# Three rovers on the real PX4 firmware, navigating without GNSS: runs tests/scripts/real_px4_team.py
# for each set-up and method and prints its table. It runs a PX4 SIH SITL binary you built
# yourself (PX4's px4_sitl_sih target); it builds nothing.
#
#   bash tests/scripts/real-px4-team.sh /path/to/PX4-Autopilot/build/px4_sitl_sih/bin/px4 [SETUP...]
#
# SETUP: nognss, gnss-lost (default: both). Each run takes about 4 minutes of real time (three SIH
# instances at 1x, three nodes); results go to $OUT (default /tmp/real-px4-team). Needs pymavlink
# (tests/requirements.txt; COOPLOC_PYTHON names the interpreter) and a cooploc binary (COOPLOC_BIN,
# default target/release/cooploc: cargo build --release).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$here/../.." && pwd)"
px4="${1:?usage: real-px4-team.sh PX4_BINARY [SETUP...]}"
shift
setups=("$@")
[ ${#setups[@]} -gt 0 ] || setups=(nognss gnss-lost)
py="${COOPLOC_PYTHON:-python3}"
out="${OUT:-/tmp/real-px4-team}"
cooploc="${COOPLOC_BIN:-$root/target/release/cooploc}"
mkdir -p "$out"
[ -x "$cooploc" ] || { echo "error: build cooploc first (cargo build --release) or name it in COOPLOC_BIN" >&2; exit 1; }
"$cooploc" --version 2>/dev/null || true
for setup in "${setups[@]}"; do
  for method in dcl dr alone; do
    echo "==> $setup $method"
    "$py" "$here/real_px4_team.py" --px4 "$px4" --cooploc "$cooploc" --setup "$setup" --method "$method" \
      --out "$out/$setup-$method" --json "$out/$setup-$method.json" | grep -E "without GNSS|team RMS|timeout|error|EKF2 vision|node:" || true
  done
done
"$py" "$here/real_team_common.py" table "$out" PX4 "${setups[@]}"
"$py" - "$here" "$out" "${setups[@]}" <<'PY'
import sys
sys.path.insert(0, sys.argv[1])
from real_team_common import load_runs
out, setups = sys.argv[2], sys.argv[3:]
for s in setups:
    runs = load_runs(out, s)
    for m in ("dcl", "dr"):
        if m in runs:
            figs = [r.get("node", {}) for r in runs[m]["rovers"]]
            print("%s %s nodes: epochs applied %s, partial %s, skipped %s, disagreements %s, vehicle_lost %s" % (
                s, m, [f.get("epochs_applied") for f in figs], [f.get("epochs_partial") for f in figs],
                [f.get("epochs_skipped") for f in figs], [f.get("epoch_disagreements") for f in figs],
                [f.get("vehicle_lost") for f in figs]))
            print("%s %s nodes' own estimate RMS (m): %s; ranges gated %s" % (
                s, m, ["%.2f" % r.get("node_own_rms_m", float("nan")) for r in runs[m]["rovers"]], [f.get("ranges_gated") for f in figs]))
    for m in ("dcl", "dr", "alone"):
        if m in runs:
            print("%s %s EKF2 (share of its 1 Hz status during the mission: EV position / velocity / yaw fused, yaw aligned): %s; sim %s x real time" % (
                s, m, ["%s/%s/%s/%s" % tuple((r.get("ekf2_fusion") or {}).get(k, "?") for k in ("cs_ev_pos", "cs_ev_vel", "cs_ev_yaw", "cs_yaw_align"))
                       for r in runs[m]["rovers"]], ["%.3f" % r.get("sim_rate", float("nan")) for r in runs[m]["rovers"]]))
PY
