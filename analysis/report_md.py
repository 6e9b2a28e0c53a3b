"""report.md: the source of the runs, warnings, notes, figures with captions, every table, and
how each statistic is computed."""

from __future__ import annotations

import os
import time
from collections import Counter

from analysis import stats
from analysis.data import MIN_SEEDS
from analysis.export import MARL_EVAL_FILE
from analysis.runs import RunRecord, Source
from analysis.tables import OPEN_LOOP_SHARE
from analysis.verdicts import LAST_EVALS, SWING_LIMIT


def _distinct(values) -> str:
    vals = sorted({str(v) for v in values if v not in (None, "")})
    return ", ".join(vals) if vals else "n/a"


def source_section(sources: list[Source], records: list[RunRecord]) -> list[str]:
    kinds = Counter(r.kind for r in records)
    statuses = Counter(r.status for r in records)
    train = [r for r in records if r.kind == "train"]
    base = [r for r in records if r.kind == "baseline"]
    per_exp = Counter(r.source for r in records)
    lines = [
        f"- experiment: `{s.name}` (id {s.experiment.experiment_id}) at `{s.tracking_uri}`: {per_exp.get(i, 0)} runs"
        for i, s in enumerate(sources)
    ]
    return lines + [
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
  run's evaluation episodes, played by the greedy policy); a cell (V, U, algorithm) holds one
  value per seed. Only FINISHED runs with that metric count; unfinished runs and runs without
  eval metrics are listed as warnings and left out. Several finished runs of one seed: the
  newest counts. Runs of several experiments join the same cell; a warning names any cell
  whose runs differ in budget, episodes or scenario parameters.
- mean: over seeds. 95% CI: Student t, mean +- t(0.975, n-1) s / sqrt(n), s the sample
  standard deviation (n/a below 2 seeds). IQM: `scipy.stats.trim_mean(x, 0.25)` over seeds
  (equal to the mean for n <= 3).
- improvement of {ref} over X: 100 (EE_{ref} - EE_X) / EE_X on the seed means, as in the paper;
  "second best" is the best other learning algorithm (kind=train) of the scenario.
- share of reference: seed-mean EE / seed-mean EE of the scenario's reference baseline, the
  `optimal` one (the exact per-slot optimum, docs/model.md) where it ran, else `greedy`, in
  whichever action mode the scenario's runs use (per_uav or per_device; the open-loop table
  names it); the column names which. Both means are over the matched seeds: those the learner,
  the reference and (in the learning verdicts) `best_fixed` all ran, since each seed has its own
  evaluation episodes; the learning verdicts name any seed left out. Open-loop check: `best_fixed`'s
  share of that reference; at {open_loop} or above a constant action counts as optimal.
- paper table: ratio of seed means mappo / other with a 95% Fieller interval over seeds
  (independent samples, t with min(n_a, n_b) - 1 degrees of freedom); improvement = 100 (ratio - 1).
- Fig. 3a (a): each run's `eval/ee_sys_mean` history (the greedy policy evaluated every
  evaluation.interval_env_steps env steps on fixed episodes, the last point being the final
  evaluation), unsmoothed; (b): each run's `episode_return_mean` history smoothed with a debiased
  EMA (weight {smooth}; 0 = none). Both are interpolated linearly onto {points} evenly spaced
  env-step values spanning the range all seeds cover and averaged over seeds (per seed the run the
  tables use); the band is a 95% percentile bootstrap of that mean over seeds ({boot} resamples), drawn only
  for n >= 2: with three seeds it is close to the range from the lowest seed to the highest.
- Fig. 3b/3c error bars: the 95% t CI over seeds above (none for a single seed). Titles state n.
- aggregates over seeds and scenarios: rliable's definitions (Agarwal et al. 2021), computed
  with scipy because rliable itself does not install on the pinned stack (docs/model.md#aggregate-statistics).
  The normalised score of a seed is its EE as a share of the scenario's reference (the
  denominator of "share of reference" above), which puts scenarios of very different EE on one
  scale. IQM: the 25% trimmed mean of all (seed, scenario) scores of an algorithm pooled
  (`analysis.stats.iqm`, the per-cell IQM's function); mean: the mean over scenarios of the
  per-scenario seed means. Optimality gap: 1 minus the mean of min(score, 1) over the pooled scores, how far
  below the reference an algorithm falls (lower is better). P({ref} > X): over the scenarios both ran, the mean of each scenario's
  share of (seed of {ref}, seed of X) pairs in which {ref} scores higher, ties counting one half
  (the Mann-Whitney U / (n m); 0.5 = no difference). Performance profile: the fraction of runs
  scoring above tau, averaged over scenarios. Intervals: 95% percentile stratified bootstrap
  (`scipy.stats.bootstrap`, each scenario's seeds resampled with replacement on their own, {agg_boot}
  resamples; {prof_boot} for the profile's bands; a scenario with one seed stays fixed; none
  without a scenario of 2+ seeds). With three seeds a scenario's resamples take few distinct
  values, so these intervals are coarse and tend to be too narrow; they carry the seed noise
  only, not the choice of scenarios. The per-cell table keeps the t interval, which is exact for normal
  seed-to-seed noise at any n.
"""


CAPTIONS = {
    "fig2": "Fig. 2: ED-UAV association at the last slot of an evaluation episode",
    "fig3a": "Fig. 3a: learning curves of the execution (greedy) policy, and the training return",
    "fig3b": "Fig. 3b: execution-phase EE against the number of EDs",
    "fig3c": "Fig. 3c: execution-phase EE against the number of UAVs",
    "fig_profile": "Performance profile: the distribution of normalised scores over seeds and scenarios",
}


def report_markdown(sources, records, org, notes, figures, captions, tables, reference, args) -> str:
    """report.md: source, warnings, notes, figures with captions, tables, statistics."""
    title = ", ".join(f"`{s.name}`" for s in sources)
    lines = [
        f"# Report: experiment{'s' if len(sources) > 1 else ''} {title}",
        "",
        f"Generated {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())} by `python -m analysis.report`.",
        "",
        "## Source",
        "",
    ]
    lines += source_section(sources, records)
    lines += ["", "## Warnings", ""]
    lines += [f"- WARNING: {w}" for w in org.warnings] or ["- none"]
    lines += ["", "## Notes", ""]
    lines += [f"- {n}" for n in notes] or ["- none"]
    lines += ["", "## Figures", ""]
    for key in ("fig2", "fig3a", "fig3b", "fig3c", "fig_profile"):
        if key not in figures:
            lines.append(f"- {CAPTIONS[key]}: not drawn (see Notes).")
            continue
        png = os.path.basename(figures[key][0])
        extra = f" {captions[key]}." if captions.get(key) else ""
        if key == "fig3a":
            extra += " Data: [fig3a_curves.csv](fig3a_curves.csv)."
        if key == "fig_profile":
            extra += " Data: [fig_profile.csv](fig_profile.csv)."
            if len(figures[key]) > 2:
                extra += " All scenarios: [fig3a_all.png](fig3a_all.png) ([svg](fig3a_all.svg))."
        lines += [f"### {CAPTIONS[key]}", "", f"![{key}]({png}) ([svg]({key}.svg)).{extra}", ""]
    md = tables["md"]
    lines += [
        "",
        "## Execution-phase EE per scenario and algorithm",
        "",
        f"CSV: [table_ee.csv](table_ee.csv). `(!)`: fewer than {MIN_SEEDS} seeds.",
        "",
        md["table_ee.md"],
        "",
        "## Open-loop check and the reference",
        "",
        "Per scenario: the reference (the exact per-slot optimum where `optimal` ran, else `greedy`, a lower "
        "bound on it), the upper bound on the per-slot optimum of the same slots (docs/model.md), so the "
        "optimum lies between the two, and `best_fixed`, the best constant action, as a share of the "
        "reference. CSV: [table_open_loop.csv](table_open_loop.csv).",
        "",
        md["table_open_loop.md"],
        "",
        "## Learning verdicts",
        "",
        "Per learner: its share of the reference, its multiple of the open-loop `best_fixed` (a result "
        "means something only above 1), and whether each seed's greedy policy had settled (its last "
        f"{LAST_EVALS} periodic evaluations within {SWING_LIMIT:.0%} of each other). "
        "CSV: [table_learning.csv](table_learning.csv).",
        "",
        tables["md_learning"],
        "",
        "## Aggregate over seeds and scenarios",
        "",
        "rliable's statistics (Agarwal et al., NeurIPS 2021) on normalised scores: each seed's execution EE "
        "as a share of its scenario's reference (the denominator of every share above), so that scenarios "
        "compare. Intervals: 95% stratified bootstrap, the seeds resampled within each scenario "
        "(see Statistics). CSV: [table_aggregate.csv](table_aggregate.csv).",
        "",
        tables["md_aggregate"],
        "",
        f"Probability of improvement: the chance that a seed of {reference or args.reference} scores higher than "
        "a seed of the other algorithm in the same scenario, averaged over the scenarios both ran (0.5: no "
        "difference; an interval containing 0.5 is no evidence either way). "
        "CSV: [table_improvement_probability.csv](table_improvement_probability.csv).",
        "",
        tables["md_improvement_probability"],
        "",
        "The performance profile is under Figures.",
        "",
        f"## Improvement of {reference or args.reference}",
        "",
        "CSV: [table_improvement.csv](table_improvement.csv).",
        "",
        md["table_improvement.md"],
        "",
        "## The paper side by side (Fig. 3b, U = 2)",
        "",
        "The paper's reported improvements (three seeds) beside ours. CSV: [table_paper.csv](table_paper.csv).",
        "",
        md["table_paper.md"],
        "",
        "## What the runs cost",
        "",
        "Measured from the runs themselves (analysis/cost.py), beside `tune --dry-run`'s estimate. "
        "CSV: [table_cost.csv](table_cost.csv).",
        "",
        tables["md_cost"],
        "",
        "## Machine-readable results",
        "",
        f"[{MARL_EVAL_FILE}]({MARL_EVAL_FILE}): marl-eval's raw-data JSON (environment `uavlora`, task `v<V>_u<U>`, "
        "one run per seed; steps = the periodic greedy-policy evaluations, absolute_metrics = the final one).",
        "",
        "## Statistics",
        "",
        STATS_TEXT.format(
            ref=reference or args.reference,
            smooth=args.smooth,
            points=args.points,
            open_loop=OPEN_LOOP_SHARE,
            boot=stats.BOOTSTRAP_RESAMPLES,
            agg_boot=stats.AGGREGATE_RESAMPLES,
            prof_boot=stats.PROFILE_RESAMPLES,
        ),
        "",
    ]
    return "\n".join(lines)
