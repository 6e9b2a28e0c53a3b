"""The report's figures: Fig. 3a (execution-policy learning curves and the training return),
Fig. 3b/3c (execution EE against V and U), Fig. 2 (an association map).

Figures must not mislead (issue 16): every series has its own colour, marker and dash pattern
(hollow markers on every second one), series that overlap are named in the notes, and every
title states the seed count n and the interval actually drawn (none for one seed).
"""

from __future__ import annotations

import csv
import math
import os
from collections import Counter

import numpy as np

from analysis import style
from analysis.data import (
    EVAL_CURVE,
    KINDS,
    PAPER_FIXED_U,
    PAPER_FIXED_V,
    PAPER_SCENARIO,
    RETURN_METRIC,
    Curve,
    Organised,
    main_scenario,
    pick_fixed,
)
from analysis.runs import ReportError, RunRecord, scenario_dict

OVERLAP_FRACTION = 0.01  # two series closer than this share of the y range at every x overlap


def looks(names) -> dict[str, dict]:
    """name -> matplotlib kwargs: colour, marker, dash pattern, hollow markers on every second."""
    names = sorted(set(names))
    colours, markers, dashes = style.colour_map(names), style.marker_map(names), style.line_style_map(names)
    return {
        n: {
            "color": colours[n],
            "marker": markers[n],
            "linestyle": dashes[n],
            "markerfacecolor": "none" if style.hollow(i) else colours[n],
        }
        for i, n in enumerate(names)
    }


def interval_text(ns, what: str) -> str:
    """What a figure's bars or bands are, given the seed counts n of its series."""
    ns = sorted({int(n) for n in ns})
    if not ns:
        return "no data"
    n_txt = f"n={ns[0]}" if len(ns) == 1 else f"n={ns[0]}-{ns[-1]}"
    if ns[-1] < 2:
        return f"{n_txt} seed: no interval"
    if ns[0] >= 2:
        return f"mean over {n_txt} seeds, {what}"
    return f"mean over {n_txt} seeds; {what} where n>=2"


def overlaps(series: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[tuple[str, str]]:
    """Pairs of series with the same x values whose y values differ by at most
    OVERLAP_FRACTION of the plotted y range at every x (they would hide each other)."""
    ys = [y for _, y in series.values() if len(y)]
    if not ys:
        return []
    span = float(np.ptp(np.concatenate(ys))) or max(1e-12, float(np.abs(np.concatenate(ys)).max()))
    names = sorted(series)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            (xa, ya), (xb, yb) = series[a], series[b]
            if len(xa) == len(xb) and np.array_equal(xa, xb) and np.all(np.abs(ya - yb) <= OVERLAP_FRACTION * span):
                out.append((a, b))
    return out


def overlap_note(label: str, pairs: list[tuple[str, str]]) -> str | None:
    if not pairs:
        return None
    txt = "; ".join(f"{a} and {b}" for a, b in pairs)
    return (
        f"{label}: these series overlap at every point (within {OVERLAP_FRACTION:.0%} of the y range), "
        f"drawn with distinct markers and dashes: {txt}"
    )


def _scen_title(scen: tuple[int, int]) -> str:
    return f"V={scen[0]}, U={scen[1]}"


def _sci_x(ax) -> None:
    import matplotlib.ticker as mticker

    fmt = mticker.ScalarFormatter(useMathText=True)
    fmt.set_powerlimits((-3, 3))
    ax.xaxis.set_major_formatter(fmt)
    ax.xaxis.get_offset_text().set_fontsize(style.SMALL_PT)


def reference_scales(org: Organised, scen: tuple[int, int], curves: dict[str, Curve]):
    """The scenario's reference (None without one) and, per algorithm, the reference's mean over
    that curve's seeds: the curve's divisor, as every share of the report divides over matched seeds."""
    ref = org.reference(scen)
    if ref is None:
        return None, {}
    return ref, {alg: getattr(org.reference(scen, c.seeds), "mean", ref.mean) for alg, c in curves.items()}


def _plot_curves(ax, curves: dict[str, Curve], lk: dict, scales: dict[str, float] | None = None) -> dict[str, tuple]:
    """Mean lines (markers on ~8 points) and bands, each divided by its scale (1 where none);
    returns the plotted series for overlaps()."""
    drawn = {}
    for alg in sorted(curves):
        c = curves[alg]
        scale = (scales or {}).get(alg, 1.0)
        y, lo, hi = c.mean / scale, c.lo / scale, c.hi / scale
        ax.plot(c.steps, y, label=f"{alg} (n={c.n_seeds})", markevery=max(1, len(c.steps) // 8), **lk[alg])
        if c.n_seeds >= 2:
            ax.fill_between(c.steps, lo, hi, color=lk[alg]["color"], alpha=0.15, linewidth=0)
        drawn[alg] = (c.steps, y)
    ax.set_xlabel("environment steps")
    _sci_x(ax)
    return drawn


def fig3a(eval_curves, return_curves, org: Organised, lk: dict, out_dir: str, smooth: float):
    """Fig. 3a: (a) the greedy policy's execution EE per slot during training, as a share of the
    scenario's reference where known (reference line at 1); (b) the training return. Returns
    (files, notes, caption)."""
    import matplotlib.pyplot as plt

    notes: list[str] = []
    main, why = main_scenario(eval_curves or return_curves)
    if main is None:
        return [], [f"Fig. 3a skipped: no training curves ({EVAL_CURVE} or {RETURN_METRIC}) in the runs."], ""
    if why:
        notes.append(f"Fig. 3a: {why}.")
    ev, ret = eval_curves.get(main, {}), return_curves.get(main, {})
    ref, scales = reference_scales(org, main, ev)
    fig, (ax_e, ax_r) = plt.subplots(2, 1, figsize=(style.COLUMN_WIDTH_IN, 4.8), layout="constrained")
    if ev:
        drawn = _plot_curves(ax_e, ev, lk, scales)
        if ref:
            ax_e.axhline(1.0, color="black", linewidth=0.8, linestyle=(0, (2, 2)), label=f"{ref.label} = 1")
            ax_e.set_ylim(top=max(ax_e.get_ylim()[1], 1.08))  # the reference line off the frame
            ax_e.set_ylabel(f"EE per slot / {ref.name}")
        else:
            ax_e.set_ylabel(r"EE$_{sys}$ per slot (bit/J)")
            notes.append(
                f"Fig. 3a: V={main[0]} U={main[1]} has neither an optimal nor a greedy baseline run; "
                "the execution curves are in bit/J with no reference line."
            )
        ax_e.set_title(
            f"(a) greedy policy, execution EE\n{interval_text([c.n_seeds for c in ev.values()], '95% bootstrap band')}"
        )
        ax_e.legend(loc="best", frameon=False)
        note = overlap_note("Fig. 3a (a)", overlaps(drawn))
        if note:
            notes.append(note)
    else:
        ax_e.text(
            0.5,
            0.5,
            "no periodic evaluation logged\n(grid: evaluation.interval_env_steps)",
            ha="center",
            va="center",
            transform=ax_e.transAxes,
        )
        ax_e.set_axis_off()
        notes.append(
            f"Fig. 3a: no run of V={main[0]} U={main[1]} has a periodic evaluation history "
            f"({EVAL_CURVE} at 2 or more env-step counts); panel (a) is empty."
        )
    smooth_txt = f"EMA w={smooth}" if smooth > 0 else "no smoothing"
    if ret:
        drawn = _plot_curves(ax_r, ret, lk)
        ax_r.set_ylabel("training episode return")
        ax_r.set_title(
            f"(b) sampled policy, training return ({smooth_txt})\n"
            f"{interval_text([c.n_seeds for c in ret.values()], '95% bootstrap band')}"
        )
        note = overlap_note("Fig. 3a (b)", overlaps(drawn))
        if note:
            notes.append(note)
    else:
        ax_r.set_axis_off()
    for ax in (ax_e, ax_r):
        ax.title.set_fontsize(style.SMALL_PT)
    files = style.save(fig, os.path.join(out_dir, "fig3a"))
    ref_txt = (
        f"share of the {ref.label} over the curve's seeds ({ref.mean:.6g} bit/J over all its seeds)"
        if ref
        else "bit/J (no reference baseline)"
    )
    n_e = interval_text([c.n_seeds for c in ev.values()], "95% bootstrap band") if ev else "not drawn"
    n_r = interval_text([c.n_seeds for c in ret.values()], "95% bootstrap band") if ret else "not drawn"
    caption = (
        f"{_scen_title(main)}: (a) execution EE per slot of the greedy policy during training, {ref_txt} "
        f"({n_e}); (b) training return of the exploring policy, which can rank the learners differently ({n_r})"
    )
    scens = sorted(eval_curves)
    if len(scens) > 1:
        ncol = min(3, len(scens))
        nrow = math.ceil(len(scens) / ncol)
        width = style.COLUMN_WIDTH_IN if ncol == 1 else style.DOUBLE_WIDTH_IN
        fig, axes = plt.subplots(nrow, ncol, figsize=(width, 2.3 * nrow), layout="constrained", squeeze=False)
        for ax, scen in zip(axes.flat, scens):
            r, sc = reference_scales(org, scen, eval_curves[scen])
            _plot_curves(ax, eval_curves[scen], lk, sc)
            if r:
                ax.axhline(1.0, color="black", linewidth=0.8, linestyle=(0, (2, 2)))
                ax.set_ylim(top=max(ax.get_ylim()[1], 1.08))
            ax.set_ylabel(f"EE / {r.name}" if r else "EE (bit/J)")
            ax.set_title(
                f"{_scen_title(scen)}\n{interval_text([c.n_seeds for c in eval_curves[scen].values()], '95% band')}",
                fontsize=style.SMALL_PT,
            )
        for ax in list(axes.flat)[len(scens) :]:
            ax.set_visible(False)
        handles = {}
        for ax in axes.flat:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                handles.setdefault(lab.split(" (n=")[0], h)
        fig.legend(
            handles.values(), handles.keys(), loc="outside lower center", ncol=min(6, len(handles)), frameon=False
        )
        fig.suptitle(
            "Greedy policy during training: execution EE per slot (dashed: reference = 1)", fontsize=style.FONT_PT
        )
        files += style.save(fig, os.path.join(out_dir, "fig3a_all"))
    return files, notes, caption


def write_curves_csv(curve_sets: dict[str, dict], org: Organised, path: str) -> None:
    """Every plotted curve point: metric, scenario, algorithm, mean and band, and the reference
    (its mean over the curve's seeds)."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(
            [
                "metric",
                "n_eds",
                "n_uavs",
                "algorithm",
                "n_seeds",
                "env_steps",
                "mean",
                "ci95_low",
                "ci95_high",
                "reference",
                "reference_ee",
            ]
        )
        for metric, curves in curve_sets.items():
            for scen in sorted(curves):
                ref, scales = reference_scales(org, scen, curves[scen]) if metric == EVAL_CURVE else (None, {})
                for alg in sorted(curves[scen]):
                    c = curves[scen][alg]
                    for i in range(len(c.steps)):
                        w.writerow(
                            [
                                metric,
                                scen[0],
                                scen[1],
                                alg,
                                c.n_seeds,
                                repr(float(c.steps[i])),
                                repr(float(c.mean[i])),
                                repr(float(c.lo[i])),
                                repr(float(c.hi[i])),
                                ref.name if ref else "",
                                repr(scales[alg]) if ref else "",
                            ]
                        )


def fig_sweep(org: Organised, axis: str, lk: dict, out_dir: str, stem: str, label: str):
    """EE against `axis` ("n_eds" or "n_uavs") with the other fixed at its most common value.
    Returns (files, notes, caption)."""
    import matplotlib.pyplot as plt

    other = "n_uavs" if axis == "n_eds" else "n_eds"
    preferred = PAPER_FIXED_U if axis == "n_eds" else PAPER_FIXED_V
    valid = [c for c in org.cells.values() if c.runs]
    pool = [c for c in valid if c.kind == "train"] or valid
    fixed = pick_fixed(Counter(getattr(c, other) for c in pool for _ in c.runs), preferred)
    sym = {"n_eds": "V", "n_uavs": "U"}
    if fixed is None:
        return [], [f"{label} skipped: no finished runs with eval metrics."], ""
    at = [c for c in valid if getattr(c, other) == fixed]
    xs = sorted({getattr(c, axis) for c in at})
    if len(xs) < 2:
        return (
            [],
            [
                f"{label} skipped: at {sym[other]}={fixed} the runs have a single {sym[axis]} value "
                f"({', '.join(map(str, xs))}), nothing to plot against (join more experiments with --experiment)."
            ],
            "",
        )
    fig, ax = plt.subplots(figsize=(style.COLUMN_WIDTH_IN, 2.9), layout="constrained")
    algs = sorted({c.algorithm for c in at}, key=lambda a: (KINDS.index(org.kind_of(a)), a))
    drawn, ns = {}, []
    for alg in algs:
        cs = sorted((c for c in at if c.algorithm == alg), key=lambda c: getattr(c, axis))
        x = np.array([getattr(c, axis) for c in cs], dtype=float)
        s = [c.summary() for c in cs]
        ns += [v.n for v in s]
        y = np.array([v.mean for v in s])
        err = np.array([v.ci_half if math.isfinite(v.ci_half) else 0.0 for v in s])
        baseline = org.kind_of(alg) == "baseline"
        ax.errorbar(
            x,
            y,
            yerr=err,
            capsize=2,
            elinewidth=0.8,
            **lk[alg],
            label=alg + (" (baseline)" if baseline and "(" not in alg else ""),
        )
        drawn[alg] = (x, y)
    ax.set_xticks(xs)
    ax.set_xlabel("number of EDs V" if axis == "n_eds" else "number of UAVs U")
    ax.set_ylabel(r"EE$_{sys}$ per slot (bit/J)")
    caption = f"{sym[other]}={fixed}; {interval_text(ns, '95% t CI bars')}"
    ax.set_title(f"Execution phase, {sym[other]}={fixed}\n{interval_text(ns, '95% t CI bars')}")
    fig.legend(loc="outside lower center", ncol=3, frameon=False)
    files = style.save(fig, os.path.join(out_dir, stem))
    note = overlap_note(label, overlaps(drawn))
    return files, [note] if note else [], caption


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


def fig2_record(org: Organised, algorithm: str | None) -> tuple[RunRecord | None, str]:
    """The run Fig. 2 plays: the best seed of the learner with the highest seed-mean execution
    EE in the paper's scenario (else over all scenarios), or of `algorithm` when given."""
    train = [c for c in org.cells.values() if c.kind == "train" and c.runs]
    if algorithm is not None:
        name = org.find_train(algorithm)
        if name is None:
            raise ReportError(
                f"--fig2-algorithm: {algorithm!r} has no training runs; learners: {org.algorithms('train') or 'none'}"
            )
        train = [c for c in train if c.algorithm == name]
        if not train:
            raise ReportError(f"--fig2-algorithm: {algorithm!r} has no FINISHED run with eval metrics")
    if not train:
        others = [r for r in org.records if r.scenario_key is not None]
        paper = [r for r in others if r.scenario_key == PAPER_SCENARIO]
        return (paper or others or [None])[0], "no learner with execution metrics"
    scen_cells = [c for c in train if c.scenario == PAPER_SCENARIO] or train
    best = max(scen_cells, key=lambda c: c.summary().mean)
    why = (
        "chosen with --fig2-algorithm"
        if algorithm is not None
        else "the learner with the highest seed-mean execution EE"
    )
    return max(best.runs, key=lambda r: r.ee), f"{best.algorithm} at {_scen_title(best.scenario)}, {why}"


def fig2(org: Organised, algorithm: str | None, out_dir: str, seed: int):
    """The association map at the last slot of one evaluation episode. Returns (files, desc, notes)."""
    import matplotlib.pyplot as plt

    from uavlora_rllib.baselines.policies import make_baseline
    from uavlora_rllib.experiment.evaluation import EVAL_SEED_BASE
    from uavlora_rllib.sim.core import BatchCore
    from uavlora_rllib.sim.render import draw_association

    notes: list[str] = []
    record, why = fig2_record(org, algorithm)
    policy, cfg, source = None, None, ""
    ckpt = record.tags.get("checkpoint") if record is not None and record.kind == "train" else None
    if ckpt and os.path.exists(ckpt):
        try:
            from uavlora_rllib.evaluate import load_checkpoint_policy

            policy, cfg = load_checkpoint_policy(ckpt, None)
            source = f"{why}: checkpoint of run {record.run_id[:8]} (seed {record.seed}): {ckpt}"
        except Exception as exc:  # noqa: BLE001 - any failure falls back to a baseline, noted
            notes.append(
                f"Fig. 2: checkpoint {ckpt} could not be loaded ({type(exc).__name__}: "
                f"{' '.join(str(exc).split())[:200]}); drawn with a baseline policy instead."
            )
    elif record is not None and record.kind == "train":
        notes.append(
            f"Fig. 2: run {record.run_id[:8]} ({why}) has no existing checkpoint path "
            f"({ckpt or 'no checkpoint tag'}); drawn with a baseline policy instead."
        )
    if policy is None:
        cfg, how = _scenario_for(record)
        for name in ("greedy", "fixed", "random"):
            try:
                policy = make_baseline(name, cfg, seed=seed)
                break
            except Exception:  # noqa: BLE001 - try the next baseline
                continue
        who = f"run {record.run_id[:8]} ({why})" if record is not None else "no run"
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
        ax,
        ed_xy,
        core.uav_xy,
        serving,
        cfg.comm_range_m,
        cfg.area_m,
        title=f"V={cfg.n_eds}, U={cfg.n_uavs}, slot {cfg.episode_len - 1}: {n_assoc}/{cfg.n_eds} associated",
    )
    ax.title.set_fontsize(style.FONT_PT)
    ax.legend(loc="upper right", fontsize=style.SMALL_PT, framealpha=0.8)
    files = style.save(fig, os.path.join(out_dir, "fig2"))
    desc = (
        f"{source}; evaluation episode seed {EVAL_SEED_BASE + seed}, last slot t={cfg.episode_len - 1}, "
        f"EE_sys of that slot {ee:.6g} bit/J, {n_assoc}/{cfg.n_eds} EDs associated"
    )
    return files, desc, notes


def fig_profile(taus: np.ndarray, profiles: dict, sets: dict, org: Organised, lk: dict, out_dir: str):
    """The performance profile (rliable's score distribution): per algorithm, the fraction of its
    (seed, scenario) runs whose normalised score exceeds tau, averaged over scenarios, with a 95%
    stratified-bootstrap band. Returns (files, notes, caption)."""
    import matplotlib.pyplot as plt

    if not profiles:
        return [], ["Performance profile skipped: no learner has runs in a scenario with a reference baseline."], ""
    fig, ax = plt.subplots(figsize=(style.COLUMN_WIDTH_IN, 2.9), layout="constrained")
    drawn, n_scen, n_runs = {}, set(), []
    for alg, (frac, lo, hi) in profiles.items():
        n = sum(x.size for x in sets[alg].values())
        n_scen.add(len(sets[alg]))
        n_runs.append(n)
        baseline = org.kind_of(alg) == "baseline"
        ax.plot(
            taus,
            frac,
            markevery=max(1, len(taus) // 8),
            drawstyle="steps-post",
            label=f"{alg}{' (baseline)' if baseline else ''} (n={n})",
            **lk[alg],
        )
        if np.all(np.isfinite(lo)):
            ax.fill_between(taus, lo, hi, color=lk[alg]["color"], alpha=0.15, linewidth=0, step="post")
        drawn[alg] = (taus, frac)
    ax.axvline(1.0, color="black", linewidth=0.8, linestyle=(0, (2, 2)), label="reference = 1")
    ax.set_xlabel(r"normalised score $\tau$ (EE / scenario's reference)")
    ax.set_ylabel(r"fraction of runs with score > $\tau$")
    ax.set_ylim(-0.02, 1.02)
    scen_txt = "/".join(str(s) for s in sorted(n_scen))
    what = (
        f"{scen_txt} scenario(s), 95% stratified bootstrap band"
        if max(n_runs) > 1
        else f"{scen_txt} scenario(s), no band"
    )
    ax.set_title(f"Performance profile\n{what}", fontsize=style.SMALL_PT)
    ax.legend(loc="lower left", frameon=False)
    files = style.save(fig, os.path.join(out_dir, "fig_profile"))
    note = overlap_note("Performance profile", overlaps(drawn))
    caption = (
        f"Fraction of (seed, scenario) runs whose execution EE exceeds tau times the scenario's reference, "
        f"averaged over {scen_txt} scenario(s); n = runs per algorithm; bands: 95% stratified bootstrap over seeds "
        "within each scenario"
    )
    return files, [note] if note else [], caption
