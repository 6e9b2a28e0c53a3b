"""How a per_device policy allocates on the CI scenario of tests/test_learning.py (V=12, U=3, T=20, LoRa PHY):
for `greedy`, `best_fixed` and a learner trained there, the EE and, for each ED's gain rank within its UAV
(0 = strongest), the histogram of its SF index and its mean TP index, over 16 episodes.

    python docs/history/measurements/ed_allocation_probe.py ALGO 'OVERRIDES_JSON' ITERATIONS
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))

import numpy as np  # noqa: E402
import ray  # noqa: E402
import test_learning as tl  # noqa: E402

from uavlora_rllib.algorithms.common import registry  # noqa: E402
from uavlora_rllib.baselines.policies import make_baseline  # noqa: E402
from uavlora_rllib.baselines.slots import Slots  # noqa: E402
from uavlora_rllib.sim.core import BatchCore  # noqa: E402

name, overrides, iters = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
cfg = tl.PER_DEVICE
EPISODES = 16


def allocation(label, policy) -> None:
    core = BatchCore(cfg, EPISODES)
    core.reset([tl.EVAL_SEED * 1000 + i for i in range(EPISODES)])
    policy.reset(core)
    rows, ee = [], 0.0
    for _ in range(cfg.episode_len):
        actions = policy.act(core)
        sf, tp, _ = core.allocations(actions)
        slots = Slots.of_core(core)
        gain = np.where(slots.associated, slots.g_serving, -1.0)
        for n in range(EPISODES):
            for u in range(cfg.n_uavs):
                eds = np.nonzero((slots.serving_idx[n] == u) & slots.associated[n])[0]
                for rank, v in enumerate(eds[np.argsort(-gain[n, eds])]):
                    rows.append((rank, sf[n, v], tp[n, v]))
        ee += core.step(actions).metrics["ee_sys"].mean()
    table = np.array(rows)
    print(f"{label}: EE {ee / cfg.episode_len:.1f}")
    for rank in range(int(table[:, 0].max()) + 1):
        sel = table[table[:, 0] == rank]
        hist = np.bincount(sel[:, 1], minlength=cfg.n_sf).tolist()
        print(
            f"  gain rank {rank}: {len(sel)} decisions, SF index histogram {hist}, mean TP index {sel[:, 2].mean():.2f}"
        )


allocation("greedy", make_baseline("greedy", cfg))
allocation("best_fixed", make_baseline("best_fixed", cfg, seed=0))
ray.init(num_cpus=1, include_dashboard=False)
entry = registry.get(name)
algo = entry.build(cfg, entry.hparams(overrides), registry.Resources(num_envs_per_env_runner=tl.ENVS), 0).build_algo()
for _ in range(iters):
    algo.train()
allocation(f"{name} after {iters} iterations", entry.greedy_policy(algo, cfg))
algo.stop()
