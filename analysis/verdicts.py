"""The learning benchmark's verdicts per scenario and learner, from the runs' execution metrics:
the share of the reference, the margin over the open-loop `best_fixed`, and whether the greedy
policy had settled (its last periodic evaluations agree). No drawing and no file writing here.

A learner's result means something only above `best_fixed` (docs/model.md#decisions); the
share target and the swing limit are the learning benchmark's (docs/model.md#learning-verdicts).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from analysis.data import BEST_FIXED, Organised
from analysis.runs import EE_KEY, RunRecord
from analysis.tables import fmt, md_table

PER_DEVICE_SHARE_TARGET = 0.9  # seed-mean greedy EE / the reference's, per_device (issue 23, for MAPPO)
SWING_LIMIT = 0.05  # the last LAST_EVALS periodic evaluations of a seed lie within this (max - min) / max
LAST_EVALS = 3
JUDGED_SEEDS, JUDGED_ENV_STEPS = 3, 200_000  # a share target is judged only on this many seeds at this budget


def share_target(action_mode: str, n_uavs: int) -> float:
    """The greedy-share target of a scenario: 0.9 in per_device; in per_uav issue 13's 0.95 / 0.85 / 0.75
    at U <= 2 / <= 4 / more (docs/model.md#learning-verdicts)."""
    if action_mode == "per_device":
        return PER_DEVICE_SHARE_TARGET
    return 0.95 if n_uavs <= 2 else 0.85 if n_uavs <= 4 else 0.75


TABLE_LEARNING_COLUMNS = (
    "n_eds",
    "n_uavs",
    "action_mode",
    "algorithm",
    "n_seeds",  # seeds that the learner, the reference and best_fixed all ran; every ratio is over these
    "unmatched_seeds",  # the learner's other seeds, left out of every ratio
    "env_steps",  # the runs' budget (stop.env_steps)
    "trained_env_steps",  # where their last evaluation was: below the budget for a run a scheduler stopped
    "reference_baseline",
    "share_of_reference",
    "best_fixed_share_of_reference",
    "share_of_best_fixed",  # > 1: the learner uses its observations
    "above_best_fixed",
    "max_last_evals_spread",  # over seeds: (max - min) / max of a seed's last LAST_EVALS evaluations
    "settled",  # max_last_evals_spread <= SWING_LIMIT
    "share_target",  # share_target(action_mode, n_uavs)
    "meets_share_target",  # share_of_reference >= share_target; empty below JUDGED_SEEDS seeds at JUDGED_ENV_STEPS
)

History = Callable[[RunRecord, str], tuple[list[float], list[float]]]


def last_evals_spread(values: list[float] | np.ndarray, last: int = LAST_EVALS) -> float:
    """(max - min) / max of the last `last` values; NaN with fewer values or a non-positive max."""
    tail = np.asarray(values, dtype=float)[-last:]
    if tail.size < last or not np.all(np.isfinite(tail)) or tail.max() <= 0:
        return math.nan
    return float((tail.max() - tail.min()) / tail.max())


def stopped_before_budget(org: Organised, history: History) -> list[str]:
    """A note per learner cell with runs whose last evaluation came before their budget
    (stop.env_steps): a scheduler stopped them early, so their EE is of a shorter training than a
    full run's and a comparison with one is not like for like."""
    notes = []
    for cell in sorted(org.cells.values(), key=lambda c: c.key):
        if cell.kind != "train":
            continue
        short = []
        for r in cell.runs:
            budget = r.params.get("stop.env_steps", "")
            steps, _ = history(r, EE_KEY)
            if budget.isdigit() and len(steps) and steps[-1] < int(budget):
                short.append(f"seed {r.seed} at {int(steps[-1])}")
        if short:
            notes.append(
                f"V={cell.n_eds} U={cell.n_uavs} {cell.algorithm}: {len(short)} of {len(cell.runs)} run(s) stopped "
                f"before the budget {cell.runs[0].params.get('stop.env_steps')} ({', '.join(short)} env steps; "
                "a scheduler's early stop): their EE is of a shorter training"
            )
    return notes


def learning_table(org: Organised, history: History) -> list[dict[str, Any]]:
    """One row per learner (kind=train) of each scenario that has a reference baseline."""
    rows = []
    for scen in org.scenarios():
        if org.reference(scen) is None:
            continue
        for cell in sorted(org.cells_of(scen), key=lambda c: c.algorithm):
            if cell.kind != "train" or not cell.runs:
                continue
            # every ratio over the seeds that the learner, the reference and best_fixed all ran:
            # each seed has its own evaluation episodes, so unmatched seeds would compare different episodes
            seeds = org.matched_seeds(cell, BEST_FIXED)
            ref = org.reference(scen, seeds) if seeds else None
            if ref is None:
                continue
            runs = [r for r in cell.runs if str(r.seed) in seeds]
            ee, bf = cell.summary(seeds=seeds).mean, org.baseline_mean(scen, BEST_FIXED, seeds)
            curves = [history(r, EE_KEY) for r in runs]
            spreads = [last_evals_spread(values) for _, values in curves]
            spread = max(spreads) if spreads and all(math.isfinite(s) for s in spreads) else math.nan
            budgets = sorted({r.params.get("stop.env_steps", "") for r in runs})
            trained = sorted({int(steps[-1]) for steps, _ in curves if len(steps)})
            share, target = ee / ref.mean, share_target(ref.mode, scen[1])
            judged = len(runs) >= JUDGED_SEEDS and all(b.isdigit() and int(b) >= JUDGED_ENV_STEPS for b in budgets)
            judged = judged and all(t >= JUDGED_ENV_STEPS for t in trained)
            rows.append({
                "n_eds": scen[0], "n_uavs": scen[1], "action_mode": ref.mode, "algorithm": cell.algorithm,
                "n_seeds": len(runs), "unmatched_seeds": " ".join(s for s in cell.seeds if s not in seeds),
                "env_steps": "/".join(b for b in budgets if b) or "",
                "trained_env_steps": "/".join(str(t) for t in trained),
                "reference_baseline": ref.name, "share_of_reference": share,
                "best_fixed_share_of_reference": bf / ref.mean, "share_of_best_fixed": ee / bf,
                "above_best_fixed": "" if not math.isfinite(bf) else str(ee > bf).lower(),
                "max_last_evals_spread": spread,
                "settled": "" if not math.isfinite(spread) else str(spread <= SWING_LIMIT).lower(),
                "share_target": target,
                "meets_share_target": str(share >= target).lower() if judged and math.isfinite(share) else "",
            })  # fmt: skip
    return rows


def learning_md(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "_No learning verdicts: they need training runs and a reference baseline run of the same scenario._"
    header = [
        "V",
        "U",
        "mode",
        "learner",
        "matched seeds",
        "env steps trained (budget)",
        "share of reference",
        "best_fixed share",
        "x best_fixed",
        "above best_fixed",
        f"last {LAST_EVALS} evals spread (max over seeds)",
        f"settled (<= {SWING_LIMIT})",
        "share target",
        "met",
    ]
    body = [[str(r["n_eds"]), str(r["n_uavs"]), r["action_mode"], r["algorithm"],
             str(r["n_seeds"]) + (f" (left out: {r['unmatched_seeds']})" if r["unmatched_seeds"] else ""), f"{r['trained_env_steps'] or 'n/a'} ({r['env_steps'] or 'n/a'})",
             fmt(r["share_of_reference"], ".3f"), fmt(r["best_fixed_share_of_reference"], ".3f"),
             fmt(r["share_of_best_fixed"], ".3f"), r["above_best_fixed"] or "n/a",
             fmt(r["max_last_evals_spread"], ".3f"), r["settled"] or "n/a (too few evaluations)",
             fmt(r["share_target"], ".2f"),
             r["meets_share_target"] or f"n/a (needs {JUDGED_SEEDS} seeds at {JUDGED_ENV_STEPS:,})"] for r in rows]  # fmt: skip
    return md_table(header, body)
