"""The learning-at-scale tables of BENCHMARKS.md from `learning.jsonl` (the rows of the retired
`bench_learn` driver, issue 13): every trial, then the mean over seeds with issue 13's verdict.

    python docs/history/measurements/final_defaults.py > /tmp/final.jsonl
    python docs/history/measurements/learning_table.py /tmp/final.jsonl

The verdict: mean greedy share >= 0.95 at U=2, 0.85 at U=4, 0.75 at U=8, judged only where >= 3
seeds ran at >= 200k env steps (else 'n/a'), and at V=10/U=2 the mean share at 60k. New learning
benchmarks run as grids (tune_configs/learning_*.yaml) and are judged by `python -m analysis.report`
(analysis/verdicts.py); this script only reads the historical rows. It imports nothing from the package.
"""

from __future__ import annotations

import json
import sys
from typing import Any, Sequence

DEFAULT_LEARNERS = ("mappo", "ippo", "qmix", "vdn", "coma")  # the table's learner order


def _fmt(x: Any, spec: str = ".3f") -> str:
    return "-" if x is None else format(x, spec)


def markdown_table(rows: Sequence[dict]) -> str:
    lines = [
        "| V | U | mode | learner | tag | seed | env steps | greedy share | sampled share | env steps to target | "
        "greedy x random | reference (bit/J) | random share | train s | wall s |",
        "|---:|---:|---|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['n_eds']} | {r['n_uavs']} | {r['action_mode']} | {r['learner']} | {r.get('tag') or ''} | {r['seed']} | "
            f"{r['env_steps']:,} | {_fmt(r['greedy_share'])} | {_fmt(r.get('sampled_share'))} | "
            f"{'-' if r['env_steps_to_target'] is None else format(r['env_steps_to_target'], ',')} "
            f"({r['target']:.0%}) | {r['greedy_ee'] / r['random_ee']:.2f} | {r['reference']} {r['reference_ee']:,.0f} | {r['random_ee'] / r['reference_ee']:.3f} | "
            f"{r['train_s']:.0f} | {r['wall_s']:.0f} |"
        )
    return "\n".join(lines)


# Issue 13's targets for the mean greedy share over >= 3 seeds at >= 200k env steps, by U; and
# at V=10/U=2 the mean greedy share at 60k env steps.
TARGET_SEEDS, TARGET_BUDGET = 3, 200_000
EARLY_TARGET = (10, 2, 60_000, 0.9)  # (V, U, env steps, share)


def share_target(n_uavs: int) -> float:
    """The greedy-share target of a scenario with n_uavs UAVs (0.95 / 0.85 / 0.75)."""
    return 0.95 if n_uavs <= 2 else 0.85 if n_uavs <= 4 else 0.75


def point_at(row: dict, env_steps: int) -> dict | None:
    """The last evaluation (curve point) at or before `env_steps` (None: none was made)."""
    points = [p for p in row["curve"] if p["env_steps"] <= env_steps]
    return points[-1] if points else None


def _mean(xs: Sequence[float | None]) -> float | None:
    xs = [x for x in xs if x is not None]
    return sum(xs) / len(xs) if xs else None


def summary_table(rows: Sequence[dict]) -> str:
    """One line per (scenario, mode, learner, tag, budget): the mean over seeds of the greedy and
    sampled shares, the worst seed, and the verdict on the target (issue 13), which needs
    >= TARGET_SEEDS seeds at >= TARGET_BUDGET env steps (else 'n/a'); at V=10/U=2 also the mean
    share of the last evaluation at or before 60k env steps (a miss only if that evaluation is at 60k)."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        key = (r["n_eds"], r["n_uavs"], r["action_mode"], r["learner"], r.get("tag") or "", r["budget_env_steps"])
        groups.setdefault(key, []).append(r)
    lines = [
        "| V | U | mode | learner | tag | budget | seeds | mean greedy share | worst seed | mean sampled share | "
        "target | verdict | mean share at 60k |",
        "|---:|---:|---|---|---|---:|---|---:|---:|---:|---:|---|---:|",
    ]
    def order(key: tuple) -> tuple:  # the scenario order (by U, then V), learners as registered
        v, u, mode, learner, tag, budget = key
        rank = DEFAULT_LEARNERS.index(learner) if learner in DEFAULT_LEARNERS else len(DEFAULT_LEARNERS)
        return (u, v, mode, rank, learner, budget, tag)

    for (v, u, mode, learner, tag, budget), rs in sorted(groups.items(), key=lambda kv: order(kv[0])):
        rs = sorted(rs, key=lambda r: r["seed"])
        greedy = _mean([r["greedy_share"] for r in rs])
        worst = min(r["greedy_share"] for r in rs)
        target = share_target(u)
        enough = len({r["seed"] for r in rs}) >= TARGET_SEEDS and budget >= TARGET_BUDGET
        verdict = "n/a" if mode != "per_uav" or not enough else ("met" if greedy >= target else "missed")
        early = "-"
        if (v, u) == EARLY_TARGET[:2] and mode == "per_uav":
            points = [point_at(r, EARLY_TARGET[2]) for r in rs]
            if None not in points:  # a mean over seeds needs a point of every seed
                at = _mean([p["greedy_share"] for p in points])
                # a share reached by an earlier evaluation was reached within 60k; a miss needs the
                # evaluation at 60k itself (rows evaluated every 40k only have 40.8k before it)
                last = min(p["env_steps"] for p in points)
                if at >= EARLY_TARGET[3]:
                    early = f"{_fmt(at)} met"
                elif last >= 0.95 * EARLY_TARGET[2]:
                    early = f"{_fmt(at)} missed"
                else:
                    early = f"{_fmt(at)} at {last:,}: n/a"
        seeds = ",".join(str(r["seed"]) for r in rs)
        lines.append(
            f"| {v} | {u} | {mode} | {learner} | {tag} | {budget:,} | {seeds} | {_fmt(greedy)} | {_fmt(worst)} | "
            f"{_fmt(_mean([r.get('sampled_share') for r in rs]))} | {target:.2f} | {verdict} | {early} |"
        )
    return "\n".join(lines)


def read_results(path: str) -> list[dict]:
    rows = []
    with open(path) as f:
        for n, line in enumerate(f, 1):
            if line.strip():
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    raise SystemExit(f"error: line {n} of {path} is not JSON (a trial cut while being written?)") from None
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else list(argv)
    if len(args) != 1 or args[0].startswith("-"):
        print("usage: python docs/history/measurements/learning_table.py RESULTS.jsonl", file=sys.stderr)
        return 2
    rows = read_results(args[0])
    print(markdown_table(rows))
    print(f"\nMean over seeds (targets: greedy share >= 0.95 at U=2, 0.85 at U=4, 0.75 at U=8, mean of "
          f">= {TARGET_SEEDS} seeds at >= {TARGET_BUDGET:,} env steps; V=10/U=2 >= 0.9 at 60k):\n")
    print(summary_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
