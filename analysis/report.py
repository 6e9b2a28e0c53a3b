"""The analysis step: the paper's Fig. 2, Fig. 3a-c and result tables from one MLflow experiment.

    python -m analysis.report --experiment NAME [--tracking-uri URI] [--out DIR]
        [--reference mappo] [--smooth 0.6] [--points 200] [--fig2-seed 0] [--no-fig2] [--no-log]

Reads the experiment's runs with MlflowClient (tags/params/metrics of the Tune callback's
schema; never Ray's result folders) and writes into DIR (default reports/NAME):

* fig3a.{png,svg}: training curve episode_return_mean against env steps, one curve per
  algorithm (mean over seeds, shaded 95% bootstrap band), for the paper's scenario V=10, U=2
  if present (else the scenario with the most training runs); fig3a_all.{png,svg} with one
  panel per scenario when there are several; fig3a_curves.csv with the plotted numbers.
* fig3b.{png,svg}: execution-phase eval/ee_sys_mean against V at the most common U;
  fig3c.{png,svg}: against U at the most common V; learners and baselines, 95% t CI bars.
  A figure whose axis has a single value is skipped (a note says so in report.md).
* fig2.{png,svg}: ED-UAV association at the last slot of one evaluation episode, played by
  the best reference-algorithm run's final checkpoint when it loads, else by `greedy`.
* table_ee.{csv,md}, table_improvement.{csv,md}; report.md linking all of it, with the
  source (grid file, commit, budgets, seeds) and a WARNING line for every cell with fewer
  than 3 seeds, unfinished runs, or runs without eval metrics.

Finally everything is logged as artifacts of the experiment's summary run (tag kind=summary;
the previous summary run is reused and its artifacts replaced). Statistics: analysis.stats.
A bad experiment name or an unreachable tracking URI prints one error line, exit code 2.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import shutil
import sys
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from typing import Any, Sequence
from urllib.parse import urlparse

import numpy as np

from analysis import stats, style
from analysis.runs import (
    EE_KEY,
    SUMMARY_KIND,
    ReportError,
    RunRecord,
    connect,
    find_experiment,
    load_runs,
    metric_history,
    scenario_dict,
)

PAPER_SCENARIO = (10, 2)  # Fig. 2 and Fig. 3a: V = 10 EDs, U = 2 UAVs
PAPER_FIXED_U = 2  # Fig. 3b
PAPER_FIXED_V = 60  # Fig. 3c
MIN_SEEDS = 3
CURVE_METRIC = "episode_return_mean"
KINDS = ("train", "baseline")
# Every file the report may write (nothing else in --out is touched or logged).
OUTPUT_FILES = tuple(
    [f"{stem}.{ext}" for stem in ("fig2", "fig3a", "fig3a_all", "fig3b", "fig3c") for ext in ("png", "svg")]
    + ["fig3a_curves.csv", "table_ee.csv", "table_ee.md", "table_improvement.csv", "table_improvement.md", "report.md"]
)
OPTIMAL = "optimal"


# ---------------------------------------------------------------- cells
@dataclass
class Cell:
    """All runs of one (V, U, algorithm): the valid ones (FINISHED with eval metrics), the rest."""

    n_eds: int
    n_uavs: int
    algorithm: str
    kind: str
    runs: list[RunRecord] = field(default_factory=list)
    unfinished: list[RunRecord] = field(default_factory=list)
    no_eval: list[RunRecord] = field(default_factory=list)
    duplicates: list[RunRecord] = field(default_factory=list)

    @property
    def key(self) -> tuple[int, int, str]:
        return (self.n_eds, self.n_uavs, self.algorithm)

    def values(self, metric: str = EE_KEY) -> np.ndarray:
        return np.array([r.metrics.get(metric, math.nan) for r in self.runs], dtype=float)

    def summary(self, metric: str = EE_KEY) -> stats.SeedSummary:
        v = self.values(metric)
        return stats.summarize(v[np.isfinite(v)])

    def mean_of(self, metric: str) -> float:
        v = self.values(metric)
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else math.nan

    @property
    def seeds(self) -> list[str]:
        return [str(r.seed) for r in self.runs]


@dataclass
class Organised:
    cells: dict[tuple[int, int, str], Cell]
    warnings: list[str]
    records: list[RunRecord]

    def scenarios(self) -> list[tuple[int, int]]:
        return sorted({(c.n_eds, c.n_uavs) for c in self.cells.values()})

    def cells_of(self, scenario: tuple[int, int]) -> list[Cell]:
        return [c for c in self.cells.values() if (c.n_eds, c.n_uavs) == scenario]

    def algorithms(self, kind: str | None = None) -> list[str]:
        return sorted({c.algorithm for c in self.cells.values() if kind is None or c.kind == kind})


def organise(records: list[RunRecord]) -> Organised:
    warnings: list[str] = []
    train_names = {r.algorithm for r in records if r.kind == "train" and r.algorithm}
    cells: dict[tuple[int, int, str], Cell] = {}
    for r in records:
        if r.kind not in KINDS:
            warnings.append(f"{r.label}: unknown kind {r.kind!r} (expected train or baseline); skipped")
            continue
        if not r.algorithm:
            warnings.append(f"{r.label}: no 'algorithm' tag; skipped")
            continue
        if r.scenario_key is None:
            warnings.append(f"{r.label}: no n_eds / n_uavs tag or scenario param; skipped")
            continue
        name = r.algorithm
        if r.kind == "baseline" and name in train_names:
            name = f"{name} (baseline)"
        key = (r.n_eds, r.n_uavs, name)
        cell = cells.get(key)
        if cell is None:
            cell = cells[key] = Cell(r.n_eds, r.n_uavs, name, r.kind)
        if r.status != "FINISHED":
            cell.unfinished.append(r)
        elif not r.has_eval:
            cell.no_eval.append(r)
        else:
            cell.runs.append(r)
    for cell in cells.values():
        # one run per seed: the newest FINISHED one (records are sorted by start time)
        by_seed: dict[str, RunRecord] = {}
        for r in cell.runs:
            seed = str(r.seed) if r.seed is not None else r.run_id
            if seed in by_seed:
                cell.duplicates.append(by_seed[seed])
            by_seed[seed] = r
        cell.runs = sorted(by_seed.values(), key=lambda r: str(r.seed))
    for key in sorted(cells):
        cell = cells[key]
        where = f"V={cell.n_eds} U={cell.n_uavs} {cell.algorithm} ({cell.kind})"
        if len(cell.runs) < MIN_SEEDS:
            seeds = ", ".join(cell.seeds) or "none"
            warnings.append(
                f"{where}: only {len(cell.runs)} seed(s) with eval metrics (seeds: {seeds}); "
                f"fewer than {MIN_SEEDS}, statistics are weak"
            )
        for r in cell.unfinished:
            warnings.append(f"{where}: unfinished run left out: {r.label}")
        for r in cell.no_eval:
            warnings.append(f"{where}: run without eval metrics ({EE_KEY}) left out: {r.label}")
        for r in cell.duplicates:
            warnings.append(f"{where}: seed {r.seed} has several finished runs; the newest is used, left out: {r.label}")
    return Organised(cells, warnings, records)


def _pick(counter: Counter, preferred: int) -> int | None:
    if not counter:
        return None
    top = max(counter.values())
    best = sorted(k for k, v in counter.items() if v == top)
    return preferred if preferred in best else best[0]


def _find_reference(org: Organised, reference: str) -> str | None:
    for name in org.algorithms("train"):
        if name.lower() == reference.lower():
            return name
    return None


# ---------------------------------------------------------------- tables
def _fmt(x: float, spec: str = ".6g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return format(x, spec)


def _order(cells: list[Cell]) -> list[Cell]:
    def key(c: Cell):
        m = c.summary().mean
        return (KINDS.index(c.kind), -(m if math.isfinite(m) else -math.inf), c.algorithm)

    return sorted(cells, key=key)


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
    "success_rate_mean",
    "share_of_optimum",
    "reference_improvement_pct",
    "n_unfinished",
    "n_without_eval",
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


def ee_table(org: Organised, reference: str | None) -> list[dict[str, Any]]:
    rows = []
    for scen in org.scenarios():
        cells = _order(org.cells_of(scen))
        opt = org.cells.get((*scen, OPTIMAL))
        opt_mean = opt.summary().mean if opt is not None and opt.kind == "baseline" else math.nan
        ref = org.cells.get((*scen, reference)) if reference else None
        ref_mean = ref.summary().mean if ref is not None else math.nan
        for c in cells:
            s = c.summary()
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
                    "share_of_optimum": s.mean / opt_mean if math.isfinite(opt_mean) and opt_mean != 0 else math.nan,
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
        for c in _order(others):
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


def _write_csv(path: str, columns: Sequence[str], rows: list[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(columns))
        w.writeheader()
        for row in rows:
            w.writerow({k: ("" if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()})


def _md_table(header: Sequence[str], rows: list[Sequence[str]]) -> str:
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
        "share of optimum",
        f"{ref} over this (%)",
        "left out",
    ]
    body = []
    for r in rows:
        ci = (
            f"[{_fmt(r['ee_ci95_low'])}, {_fmt(r['ee_ci95_high'])}]"
            if math.isfinite(r["ee_ci95_low"])
            else "n/a"
        )
        left = []
        if r["n_unfinished"]:
            left.append(f"{r['n_unfinished']} unfinished")
        if r["n_without_eval"]:
            left.append(f"{r['n_without_eval']} without eval")
        body.append(
            [
                str(r["n_eds"]),
                str(r["n_uavs"]),
                r["algorithm"],
                r["kind"],
                str(r["n_seeds"]) + (" (!)" if r["n_seeds"] < MIN_SEEDS else ""),
                _fmt(r["ee_mean"]),
                ci,
                _fmt(r["ee_iqm"]),
                _fmt(r["success_rate_mean"], ".3f"),
                _fmt(r["share_of_optimum"], ".3f"),
                _fmt(r["reference_improvement_pct"], "+.2f"),
                ", ".join(left) or "-",
            ]
        )
    return _md_table(header, body)


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
                _fmt(rs[0]["ee_reference"]),
                second["other"] if second else "n/a",
                _fmt(second["improvement_pct"], "+.2f") if second else "n/a",
            ]
            + [_fmt(imp.get(o, math.nan), "+.2f") for o in others]
        )
    return _md_table(header, body)


# ---------------------------------------------------------------- figures
def _scen_title(scen: tuple[int, int]) -> str:
    return f"V={scen[0]} EDs, U={scen[1]} UAVs"


def training_curves(client, org: Organised, smooth: float, points: int):
    """{scenario: {algorithm: (grid, mean, lo, hi, n_seeds)}} from the train runs' histories,
    and notes. FINISHED runs only, unless an algorithm has none (then all its runs)."""
    notes: list[str] = []
    out: dict[tuple[int, int], dict[str, tuple]] = {}
    groups: dict[tuple[int, int, str], list[RunRecord]] = defaultdict(list)
    for r in org.records:
        if r.kind == "train" and r.algorithm and r.scenario_key is not None:
            groups[(r.n_eds, r.n_uavs, r.algorithm)].append(r)
    for (v, u, alg), runs in sorted(groups.items()):
        finished = [r for r in runs if r.status == "FINISHED"]
        use = finished or runs
        if not finished:
            notes.append(f"V={v} U={u} {alg}: no FINISHED run; its curve uses unfinished runs")
        curves = []
        for r in use:
            steps, vals = metric_history(client, r.run_id, CURVE_METRIC)
            if len(steps) >= 1:
                curves.append((np.asarray(steps), stats.ema(vals, smooth)))
        if not curves:
            continue
        grid = stats.common_grid([(s[0], s[-1]) for s, _ in curves], points)
        if grid.size == 0:
            notes.append(f"V={v} U={u} {alg}: the seeds' env-step ranges do not overlap; no curve")
            continue
        y = stats.interpolate(curves, grid)
        mean, lo, hi = stats.bootstrap_ci95(y)
        out.setdefault((v, u), {})[alg] = (grid, mean, lo, hi, len(curves))
    return out, notes


def _plot_curves(ax, curves: dict[str, tuple], colours: dict[str, str], title: str) -> None:
    import matplotlib.ticker as mticker

    for alg in sorted(curves):
        grid, mean, lo, hi, n = curves[alg]
        c = colours[alg]
        ax.plot(grid, mean, color=c, label=f"{alg} (n={n})")
        ax.fill_between(grid, lo, hi, color=c, alpha=0.2, linewidth=0)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return (mean)")
    ax.set_title(title)
    fmt = mticker.ScalarFormatter(useMathText=True)
    fmt.set_powerlimits((-3, 3))
    ax.xaxis.set_major_formatter(fmt)
    ax.xaxis.get_offset_text().set_fontsize(style.SMALL_PT)


def fig3a(curves, colours, out_dir: str, smooth: float) -> tuple[list[str], list[str]]:
    import matplotlib.pyplot as plt

    files: list[str] = []
    notes: list[str] = []
    if not curves:
        return files, [f"Fig. 3a skipped: no training curves ({CURVE_METRIC}) in the experiment."]
    smooth_txt = f"EMA w={smooth}" if smooth > 0 else "no smoothing"
    if PAPER_SCENARIO in curves:
        main = PAPER_SCENARIO
    else:
        main = max(curves, key=lambda s: (sum(c[4] for c in curves[s].values()), -s[0], -s[1]))
        notes.append(f"Fig. 3a: the paper's scenario V=10, U=2 has no curves; drawn for V={main[0]}, U={main[1]}.")
    fig, ax = plt.subplots(figsize=(style.COLUMN_WIDTH_IN, 2.6), layout="constrained")
    _plot_curves(ax, curves[main], colours, f"{_scen_title(main)} ({smooth_txt}, 95% bootstrap CI)")
    ax.legend(loc="best", frameon=False)
    files += style.save(fig, os.path.join(out_dir, "fig3a"))
    if len(curves) > 1:
        scens = sorted(curves)
        ncol = min(3, len(scens))
        nrow = math.ceil(len(scens) / ncol)
        width = style.COLUMN_WIDTH_IN if ncol == 1 else style.DOUBLE_WIDTH_IN
        fig, axes = plt.subplots(nrow, ncol, figsize=(width, 2.3 * nrow), layout="constrained", squeeze=False)
        for ax, scen in zip(axes.flat, scens):
            _plot_curves(ax, curves[scen], colours, _scen_title(scen))
        for ax in list(axes.flat)[len(scens) :]:
            ax.set_visible(False)
        handles = {}
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                handles.setdefault(lab.split(" (n=")[0], h)
        fig.legend(handles.values(), handles.keys(), loc="outside lower center", ncol=min(6, len(handles)), frameon=False)
        fig.suptitle(f"Training curves, mean over seeds ({smooth_txt}, 95% bootstrap CI)", fontsize=style.FONT_PT)
        files += style.save(fig, os.path.join(out_dir, "fig3a_all"))
    return files, notes


def write_curves_csv(curves, path: str) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["n_eds", "n_uavs", "algorithm", "n_seeds", "env_steps", "mean", "ci95_low", "ci95_high"])
        for scen in sorted(curves):
            for alg in sorted(curves[scen]):
                grid, mean, lo, hi, n = curves[scen][alg]
                for i in range(len(grid)):
                    w.writerow([scen[0], scen[1], alg, n, repr(float(grid[i])), repr(float(mean[i])),
                                repr(float(lo[i])), repr(float(hi[i]))])


def fig_sweep(org: Organised, axis: str, colours, markers, out_dir: str, stem: str, label: str):
    """EE against `axis` ("n_eds" or "n_uavs") with the other one fixed at its most common value."""
    import matplotlib.pyplot as plt

    other = "n_uavs" if axis == "n_eds" else "n_eds"
    preferred = PAPER_FIXED_U if axis == "n_eds" else PAPER_FIXED_V
    valid = [c for c in org.cells.values() if c.runs]
    pool = [c for c in valid if c.kind == "train"] or valid
    fixed = _pick(Counter(getattr(c, other) for c in pool for _ in c.runs), preferred)
    sym = {"n_eds": "V", "n_uavs": "U"}
    if fixed is None:
        return [], f"{label} skipped: no finished runs with eval metrics."
    at = [c for c in valid if getattr(c, other) == fixed]
    xs = sorted({getattr(c, axis) for c in at})
    if len(xs) < 2:
        return [], (
            f"{label} skipped: at {sym[other]}={fixed} the experiment has a single {sym[axis]} value "
            f"({', '.join(map(str, xs))}), nothing to plot against."
        )
    fig, ax = plt.subplots(figsize=(style.COLUMN_WIDTH_IN, 2.9), layout="constrained")
    algs = sorted({c.algorithm for c in at}, key=lambda a: (KINDS.index(org_kind(org, a)), a))
    for alg in algs:
        cs = sorted((c for c in at if c.algorithm == alg), key=lambda c: getattr(c, axis))
        x = [getattr(c, axis) for c in cs]
        s = [c.summary() for c in cs]
        y = np.array([v.mean for v in s])
        err = np.array([v.ci_half if math.isfinite(v.ci_half) else 0.0 for v in s])
        baseline = org_kind(org, alg) == "baseline"
        ax.errorbar(
            x, y, yerr=err, color=colours[alg], marker=markers[alg], capsize=2, elinewidth=0.8,
            linestyle="--" if baseline else "-", label=alg + (" (baseline)" if baseline and "(" not in alg else ""),
        )
    ax.set_xticks(xs)
    ax.set_xlabel("number of EDs V" if axis == "n_eds" else "number of UAVs U")
    ax.set_ylabel(r"EE$_{sys}$ per slot (bit/J)")
    ax.set_title(f"Execution phase, {sym[other]}={fixed} (mean over seeds, 95% t CI)")
    fig.legend(loc="outside lower center", ncol=3, frameon=False)
    files = style.save(fig, os.path.join(out_dir, stem))
    return files, None


def org_kind(org: Organised, alg: str) -> str:
    for c in org.cells.values():
        if c.algorithm == alg:
            return c.kind
    return "train"


def _scenario_for(record: RunRecord | None):
    from uavlora_rllib.config_errors import ConfigError
    from uavlora_rllib.sim.scenario import ScenarioConfig

    if record is None:
        return ScenarioConfig(), "no runs: default scenario"
    data = scenario_dict(record.params)
    data["n_eds"], data["n_uavs"] = record.n_eds, record.n_uavs
    try:
        return ScenarioConfig.from_dict(data), "the run's scenario params"
    except ConfigError as exc:
        return ScenarioConfig(n_eds=record.n_eds, n_uavs=record.n_uavs), f"default scenario with V, U ({exc})"


def fig2(org: Organised, reference: str | None, out_dir: str, seed: int):
    """The association map at the last slot of one evaluation episode (see the module docstring)."""
    import matplotlib.pyplot as plt

    from uavlora_rllib.baselines.policies import make_baseline
    from uavlora_rllib.sim.core import BatchCore
    from uavlora_rllib.experiment.evaluation import EVAL_SEED_BASE
    from uavlora_rllib.sim.render import draw_association

    notes: list[str] = []
    train = [c for c in org.cells.values() if c.kind == "train" and c.runs]
    ref_cells = [c for c in train if c.algorithm == reference] or train
    record = None
    if ref_cells:
        scen_cells = [c for c in ref_cells if (c.n_eds, c.n_uavs) == PAPER_SCENARIO] or ref_cells
        record = max((r for c in scen_cells for r in c.runs), key=lambda r: r.ee)
    else:
        others = [r for r in org.records if r.scenario_key is not None]
        paper = [r for r in others if r.scenario_key == PAPER_SCENARIO]
        record = (paper or others or [None])[0]
    policy, cfg, source = None, None, ""
    ckpt = record.tags.get("checkpoint") if record is not None and record.kind == "train" else None
    if ckpt and os.path.exists(ckpt):
        try:
            from uavlora_rllib.evaluate import load_checkpoint_policy

            policy, cfg = load_checkpoint_policy(ckpt, None)
            source = f"{record.algorithm} checkpoint of run {record.run_id[:8]} (seed {record.seed}): {ckpt}"
        except Exception as exc:  # noqa: BLE001 - any failure falls back to a baseline, noted
            notes.append(f"Fig. 2: checkpoint {ckpt} could not be loaded ({type(exc).__name__}: "
                         f"{' '.join(str(exc).split())[:200]}); drawn with a baseline policy instead.")
    elif record is not None and record.kind == "train":
        notes.append(f"Fig. 2: run {record.run_id[:8]} has no existing checkpoint path "
                     f"({ckpt or 'no checkpoint tag'}); drawn with a baseline policy instead.")
    if policy is None:
        cfg, how = _scenario_for(record)
        for name in ("greedy", "fixed", "random"):
            try:
                policy = make_baseline(name, cfg, seed=seed)
                break
            except Exception:  # noqa: BLE001 - try the next baseline
                continue
        who = f"run {record.run_id[:8]}" if record is not None else "no run"
        source = f"baseline '{policy.name}' on the scenario of {who} ({how})"
    core = BatchCore(cfg, 1)
    core.reset([EVAL_SEED_BASE + seed])
    policy.reset(core)
    ed_xy, serving, ee = core.ed_xy[0].copy(), core.serving[0].copy(), math.nan
    for _ in range(cfg.episode_len):
        ed_xy, serving = core.ed_xy[0].copy(), core.serving[0].copy()
        res = core.step(policy.act(core))
        ee = float(res.metrics["ee_sys"][0])
    fig, ax = plt.subplots(figsize=(style.COLUMN_WIDTH_IN, 3.3), layout="constrained")
    n_assoc = int((serving >= 0).sum())
    draw_association(
        ax, ed_xy, core.uav_xy, serving, cfg.comm_range_m, cfg.area_m,
        title=f"V={cfg.n_eds}, U={cfg.n_uavs}, slot {cfg.episode_len - 1}: {n_assoc}/{cfg.n_eds} associated",
    )
    ax.title.set_fontsize(style.FONT_PT)
    ax.legend(loc="upper right", fontsize=style.SMALL_PT, framealpha=0.8)
    files = style.save(fig, os.path.join(out_dir, "fig2"))
    desc = (f"{source}; evaluation episode seed {EVAL_SEED_BASE + seed}, last slot t={cfg.episode_len - 1}, "
            f"EE_sys of that slot {ee:.6g} bit/J, {n_assoc}/{cfg.n_eds} EDs associated")
    return files, desc, notes


# ---------------------------------------------------------------- report
def _distinct(values) -> str:
    vals = sorted({str(v) for v in values if v not in (None, "")})
    return ", ".join(vals) if vals else "n/a"


def source_section(exp, tracking_uri: str, records: list[RunRecord]) -> list[str]:
    kinds = Counter(r.kind for r in records)
    statuses = Counter(r.status for r in records)
    train = [r for r in records if r.kind == "train"]
    base = [r for r in records if r.kind == "baseline"]
    return [
        f"- experiment: `{exp.name}` (id {exp.experiment_id}) at `{tracking_uri}`",
        f"- runs: {len(records)} ({', '.join(f'{k}: {v}' for k, v in sorted(kinds.items())) or 'none'}); "
        f"status: {', '.join(f'{k}: {v}' for k, v in sorted(statuses.items())) or 'n/a'}",
        f"- grid file(s): {_distinct(r.tags.get('grid_file') for r in records)}",
        f"- git commit(s): {_distinct(r.tags.get('git_commit') for r in records)}",
        f"- training budget (env steps, tag budget_env_steps): {_distinct(r.tags.get('budget_env_steps') for r in train)}; "
        f"stop.env_steps: {_distinct(r.params.get('stop.env_steps') for r in train)}",
        f"- execution-phase episodes (eval.episodes): {_distinct(r.params.get('eval.episodes') for r in records)}; "
        f"episode length: {_distinct(r.params.get('scenario.episode_len') for r in records)}",
        f"- training seeds: {_distinct(r.seed for r in train)}; baseline seeds: {_distinct(r.seed for r in base)}",
        f"- algorithms: {_distinct(r.algorithm for r in train)}; baselines: {_distinct(r.algorithm for r in base)}",
    ]


STATS_TEXT = """\
- EE is each run's execution-phase `eval/ee_sys_mean` (EE_sys per slot, averaged over the
  run's evaluation episodes); a cell (V, U, algorithm) holds one value per seed. Only
  FINISHED runs with that metric count; unfinished runs and runs without eval metrics are
  listed as warnings and left out. Several finished runs of one seed: the newest counts.
- mean: over seeds. 95% CI: Student t, mean +- t(0.975, n-1) s / sqrt(n), s the sample
  standard deviation (n/a below 2 seeds). IQM: `scipy.stats.trim_mean(x, 0.25)` over seeds
  (equal to the mean for n <= 3).
- improvement of {ref} over X: 100 (EE_{ref} - EE_X) / EE_X on the seed means, as in the paper;
  "second best" is the best other learning algorithm (kind=train) of the scenario.
- share of optimum: seed-mean EE / seed-mean EE of the `optimal` baseline of the same scenario
  (the exact per-slot optimum, SPEC.md "What the optimum is").
- Fig. 3a: each run's `episode_return_mean` history (x = env steps) is smoothed with a
  debiased EMA (weight {smooth}; 0 = none), interpolated linearly onto {points} evenly spaced
  env-step values spanning the range all seeds cover, and averaged over seeds (FINISHED runs);
  the band is a 95% percentile bootstrap of that mean over seeds ({boot} resamples).
- Fig. 3b/3c error bars: the 95% t CI over seeds above (none for a single seed).
"""


def build_report(client, exp, tracking_uri: str, out_dir: str, args) -> dict[str, Any]:
    with style.context():
        return _build_report(client, exp, tracking_uri, out_dir, args)


def _build_report(client, exp, tracking_uri: str, out_dir: str, args) -> dict[str, Any]:
    records, summaries = load_runs(client, exp.experiment_id)
    org = organise(records)
    reference = _find_reference(org, args.reference)
    os.makedirs(out_dir, exist_ok=True)
    for name in OUTPUT_FILES:  # a fresh report: stale outputs of a previous one must not survive
        p = os.path.join(out_dir, name)
        if os.path.isfile(p):
            os.remove(p)
    colours = style.colour_map(org.algorithms())
    markers = style.marker_map(org.algorithms())
    notes: list[str] = []
    if reference is None:
        notes.append(f"No training runs of the reference algorithm {args.reference!r}: no improvement table.")

    rows = ee_table(org, reference)
    _write_csv(os.path.join(out_dir, "table_ee.csv"), TABLE_EE_COLUMNS, rows)
    imp_rows = improvement_table(org, reference)
    _write_csv(os.path.join(out_dir, "table_improvement.csv"), TABLE_IMP_COLUMNS, imp_rows)
    ee_md = ee_table_md(rows, reference)
    imp_md = improvement_md(imp_rows, reference or args.reference)
    with open(os.path.join(out_dir, "table_ee.md"), "w") as fh:
        fh.write(ee_md + "\n")
    with open(os.path.join(out_dir, "table_improvement.md"), "w") as fh:
        fh.write(imp_md + "\n")

    figures: dict[str, list[str]] = {}
    curves, cnotes = training_curves(client, org, args.smooth, args.points)
    notes += cnotes
    colours.update(style.colour_map(list(colours) + [a for s in curves.values() for a in s]))
    files, n3a = fig3a(curves, colours, out_dir, args.smooth)
    notes += n3a
    if files:
        figures["fig3a"] = files
        write_curves_csv(curves, os.path.join(out_dir, "fig3a_curves.csv"))
    for axis, stem, label in (("n_eds", "fig3b", "Fig. 3b"), ("n_uavs", "fig3c", "Fig. 3c")):
        files, note = fig_sweep(org, axis, colours, markers, out_dir, stem, label)
        if files:
            figures[stem] = files
        if note:
            notes.append(note)
    fig2_desc = None
    if args.no_fig2:
        notes.append("Fig. 2 skipped (--no-fig2).")
    else:
        try:
            files, fig2_desc, n2 = fig2(org, reference, out_dir, args.fig2_seed)
            figures["fig2"] = files
            notes += n2
        except Exception as exc:  # noqa: BLE001 - the report must not die on the simulator
            notes.append(f"Fig. 2 skipped: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}")

    warnings = org.warnings
    lines = [f"# Report: experiment `{exp.name}`", "", f"Generated {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())} "
             f"by `python -m analysis.report`.", "", "## Source", ""]
    lines += source_section(exp, tracking_uri, records)
    lines += ["", "## Warnings", ""]
    lines += [f"- WARNING: {w}" for w in warnings] or ["- none"]
    lines += ["", "## Notes", ""]
    lines += [f"- {n}" for n in notes] or ["- none"]
    lines += ["", "## Figures", ""]
    captions = {
        "fig2": "Fig. 2: ED-UAV association at the last slot of an evaluation episode",
        "fig3a": "Fig. 3a: training curves (episode return against env steps)",
        "fig3b": "Fig. 3b: execution-phase EE against the number of EDs",
        "fig3c": "Fig. 3c: execution-phase EE against the number of UAVs",
    }
    for key in ("fig2", "fig3a", "fig3b", "fig3c"):
        if key not in figures:
            lines.append(f"- {captions[key]}: not drawn (see Notes).")
            continue
        png = os.path.basename(figures[key][0])
        extra = ""
        if key == "fig3a":
            extra = " Data: [fig3a_curves.csv](fig3a_curves.csv)."
            if len(figures[key]) > 2:
                extra += " All scenarios: [fig3a_all.png](fig3a_all.png) ([svg](fig3a_all.svg))."
        if key == "fig2" and fig2_desc:
            extra = f" Source: {fig2_desc}."
        lines += [f"### {captions[key]}", "", f"![{key}]({png}) ([svg]({key}.svg)).{extra}", ""]
    lines += ["", "## Execution-phase EE per scenario and algorithm", "",
              "CSV: [table_ee.csv](table_ee.csv). `(!)`: fewer than 3 seeds.", "", ee_md, "",
              f"## Improvement of {reference or args.reference}", "",
              "CSV: [table_improvement.csv](table_improvement.csv).", "", imp_md, "",
              "## Statistics", "",
              STATS_TEXT.format(ref=reference or args.reference, smooth=args.smooth, points=args.points,
                                boot=stats.BOOTSTRAP_RESAMPLES), ""]
    report_path = os.path.join(out_dir, "report.md")
    with open(report_path, "w") as fh:
        fh.write("\n".join(lines))
    return {"report": report_path, "figures": figures, "warnings": warnings, "notes": notes,
            "summaries": summaries, "rows": rows, "improvements": imp_rows, "n_runs": len(records)}


def _local_path(uri: str) -> str | None:
    p = urlparse(uri)
    if p.scheme in ("", "file"):
        return p.path if p.scheme == "file" else uri
    return None


def log_summary(client, exp, summaries, out_dir: str, result: dict[str, Any]) -> str:
    """Log out_dir as artifacts of the experiment's summary run (the newest is reused, older
    ones are deleted, the reused run's previous artifacts are removed when stored locally)."""
    if summaries:
        run_id = summaries[0].info.run_id
        for extra in summaries[1:]:
            client.delete_run(extra.info.run_id)
        local = _local_path(summaries[0].info.artifact_uri or "")
        if local and os.path.isdir(local):
            for name in os.listdir(local):
                p = os.path.join(local, name)
                shutil.rmtree(p) if os.path.isdir(p) else os.remove(p)
        client.update_run(run_id, status="RUNNING")
    else:
        run_id = client.create_run(exp.experiment_id, run_name="summary", tags={"kind": SUMMARY_KIND}).info.run_id
    client.set_tag(run_id, "kind", SUMMARY_KIND)
    client.set_tag(run_id, "report_generated_utc", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    client.set_tag(run_id, "report_runs", str(result["n_runs"]))
    client.set_tag(run_id, "report_warnings", str(len(result["warnings"])))
    for name in OUTPUT_FILES:
        path = os.path.join(out_dir, name)
        if os.path.isfile(path):
            client.log_artifact(run_id, path)
    client.set_terminated(run_id, "FINISHED")
    return run_id


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:
        raise ReportError(message)


def _smooth(text: str) -> float:
    try:
        w = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1), got {text!r}") from None
    if not 0.0 <= w < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {w}")
    return w


def _points(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2, got {text!r}") from None
    if n < 2:
        raise argparse.ArgumentTypeError(f"must be >= 2, got {n}")
    return n


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m analysis.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--experiment", required=True, help="MLflow experiment name (the grid's 'experiment')")
    p.add_argument("--tracking-uri", default="sqlite:///mlflow.db", help="MLflow tracking URI (default sqlite:///mlflow.db)")
    p.add_argument("--out", default=None, help="output folder (default reports/<experiment>)")
    p.add_argument("--reference", default="mappo", help="algorithm whose improvement is reported (default mappo)")
    p.add_argument("--smooth", type=_smooth, default=0.6, help="EMA weight of Fig. 3a curves in [0, 1) (default 0.6)")
    p.add_argument("--points", type=_points, default=200, help="env-step grid points of Fig. 3a (default 200)")
    p.add_argument("--fig2-seed", type=int, default=0, help="evaluation episode of Fig. 2 (seed offset, default 0)")
    p.add_argument("--no-fig2", action="store_true", help="skip Fig. 2 (no simulation)")
    p.add_argument("--no-log", action="store_true", help="do not log the outputs to an MLflow summary run")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        client = connect(args.tracking_uri)
        exp = find_experiment(client, args.experiment, args.tracking_uri)
    except ReportError as exc:
        print(f"report: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    out_dir = args.out or os.path.join("reports", args.experiment)
    result = build_report(client, exp, args.tracking_uri, out_dir, args)
    logged = ""
    if not args.no_log:
        run_id = log_summary(client, exp, result["summaries"], out_dir, result)
        logged = f"; logged to summary run {run_id}"
    figs = ", ".join(sorted(result["figures"])) or "none"
    print(f"report: {result['report']} ({result['n_runs']} runs, figures: {figs}, "
          f"{len(result['warnings'])} warning(s)){logged}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
