#!/bin/bash
# BENCHMARKS.md "Training cost vs U": bench_train's env steps/s of several checkouts, interleaved in two rounds
# (the order reversed in round 2), one JSON line per run appended to OUT.
#
#   git worktree add /tmp/wt6f 6f5d51a; git worktree add /tmp/wtprev PREV
#   PY=$(pwd)/.venv/bin/python bash docs/history/measurements/bench_versions.sh out.jsonl old=/tmp/wt6f prev=/tmp/wtprev new=.
#
# NAME=CHECKOUT@bfloat16 runs that checkout with --learner-precision bfloat16 (the row's "precision"; @float32 and
# no suffix run it without the flag).
#
# CASES (env, optional): "algo U mode [V]" cases separated by commas (V: EDs, 60 if left out); a case skips a
# checkout named old for qmix/vdn per_device (6f5d51a has no per_device form of them).
. "$(dirname "$0")/bench_checks.sh"  # NAME, HERE, bench_fail, bench_python (PY), bench_out
[ $# -ge 2 ] || bench_fail "usage: $NAME OUT.jsonl NAME=CHECKOUT..."
OUT=$1; shift
bench_python
split() { # NAME=CHECKOUT[@float32|@bfloat16] -> dir, precision (only those two suffixes: a path may hold an @)
  dir=${1#*=} precision=float32
  case $dir in *@float32 | *@bfloat16) precision=${dir##*@} dir=${dir%@*} ;; esac
}
for spec in "$@"; do
  split "$spec"
  [ "$dir" != "$spec" ] && [ -d "$dir/uavlora_rllib" ] || bench_fail "NAME=CHECKOUT: $spec is not NAME=a checkout of this project"
done
bench_out "$OUT"
CASES=${CASES:-"mappo 8 per_device,qmix 8 per_device,mappo 8 per_uav,qmix 8 per_uav,mappo 2 per_device,qmix 2 per_uav"}
run() { # name NAME=CHECKOUT[@precision] algo U mode round V
  local line dir precision extra=""
  split "$2"
  # the flag only where asked: checkouts from before it (6f5d51a) run float32 without it
  [ "$precision" = bfloat16 ] && extra="--learner-precision bfloat16"
  line=$(cd "$dir" && "$PY" -m uavlora_rllib.bench_train "$3" --n-eds "$7" --n-uavs "$4" --iterations 3 --torch-threads 1 \
    --action-mode "$5" $extra --json 2>/dev/null | grep '^{' | tail -1)
  echo "{\"ver\":\"$1\",\"commit\":\"$(git -C "$dir" rev-parse --short HEAD 2>/dev/null || echo none)\",\"precision\":\"$precision\",\"algo\":\"$3\",\"V\":$7,\"U\":$4,\"mode\":\"$5\",\"round\":$6,\"load\":\"$(cut -d' ' -f1 /proc/loadavg)\",\"res\":${line:-null}}" >>"$OUT"
}
IFS=, read -ra cases <<<"$CASES"
forward=("$@") backward=()
for ((i = $#; i >= 1; i--)); do backward+=("${!i}"); done
for round in 1 2; do
  specs=("${forward[@]}")
  [ $round = 2 ] && specs=("${backward[@]}")
  for case in "${cases[@]}"; do
    set -- $case
    for spec in "${specs[@]}"; do
      name=${spec%%=*}
      [ "$name" = old ] && [ "$3" = per_device ] && [ "$1" != mappo ] && [ "$1" != ippo ] && continue
      run "$name" "$spec" "$1" "$2" "$3" $round "${4:-60}"
    done
  done
done
