# Sourced by bench_args.sh and bench_versions.sh: the checks every bench script runs before any run (a run cannot
# report a bad input: its row is null), each ending in one line and exit 2. Sets NAME, HERE (this checkout) and,
# through bench_python, PY (absolute, since the runs cd into each checkout).
set -u
NAME=$(basename "$0") HERE=$(pwd)
bench_fail() { echo "$1" >&2; exit 2; }
bench_python() {
  PY=${PY:-$HERE/.venv/bin/python}
  [ -f "$PY" ] && [ -x "$PY" ] || bench_fail "no python at $PY: set PY=/path/to/.venv/bin/python"
  PY=$(cd "$(dirname "$PY")" && pwd)/$(basename "$PY")
  [ -d "$HERE/uavlora_rllib" ] || bench_fail "run from this project's root (no uavlora_rllib/ in $HERE)"
}
bench_out() { { : >>"$1"; } 2>/dev/null || bench_fail "OUT.jsonl: cannot append to $1"; }
