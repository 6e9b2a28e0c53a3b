"""Execution-policy learning curves: the greedy policy evaluated periodically during training.

The training return RLlib reports is that of the sampled, exploring policy, and it can rank
the learners the opposite way to the execution phase (issue 16: COMA lowest by return, highest
by execution EE). So every algorithm, through one RLlib callback, evaluates the policy it will
be judged by, the registry entry's greedy policy, every `interval_env_steps` env steps, with
`evaluation.run_episodes` on fixed evaluation episodes (seeds EVAL_SEED_BASE + seed * 10_000
+ k: disjoint from training, and the same at every point of a run, so the curve moves only
when the policy does). The first training iteration is evaluated too (the untrained policy).

The metrics go into the iteration's result as ``eval/<k>`` (and ``eval/<k>_ci95``,
``eval/episodes``), exactly the keys of the final execution-phase evaluation: the Tune
trainable passes them on (`metrics_from_result`) and the MLflow callback logs them at the
iteration's env-step count, so ``eval/ee_sys_mean`` is one series whose last point is the
final evaluation (same episodes, same seeds). The report's Fig. 3a draws these series.

The sampled policy (the registry entry's ``policy(..., explore=True)``: actions drawn from the
actor's distribution, or QMIX/VDN's final epsilon-greedy) is evaluated on the same episodes,
with its own action stream seeded by the evaluation seed, and logged as ``eval_sampled/<k>``:
the gap between the two curves shows how much greedy execution loses (or gains) against the
policy that was trained. The final evaluation plays both too (the trainable's `evaluate`), so
the last point of each series is the final policy's, whatever the interval.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from ray.rllib.callbacks.callbacks import RLlibCallback
from ray.rllib.utils import force_list
from ray.rllib.utils.annotations import override

from uavlora_rllib.sim.scenario import ScenarioConfig

EVAL_PREFIX = "eval/"
EVAL_SAMPLED_PREFIX = "eval_sampled/"
DEFAULT_CURVE_POINTS = 20  # evaluation.interval_env_steps unset: about this many points per run


@dataclass(frozen=True)
class PeriodicEvalSettings:
    """What the callback evaluates, and when."""

    scenario: ScenarioConfig
    interval_env_steps: int  # >= 1
    episodes: int  # evaluation episodes per point (the grid's evaluation.episodes)
    seed: int  # the trial's seed: selects the fixed evaluation episodes


def resolve_interval(interval_env_steps: int | None, budget_env_steps: int) -> int:
    """The grid's `evaluation.interval_env_steps`: None -> budget / DEFAULT_CURVE_POINTS
    (at least 1); 0 -> 0 (no periodic evaluation); otherwise itself."""
    if interval_env_steps is None:
        return max(1, int(budget_env_steps) // DEFAULT_CURVE_POINTS)
    return int(interval_env_steps)


class PeriodicEvalCallback(RLlibCallback):
    """Evaluates the greedy (and, where the entry has one, the sampled) policy every
    `settings.interval_env_steps` env steps and adds the metrics to the train result.

    `settings` is a class attribute because RLlib instantiates callback classes without
    arguments; `attach` makes one subclass per trial that carries them.
    """

    settings: ClassVar[PeriodicEvalSettings | None] = None

    def __init__(self) -> None:
        super().__init__()
        self._next_env_steps = 0  # evaluate at the first iteration, then every interval
        # wall time spent evaluating [s], logged so that a user sees what the learning curve costs
        self.seconds_total = 0.0
        self.evaluations = 0

    @override(RLlibCallback)
    def on_train_result(self, *, algorithm, metrics_logger=None, result: dict, **kwargs) -> None:
        from uavlora_rllib.experiment.run_schema import ENV_STEPS, training_summary

        s = self.settings
        if s is None or s.interval_env_steps < 1:
            return
        steps = training_summary(result)[ENV_STEPS]
        if steps < self._next_env_steps:
            return
        # the next point: the first multiple of the interval above this iteration's count
        self._next_env_steps = (steps // s.interval_env_steps + 1) * s.interval_env_steps
        t0 = time.perf_counter()
        result.update(evaluate_policies(algorithm, s))
        self.seconds_total += time.perf_counter() - t0
        self.evaluations += 1


def evaluate_policies(algorithm, s: PeriodicEvalSettings) -> dict[str, float]:
    """{"eval/<k>": ..., "eval_sampled/<k>": ...} of the algorithm's current policies."""
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.experiment.evaluation import run_episodes
    from uavlora_rllib.experiment.run_schema import eval_metrics

    entry = registry.entry_for_algorithm(algorithm)
    out: dict[str, float] = {}
    for prefix, explore in ((EVAL_PREFIX, False), (EVAL_SAMPLED_PREFIX, True)):
        policy = entry.policy(algorithm, s.scenario, explore=explore, seed=s.seed)
        summary = run_episodes(policy, s.scenario, s.episodes, s.seed).summary()
        out.update({prefix + k[len(EVAL_PREFIX) :]: v for k, v in eval_metrics(summary).items()})
    return out


def attach(config, settings: PeriodicEvalSettings):
    """Add a PeriodicEvalCallback carrying `settings` to an AlgorithmConfig (the algorithm's
    own callback classes and functional callbacks are kept). Returns the config."""
    if settings.interval_env_steps < 1:
        return config
    cls = type("PeriodicEvalCallbackForTrial", (PeriodicEvalCallback,), {"settings": settings})
    existing = [c for c in force_list(config.callbacks_class) if c is not RLlibCallback]
    config.callbacks(callbacks_class=existing + [cls])
    return config


def metrics_from_result(result: Mapping[str, Any]) -> dict[str, float]:
    """The periodic evaluation's keys of an `algo.train()` result (empty when none ran)."""
    return {k: v for k, v in result.items() if k.startswith((EVAL_PREFIX, EVAL_SAMPLED_PREFIX))}
