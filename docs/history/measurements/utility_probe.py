"""Do a trained QMIX/VDN's per-ED branch utilities know what one ED's (SF, TP) is worth? (issue 23)

On the per_device CI scenario of tests/test_learning.py, train QMIX or VDN (as ci_probe.py does), then play its
greedy actions on the test's evaluation episodes and, at every slot, compare each served ED's 30 slot utilities
Q_k(o_u, .) with the simulator's exact reward for each of that ED's (SF, TP) pairs, the others held at the
policy's action (baselines/slots.py AllocationScorer.score_ed_moves). Printed, averaged over served EDs:
  corr:      Pearson correlation of the utilities with the exact values over the ED's 30 pairs
  same:      share of EDs whose utility argmax is the exact best pair (chance 1/30)
  rank:      how many pairs the utilities put above the exact best one
  loss:      exact reward given up by the utility argmax against the best pair [reward units]

    python docs/history/measurements/utility_probe.py ALGO 'OVERRIDES_JSON' ITERATIONS
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch
from ray.rllib.core.columns import Columns

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))

import test_learning as tl  # noqa: E402
from br_probe import slot_settings  # noqa: E402

from uavlora_rllib.baselines.slots import AllocationScorer, Slots  # noqa: E402
from uavlora_rllib.experiment.evaluation import run_episodes  # noqa: E402


class UtilityProbe:
    """Wraps a trained QMIX/VDN ModulePolicy: plays its greedy actions and scores its slot utilities."""

    def __init__(self, policy, cfg):
        self.policy, self.cfg = policy, cfg
        self.stats: dict[str, list] = {"corr": [], "same": [], "rank": [], "loss": []}

    def reset(self, core):
        self.policy.reset(core)

    def act(self, core):
        pol = self.policy
        if pol.state is None or next(iter(pol.state.values())).shape[0] != core.n:
            pol.reset(core)
        obs = torch.as_tensor(np.clip(core.obs, -1.0, 1.0), dtype=torch.float32).unsqueeze(1)  # as ModulePolicy.act
        with torch.no_grad():  # the utilities behind this slot's greedy action (same obs, same GRU state)
            (slot_q, _), _ = pol.module._step({Columns.OBS: obs, Columns.STATE_IN: pol.state})
        actions = np.asarray(pol.act(core))
        slots, links = Slots.of_core(core), core.links
        n, v = slots.g_serving.shape
        setting = slot_settings(core, actions, self.cfg)
        scorer = AllocationScorer(self.cfg, core.tables, "reward")
        exact, _ = scorer.score_ed_moves(
            setting, actions[:, :, -1].astype(np.int64), slots, np.broadcast_to(np.arange(v), (n, v))
        )  # [N, V, P]
        rows = np.arange(n)[:, None]
        q = slot_q.numpy()[rows, links.serving_idx, np.maximum(links.slot_of_ed, 0)]  # each ED's utilities [N, V, P]
        keep = slots.associated & (exact.std(-1) > 1e-9)
        q, e = q[keep], exact[keep]  # [M, P]
        qc, ec = q - q.mean(-1, keepdims=True), e - e.mean(-1, keepdims=True)
        corr = (qc * ec).sum(-1) / np.sqrt((qc**2).sum(-1) * (ec**2).sum(-1) + 1e-30)
        best, pick = e.argmax(-1), q.argmax(-1)
        m = np.arange(len(q))
        self.stats["corr"].extend(corr)
        self.stats["same"].extend(pick == best)
        self.stats["rank"].extend((q > q[m, best][:, None]).sum(-1))
        self.stats["loss"].extend(e[m, best] - e[m, pick])
        return actions


if __name__ == "__main__":
    import ray

    from uavlora_rllib.algorithms.common import registry

    name, overrides, iters = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
    cfg = tl.PER_DEVICE
    ray.init(num_cpus=1, include_dashboard=False)
    entry = registry.get(name)
    algo = entry.build(cfg, entry.hparams(overrides), registry.Resources(num_envs_per_env_runner=tl.ENVS), 0)
    algo = algo.build_algo()
    for _ in range(iters):
        algo.train()
    probe = UtilityProbe(entry.greedy_policy(algo, cfg), cfg)
    ee = run_episodes(probe, cfg, tl.EVAL_EPISODES, tl.EVAL_SEED).mean("ee_sys_mean")
    s = {k: float(np.mean(x)) for k, x in probe.stats.items()}
    print(f"{name} {iters} its: EE {ee:.1f}  " + "  ".join(f"{k} {x:.3f}" for k, x in s.items()), flush=True)
    algo.stop()
