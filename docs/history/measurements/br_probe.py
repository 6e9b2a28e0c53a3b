"""How far a policy's per_device joint action is from a point where no single ED can do better (issue 23).

On the per_device CI scenario of tests/test_learning.py, train a learner (as ci_probe.py does), then play
its greedy actions on the test's evaluation episodes and, at every slot, score every single-ED change of
(SF, TP) with the simulator's own equations (baselines/slots.py AllocationScorer.score_ed_moves), the
others held at the policy's action. Printed, per policy, under the reward the learners maximise:
  at_br:   share of served EDs whose (SF, TP) is already a best response to the others' (no single move
           raises the slot's reward by more than 1e-6 relative)
  gain1:   mean over slots of the best single-ED move's reward gain, relative to the slot's reward
  ascent:  the slot reward the policy's action has, relative to where steepest single-move ascent from it
           stops (PerDeviceGreedy._ascend under the reward), averaged over slots; and the same in EE_sys
A policy whose actions are best responses (at_br near 1) but low is stuck at a poor equilibrium; one far
from best responses (low at_br, high gain1) has per-ED choices the simulator says are wrong one by one.

    python docs/history/measurements/br_probe.py ALGO 'OVERRIDES_JSON' ITERATIONS
    python docs/history/measurements/br_probe.py none '{}' 0     # the baselines only
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))

import test_learning as tl  # noqa: E402

from uavlora_rllib.baselines.per_device import PerDeviceGreedy  # noqa: E402
from uavlora_rllib.baselines.policies import make_baseline  # noqa: E402
from uavlora_rllib.baselines.slots import AllocationScorer, Slots  # noqa: E402
from uavlora_rllib.experiment.evaluation import run_episodes  # noqa: E402


def slot_settings(core, actions, cfg) -> np.ndarray:
    """Each ED's (SF, TP) setting index sf n_tp + tp [N, V] under the agents' actions (0 where unserved),
    from the simulator's own decoding: the index AllocationScorer scores."""
    slots = Slots.of_core(core)
    sf, tp, _ = core.decoder.allocations(actions, core.links)
    return np.where(slots.associated, sf * cfg.n_tp + tp, 0).astype(np.int64)


class Probe:
    """Wraps a policy: plays its actions and records the single-move statistics of each slot."""

    def __init__(self, policy, cfg):
        self.policy, self.cfg = policy, cfg
        self.name = getattr(policy, "name", "policy")
        self.stats: dict[str, list] = {"at_br": [], "gain1": [], "ascent_r": [], "ascent_ee": []}
        self.climber = PerDeviceGreedy(cfg, objective="reward")

    def reset(self, core):
        self.policy.reset(core)

    def act(self, core):
        actions = np.asarray(self.policy.act(core))
        cfg, slots = self.cfg, Slots.of_core(core)
        n, v = slots.g_serving.shape
        setting = slot_settings(core, actions, cfg)
        bw = actions[:, :, -1].astype(np.int64)
        scorer = AllocationScorer(cfg, core.tables, "reward")
        setting_ok, bw_ok = scorer.allowed(slots)  # everything, under "reward"
        m = scorer.metrics(setting, bw, slots)
        r0, ee0 = m["reward"], m["ee_sys"]
        pe, _ = scorer.score_ed_moves(setting, bw, slots, np.broadcast_to(np.arange(v), (n, v)))  # [N, V, n_set]
        best = pe.max(-1)  # [N, V]
        scale = np.maximum(np.abs(r0), 1e-9)[:, None]
        at_br = (best - r0[:, None]) <= 1e-6 * scale
        self.stats["at_br"].append(at_br[slots.associated].mean())
        self.stats["gain1"].append(np.mean(np.where(slots.associated, best - r0[:, None], 0).max(1) / scale[:, 0]))
        self.climber._scorer = scorer
        s2, b2, _, _ = self.climber._ascend(setting.copy(), bw.copy(), slots, setting_ok, bw_ok)
        m2 = scorer.metrics(s2, b2, slots)
        self.stats["ascent_r"].append(np.mean(r0 / m2["reward"]))
        self.stats["ascent_ee"].append(np.mean(ee0 / np.maximum(m2["ee_sys"], 1e-9)))
        return actions

    def line(self, ee):
        s = {k: float(np.mean(x)) for k, x in self.stats.items()}
        return (
            f"{self.name:12s} EE {ee:7.1f}  at_br {s['at_br']:.3f}  gain1 {s['gain1']:.4f}  "
            f"ascent r {s['ascent_r']:.3f} ee {s['ascent_ee']:.3f}"
        )


def probe(policy, cfg, name=None):
    p = Probe(policy, cfg)
    if name:
        p.name = name
    ee = run_episodes(p, cfg, tl.EVAL_EPISODES, tl.EVAL_SEED).mean("ee_sys_mean")
    print(p.line(ee), flush=True)


if __name__ == "__main__":
    name, overrides, iters = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
    cfg = tl.PER_DEVICE
    if name == "none":
        for b in ("best_fixed", "greedy", "random"):
            probe(make_baseline(b, cfg, seed=0), cfg, b)
        sys.exit(0)
    import ray

    from uavlora_rllib.algorithms.common import registry

    ray.init(num_cpus=1, include_dashboard=False)
    entry = registry.get(name)
    algo = entry.build(cfg, entry.hparams(overrides), registry.Resources(num_envs_per_env_runner=tl.ENVS), 0)
    algo = algo.build_algo()
    t0 = time.perf_counter()
    for _ in range(iters):
        algo.train()
    print(f"{name}: {iters} iterations in {time.perf_counter() - t0:.0f} s", flush=True)
    probe(entry.greedy_policy(algo, cfg), cfg, name)
    algo.stop()
