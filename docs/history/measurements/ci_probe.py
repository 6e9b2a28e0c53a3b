"""A learner's curve on the per_device CI scenario of tests/test_learning.py (V=12, U=3, T=20, LoRa PHY):
train with the given overrides and print the greedy EE on the test's evaluation episodes, as a multiple of
the open-loop best_fixed, every K iterations. What the test checks at one budget, at several.

    python docs/history/measurements/ci_probe.py ALGO 'OVERRIDES_JSON' ITERATIONS EVERY ['REWARD_WEIGHTS_JSON']

e.g. python docs/history/measurements/ci_probe.py mappo '{"share_actor": false, "lr": 2e-3, "num_epochs": 8,
"num_minibatches": 2, "batch_episodes": 8, "gamma": 0.0, "actor_heads": "shared"}' 160 20
(REWARD_WEIGHTS_JSON, e.g. '{"w1": 4e-4}', replaces the scenario's reward weights; LEARNER_PRECISION=bfloat16 in
the environment trains with resources.learner_precision bfloat16.)
"""

import dataclasses
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))

import ray  # noqa: E402
import test_learning as tl  # noqa: E402

from uavlora_rllib.algorithms.common import registry  # noqa: E402
from uavlora_rllib.baselines.policies import make_baseline  # noqa: E402
from uavlora_rllib.experiment.evaluation import run_episodes  # noqa: E402
from uavlora_rllib.sim.scenario import RewardWeights  # noqa: E402

name, overrides, iters, every = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
cfg = tl.PER_DEVICE
if len(sys.argv) > 5:
    cfg = dataclasses.replace(cfg, reward=RewardWeights(**json.loads(sys.argv[5])))
bf = run_episodes(make_baseline("best_fixed", cfg, seed=0), cfg, tl.EVAL_EPISODES, tl.EVAL_SEED).mean("ee_sys_mean")
print(f"best_fixed {bf:.1f}", flush=True)
ray.init(num_cpus=1, include_dashboard=False)
entry = registry.get(name)
resources = registry.Resources(
    num_envs_per_env_runner=tl.ENVS, learner_precision=os.environ.get("LEARNER_PRECISION", "float32")
)
algo = entry.build(cfg, entry.hparams(overrides), resources, 0).build_algo()
t0 = time.perf_counter()
for i in range(1, iters + 1):
    algo.train()
    if i % every == 0:
        ee = run_episodes(entry.greedy_policy(algo, cfg), cfg, tl.EVAL_EPISODES, tl.EVAL_SEED).mean("ee_sys_mean")
        print(f"{name} it {i}: {ee:.1f} = {ee / bf:.3f}x best_fixed ({time.perf_counter() - t0:.0f} s)", flush=True)
algo.stop()
