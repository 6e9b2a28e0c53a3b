"""Aggregates over seeds AND scenarios, as rliable computes them (Agarwal et al., NeurIPS 2021):
the IQM and the mean of the normalised scores with stratified-bootstrap 95% intervals, the
probability that the reference learner (MAPPO by default) beats each other learner, and the
performance profile. The statistics are analysis.stats's; this module builds their inputs and
the table rows. No drawing and no file writing here (figures.fig_profile draws the profile).

Normalised score: a seed's execution EE (`eval/ee_sys_mean`) as a share of its scenario's
reference, Organised.reference (the per-slot optimum where `optimal` ran, else `greedy`), the
same denominator as every "share of reference" of the report; it makes the scenarios, whose EE
differs by orders of magnitude, comparable. Scenarios without a reference are left out.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from analysis import stats
from analysis.data import BEST_FIXED, KINDS, Organised
from analysis.tables import fmt, md_table

Scenario = tuple[int, int]

TABLE_AGGREGATE_COLUMNS = (
    "algorithm",
    "kind",
    "n_scenarios",
    "n_runs",  # (seed, scenario) scores pooled
    "scenarios",  # "V10U2 V20U2 ..."
    "iqm",
    "iqm_ci95_low",
    "iqm_ci95_high",
    "mean",
    "mean_ci95_low",
    "mean_ci95_high",
    "optimality_gap",  # 1 - mean(min(score, 1)): lower is better
    "optimality_gap_ci95_low",
    "optimality_gap_ci95_high",
)
TABLE_POI_COLUMNS = (
    "reference",
    "other",
    "other_kind",
    "n_scenarios",  # the scenarios both ran (with a reference)
    "scenarios",
    "probability_of_improvement",  # P(reference > other)
    "ci95_low",
    "ci95_high",
)
PROFILE_COLUMNS = ("algorithm", "n_scenarios", "n_runs", "tau", "fraction_above", "ci95_low", "ci95_high")
PROFILE_POINTS = 201


def _scen_label(scen: Scenario) -> str:
    return f"V{scen[0]}U{scen[1]}"


def score_sets(org: Organised) -> dict[str, dict[Scenario, np.ndarray]]:
    """{algorithm: {scenario: normalised scores, one per seed}} over the scenarios with a reference."""
    out: dict[str, dict[Scenario, np.ndarray]] = {}
    for cell in org.cells.values():
        scores = org.normalised(cell)
        if scores.size:
            out.setdefault(cell.algorithm, {})[cell.scenario] = scores
    return out


def _ordered(org: Organised, names) -> list[str]:
    return sorted(names, key=lambda a: (KINDS.index(org.kind_of(a)), a))


def aggregate_table(org: Organised, sets: dict[str, dict[Scenario, np.ndarray]]) -> list[dict[str, Any]]:
    """One row per algorithm: IQM, mean and optimality gap over its (seed, scenario) scores with 95%
    stratified-bootstrap CIs;
    learners first, each kind by descending IQM."""
    rows = []
    for alg in _ordered(org, sets):
        scens = sorted(sets[alg])
        strata = [sets[alg][s] for s in scens]
        row: dict[str, Any] = {
            "algorithm": alg,
            "kind": org.kind_of(alg),
            "n_scenarios": len(scens),
            "n_runs": sum(x.size for x in strata),
            "scenarios": " ".join(map(_scen_label, scens)),
        }
        for name, fn in (
            ("iqm", stats.aggregate_iqm),
            ("mean", stats.aggregate_mean),
            ("optimality_gap", stats.aggregate_optimality_gap),
        ):
            point, lo, hi = stats.stratified_bootstrap(fn, strata)
            row.update({name: float(point), f"{name}_ci95_low": float(lo), f"{name}_ci95_high": float(hi)})
        rows.append(row)
    # learners before baselines, each by descending IQM, then by name (as the per-cell table)
    return sorted(rows, key=lambda r: (KINDS.index(r["kind"]), -r["iqm"], r["algorithm"]))


def compared(org: Organised, sets: dict[str, dict[Scenario, np.ndarray]], reference: str | None) -> list[str]:
    """The algorithms the reference is compared with and the profile draws besides it: the other
    learners, and best_fixed, the open-loop floor a learner must beat."""
    return [a for a in _ordered(org, sets)
            if a != reference and (org.kind_of(a) == "train" or a == BEST_FIXED)]  # fmt: skip


def improvement_probability_table(
    org: Organised, sets: dict[str, dict[Scenario, np.ndarray]], reference: str | None
) -> list[dict[str, Any]]:
    """P(reference > other) over the scenarios both ran, with its 95% stratified-bootstrap CI."""
    rows: list[dict[str, Any]] = []
    if reference is None or reference not in sets:
        return rows
    for other in compared(org, sets, reference):
        scens = sorted(set(sets[reference]) & set(sets[other]))
        if not scens:
            continue
        strata = [sets[reference][s] for s in scens] + [sets[other][s] for s in scens]
        point, lo, hi = stats.stratified_bootstrap(stats.poi_statistic(len(scens)), strata)
        rows.append(
            {
                "reference": reference,
                "other": other,
                "other_kind": org.kind_of(other),
                "n_scenarios": len(scens),
                "scenarios": " ".join(map(_scen_label, scens)),
                "probability_of_improvement": float(point),
                "ci95_low": float(lo),
                "ci95_high": float(hi),
            }
        )
    return rows


def profile_taus(sets: dict[str, dict[Scenario, np.ndarray]], algorithms: list[str]) -> np.ndarray:
    """PROFILE_POINTS thresholds spanning the drawn algorithms' scores and the reference (1), with a
    5% margin on each side: every profile starts at 1 and ends at 0."""
    allv = np.concatenate([x for a in algorithms for x in sets[a].values()] or [np.ones(1)])
    lo, hi = float(allv.min()), max(1.0, float(allv.max()))
    pad = 0.05 * max(hi - lo, 0.1)
    return np.linspace(lo - pad, hi + pad, PROFILE_POINTS)


def performance_profiles(org: Organised, sets: dict[str, dict[Scenario, np.ndarray]], reference: str | None):
    """(taus, {algorithm: (fraction above tau, ci low, ci high)}) for the reference and compared()."""
    algs = ([reference] if reference in sets else []) + compared(org, sets, reference)
    taus = profile_taus(sets, algs)
    out = {}
    for alg in algs:
        strata = [sets[alg][s] for s in sorted(sets[alg])]
        out[alg] = stats.stratified_bootstrap(stats.performance_profile(taus), strata, n_boot=stats.PROFILE_RESAMPLES)
    return taus, out


def profile_rows(sets, taus: np.ndarray, profiles: dict) -> list[dict[str, Any]]:
    rows = []
    for alg, (frac, lo, hi) in profiles.items():
        n_s, n_r = len(sets[alg]), sum(x.size for x in sets[alg].values())
        rows += [
            {
                "algorithm": alg,
                "n_scenarios": n_s,
                "n_runs": n_r,
                "tau": float(t),
                "fraction_above": float(f),
                "ci95_low": float(a),
                "ci95_high": float(b),
            }
            for t, f, a, b in zip(taus, frac, lo, hi)
        ]
    return rows


def mixed_scenarios_note(rows: list[dict[str, Any]]) -> str | None:
    """A note when the learners' aggregates cover different scenarios (then they do not compare)."""
    learners = {r["algorithm"]: r["scenarios"] for r in rows if r["kind"] == "train"}
    if len(set(learners.values())) <= 1:
        return None
    return (
        "Aggregate table: the learners cover different scenarios ("
        + "; ".join(f"{a}: {s}" for a, s in sorted(learners.items()))
        + "); their IQM and mean compare only over the same scenarios (the probability of improvement uses "
        "the scenarios both ran)."
    )


def _ci(lo: float, hi: float, spec: str = ".3f") -> str:
    return f"[{fmt(lo, spec)}, {fmt(hi, spec)}]" if math.isfinite(lo) else "n/a (1 seed per scenario)"


def aggregate_md(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "_No aggregate: it needs FINISHED runs with eval metrics in a scenario with a reference baseline._"
    header = [
        "algorithm",
        "kind",
        "scenarios",
        "runs",
        "IQM",
        "95% CI (stratified bootstrap)",
        "mean",
        "95% CI (stratified bootstrap)",
        "optimality gap",
        "95% CI (stratified bootstrap)",
    ]
    body = [[r["algorithm"], r["kind"], f"{r['n_scenarios']} ({r['scenarios']})", str(r["n_runs"]),
             fmt(r["iqm"], ".3f"), _ci(r["iqm_ci95_low"], r["iqm_ci95_high"]),
             fmt(r["mean"], ".3f"), _ci(r["mean_ci95_low"], r["mean_ci95_high"]),
             fmt(r["optimality_gap"], ".3f"),
             _ci(r["optimality_gap_ci95_low"], r["optimality_gap_ci95_high"])] for r in rows]  # fmt: skip
    return md_table(header, body)


def improvement_probability_md(rows: list[dict[str, Any]], reference: str | None) -> str:
    if not rows:
        return (
            f"_No probability of improvement: it needs normalised scores of {reference or 'the reference'} and "
            "of another learner (or best_fixed) in a common scenario._"
        )
    ref = rows[0]["reference"]
    header = ["other", "kind", "common scenarios", f"P({ref} > other)", "95% CI (stratified bootstrap)"]
    body = [[r["other"], r["other_kind"], f"{r['n_scenarios']} ({r['scenarios']})",
             fmt(r["probability_of_improvement"], ".3f"), _ci(r["ci95_low"], r["ci95_high"])] for r in rows]  # fmt: skip
    return md_table(header, body)
