#!/bin/bash
# BENCHMARKS.md "Training cost vs U", COMA's critic cost: bench_train's env steps/s of COMA per_uav at V=60/U=8,
# this checkout against OLD (a worktree of the issue's baseline commit), in the order this, old, old, this; one JSON
# line per run appended to OUT.
#
#   git worktree add /tmp/wt6f 6f5d51a
#   PY=$(pwd)/.venv/bin/python bash docs/history/measurements/bench_coma_pair.sh /tmp/wt6f bench_coma_pair.jsonl
. "$(dirname "$0")/bench_args.sh"  # OLD, OUT, HERE, PY, checked
for v in this old old this; do
  dir=$HERE; [ $v = old ] && dir=$OLD
  load=$(cut -d' ' -f1 /proc/loadavg)
  line=$(cd "$dir" && "$PY" -m uavlora_rllib.bench_train coma --n-eds 60 --n-uavs 8 --iterations 2 --torch-threads 1 \
    --num-cpus 1 --json 2>/dev/null | grep '^{' | tail -1)
  echo "{\"ver\":\"$v\",\"load\":\"$load\",\"t\":\"$(date +%T)\",\"res\":${line:-null}}" >>"$OUT"
done
