#!/bin/bash
# usage: speedrun.sh SPEED  -> prints per node imu/odometer/dropped/applied/partial and wall time
cd "$(dirname "$0")/../.."
BIN=${BIN:-${CARGO_TARGET_DIR:-target}/release/cooploc}
SPEED=$1

D=$(mktemp -d)
$BIN sitl sitl/scenarios/paper.toml --seed 1 --run 0 --schedule 1hz --speed $SPEED --base-port 0 --wait-for-peers --sim-state-hz 1 > $D/sitl.out 2>$D/sitl.err &
SP=$!
for i in 1 2 3; do for k in $(seq 100); do grep -q "^vehicle $i " $D/sitl.out 2>/dev/null && break; sleep 0.1; done; done
PEERS=()
for i in 1 2 3; do
  A=$(grep "^vehicle $i " $D/sitl.out | awk '{print $NF}')
  $BIN node --scenario sitl/scenarios/paper.toml --id $i --vehicle udpout:$A --init-from-run 1:0 --idle-exit-s 1.5 "${PEERS[@]}" > $D/node$i.out 2>$D/node$i.err &
  for k in $(seq 100); do grep -q "coop udp" $D/node$i.out 2>/dev/null && break; sleep 0.1; done
  PEERS+=(--peer $(grep "coop udp" $D/node$i.out | awk '{print $NF}'))
done
START=$(date +%s.%N)
wait $SP
END=$(date +%s.%N)
wait
echo "speed $SPEED sitl wall $(echo "$END - $START" | bc) s"
for i in 1 2 3; do grep "done" $D/node$i.out | grep -o "dropped_inputs [0-9]* vehicle_frames [0-9]* vehicle_lost [0-9]*" | sed "s/^/node $i /"; grep "stats" $D/node$i.out | grep -oE "(imu|odometer|imu_rejected|odometer_rejected|records_resent|epochs_applied|epochs_partial|epoch_disagreements): [0-9]+" | tr '\n' ' ' | sed "s/^/node $i /"; echo; done
rm -rf $D
