"""Results as a marl-eval JSON file (the raw-data format of InstaDeep's marl-eval, which
BenchMARL's JSON logger also writes), so they can go into the community's statistics tools.

Structure (marl-eval README, "Data Structure for Raw Experiment data")::

    {"uavlora": {                                  # environment
        "v10_u2": {                                # task: one scenario, lower case
            "mappo": {                             # algorithm
                "seed_0": {                        # one independent run
                    "step_0": {"step_count": 0, "ee_sys_mean": [..], "return": [..], ...},
                    ...
                    "step_k": {...},
                    "absolute_metrics": {"ee_sys_mean": [..], "return": [..], ...}}}}}}

What marl-eval's loader relies on, and what this writer guarantees: "absolute_metrics" is the
LAST key of every run (marl-eval takes the last key as the absolute metrics and the others as
the time steps); "step_count" is an int, non-decreasing; every metric is a list of numbers; all
steps and absolute_metrics carry the same metric names; every run of the file has the same
number of steps, the same places of the evaluation schedule (`marl_eval_data`; a note says when
some run's points were left out) and every (task, algorithm)
the same number of runs (a note says when they differ; marl-eval's DiagnoseData keeps the
smallest count).

Sources: the steps are the periodic greedy-policy evaluations (`eval/<k>` history, x = env
steps; experiment/periodic_eval.py); absolute_metrics is the final execution-phase evaluation
(the run's `eval/<k>`). MLflow keeps the mean over an evaluation's episodes, not each
episode, so every list holds ONE value, that mean. Learners (kind=train) only: baselines have
no training steps. Metrics: ee_sys_mean (bit/J per slot), ee_sys_episode_sum, success_rate,
and "return" (the greedy policy's undiscounted episode return, eval/episode_return).

Checked against marl-eval itself: the PyPI package (id-marl-eval 0.0.4) does not install on
Python 3.11 here (its pinned pandas fails to build), so the tests check the structure above
precisely; a report's file was also run once through marl-eval's own loader from its repository
(DiagnoseData.check_data: every check True; data_process_pipeline and create_matrices_for_rliable:
[runs x tasks] and [runs x tasks x steps] matrices per algorithm).
"""

from __future__ import annotations

import json
import math
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np

from analysis.data import Organised
from analysis.runs import RunRecord
from uavlora_rllib.experiment.run_schema import EVAL_INTERVAL_PARAM, number

ENVIRONMENT = "uavlora"
MARL_EVAL_FILE = "results_marl_eval.json"  # its name in a report's folder
ABSOLUTE = "absolute_metrics"
# marl-eval metric name -> our MLflow metric
METRICS = {
    "ee_sys_mean": "eval/ee_sys_mean",
    "ee_sys_episode_sum": "eval/ee_sys_episode_sum",
    "success_rate": "eval/success_rate",
    "return": "eval/episode_return",
}


def task_name(n_eds: int, n_uavs: int) -> str:
    return f"v{n_eds}_u{n_uavs}"


def schedule_places(steps: list[float], interval: float) -> dict[int, float]:
    """A run's evaluations by their place k in the evaluation schedule -> env step. An evaluation runs
    at the first iteration at or past each multiple k I of the interval (experiment/periodic_eval.py),
    so it is the k-th when floor(step / I) = k; a second one in the same interval (a restored trial
    evaluates at once) is left out: the first is the scheduled one."""
    out: dict[int, float] = {}
    for x in sorted(steps):
        out.setdefault(int(x // interval), x)
    return out


def schedule_interval(gaps: list[float], budget: float | None, logged: float | None = None) -> float | None:
    """The evaluation interval [env steps]: the run's param eval.interval_env_steps where it logged one;
    for a run from before that param, the budget over the number of intervals the median gap between
    evaluations gives (a gap is an interval plus or minus an iteration; right where the interval divides
    the budget, as the default budget / 20 does), or that gap without a budget; None without either."""
    if logged:
        return logged
    if not gaps:
        return None
    gap = float(np.median(gaps))
    return budget / max(1, round(budget / gap)) if budget else gap


def marl_eval_data(org: Organised, history: Callable) -> tuple[dict[str, Any], list[str]]:
    """The marl-eval dict of the organised runs, and notes. `history(record, key)` ->
    (steps, values) as in analysis.data. marl-eval compares runs step by step by position, so every
    run keeps the evaluations at the places of the schedule that every run has (`schedule_places`):
    step_i is the same point of training in every run."""
    notes: list[str] = []
    # (task, algorithm, seed) -> the run, its metrics' series, their common steps, its absolute metrics
    found: dict[tuple[str, str, str], tuple[RunRecord, dict[str, dict], list[float], dict[str, list[float]]]] = {}
    gaps: dict[str, list[float]] = {}
    for cell in sorted(org.cells.values(), key=lambda c: c.key):
        if cell.kind != "train":
            continue
        task = task_name(cell.n_eds, cell.n_uavs)
        for r in cell.runs:
            series = {name: dict(zip(*history(r, key))) for name, key in METRICS.items()}
            absolute = {
                name: [float(r.metrics[key])]
                for name, key in METRICS.items()
                if math.isfinite(r.metrics.get(key, math.nan))
            }
            if len(absolute) < len(METRICS):
                notes.append(f"marl-eval export: {r.label} lacks some final metrics; left out")
                continue
            steps = sorted(set.intersection(*(set(s) for s in series.values())))
            found[(task, cell.algorithm, f"seed_{r.seed}")] = (r, series, steps, absolute)
            gaps.setdefault(task, []).extend(np.diff(steps).tolist())
    if not found:
        return {ENVIRONMENT: {}}, notes + ["marl-eval export: no learner run with execution metrics; the file is empty"]
    places: dict[tuple[str, str, str], dict[int, float]] = {}
    for key, (r, _, steps, _) in found.items():
        interval = schedule_interval(
            gaps[key[0]], number(r.params.get("stop.env_steps")), number(r.params.get(EVAL_INTERVAL_PARAM))
        )
        places[key] = schedule_places(steps, interval) if interval else dict(enumerate(steps))
    common = sorted(set.intersection(*(set(p) for p in places.values())))
    n_points = Counter(len(p) for p in places.values())
    if len(n_points) > 1 or any(len(p) > len(common) for p in places.values()):
        notes.append(
            f"marl-eval export: runs have {', '.join(f'{k} ({v} runs)' for k, v in sorted(n_points.items()))} "
            f"evaluation points on the evaluation schedule; each keeps the {len(common)} places every run has "
            "(marl-eval needs equal counts and compares runs step by step)"
        )
    data: dict[str, Any] = {ENVIRONMENT: {}}
    for (task, alg, seed), (_, series, _, absolute) in found.items():
        run: dict[str, Any] = {}
        for i, k in enumerate(common):
            s = places[(task, alg, seed)][k]
            run[f"step_{i}"] = {"step_count": int(s), **{n: [float(series[n][s])] for n in METRICS}}
        run[ABSOLUTE] = absolute  # last key, as marl-eval expects
        data[ENVIRONMENT].setdefault(task, {}).setdefault(alg, {})[seed] = run
    counts = Counter(len(seeds) for algs in data[ENVIRONMENT].values() for seeds in algs.values())
    if len(counts) > 1:
        notes.append(
            f"marl-eval export: the (task, algorithm) pairs have different numbers of runs "
            f"({', '.join(map(str, sorted(counts)))}); marl-eval keeps the smallest"
        )
    algsets = {tuple(sorted(algs)) for algs in data[ENVIRONMENT].values()}
    if len(algsets) > 1:
        notes.append("marl-eval export: the tasks have different algorithm sets; marl-eval keeps the common ones")
    return data, notes


def write_marl_eval(path: str, data: dict[str, Any]) -> None:
    with open(path, "w") as fh:
        json.dump(data, fh, indent=2)
        fh.write("\n")
