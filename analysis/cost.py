"""What the runs of a report cost, measured from MLflow: `table_cost` (docs/cluster.md#what-a-grid-costs).

`tune --dry-run` estimates a grid's CPU-hours from a calibration; this table states what the grid took.
- A trial: its own working time (metric `cost/trial_wall_s`, experiment/trial_clock.py: build, training,
  evaluations and checkpoints of every actor that ran it, a pause between SIGINT and `--resume` left out)
  x the CPUs its resources reserve (`calibration.trial_cpus`, as the estimate counts them). Runs logged
  before that metric existed count their run's start to end instead, a pause included: their row says so
  through a longest run far above the median.
- A baseline: its evaluation's own time on its one CPU (metric `cost/eval_wall_s`); runs logged before
  that metric existed have none and are counted as unmeasured.
Unfinished runs are left out. Rows: one per scenario and cell (an algorithm, or one sampled configuration of
it: analysis.data.cell_name) or baseline.
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from analysis.data import cell_name
from analysis.runs import RunRecord, section_dict
from analysis.tables import fmt, md_table
from uavlora_rllib.algorithms.common.registry import Resources
from uavlora_rllib.experiment.baseline_tasks import BASELINE_CPUS
from uavlora_rllib.experiment.calibration import trial_cpus
from uavlora_rllib.experiment.run_schema import EVAL_WALL_METRIC, TRIAL_WALL_METRIC

TABLE_COST_COLUMNS = (
    "n_eds", "n_uavs", "name", "kind", "runs", "cpus_per_run",
    "minutes_min", "minutes_median", "minutes_max", "cpu_hours", "unmeasured", "by_span",
)  # fmt: skip


def run_cpus(record: RunRecord) -> float:
    """CPUs one run reserved: a trial's from its resources.* params, a baseline's one."""
    if record.kind != "train":
        return BASELINE_CPUS
    logged = section_dict(record.params, "resources")
    return trial_cpus(Resources(**{f: logged[f] for f in Resources.__dataclass_fields__ if f in logged}))


def run_seconds(record: RunRecord) -> float:
    """A finished run's measured seconds (module docstring); nan where there is no measurement."""
    if record.kind == "train":
        if record.status != "FINISHED" or record.end_time is None:
            return math.nan
        if TRIAL_WALL_METRIC in record.metrics:
            return float(record.metrics[TRIAL_WALL_METRIC])
        return (record.end_time - record.start_time) / 1000.0
    return float(record.metrics.get(EVAL_WALL_METRIC, math.nan))


def timed_by_span(record: RunRecord) -> bool:
    """Whether a trial's seconds are its run's start to end (logged before `cost/trial_wall_s`)."""
    return record.kind == "train" and TRIAL_WALL_METRIC not in record.metrics


def cost_table(records: list[RunRecord]) -> list[dict[str, Any]]:
    """One row per (V, U, cell or baseline) over the FINISHED runs."""
    groups: dict[tuple[int, int, str, str], list[RunRecord]] = {}
    for r in records:
        if r.status == "FINISHED" and r.scenario_key is not None and r.algorithm and r.kind in ("train", "baseline"):
            # a trial's cell, as in the other tables: a sweep's configurations are rows of their own
            groups.setdefault((*r.scenario_key, cell_name(r), r.kind), []).append(r)
    rows = []
    for (v, u, name, kind), runs in sorted(groups.items(), key=lambda kv: (kv[0][:2], kv[0][3] != "train", kv[0][2])):
        measured = [(s, run_cpus(r), timed_by_span(r)) for r in runs if math.isfinite(s := run_seconds(r))]
        minutes = [s / 60.0 for s, _, _ in measured]
        rows.append({
            "n_eds": v, "n_uavs": u, "name": name, "kind": kind, "runs": len(runs),
            "cpus_per_run": max((c for _, c, _ in measured), default=math.nan),
            "minutes_min": min(minutes, default=math.nan),
            "minutes_median": statistics.median(minutes) if minutes else math.nan,
            "minutes_max": max(minutes, default=math.nan),
            "cpu_hours": sum(s * c for s, c, _ in measured) / 3600.0,
            "unmeasured": len(runs) - len(measured),
            "by_span": sum(span for _, _, span in measured),
        })  # fmt: skip
    return rows


def cost_totals(rows: list[dict[str, Any]]) -> dict[str, float]:
    """CPU-hours of the trials, of the baselines, and both."""
    trials = sum(r["cpu_hours"] for r in rows if r["kind"] == "train")
    baselines = sum(r["cpu_hours"] for r in rows if r["kind"] == "baseline")
    return {"trials": trials, "baselines": baselines, "total": trials + baselines}


def cost_md(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "No finished runs: nothing to cost."
    body = [
        [
            str(r["n_eds"]), str(r["n_uavs"]), r["name"], r["kind"], str(r["runs"]), fmt(r["cpus_per_run"], "g"),
            f"{fmt(r['minutes_median'], '.1f')} ({fmt(r['minutes_min'], '.1f')}-{fmt(r['minutes_max'], '.1f')})"
            if math.isfinite(r["minutes_median"])
            else "n/a",
            fmt(r["cpu_hours"], ".3f"), str(r["unmeasured"]) if r["unmeasured"] else "-",
            str(r["by_span"]) if r["by_span"] else "-",
        ]
        for r in rows
    ]  # fmt: skip
    t = cost_totals(rows)
    unmeasured = sum(r["unmeasured"] for r in rows)
    header = ["V", "U", "algorithm / baseline", "kind", "runs", "CPUs per run", "minutes per run: median (range)",
              "CPU-hours", "unmeasured runs", "runs timed by their span"]  # fmt: skip
    return (
        md_table(header, body)
        + f"\n\nIn all: {t['total']:.2f} CPU-hours = trials {t['trials']:.2f} + baselines {t['baselines']:.3f}"
        + (f" ({unmeasured} unmeasured runs not counted). " if unmeasured else ". ")
        + "A trial is its own working time (metric cost/trial_wall_s, a pause before --resume left out; runs "
        "logged before that metric are timed by their span, their MLflow run's start to end, a pause included) "
        "x the CPUs it reserves; "
        "a baseline is its evaluation's time on one CPU."
    )
