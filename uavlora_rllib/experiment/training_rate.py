"""How fast one algorithm trains on one scenario: env steps per second end to end.

The one measurement behind `bench_train` and the grid calibration (`experiment.calibration`):
build the registry entry's algorithm, run warm-up iterations, then time `iterations` training
iterations. Ray must already be running (the caller starts it, once for many measurements).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

# RLlib's per-iteration timers -> the names of this module's rows
TIMER_KEYS = {"env_runner_sampling_timer": "sample_s", "learner_update_timer": "learn_s", "synch_weights": "sync_s"}
EMA_COEFF = 0.01  # RLlib's default for `metrics.log_time` (Stats with ema_coeff=0.01)
MAX_WARMUP_ITERATIONS = 100  # warmup_until_learning: give up waiting for the first update here


@dataclass
class TrainingRate:
    """The timed iterations of one measurement (rows: wall_s, env_steps, sample_s, learn_s, sync_s)."""

    build_s: float  # building the algorithm (env runners included)
    warmup_iterations: int  # untimed iterations before the timed ones
    learning_started: bool  # the learner updated during the timed iterations
    rows: list[dict[str, float]]
    total_s: float  # wall clock of the timed iterations
    after: Any = field(default=None)  # what `after(algo)` returned

    @property
    def env_steps(self) -> int:
        return int(sum(r["env_steps"] for r in self.rows))

    @property
    def env_steps_per_s(self) -> float:
        return self.env_steps / max(self.total_s, 1e-9)

    @property
    def seconds_per_iteration(self) -> float:
        return self.total_s / max(len(self.rows), 1)

    @property
    def env_steps_per_iteration(self) -> float:
        return self.env_steps / max(len(self.rows), 1)

    def summed(self, key: str) -> float:
        """The timed iterations' own values of `key` (a row field), summed."""
        return float(sum(r[key] for r in self.rows))


def this_iteration(ema_now: float | None, ema_before: float | None) -> float:
    """RLlib reports timers as an EMA (coefficient 0.01) over all iterations; recover this
    iteration's own value: x = (ema_now - (1 - c) ema_before) / c."""
    if ema_now is None:
        return float("nan")
    if ema_before is None:
        return float(ema_now)
    return max(0.0, (ema_now - (1.0 - EMA_COEFF) * ema_before) / EMA_COEFF)


def _timers(result: dict) -> dict:
    return dict(result.get("timers", {}))


def measure_training(
    entry,
    scenario,
    hparams,
    resources,
    seed: int,
    iterations: int,
    *,
    warmup_until_learning: bool = False,
    after: Callable[[Any], Any] | None = None,
) -> TrainingRate:
    """Build `entry`'s algorithm for (scenario, hparams, resources, seed), train one warm-up
    iteration (with `warmup_until_learning`, more until the learner has updated, as a replay
    algorithm only learns once its buffer fills), then time `iterations` iterations.
    `after(algo)` runs on the trained algorithm before it stops (e.g. to time an evaluation)."""
    from uavlora_rllib.algorithms.common.torch_process import setup_torch_process

    if iterations < 1:
        raise ValueError(f"iterations: must be >= 1, got {iterations}")
    setup_torch_process(resources.torch_threads)
    t0 = time.perf_counter()
    algo = entry.algorithm_config(scenario, hparams, resources, seed).build_algo()
    build_s = time.perf_counter() - t0
    try:
        prev = _timers(algo.train())  # first sampling, connector setup, optimizer state
        warmup = 1
        while warmup_until_learning and "learner_update_timer" not in prev and warmup < MAX_WARMUP_ITERATIONS:
            prev = _timers(algo.train())
            warmup += 1
        rows = []
        start = time.perf_counter()
        for _ in range(iterations):
            t = time.perf_counter()
            res = algo.train()
            row = {"wall_s": time.perf_counter() - t, "env_steps": res["env_runners"].get("num_env_steps_sampled", 0)}
            cur = _timers(res)
            for key, name in TIMER_KEYS.items():
                row[name] = this_iteration(cur.get(key), prev.get(key))
            prev = cur
            rows.append(row)
        total_s = time.perf_counter() - start
        out = TrainingRate(build_s, warmup, "learner_update_timer" in prev, rows, total_s)
        if after is not None:
            out.after = after(algo)
        return out
    finally:
        algo.stop()
