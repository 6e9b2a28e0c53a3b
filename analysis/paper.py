"""The paper's reported results beside ours (Fig. 3b, U = 2), with a verdict per cell.

The paper (uav-lora-mappo-vtc2026.tex, Section V, the paragraph on Fig. 3(b)) reports, from the
execution phase averaged over three seeds: MAPPO improves EE over the second-best algorithm,
VDN, by 36.02, 3.29, 8.30, 39.01, 11.29 and 7.91 % for V = 10, 20, 40, 60, 80, 100 active EDs
(U = 2 UAVs), and "outperforms QMIX by more than a factor of two in most cases".

Ours, per V at U = 2: the improvement 100 (ratio - 1) of the seed-mean execution EE of mappo
over vdn, and the ratio mappo / qmix, each with its 95% Fieller interval over seeds
(analysis.stats.ratio_ci95). Verdicts: "not run" (a cell is missing), "too few seeds" (fewer
than MIN_SEEDS on a side: the interval would not mean much), "inside our CI" / "outside our CI"
for the VDN numbers, and for the QMIX claim "agrees" (interval above 2), "disagrees" (below 2)
or "undecided" (interval contains 2); "not comparable" where the runs are not of the paper's
scenario (another action mode, rate model, reward, episode length, ...: any scenario.* param off
ScenarioConfig's defaults).
"""

from __future__ import annotations

import math
from typing import Any

from analysis import stats
from analysis.data import MIN_SEEDS, Organised
from analysis.tables import fmt, md_table

PAPER_U = 2
PAPER_VDN_IMPROVEMENT_PCT = {10: 36.02, 20: 3.29, 40: 8.30, 60: 39.01, 80: 11.29, 100: 7.91}
PAPER_QMIX_FACTOR = 2.0  # "more than a factor of two over QMIX in most cases"
OURS, VDN, QMIX = "mappo", "vdn", "qmix"

PAPER_COLUMNS = (
    "n_eds",
    "n_uavs",
    "other",
    "paper_claim",
    "ours_point",
    "ours_ci95_low",
    "ours_ci95_high",
    "n_seeds_mappo",
    "n_seeds_other",
    "verdict",
)


def paper_scenario_params(v: int) -> dict[str, str]:
    """The scenario.* params of the paper's scenario at V EDs and U = 2 (ScenarioConfig's defaults
    are the paper's model, docs/model.md), as a run logs them."""
    from analysis.runs import resolved_params
    from uavlora_rllib.experiment.run_schema import run_params
    from uavlora_rllib.sim.scenario import ScenarioConfig

    params = resolved_params(run_params(ScenarioConfig(n_eds=v, n_uavs=PAPER_U), None, 1))
    return {k: val for k, val in params.items() if k.startswith("scenario.")}


def _not_the_papers(org: Organised, v: int, names: tuple[str, ...], paper: dict[str, str]) -> list[str]:
    """The scenario settings in which the cells' runs differ from the paper's (`paper`,
    paper_scenario_params) as "key value"; a param an older run did not log is not counted."""
    found: dict[str, set[str]] = {}
    for name in names:
        cell = org.cells.get((v, PAPER_U, name))
        for run in cell.runs if cell is not None else []:
            for k, val in run.params.items():
                if k in paper and val != paper[k]:
                    found.setdefault(k, set()).add(val)
    return [f"{k} {'/'.join(sorted(vals))}" for k, vals in sorted(found.items())]


def _values(org: Organised, v: int, name: str):
    """The per-seed execution EE of a learner at (V, U=2); None when it has no valid run."""
    cell = org.cells.get((v, PAPER_U, name))
    return cell.values() if cell is not None and cell.runs else None  # valid runs: all finite


def _verdict_common(a, b) -> str | None:
    if a is None or b is None:
        return "not run"
    if min(a.size, b.size) < MIN_SEEDS:
        return f"too few seeds (need {MIN_SEEDS} a side)"
    return None


def paper_rows(org: Organised) -> list[dict[str, Any]]:
    """One row per paper V and comparison (vdn: improvement %, qmix: ratio)."""
    rows = []
    for v, paper_pct in PAPER_VDN_IMPROVEMENT_PCT.items():
        a = _values(org, v, OURS)
        paper = paper_scenario_params(v)
        for other in (VDN, QMIX):
            b = _values(org, v, other)
            point = lo = hi = math.nan
            if a is not None and b is not None and a.size and b.size and b.mean() != 0:
                ratio = float(a.mean() / b.mean())
                rlo, rhi = stats.ratio_ci95(a, b)
                if other == VDN:
                    point, lo, hi = 100 * (ratio - 1), 100 * (rlo - 1), 100 * (rhi - 1)
                else:
                    point, lo, hi = ratio, rlo, rhi
            verdict = _verdict_common(a, b)
            other_scenario = _not_the_papers(org, v, (OURS, other), paper)
            # the paper's numbers are of its own scenario only: said before any count of seeds
            if verdict != "not run" and other_scenario:
                verdict = f"not comparable: not the paper's scenario ({', '.join(other_scenario)})"
            if verdict is None:
                if not (math.isfinite(lo) and math.isfinite(hi)):
                    verdict = "undecided (our CI is unbounded)"
                elif other == VDN:
                    verdict = (
                        "inside our CI"
                        if lo <= paper_pct <= hi
                        else (f"outside our CI (ours {'lower' if hi < paper_pct else 'higher'})")
                    )
                elif lo > PAPER_QMIX_FACTOR:
                    verdict = "agrees (our CI above 2x)"
                elif hi < PAPER_QMIX_FACTOR:
                    verdict = "disagrees (our CI below 2x)"
                else:
                    verdict = "undecided (our CI contains 2x)"
            rows.append(
                {
                    "n_eds": v,
                    "n_uavs": PAPER_U,
                    "other": other,
                    "paper_claim": f"{paper_pct:+.2f}%" if other == VDN else f"> {PAPER_QMIX_FACTOR:g}x (most V)",
                    "ours_point": point,
                    "ours_ci95_low": lo,
                    "ours_ci95_high": hi,
                    "n_seeds_mappo": 0 if a is None else int(a.size),
                    "n_seeds_other": 0 if b is None else int(b.size),
                    "verdict": verdict,
                }
            )
    return rows


def _ci(lo: float, hi: float, spec: str) -> str:
    if math.isnan(lo):
        return "n/a"
    if math.isinf(lo) or math.isinf(hi):
        return "unbounded"
    return f"[{format(lo, spec)}, {format(hi, spec)}]"


def paper_md(rows: list[dict[str, Any]]) -> str:
    """Two tables (VDN improvement, QMIX factor) and a one-line summary of the QMIX claim."""
    parts = []
    for other, what, spec, unit in (
        (VDN, "MAPPO over VDN (%)", "+.2f", ""),
        (QMIX, "MAPPO / QMIX (factor)", ".3g", "x"),
    ):
        header = ["V", "U", f"paper: {what}", "ours", "ours 95% CI (Fieller)", "seeds mappo / " + other, "verdict"]
        body = []
        for r in (r for r in rows if r["other"] == other):
            body.append(
                [
                    str(r["n_eds"]),
                    str(r["n_uavs"]),
                    r["paper_claim"],
                    fmt(r["ours_point"], spec) + (unit if math.isfinite(r["ours_point"]) else ""),
                    _ci(r["ours_ci95_low"], r["ours_ci95_high"], spec),
                    f"{r['n_seeds_mappo']} / {r['n_seeds_other']}",
                    r["verdict"],
                ]
            )
        parts.append(md_table(header, body))
    q = [r for r in rows if r["other"] == QMIX and math.isfinite(r["ours_point"])]
    above = sum(r["ours_point"] > PAPER_QMIX_FACTOR for r in q)
    ci_above = sum(r["verdict"].startswith("agrees") for r in q)
    parts.append(
        f'QMIX claim ("more than a factor of two in most cases"): ours is above 2x at {above} of {len(q)} '
        f"V value(s) with both algorithms run (point estimate), with the whole 95% CI above 2x at {ci_above}."
    )
    return "\n\n".join(parts)
