#!/bin/bash
# Runs sitl at real time with three nodes for DUR seconds and prints each node's CPU share.
cd "$(dirname "$0")/../.."
BIN=${BIN:-${CARGO_TARGET_DIR:-target}/release/cooploc}
DUR=${1:-60}

D=$(mktemp -d)
$BIN sitl sitl/scenarios/paper.toml --seed 1 --run 0 --schedule 1hz --speed 1 --base-port 0 --wait-for-peers --sim-state-hz 1 > $D/sitl.out 2>$D/sitl.err &
SP=$!
for i in 1 2 3; do for k in $(seq 100); do grep -q "^vehicle $i " $D/sitl.out 2>/dev/null && break; sleep 0.1; done; done
PEERS=(); PIDS=()
for i in 1 2 3; do
  A=$(grep "^vehicle $i " $D/sitl.out | awk '{print $NF}')
  $BIN node --scenario sitl/scenarios/paper.toml --id $i --vehicle udpout:$A --init-from-run 1:0 "${PEERS[@]}" > $D/node$i.out 2>$D/node$i.err &
  PIDS+=($!)
  for k in $(seq 100); do grep -q "coop udp" $D/node$i.out 2>/dev/null && break; sleep 0.1; done
  PEERS+=(--peer $(grep "coop udp" $D/node$i.out | awk '{print $NF}'))
done
TCK=$(getconf CLK_TCK)
cpu() { awk '{print $14+$15}' /proc/$1/stat; }
sleep 5
declare -A C0; for p in "${PIDS[@]}" $SP; do C0[$p]=$(cpu $p); done
T0=$(date +%s.%N)
sleep $DUR
T1=$(date +%s.%N)
for p in "${PIDS[@]}" $SP; do C1=$(cpu $p); echo "pid $p cpu share $(echo "scale=4; ($C1 - ${C0[$p]}) / $TCK / ($T1 - $T0) * 100" | bc) %"; done
kill -INT "${PIDS[@]}" $SP; wait
grep -h "done" $D/node*.out | cut -c1-200
rm -rf $D
