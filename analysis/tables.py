"""The report's tables: execution-phase EE per cell, the reference algorithm's improvements,
as rows (for CSV) and as Markdown. Statistics come from analysis.stats; cells from analysis.data.
"""

from __future__ import annotations

import csv
import math
from collections import defaultdict
from collections.abc import Sequence
from typing import Any

from analysis import stats
from analysis.data import BEST_FIXED, KINDS, MIN_SEEDS, OPTIMAL, Cell, Organised
from analysis.runs import EE_KEY, SAMPLED_EE_KEY

TABLE_EE_COLUMNS = (
    "n_eds",
    "n_uavs",
    "algorithm",
    "kind",
    "n_seeds",
    "seeds",
    "ee_mean",
    "ee_ci95_low",
    "ee_ci95_high",
    "ee_iqm",
    "ee_std",
    "ee_episode_sum_mean",
    "sampled_ee_mean",
    "sampled_share_of_reference",
    "success_rate_mean",
    "reference_baseline",  # "optimal" where the scenario has it, else "greedy", else empty
    "share_of_reference",  # ee_mean / the reference's seed-mean EE
    "reference_improvement_pct",
    "n_unfinished",
    "n_without_eval",
)
# best_fixed's share of the reference from which a constant counts as optimal (the issue's
# threshold: learners cannot be told apart there)
OPEN_LOOP_SHARE = 0.98
TABLE_OPEN_LOOP_COLUMNS = (
    "n_eds",
    "n_uavs",
    "action_mode",
    "reference_baseline",
    "ee_reference",
    "ee_upper_bound",  # seed mean of the reference's eval/ee_sys_upper_bound
    "reference_share_of_bound",  # the optimum lies between the reference and the bound
    "ee_best_fixed",
    "best_fixed_share_of_reference",
    "constant_is_optimal",  # share >= OPEN_LOOP_SHARE
)
TABLE_IMP_COLUMNS = (
    "n_eds",
    "n_uavs",
    "reference",
    "other",
    "other_kind",
    "ee_reference",
    "ee_other",
    "improvement_pct",
    "is_second_best",
)


def fmt(x: Any, spec: str = ".6g") -> str:
    """A number for Markdown; n/a for None, NaN and inf."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return format(x, spec)


def order(cells: list[Cell]) -> list[Cell]:
    """Learners before baselines, each by descending seed-mean EE, then by name."""

    def key(c: Cell):
        m = c.summary().mean
        return (KINDS.index(c.kind), -(m if math.isfinite(m) else -math.inf), c.algorithm)

    return sorted(cells, key=key)


def ee_table(org: Organised, reference: str | None) -> list[dict[str, Any]]:
    rows = []
    for scen in org.scenarios():
        ref_base = org.reference(scen)
        ref = org.cells.get((*scen, reference)) if reference else None
        ref_mean = ref.summary().mean if ref is not None else math.nan
        for c in order(org.cells_of(scen)):
            s = c.summary()
            # a share divides by the reference on the same evaluation episodes: over the seeds both ran
            # (Organised.matched_seeds), as every other share of the report; the EE columns keep all seeds
            seeds = org.matched_seeds(c)
            ref_seeds = org.reference(scen, seeds) if seeds else None
            rows.append(
                {
                    "n_eds": c.n_eds,
                    "n_uavs": c.n_uavs,
                    "algorithm": c.algorithm,
                    "kind": c.kind,
                    "n_seeds": s.n,
                    "seeds": " ".join(c.seeds),
                    "ee_mean": s.mean,
                    "ee_ci95_low": s.ci_low,
                    "ee_ci95_high": s.ci_high,
                    "ee_iqm": s.iqm,
                    "ee_std": s.std,
                    "ee_episode_sum_mean": c.mean_of("eval/ee_sys_episode_sum"),
                    "success_rate_mean": c.mean_of("eval/success_rate"),
                    # the same episodes played with actions drawn from the trained policy (learners only)
                    "sampled_ee_mean": c.mean_of(SAMPLED_EE_KEY),
                    "sampled_share_of_reference": (
                        c.mean_of(SAMPLED_EE_KEY, seeds) / ref_seeds.mean if ref_seeds else math.nan
                    ),
                    "reference_baseline": ref_base.name if ref_base else "",
                    "share_of_reference": c.mean_of(EE_KEY, seeds) / ref_seeds.mean if ref_seeds else math.nan,
                    "reference_improvement_pct": (
                        stats.improvement_pct(ref_mean, s.mean) if c.algorithm != reference else math.nan
                    ),
                    "n_unfinished": len(c.unfinished),
                    "n_without_eval": len(c.no_eval),
                }
            )
    return rows


def improvement_table(org: Organised, reference: str | None) -> list[dict[str, Any]]:
    """The reference's improvement over every other algorithm of each scenario; the second best
    is the best OTHER LEARNING algorithm (kind=train) by seed-mean EE, as in the paper."""
    rows: list[dict[str, Any]] = []
    if reference is None:
        return rows
    for scen in org.scenarios():
        ref = org.cells.get((*scen, reference))
        if ref is None or not ref.runs:
            continue
        ref_mean = ref.summary().mean
        others = [c for c in org.cells_of(scen) if c.algorithm != reference and c.runs]
        learners = [c for c in others if c.kind == "train"]
        second = max(learners, key=lambda c: c.summary().mean).algorithm if learners else None
        for c in order(others):
            m = c.summary().mean
            rows.append(
                {
                    "n_eds": scen[0],
                    "n_uavs": scen[1],
                    "reference": reference,
                    "other": c.algorithm,
                    "other_kind": c.kind,
                    "ee_reference": ref_mean,
                    "ee_other": m,
                    "improvement_pct": stats.improvement_pct(ref_mean, m),
                    "is_second_best": c.algorithm == second,
                }
            )
    return rows


def write_csv(path: str, columns: Sequence[str], rows: list[dict[str, Any]]) -> None:
    """Rows as CSV; NaN and inf as empty cells."""
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        for row in rows:
            w.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()})


def md_table(header: Sequence[str], rows: list[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def ee_table_md(rows: list[dict[str, Any]], reference: str | None) -> str:
    ref = reference or "reference"
    header = [
        "V",
        "U",
        "algorithm",
        "kind",
        "seeds",
        "EE mean (bit/J)",
        "95% CI (t)",
        "IQM",
        "success rate",
        "share of reference",
        "sampled EE mean (bit/J)",
        "sampled share",
        f"{ref} over this (%)",
        "left out",
    ]
    body = []
    for r in rows:
        ci = (
            f"[{fmt(r['ee_ci95_low'])}, {fmt(r['ee_ci95_high'])}]" if math.isfinite(r["ee_ci95_low"]) else "n/a (n < 2)"
        )
        left = []
        if r["n_unfinished"]:
            left.append(f"{r['n_unfinished']} unfinished")
        if r["n_without_eval"]:
            left.append(f"{r['n_without_eval']} without eval")
        share = fmt(r["share_of_reference"], ".3f")
        if r["reference_baseline"]:
            share += f" of {r['reference_baseline']}"
        body.append(
            [
                str(r["n_eds"]),
                str(r["n_uavs"]),
                r["algorithm"],
                r["kind"],
                str(r["n_seeds"]) + (" (!)" if r["n_seeds"] < MIN_SEEDS else ""),
                fmt(r["ee_mean"]),
                ci,
                fmt(r["ee_iqm"]),
                fmt(r["success_rate_mean"], ".3f"),
                share,
                fmt(r["sampled_ee_mean"]) if math.isfinite(r["sampled_ee_mean"]) else "-",
                fmt(r["sampled_share_of_reference"], ".3f") if math.isfinite(r["sampled_share_of_reference"]) else "-",
                fmt(r["reference_improvement_pct"], "+.2f"),
                ", ".join(left) or "-",
            ]
        )
    return md_table(header, body)


def improvement_md(rows: list[dict[str, Any]], reference: str | None) -> str:
    if not rows:
        return (
            f"_No improvement table: it needs FINISHED runs with eval metrics of {reference or 'the reference'} "
            "and of at least one other algorithm in the same scenario._"
        )
    by_scen: dict[tuple[int, int], list[dict[str, Any]]] = defaultdict(list)
    for r in rows:
        by_scen[(r["n_eds"], r["n_uavs"])].append(r)
    others = sorted({r["other"] for r in rows})
    header = ["V", "U", f"{reference} EE", "second best", "over second best (%)"] + [f"over {o} (%)" for o in others]
    body = []
    for scen in sorted(by_scen):
        rs = by_scen[scen]
        second = next((r for r in rs if r["is_second_best"]), None)
        imp = {r["other"]: r["improvement_pct"] for r in rs}
        body.append(
            [
                str(scen[0]),
                str(scen[1]),
                fmt(rs[0]["ee_reference"]),
                second["other"] if second else "n/a",
                fmt(second["improvement_pct"], "+.2f") if second else "n/a",
            ]
            + [fmt(imp.get(o, math.nan), "+.2f") for o in others]
        )
    return md_table(header, body)


def open_loop_table(org: Organised) -> list[dict[str, Any]]:
    """Per scenario with a reference: the reference, its upper bound, and best_fixed's share."""
    rows = []
    for scen in org.scenarios():
        bf_cell = org.cells.get((*scen, BEST_FIXED))
        # over the seeds both ran (each seed has its own evaluation episodes); the reference alone without best_fixed
        seeds = org.matched_seeds(bf_cell) if bf_cell is not None and bf_cell.kind == "baseline" else None
        ref = org.reference(scen, seeds or None)
        if ref is None:
            continue
        bf = org.baseline_mean(scen, BEST_FIXED, seeds or None)
        share = bf / ref.mean
        rows.append({
            "n_eds": scen[0], "n_uavs": scen[1], "action_mode": ref.mode, "reference_baseline": ref.name,
            "ee_reference": ref.mean, "ee_upper_bound": ref.bound, "reference_share_of_bound": ref.mean / ref.bound,
            "ee_best_fixed": bf, "best_fixed_share_of_reference": share,
            "constant_is_optimal": "" if not math.isfinite(share) else str(share >= OPEN_LOOP_SHARE).lower(),
        })  # fmt: skip
    return rows


def open_loop_verdict(r: dict[str, Any]) -> str:
    """One plain sentence on the open-loop check of a scenario."""
    where = f"V={r['n_eds']} U={r['n_uavs']} ({r['action_mode']})"
    share = r["best_fixed_share_of_reference"]
    if not math.isfinite(share):
        return f"{where}: no best_fixed run, so no open-loop check."
    if share >= OPEN_LOOP_SHARE:
        return (
            f"{where}: a constant action is optimal here (best_fixed reaches {share:.3f} of the "
            f"{r['reference_baseline']} reference): the observations are not needed, and learners cannot be "
            "told apart on this scenario."
        )
    return (
        f"{where}: best_fixed reaches {share:.3f} of the {r['reference_baseline']} reference: acting on the "
        "observations pays, so this scenario can rank learners."
    )


def open_loop_md(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "_No open-loop check: it needs a reference baseline run (optimal or greedy) of a scenario._"
    header = [
        "V",
        "U",
        "mode",
        "reference",
        "reference EE (bit/J)",
        "upper bound (bit/J)",
        "reference / bound",
        "best_fixed EE (bit/J)",
        "best_fixed share",
        f"constant optimal (>= {OPEN_LOOP_SHARE})",
    ]
    body = []
    for r in rows:
        exact = r["reference_baseline"] == OPTIMAL
        body.append([str(r["n_eds"]), str(r["n_uavs"]), r["action_mode"],
                     r["reference_baseline"] + (" (exact)" if exact else " (lower bound on the optimum)"),
                     fmt(r["ee_reference"]), fmt(r["ee_upper_bound"]), fmt(r["reference_share_of_bound"], ".3f"),
                     fmt(r["ee_best_fixed"]), fmt(r["best_fixed_share_of_reference"], ".3f"),
                     r["constant_is_optimal"] or "n/a"])  # fmt: skip
    return md_table(header, body) + "\n\n" + "\n".join(f"- {open_loop_verdict(r)}" for r in rows)
