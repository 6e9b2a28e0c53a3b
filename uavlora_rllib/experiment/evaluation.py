"""The execution phase (docs/model.md#execution-phase): run a policy on fresh episodes and summarise the paper's metrics.

One interface serves every policy, learned or not: a `Policy` sees the batch core (its
observations, global state and, for oracle baselines, the true channel) and returns the
actions of all scenarios at once. Episodes are seeded from EVAL_SEED_BASE, disjoint from the
training seeds (which are small integers and RLlib's offsets of them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from scipy import stats

from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

EVAL_SEED_BASE = 1_000_000

# Per-episode metrics; each is the mean over the episode's slots unless the name says otherwise.
EPISODE_METRICS = (
    "ee_sys_mean",  # EE_sys[t] averaged over slots, bits/J
    "ee_sys_episode_sum",  # the paper's EE_sys: sum over the episode's slots, bits/J
    "success_rate",  # Xi
    "mean_sinr_db",
    "unassociated_frac",  # unassociated EDs / V
    "p_total_w",
    "reward_mean",  # shared reward per slot
    "episode_return",  # undiscounted sum of rewards
)
# Logged only when asked for (run_episodes' `bound`): an upper bound on the per-slot optimum of
# EE_sys, averaged over the slots (bit/J; docs/model.md#an-upper-bound-on-the-per-slot-optimum).
BOUND_METRIC = "ee_sys_upper_bound"


class Policy(Protocol):
    """Acts for all UAVs of all scenarios of a batch core."""

    name: str

    def reset(self, core: BatchCore) -> None:
        """Called right after core.reset(): clear any per-episode (e.g. recurrent) state."""

    def act(self, core: BatchCore) -> np.ndarray:
        """Actions for the current slot: int array [N, U] (per_uav) or [N, U, 2 Lambda + 1]."""


def t_half_width_95(x) -> float:
    """Half-width of the 95% Student-t confidence interval of the mean of x (at least 2 values).
    The one place this interval is computed: the execution phase over episodes, and the
    analysis over seeds (analysis.stats.t_ci95)."""
    x = np.asarray(x, dtype=float)
    return float(stats.t.ppf(0.975, x.size - 1) * x.std(ddof=1) / np.sqrt(x.size))


@dataclass
class EvalResult:
    per_episode: dict[str, np.ndarray]  # metric -> [episodes]
    episodes: int
    seed: int

    def mean(self, key: str) -> float:
        return float(np.mean(self.per_episode[key]))

    def ci95(self, key: str) -> float:
        """Half-width of the 95% Student-t confidence interval of the mean over episodes."""
        x = self.per_episode[key]
        return t_half_width_95(x) if len(x) >= 2 else 0.0

    def summary(self) -> dict:
        keys = [k for k in (*EPISODE_METRICS, BOUND_METRIC) if k in self.per_episode]
        out: dict = {k: self.mean(k) for k in keys}
        out["ci95"] = {k: self.ci95(k) for k in keys}
        out["episodes"] = self.episodes
        return out


def run_episodes(
    policy: Policy,
    cfg: ScenarioConfig,
    episodes: int = 10,
    seed: int = 0,
    n_envs: int | None = None,
    bound: Callable[[BatchCore], np.ndarray] | None = None,
) -> EvalResult:
    """Play `episodes` full episodes (seeds EVAL_SEED_BASE + seed * 10_000 + k) in batches.
    `bound`: core -> [N] bit/J of each slot (e.g. baselines.bound.upper_bound_of_core), averaged
    per episode as BOUND_METRIC."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {episodes}")
    n_envs = min(episodes, 32) if n_envs is None else n_envs
    first = EVAL_SEED_BASE + seed * 10_000
    per_ep: dict[str, list[float]] = {k: [] for k in EPISODE_METRICS}
    core = BatchCore(cfg, n_envs)
    done = 0
    while done < episodes:
        core.reset([first + done + i for i in range(n_envs)])
        policy.reset(core)
        sums = {
            k: np.zeros(n_envs)
            for k in ("ee_sys", "success_rate", "mean_sinr_db", "n_unassociated", "p_total_w", "reward")
        }
        bound_sum = np.zeros(n_envs)
        for _ in range(cfg.episode_len):
            if bound is not None:
                bound_sum += bound(core)
            res = core.step(policy.act(core))
            for k in sums:
                sums[k] += res.metrics[k]
        take = min(n_envs, episodes - done)
        t = cfg.episode_len
        per_ep["ee_sys_mean"] += list(sums["ee_sys"][:take] / t)
        per_ep["ee_sys_episode_sum"] += list(sums["ee_sys"][:take])
        per_ep["success_rate"] += list(sums["success_rate"][:take] / t)
        per_ep["mean_sinr_db"] += list(sums["mean_sinr_db"][:take] / t)
        per_ep["unassociated_frac"] += list(sums["n_unassociated"][:take] / (t * cfg.n_eds))
        per_ep["p_total_w"] += list(sums["p_total_w"][:take] / t)
        per_ep["reward_mean"] += list(sums["reward"][:take] / t)
        per_ep["episode_return"] += list(sums["reward"][:take])
        if bound is not None:
            per_ep.setdefault(BOUND_METRIC, []).extend(bound_sum[:take] / t)
        done += take
    return EvalResult({k: np.asarray(v) for k, v in per_ep.items()}, episodes, seed)
