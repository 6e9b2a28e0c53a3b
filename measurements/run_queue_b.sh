#!/bin/bash
# Queue B (after queue A): VDN with one agent net per UAV at V=60/U=4, then a MAPPO candidate at U=8.
cd "$(dirname "$0")/.." && export PYTHONPATH=$PWD RAY_TMPDIR=/tmp/ray_learn
while kill -0 "$(cat /tmp/learn_queue_a.pid)" 2>/dev/null; do sleep 10; done
P=/work/main/.venv/bin/python
O=measurements/learning.jsonl
$P -m uavlora_rllib.bench_learn --scenarios 60x4 --learners vdn --set vdn.updates_per_iteration=16 --set vdn.share_agent_net=false --env-steps 100000 --tag "updates_per_iteration=16, share_agent_net=false" --out $O
$P -m uavlora_rllib.bench_learn --scenarios 60x8 --learners mappo --set mappo.share_actor=false --set mappo.num_minibatches=8 --env-steps 100000 --tag "share_actor=false, num_minibatches=8" --out $O
