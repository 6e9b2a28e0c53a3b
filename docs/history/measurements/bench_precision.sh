#!/bin/bash
# docs/history/benchmarks-2026.md "Training cost vs U, float32 and bfloat16": bench_train's env steps/s of OLD (a worktree of the issue's baseline commit),
# this checkout in float32 and this checkout with bfloat16 products, interleaved in two rounds (the order reversed in
# round 2), one JSON line per run appended to OUT.
#
#   git worktree add /tmp/wt6f 6f5d51a
#   PY=$(pwd)/.venv/bin/python bash docs/history/measurements/bench_precision.sh /tmp/wt6f bench_precision.jsonl
. "$(dirname "$0")/bench_args.sh"  # OLD, OUT, HERE, PY, checked
run() { # version algorithm U mode round
  local dir=$HERE extra="" line
  [ "$1" = old ] && dir=$OLD
  [ "$1" = bf16 ] && extra="--learner-precision bfloat16"
  line=$(cd "$dir" && "$PY" -m uavlora_rllib.bench_train "$2" --n-eds 60 --n-uavs "$3" --iterations 3 --torch-threads 1 \
    --action-mode "$4" $extra --json 2>/dev/null | grep '^{' | tail -1)
  echo "{\"ver\":\"$1\",\"algo\":\"$2\",\"U\":$3,\"mode\":\"$4\",\"round\":$5,\"load\":\"$(cut -d' ' -f1 /proc/loadavg)\",\"res\":${line:-null}}" >>"$OUT"
}
for round in 1 2; do
  for case in "mappo 8 per_uav" "qmix 8 per_uav" "mappo 2 per_uav" "qmix 2 per_uav" "mappo 8 per_device" "qmix 8 per_device"; do
    set -- $case
    versions="old f32 bf16"; [ $round = 2 ] && versions="bf16 f32 old"
    for v in $versions; do
      [ $v = old ] && [ "$1 $3" = "qmix per_device" ] && continue  # 6f5d51a's QMIX has no per_device form
      run $v "$1" "$2" "$3" $round
    done
  done
done
