#!/bin/bash
# BENCHMARKS.md "Training cost vs U", COMA's critic cost: bench_train's env steps/s of COMA per_uav at V=60/U=8,
# this checkout against OLD (a worktree of the issue's baseline commit), in the order this, old, old, this; one JSON
# line per run appended to OUT.
#
#   git worktree add /tmp/wt6f 6f5d51a
#   PY=$(pwd)/.venv/bin/python bash docs/history/measurements/bench_coma_pair.sh /tmp/wt6f bench_coma_pair.jsonl
set -u
# bad arguments stop here with one line and exit 2, before any run (a run cannot report them: its row is null)
[ $# -eq 2 ] || { echo "usage: bench_coma_pair.sh OLD_CHECKOUT OUT.jsonl" >&2; exit 2; }
OLD=$1 OUT=$2 HERE=$(pwd) PY=${PY:-$(pwd)/.venv/bin/python}
[ -f "$PY" ] && [ -x "$PY" ] || { echo "no python at $PY: set PY=/path/to/.venv/bin/python" >&2; exit 2; }
PY=$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY")  # absolute: the runs cd into each checkout
[ -d "$OLD" ] || { echo "OLD_CHECKOUT: no directory $OLD" >&2; exit 2; }
[ -d "$OLD/uavlora_rllib" ] || { echo "OLD_CHECKOUT: $OLD is not a checkout of this project (no uavlora_rllib/)" >&2; exit 2; }
[ -d "$HERE/uavlora_rllib" ] || { echo "run from this project's root (no uavlora_rllib/ in $HERE)" >&2; exit 2; }
{ : >>"$OUT"; } 2>/dev/null || { echo "OUT.jsonl: cannot append to $OUT" >&2; exit 2; }
for v in this old old this; do
  dir=$HERE; [ $v = old ] && dir=$OLD
  load=$(cut -d' ' -f1 /proc/loadavg)
  line=$(cd "$dir" && "$PY" -m uavlora_rllib.bench_train coma --n-eds 60 --n-uavs 8 --iterations 2 --torch-threads 1 \
    --num-cpus 1 --json 2>/dev/null | grep '^{' | tail -1)
  echo "{\"ver\":\"$v\",\"load\":\"$load\",\"t\":\"$(date +%T)\",\"res\":${line:-null}}" >>"$OUT"
done
