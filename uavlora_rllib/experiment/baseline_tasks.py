"""Baseline evaluations as Ray tasks, in parallel with the trials and with each other.

Each baseline x seed x V x U is one task (one CPU) anywhere on the cluster; the task only
computes the evaluation summary. Its MLflow run is written by the driver when the result
arrives (`Tracker.log_baseline`), so a database such as SQLite keeps a single writer, and a
driver killed while tasks run leaves no half-written run behind: the next run of the grid
evaluates what is not FINISHED yet and adopts any run a killed driver left unfinished.

`BaselinePool` collects results on a driver thread while Tune trains in the main thread;
`baselines_to_run` picks the runs not FINISHED yet and `baseline_logger` writes each result.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any, TextIO

from uavlora_rllib.experiment.grid import BaselineSpec, GridConfig, baseline_runs

BASELINE_CPUS = 1.0  # the simulator and every baseline are single-threaded NumPy


def evaluate_baseline(spec: BaselineSpec, episodes: int) -> dict[str, Any]:
    """The evaluation summary of one baseline run (runs inside a Ray task)."""
    from uavlora_rllib.baselines.bound import upper_bound_of_core
    from uavlora_rllib.baselines.policies import BASELINES, REFERENCES, make_baseline
    from uavlora_rllib.experiment.evaluation import run_episodes
    from uavlora_rllib.experiment.grid import import_plugins

    if spec.baseline not in BASELINES:  # a plugin's baseline registers itself on import, on this node
        import_plugins(list(spec.plugins))
    t0 = time.perf_counter()
    policy = make_baseline(spec.baseline, spec.scenario, seed=spec.seed)
    # the references also log the upper bound of the same slots, so the report can bracket the optimum
    bound = upper_bound_of_core if spec.baseline in REFERENCES else None
    summary = run_episodes(policy, spec.scenario, episodes, spec.seed, bound=bound).summary()
    summary["_wall_s"] = time.perf_counter() - t0
    return summary


def failure_text(exc: BaseException, limit: int = 300) -> str:
    """What a failed evaluation raised, on one line: the task's own exception (a RayTaskError's cause) as
    `Type: message`, not the remote traceback that str() of a RayTaskError begins with."""
    from uavlora_rllib.config_errors import exception_line

    return exception_line(getattr(exc, "cause", None) or exc)[:limit]


class BaselinePool:
    """Submits the baseline tasks and logs each result to MLflow as it arrives."""

    def __init__(
        self,
        specs: list[BaselineSpec],
        episodes: int,
        log: Callable[[BaselineSpec, Any], None],
        out: TextIO | None = None,
    ):
        self.specs = specs
        self.episodes = episodes
        self.log = log  # (spec, summary dict or the task's exception) -> None; writes MLflow
        self.out = out or sys.stdout
        self.failed: list[tuple[str, str]] = []
        self.logged = 0
        self.error: BaseException | None = None  # a logging failure (MLflow down): stops the pool
        self._refs: dict[Any, BaselineSpec] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> BaselinePool:
        import ray

        from uavlora_rllib.baselines.policies import evaluation_seconds

        task = ray.remote(num_cpus=BASELINE_CPUS, max_retries=3)(evaluate_baseline)
        if self.specs:  # the phase's progress: this line, then one "(k/n)" line per result
            cost = sum(evaluation_seconds(s.baseline, s.scenario, self.episodes) for s in self.specs)
            print(
                f"baselines: {len(self.specs)} evaluations submitted as Ray tasks, about "
                f"{cost / 60:.1f} CPU-minutes in all (estimate)",
                file=self.out,
                flush=True,
            )
        for spec in self.specs:
            self._refs[task.options(name=f"baseline:{spec.name}").remote(spec, self.episodes)] = spec
        if self._refs:
            self._thread = threading.Thread(target=self._collect, name="baseline-results", daemon=True)
            self._thread.start()
        return self

    def _collect(self) -> None:
        import ray

        pending = list(self._refs)
        while pending and not self._stop.is_set():
            ready, pending = ray.wait(pending, num_returns=1, timeout=1.0)
            for ref in ready:
                spec = self._refs[ref]
                try:
                    result: Any = ray.get(ref)
                except Exception as exc:  # the evaluation raised (or its node died 4 times)
                    result = exc
                try:
                    self.log(spec, result)
                except BaseException as exc:  # noqa: BLE001 - reported by the driver after Tune
                    self.error = exc
                    self._stop.set()
                    return
                self.logged += 1
                if isinstance(result, BaseException):
                    msg = failure_text(result)
                    self.failed.append((spec.name, msg))
                    print(
                        f"baseline {spec.name}: FAILED: {msg} ({self.logged}/{len(self.specs)})",
                        file=self.out,
                        flush=True,
                    )
                else:
                    print(
                        f"baseline {spec.name}: evaluated in {result.get('_wall_s', 0.0):.1f} s "
                        f"({self.logged}/{len(self.specs)})",
                        file=self.out,
                        flush=True,
                    )

    @property
    def pending(self) -> int:
        return len(self.specs) - self.logged

    def wait(self) -> None:
        """Until every result is logged (or logging failed)."""
        if self._thread is not None:
            while self._thread.is_alive():
                self._thread.join(timeout=1.0)

    def cancel(self) -> None:
        """Stop collecting and cancel the tasks not yet done (an interrupted grid)."""
        import ray

        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        for ref in self._refs:
            try:
                ray.cancel(ref, force=True)
            except Exception:  # already finished, or the cluster is gone
                pass


def baselines_to_run(grid: GridConfig, tracker, out=None) -> list[BaselineSpec]:
    """The grid's baseline runs that are not FINISHED in MLflow yet."""
    from uavlora_rllib.experiment.run_schema import run_params

    out = out or sys.stdout
    todo = []
    for b in baseline_runs(grid):
        params = run_params(b.scenario, None, grid.evaluation.episodes)
        if tracker.finished_baseline(b.baseline, b.seed, b.n_eds, b.n_uavs, params):
            print(f"baseline {b.name}: already in MLflow, skipped", file=out, flush=True)
        else:
            todo.append(b)
    return todo


def baseline_logger(grid: GridConfig, tracker):
    """(spec, summary or the task's exception) -> the baseline's one MLflow run."""
    from uavlora_rllib.experiment.run_schema import run_params

    def log(spec: BaselineSpec, result: Any) -> None:
        params = run_params(spec.scenario, None, grid.evaluation.episodes)

        def evaluate() -> dict:
            if isinstance(result, BaseException):
                raise result
            return result

        try:
            tracker.log_baseline(
                spec.baseline, spec.name, spec.seed, spec.n_eds, spec.n_uavs, params, evaluate, grid.stop.env_steps
            )
        except Exception as exc:
            if exc is not result:  # the evaluation's own error is recorded as a FAILED run
                raise

    return log
