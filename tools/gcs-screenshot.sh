#!/bin/bash
# The ground station's page with the team's health, as a user sees it, for docs/ground-station.md:
# `cooploc sitl` (paper scenario, real time), three nodes with the radio encoding (compact),
# `cooploc gcs` with the vehicles' links and a SiK radio's capacity (5,400 B/s); after 30 s node 3 is killed and
# restarted from its vehicle's SIM_STATE (a companion reboot): the team disagrees, asks for a
# store and heals. Headless Chromium then takes the screenshot.
# Usage: tools/gcs-screenshot.sh OUT.png   (needs target/release/cooploc and chromium)
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${BIN:-${CARGO_TARGET_DIR:-target}/release/cooploc}
OUT=${1:?usage: tools/gcs-screenshot.sh OUT.png}
D=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$D"' EXIT

wait_for() { for _ in $(seq 300); do grep -q "$2" "$1" 2>/dev/null && return 0; sleep 0.1; done; echo "no '$2' in $1" >&2; exit 1; }

"$BIN" sitl sitl/scenarios/paper.toml --seed 1 --run 0 --speed 1 --base-port 0 --wait-for-peers --sim-state-hz 5 > "$D/sitl.out" 2> "$D/sitl.err" &
for i in 1 2 3; do wait_for "$D/sitl.out" "^vehicle $i "; done
addr() { grep "^vehicle $1 " "$D/sitl.out" | awk '{print $NF}'; }

KEY="$D/team.key"
"$BIN" keygen "$KEY" > /dev/null
GCS_ARGS=(--team-key "$KEY")
for i in 1 2 3; do GCS_ARGS+=(--vehicle "$i=udpout:$(addr $i)"); done
"$BIN" gcs --coop 127.0.0.1:0 --http 127.0.0.1:0 --no-foxglove --link-capacity 5400 "${GCS_ARGS[@]}" > "$D/gcs.out" 2> "$D/gcs.err" &
wait_for "$D/gcs.out" "gcs http "
HTTP=$(grep "gcs http " "$D/gcs.out" | awk '{print $NF}')
GCS=$(grep "gcs coop udp " "$D/gcs.out" | awk '{print $NF}')

PEERS=(--peer "$GCS")
start_node() { # id, extra args...
  local i=$1; shift
  "$BIN" node --scenario sitl/scenarios/paper.toml --id "$i" --vehicle "udpout:$(addr "$i")" --encoding compact --team-key "$KEY" "$@" "${PEERS[@]}" > "$D/node$i.out" 2> "$D/node$i.err" &
  echo $! > "$D/node$i.pid"
  wait_for "$D/node$i.out" "coop udp"
}
for i in 1 2 3; do
  start_node "$i" --init-from-run 1:0
  PEERS+=(--peer "$(grep "coop udp" "$D/node$i.out" | awk '{print $NF}')")
done

sleep 30
kill "$(cat "$D/node3.pid")"
sleep 1
start_node 3   # from the vehicle's SIM_STATE, as a rebooted companion
sleep 30

chromium --headless --no-sandbox --disable-gpu --no-first-run --disable-background-networking \
  --hide-scrollbars --virtual-time-budget=4000 --window-size=1400,1250 \
  --user-data-dir="$D/chromium" --screenshot="$OUT" "$HTTP" > /dev/null 2>&1
curl -s "${HTTP}api/state" > "$D/state.json" || true
python3 - "$D/state.json" <<'EOF'
import json, sys
h = json.load(open(sys.argv[1]))["health"]
print("health: disagreements %d heals %d unhealed_since %s last_epoch %s load %.0f%%" % (
    h["disagreements"], h["heals"], h["unhealed_since"], h["last_epoch"], h["team_load_pct"] or 0))
for n in h["nodes"]:
    print("  %s: %.2f Hz, %.0f B/s (%.0f%% of %.0f), %s, outvoted %d, store asked %d" % (
        n["name"], n["estimate_rate_hz"] or 0, n["bytes_per_s"], n["budget_used_pct"] or 0,
        n["budget_bytes_per_s"] or 0, n["signing"], n["outvoted"], n["store_wanted"]))
EOF
echo "screenshot: $OUT"
