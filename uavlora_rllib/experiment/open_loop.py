"""How open-loop a policy is (docs/model.md#open-loop-share-of-a-policy): the share of its decisions
that equal its own most frequent decision of the same UAV and action component, and what replaying
that modal action as a constant earns on the same episodes.

`best_fixed` asks what the best constant earns; this asks whether a given policy, a learner's
greedy one above all, is itself close to a constant. A policy whose decisions are mostly its mode,
and whose mode earns about what it does, ignores its observations (issue 23).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from uavlora_rllib.experiment.evaluation import EvalResult, Policy, run_episodes
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

MAX_BATCH = 32  # scenarios played at once (run_episodes' default batch)


@dataclass(frozen=True)
class OpenLoopCheck:
    modal_share: float  # decisions equal to the mode of their (UAV, component), of those that act [0, 1]
    policy_ee: float  # mean EE_sys of the policy on the episodes [bit/J]
    modal_ee: float  # mean EE_sys of its modal action replayed as a constant, same episodes [bit/J]
    action: np.ndarray  # the modal action: [U] (per_uav) or [U, 2 quota + 1] (per_device)
    result: EvalResult  # the policy's own run, whose mean EE is policy_ee

    @property
    def modal_ratio(self) -> float:
        """modal_ee / policy_ee: near 1 (or above) means the policy earns what a constant does."""
        return self.modal_ee / self.policy_ee if self.policy_ee > 0 else float("nan")


class _Recorder:
    """Plays `policy` and keeps each slot's actions with the mask of the components that act:
    in per_device mode an ED slot's (SF, TP) acts only when the UAV serves that many EDs."""

    def __init__(self, policy: Policy, cfg: ScenarioConfig):
        self.policy, self.cfg = policy, cfg
        self.name = getattr(policy, "name", "policy")
        self.actions: list[np.ndarray] = []
        self.masks: list[np.ndarray] = []

    def reset(self, core: BatchCore) -> None:
        self.policy.reset(core)

    def act(self, core: BatchCore) -> np.ndarray:
        a = np.asarray(self.policy.act(core))
        self.actions.append(a.copy())
        self.masks.append(_acting(core, self.cfg, a.shape))
        return a


def _acting(core: BatchCore, cfg: ScenarioConfig, shape: tuple[int, ...]) -> np.ndarray:
    if cfg.action_mode == "per_uav":
        return np.ones(shape, dtype=bool)
    # the components the simulator reads (sim.actions): each served ED's (SF, TP) at its UAV's
    # slot `slot_of_ed`, and every UAV's BW
    mask = np.zeros(shape, dtype=bool)
    mask[..., -1] = True
    n, ed = np.nonzero(core.associated)
    slot = core.slot_of_ed[n, ed]
    mask[n, core.serving[n, ed], 2 * slot] = True
    mask[n, core.serving[n, ed], 2 * slot + 1] = True
    return mask


class _Constant:
    def __init__(self, action: np.ndarray):
        self.name, self.action = "modal constant", action

    def reset(self, core: BatchCore) -> None:
        pass

    def act(self, core: BatchCore) -> np.ndarray:
        return np.broadcast_to(self.action, (core.n,) + self.action.shape).copy()


def open_loop_check(
    policy: Policy,
    cfg: ScenarioConfig,
    episodes: int = 10,
    seed: int = 0,
    play: Callable[[Policy, int], EvalResult] | None = None,
) -> OpenLoopCheck:
    """Play `episodes` evaluation episodes (run_episodes' seeds) with `policy`, then its modal action.
    `play(policy, n_envs)` plays the policy's run (default: run_episodes), so that a caller that
    reports the policy's EE reports this one run, not a second one with its RNG advanced."""
    n_envs = max(n for n in range(1, min(episodes, MAX_BATCH) + 1) if episodes % n == 0)  # no padding scenario
    rec = _Recorder(policy, cfg)
    if play is None:
        result = run_episodes(rec, cfg, episodes, seed, n_envs=n_envs)
    else:
        result = play(rec, n_envs)
    policy_ee = result.mean("ee_sys_mean")
    acts = np.concatenate(rec.actions)  # [episodes x T, U(, L)]
    acting = np.concatenate(rec.masks)
    flat, flat_mask = acts.reshape(len(acts), -1), acting.reshape(len(acting), -1)
    # per column, the mode over the rows where it acts (the smallest value on ties); a column that
    # never acted (an ED slot no UAV filled) keeps its mode over all rows: it changes no EE either way
    mode = np.array(
        [stats.mode(col[m] if m.any() else col, keepdims=False).mode for col, m in zip(flat.T, flat_mask.T)]
    )
    share = float((flat == mode)[flat_mask].mean())
    action = mode.reshape(acts.shape[1:]).astype(np.int64)
    modal_ee = run_episodes(_Constant(action), cfg, episodes, seed, n_envs=n_envs).mean("ee_sys_mean")
    return OpenLoopCheck(share, float(policy_ee), float(modal_ee), action, result)
