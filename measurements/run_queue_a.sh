#!/bin/bash
# Queue A: candidate defaults at V=60/U=4 (100k env steps), then V=10/U=2 (60k), one trial at a time.
cd "$(dirname "$0")/.." && export PYTHONPATH=$PWD RAY_TMPDIR=/tmp/ray_learn
P=/work/main/.venv/bin/python
O=measurements/learning.jsonl
$P -m uavlora_rllib.bench_learn --scenarios 60x4 --learners ippo --set ippo.share_actor=false --env-steps 100000 --tag "share_actor=false" --out $O
$P -m uavlora_rllib.bench_learn --scenarios 60x4 --learners vdn --set vdn.updates_per_iteration=16 --env-steps 100000 --tag "updates_per_iteration=16" --out $O
$P -m uavlora_rllib.bench_learn --scenarios 60x4 --learners coma --env-steps 100000 --tag "defaults" --out $O
$P -m uavlora_rllib.bench_learn --scenarios 10x2 --learners mappo --set mappo.share_actor=false --env-steps 60000 --eval-every 10000 --tag "share_actor=false" --out $O
$P -m uavlora_rllib.bench_learn --scenarios 10x2 --learners mappo --action-mode per_device --set mappo.share_actor=false --env-steps 60000 --eval-every 10000 --tag "per_device, share_actor=false" --out $O
