# Sourced by the bench_*.sh scripts here that compare this checkout with one other: their two arguments
# OLD_CHECKOUT OUT.jsonl and the interpreter PY, checked before any run (bench_checks.sh).
# Sets OLD, OUT, HERE (this checkout) and PY (absolute, since the runs cd into each checkout).
. "$(dirname "${BASH_SOURCE[0]}")/bench_checks.sh"
[ $# -eq 2 ] || bench_fail "usage: $NAME OLD_CHECKOUT OUT.jsonl"
OLD=$1 OUT=$2
bench_python
[ -d "$OLD" ] || bench_fail "OLD_CHECKOUT: no directory $OLD"
[ -d "$OLD/uavlora_rllib" ] || bench_fail "OLD_CHECKOUT: $OLD is not a checkout of this project (no uavlora_rllib/)"
bench_out "$OUT"
