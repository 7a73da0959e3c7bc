#!/bin/bash
# A restart the team must not wait for, on real processes (issue 33; docs/robustness.md, "The
# phase of a restart"): `cooploc sitl` (the paper scenario at 5x) and three nodes on loopback, node
# 3 with --state-file; node 3 is killed (SIGKILL) 20 s of wall time in and started again with the
# same arguments 1 s later, so it misses about five epochs. Prints, per node, the epochs applied
# and partial, the longest wait from a broadcast to its joint update, and the epochs run without
# waiting for the restarted node (signed only), then how node 3 restored its state.
#
#   bash tests/scripts/restart-wait.sh signed|insecure [BASE_PORT]    (about 85 s)
#   BIN=path/to/cooploc bash tests/scripts/restart-wait.sh signed
#
# Not a CI test: the kill falls wherever the wall clock puts it.
set -u
cd "$(dirname "$0")/../.."
BIN=${BIN:-${CARGO_TARGET_DIR:-target}/release/cooploc}
MODE=${1:?signed or insecure}; B=${2:-24100}; D=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null; rm -rf "$D"' EXIT
echo "the passphrase of this run" > $D/team.key
$BIN sitl sitl/scenarios/paper.toml --speed 5 --base-port 0 --wait-for-peers > $D/sitl.log 2>&1 &
SITL=$!
for i in $(seq 50); do [ "$(grep -c '^vehicle ' $D/sitl.log)" -ge 3 ] && break; sleep 0.1; done
declare -A ADDR
while read -r _ id rest; do ADDR[$id]=$(echo "$rest" | awk '{print $NF}'); done < <(grep '^vehicle ' $D/sitl.log)
args() {
  local id=$1; local a=(node --scenario sitl/scenarios/paper.toml --id $id --vehicle udpout:${ADDR[$id]} --coop-bind 127.0.0.1:$((B+id)) --idle-exit-s 3)
  for j in 1 2 3; do [ $j != $id ] && a+=(--peer 127.0.0.1:$((B+j))); done
  if [ $MODE = signed ]; then a+=(--team-key $D/team.key); else a+=(--insecure); fi
  [ $id = 3 ] && a+=(--state-file $D/n3.state)
  echo "${a[@]}"
}
for id in 1 2 3; do $BIN $(args $id) > $D/n$id.log 2>&1 & eval P$id=$!; done
sleep 20; kill -9 $P3; sleep 1
$BIN $(args 3) > $D/n3b.log 2>&1 & P3=$!
wait $P1 $P2 $P3; kill $SITL 2>/dev/null
for f in n1 n2 n3b; do
  echo "$MODE $f: $(grep -o 'epochs_applied: [0-9]*, epochs_partial: [0-9]*, longest_wait_us: [0-9]*, epochs_not_waited: [0-9]*' $D/$f.log) | $(grep -o 'done:.\{0,90\}' $D/$f.log | head -1)"
done
grep -h "restored\|saved state\|start state" $D/n3b.log | head -3
exit 0
