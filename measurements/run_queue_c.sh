#!/bin/bash
# Queue C (after queue B): the value-decomposition candidate (one agent net per UAV, 16 updates) at U=8.
cd "$(dirname "$0")/.." && export PYTHONPATH=$PWD RAY_TMPDIR=/tmp/ray_learn
while kill -0 "$(cat /tmp/learn_queue_b.pid)" 2>/dev/null; do sleep 10; done
P=/work/main/.venv/bin/python
O=measurements/learning.jsonl
for L in qmix vdn; do
$P -m uavlora_rllib.bench_learn --scenarios 60x8 --learners $L --set $L.updates_per_iteration=16 --set $L.share_agent_net=false --env-steps 100000 --tag "updates_per_iteration=16, share_agent_net=false" --out $O
done
