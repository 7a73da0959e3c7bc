#!/bin/bash
# A live team of N nodes at real time on this computer (issue 33 item 5, issue 36): `cooploc sitl`
# runs N vehicles (the paper's three trajectories repeated on a grid, 400 m apart, every pair
# ranging at 1 Hz), one `cooploc node` per vehicle, signed (one team key), compact records, unicast
# peers on 127.0.0.1. After DUR seconds of vehicle time every node is stopped and the script
# prints, per node, the epochs applied, partial and skipped, the disagreements, the resends, the
# bytes sent and its CPU share; then one summary line.
#
#   bash tests/scripts/live-team.sh [N] [DUR]       (N=32, DUR=60 by default)
#   BIN=path/to/cooploc bash tests/scripts/live-team.sh 64 60
#   MULTICAST=1 bash tests/scripts/live-team.sh 32 60   (no peer lists: every node on the
#       default multicast group over loopback, `--multicast on --multicast-interface 127.0.0.1`)
#
# Not a CI test: it needs N+1 processes at real time (a 2-core machine saturates near 32 nodes).
set -u
cd "$(dirname "$0")/../.."
BIN=${BIN:-${CARGO_TARGET_DIR:-target}/release/cooploc}
N=${1:-32}
DUR=${2:-60}
D=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null; wait 2>/dev/null' EXIT

# The scenario: paper.toml up to its platforms, then N platforms, the paper's three trajectories
# in turn, each trio shifted on a grid.
awk -v n="$N" '
  /^\[\[platforms\]\]/ { k++; inplat=1 }
  !inplat { head = head $0 "\n"; next }
  { block[k] = block[k] $0 "\n" }
  END {
    sub(/name = "paper"/, "name = \"paper-" n "\"", head)
    printf "%s", head
    for (i = 1; i <= n; i++) {
      b = block[(i - 1) % 3 + 1]; trio = int((i - 1) / 3)
      dx = 400 * (trio % 4); dy = 400 * int(trio / 4)
      sub(/id = [0-9]+/, "id = " i, b)
      match(b, /start_ned_m = \[[^]]*\]/)
      split(substr(b, RSTART + 15, RLENGTH - 16), p, ",")
      b = substr(b, 1, RSTART - 1) sprintf("start_ned_m = [%.1f, %.1f, 0.0]", p[1] + dx, p[2] + dy) substr(b, RSTART + RLENGTH)
      printf "%s", b
    }
  }' sitl/scenarios/paper.toml > "$D/team.toml"

"$BIN" keygen "$D/team.key" > /dev/null || exit 1
"$BIN" sitl "$D/team.toml" --seed 1 --run 0 --schedule 1hz --speed 1 --base-port 0 --wait-for-peers --sim-state-hz 1 > "$D/sitl.out" 2> "$D/sitl.err" &
SP=$!
for k in $(seq 300); do [ "$(grep -c '^vehicle ' "$D/sitl.out")" -ge "$N" ] && break; sleep 0.1; done
PEERS=(); PIDS=()
MC=()
[ -n "${MULTICAST:-}" ] && MC=(--multicast on --multicast-interface 127.0.0.1)
for i in $(seq "$N"); do
  A=$(grep "^vehicle $i " "$D/sitl.out" | awk '{print $4}')
  "$BIN" node --scenario "$D/team.toml" --id "$i" --vehicle "udpout:$A" --init-from-run 1:0 --encoding compact \
    --team-key "$D/team.key" --signing-state "$D/signing$i" "${PEERS[@]}" "${MC[@]}" > "$D/node$i.out" 2> "$D/node$i.err" &
  PIDS+=($!)
  for k in $(seq 100); do grep -q "coop udp" "$D/node$i.out" 2>/dev/null && break; sleep 0.1; done
  [ -z "${MULTICAST:-}" ] && PEERS+=(--peer "$(grep "coop udp" "$D/node$i.out" | awk '{print $NF}')")
done
TCK=$(getconf CLK_TCK)
cpu() { awk '{print $14+$15}' "/proc/$1/stat"; }
sleep 5
declare -A C0
for p in "${PIDS[@]}" $SP; do C0[$p]=$(cpu "$p"); done
T0=$(date +%s.%N)
sleep "$DUR"
T1=$(date +%s.%N)
declare -A SHARE
for p in "${PIDS[@]}" $SP; do SHARE[$p]=$(awk -v a="$(cpu "$p")" -v b="${C0[$p]}" -v k="$TCK" -v t0="$T0" -v t1="$T1" 'BEGIN { printf "%.2f", (a - b) * 100 / k / (t1 - t0) }'); done
kill -INT "${PIDS[@]}"
wait "${PIDS[@]}"
kill -INT $SP; wait $SP
echo "live team: $N nodes, $DUR s measured, $(nproc) cores; sitl ${SHARE[$SP]}% of a core"
echo "| node | t s | applied | partial | skipped | disagreements | store mismatches | heals | resends | limited | B/s sent | CPU % |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|"
i=0
for p in "${PIDS[@]}"; do
  i=$((i + 1)); f="$D/node$i.out"
  st=$(grep "^node $i stats" "$f")
  g() { echo "$st" | grep -o "$1: [0-9]*" | awk '{print $2}'; }
  t=$(grep "^node $i done" "$f" | awk '{print $5 / 1e6}')
  bs=$(grep "^node $i coop_tx" "$f" | grep -o "[0-9]* B/s sent" | awk '{print $1}')
  echo "| $i | $t | $(g epochs_applied) | $(g epochs_partial) | $(g epochs_skipped) | $(g epoch_disagreements) | $(g store_mismatches) | $(g heals) | $(g records_resent) | $(g resends_limited) | $bs | ${SHARE[$p]} |"
done | tee "$D/table.md"
# Epochs due: those at 1 s, 2 s, ... up to half a second before the node stopped.
awk -F'|' '{ t = $3 + 0; due = int(t - 0.5); if (due < 1) next; a = $4 / due; if (min == "" || a < min) min = a;
  dis += $7 + $8; cpu += $13; bs += $12; n++ }
  END { printf "summary: %d nodes, lowest share of due epochs applied %.3f, disagreements + store mismatches %d, mean CPU %.2f%% of a core, mean %.0f B/s sent per node\n", n, min, dis, cpu / n, bs / n }' "$D/table.md"
echo "outputs in $D"
