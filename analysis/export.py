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
number of steps (runs are cut to the shortest, a note says when) and every (task, algorithm)
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

from analysis.data import Organised

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


def marl_eval_data(org: Organised, history: Callable) -> tuple[dict[str, Any], list[str]]:
    """The marl-eval dict of the organised runs, and notes. `history(record, key)` ->
    (steps, values) as in analysis.data."""
    notes: list[str] = []
    runs: dict[tuple[str, str, str], dict[str, Any]] = {}
    for cell in sorted(org.cells.values(), key=lambda c: c.key):
        if cell.kind != "train":
            continue
        for r in cell.runs:
            series = {name: dict(zip(*history(r, key))) for name, key in METRICS.items()}
            steps = sorted(set.intersection(*(set(s) for s in series.values())))
            absolute = {
                name: [float(r.metrics[key])]
                for name, key in METRICS.items()
                if math.isfinite(r.metrics.get(key, math.nan))
            }
            if len(absolute) < len(METRICS):
                notes.append(f"marl-eval export: {r.label} lacks some final metrics; left out")
                continue
            run = {
                f"step_{i}": {"step_count": int(s), **{n: [float(series[n][s])] for n in METRICS}}
                for i, s in enumerate(steps)
            }
            runs[(task_name(cell.n_eds, cell.n_uavs), cell.algorithm, f"seed_{r.seed}")] = run | {ABSOLUTE: absolute}
    if not runs:
        return {ENVIRONMENT: {}}, notes + ["marl-eval export: no learner run with execution metrics; the file is empty"]
    n_steps = Counter(len(run) - 1 for run in runs.values())
    shortest = min(n_steps)
    if len(n_steps) > 1:
        notes.append(
            f"marl-eval export: runs have {', '.join(f'{k} ({v} runs)' for k, v in sorted(n_steps.items()))} "
            f"evaluation steps; all are cut to the first {shortest} (marl-eval needs equal counts)"
        )
    data: dict[str, Any] = {ENVIRONMENT: {}}
    for (task, alg, seed), run in runs.items():
        kept = {f"step_{i}": run[f"step_{i}"] for i in range(shortest)}
        kept[ABSOLUTE] = run[ABSOLUTE]  # last key, as marl-eval expects
        data[ENVIRONMENT].setdefault(task, {}).setdefault(alg, {})[seed] = kept
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
