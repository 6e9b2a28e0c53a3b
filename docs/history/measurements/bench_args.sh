# Sourced by the bench_*.sh scripts here: their two arguments OLD_CHECKOUT OUT.jsonl and the interpreter PY,
# checked before any run (a run cannot report a bad one: its row is null), each with one line and exit 2.
# Sets OLD, OUT, HERE (this checkout) and PY (absolute, since the runs cd into each checkout).
set -u
NAME=$(basename "$0")
[ $# -eq 2 ] || { echo "usage: $NAME OLD_CHECKOUT OUT.jsonl" >&2; exit 2; }
OLD=$1 OUT=$2 HERE=$(pwd) PY=${PY:-$(pwd)/.venv/bin/python}
[ -f "$PY" ] && [ -x "$PY" ] || { echo "no python at $PY: set PY=/path/to/.venv/bin/python" >&2; exit 2; }
PY=$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY")
[ -d "$OLD" ] || { echo "OLD_CHECKOUT: no directory $OLD" >&2; exit 2; }
[ -d "$OLD/uavlora_rllib" ] || { echo "OLD_CHECKOUT: $OLD is not a checkout of this project (no uavlora_rllib/)" >&2; exit 2; }
[ -d "$HERE/uavlora_rllib" ] || { echo "run from this project's root (no uavlora_rllib/ in $HERE)" >&2; exit 2; }
{ : >>"$OUT"; } 2>/dev/null || { echo "OUT.jsonl: cannot append to $OUT" >&2; exit 2; }
