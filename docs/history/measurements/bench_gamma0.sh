#!/bin/bash
# BENCHMARKS.md "Training cost vs U": QMIX and VDN per_device at gamma 0 (the benchmark's discount), bench_train's
# env steps/s of OLD (a worktree of the commit before the target networks were skipped at gamma 0) and of this
# checkout, interleaved in three rounds (the order reversed in round 2), one JSON line per run appended to OUT.
#
#   git worktree add /tmp/wtprev <commit before>
#   bash docs/history/measurements/bench_gamma0.sh /tmp/wtprev bench_gamma0.jsonl
. "$(dirname "$0")/bench_args.sh"  # OLD, OUT, HERE, PY, checked
run() { # version algorithm U round
  local dir=$HERE line
  [ "$1" = old ] && dir=$OLD
  line=$(cd "$dir" && "$PY" -m uavlora_rllib.bench_train "$2" --n-eds 60 --n-uavs "$3" --iterations 3 --torch-threads 1 \
    --action-mode per_device --set gamma=0.0 --json 2>/dev/null | grep '^{' | tail -1)
  echo "{\"ver\":\"$1\",\"algo\":\"$2\",\"U\":$3,\"round\":$4,\"load\":\"$(cut -d' ' -f1 /proc/loadavg)\",\"res\":${line:-null}}" >>"$OUT"
}
for round in 1 2 3; do
  for case in "qmix 8" "vdn 8" "qmix 2"; do
    set -- $case
    versions="old new"; [ $round = 2 ] && versions="new old"
    for v in $versions; do run $v "$1" "$2" $round; done
  done
done
