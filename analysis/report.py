"""The analysis step: the paper's Fig. 2, Fig. 3a-c, result tables and the paper side by side,
from one or several MLflow experiments.

    python -m analysis.report --experiment NAME_OR_GLOB [--experiment ...] [--tracking-uri URI ...]
        [--out DIR] [--reference mappo] [--smooth 0.6] [--points 200] [--fig2-seed 0]
        [--fig2-algorithm NAME] [--no-fig2] [--no-log]

Reads the runs with MlflowClient (tags/params/metrics of the Tune callback's schema; never
Ray's result folders). Several --experiment values (names or shell globs such as 'sweep_V*')
and several --tracking-uri values are joined: every experiment matching a pattern at any URI
is read, so a sweep split over experiments or clusters gets its Fig. 3b/3c. Writes into DIR
(default reports/<experiment>, or reports/<a>+<b>... for several):

* fig3a.{png,svg}: (a) the greedy policy's execution EE per slot during training (the
  periodic evaluation, eval/ee_sys_mean against env steps) as a share of the scenario's
  reference, the per-slot optimum where the `optimal` baseline ran, else the greedy baseline,
  drawn as a line at 1; (b) the training return of the exploring policy. For the paper's
  scenario V=10, U=2 if present (else the scenario with the most seeds); fig3a_all.{png,svg}:
  panel (a) for every scenario; fig3a_curves.csv: the plotted numbers.
* fig3b.{png,svg} / fig3c.{png,svg}: execution EE against V at the most common U / against U
  at the most common V, learners and baselines; skipped (with a note) for a single value.
* fig2.{png,svg}: the ED-UAV association at the last slot of an evaluation episode, played by
  the best learner by execution EE (or --fig2-algorithm), from its best seed's checkpoint when
  that loads, else by a baseline.
* table_ee.{csv,md}, table_improvement.{csv,md}, table_paper.{csv,md} (the paper's numbers
  beside ours, analysis.paper), table_open_loop.{csv,md} (per scenario: the reference and its
  action mode, the upper bound on the optimum, best_fixed's share and whether a constant is
  optimal there), table_learning.{csv,md} (analysis.verdicts: each learner's share of the reference
  and of best_fixed, and whether its last evaluations had settled), results_marl_eval.json (analysis.export), and report.md linking
  all of it with the source, a WARNING line for every weak or mixed cell, and notes (overlapping
  series, skipped figures, truncations).
* aggregates over seeds and scenarios (analysis.aggregate, rliable's definitions): table_aggregate.{csv,md}
  (IQM and mean of the normalised scores with 95% stratified-bootstrap CIs),
  table_improvement_probability.{csv,md} (P(--reference > X) for every other learner and best_fixed),
  fig_profile.{png,svg} and fig_profile.csv (the performance profile). Normalised score: a seed's
  execution EE as a share of its scenario's reference, the denominator of every share above.

With one experiment the outputs are logged as artifacts of the grid's parent run (tag
kind=grid), in its folder ``report/`` (replaced on every report), beside the grid's trials and
baselines; an experiment written before parents existed gets a summary run instead (tag
kind=summary; reused, its artifacts replaced). With several, nothing is logged (no single experiment owns the
report; a note says so). Modules: data (cells, references, curves), tables, figures, paper,
export, stats. Every expected failure (bad flag, unknown experiment, unreachable URI, --out a
file or not writable) prints one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any
from urllib.parse import urlparse

from analysis import stats, style
from analysis.aggregate import (
    PROFILE_COLUMNS,
    TABLE_AGGREGATE_COLUMNS,
    TABLE_POI_COLUMNS,
    aggregate_md,
    aggregate_table,
    improvement_probability_md,
    improvement_probability_table,
    mixed_scenarios_note,
    performance_profiles,
    profile_rows,
    score_sets,
)
from analysis.data import (
    CURVE_METRICS,
    EVAL_CURVE,
    MIN_SEEDS,
    RETURN_METRIC,
    curves,
    mlflow_history,
    organise,
)
from analysis.export import marl_eval_data, write_marl_eval
from analysis.figures import fig2, fig2_record, fig3a, fig_profile, fig_sweep, looks, write_curves_csv
from analysis.paper import PAPER_COLUMNS, paper_md, paper_rows
from analysis.runs import GRID_KIND, SUMMARY_KIND, ReportError, RunRecord, Source, load_runs, resolve_sources
from analysis.tables import (
    OPEN_LOOP_SHARE,
    TABLE_EE_COLUMNS,
    TABLE_IMP_COLUMNS,
    TABLE_OPEN_LOOP_COLUMNS,
    ee_table,
    ee_table_md,
    improvement_md,
    improvement_table,
    open_loop_md,
    open_loop_table,
    write_csv,
)
from analysis.verdicts import LAST_EVALS, SWING_LIMIT, TABLE_LEARNING_COLUMNS, learning_md, learning_table
from uavlora_rllib.cli_args import Parser, UsageError, fail, float_in, int_in, seed

# Every file the report may write (nothing else in --out is touched or logged).
OUTPUT_FILES = tuple(
    [f"{stem}.{ext}" for stem in ("fig2", "fig3a", "fig3a_all", "fig3b", "fig3c", "fig_profile") for ext in ("png", "svg")]
    + ["fig3a_curves.csv", "table_ee.csv", "table_ee.md", "table_improvement.csv", "table_improvement.md",
       "table_paper.csv", "table_paper.md", "table_open_loop.csv", "table_open_loop.md", "table_learning.csv",
       "table_learning.md", "table_aggregate.csv", "table_aggregate.md", "table_improvement_probability.csv",
       "table_improvement_probability.md", "fig_profile.csv", "results_marl_eval.json",
       "report.md"]
)
MARL_EVAL_FILE = "results_marl_eval.json"


def progress(total: int, desc: str):
    """A tqdm bar on stderr (shown on a terminal only: off in logs and pipes)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=None, leave=False)


# ---------------------------------------------------------------- report.md
def _distinct(values) -> str:
    vals = sorted({str(v) for v in values if v not in (None, "")})
    return ", ".join(vals) if vals else "n/a"


def source_section(sources: list[Source], records: list[RunRecord]) -> list[str]:
    kinds = Counter(r.kind for r in records)
    statuses = Counter(r.status for r in records)
    train = [r for r in records if r.kind == "train"]
    base = [r for r in records if r.kind == "baseline"]
    per_exp = Counter(r.source for r in records)
    lines = [f"- experiment: `{s.name}` (id {s.experiment.experiment_id}) at `{s.tracking_uri}`: "
             f"{per_exp.get(i, 0)} runs" for i, s in enumerate(sources)]
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
  names it); the column names which. Open-loop check: `best_fixed`'s share of that reference;
  at {open_loop} or above a constant action counts as optimal.
- paper table: ratio of seed means mappo / other with a 95% Fieller interval over seeds
  (independent samples, t with min(n_a, n_b) - 1 degrees of freedom); improvement = 100 (ratio - 1).
- Fig. 3a (a): each run's `eval/ee_sys_mean` history (the greedy policy evaluated every
  evaluation.interval_env_steps env steps on fixed episodes, the last point being the final
  evaluation), unsmoothed; (b): each run's `episode_return_mean` history smoothed with a debiased
  EMA (weight {smooth}; 0 = none). Both are interpolated linearly onto {points} evenly spaced
  env-step values spanning the range all seeds cover and averaged over seeds (FINISHED runs);
  the band is a 95% percentile bootstrap of that mean over seeds ({boot} resamples), drawn only
  for n >= 2.
- Fig. 3b/3c error bars: the 95% t CI over seeds above (none for a single seed). Titles state n.
- aggregates over seeds and scenarios: rliable's definitions (Agarwal et al. 2021), computed
  with scipy because rliable itself does not install on the pinned stack (docs/model.md#aggregate-statistics).
  The normalised score of a seed is its EE as a share of the scenario's reference (the
  denominator of "share of reference" above), which puts scenarios of very different EE on one
  scale. IQM: the 25% trimmed mean of all (seed, scenario) scores of an algorithm pooled
  (`analysis.stats.iqm`, the per-cell IQM's function); mean: the mean over scenarios of the
  per-scenario seed means. P({ref} > X): over the scenarios both ran, the mean of each scenario's
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


def prepare_out_dir(out_dir: str) -> None:
    """Create the output folder (ReportError when it is a file or cannot be created) and remove
    the previous report's files, so stale outputs cannot survive."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ReportError(f"--out: {out_dir!r} is a file; expected a folder (existing or new)")
    try:
        os.makedirs(out_dir, exist_ok=True)
        for name in OUTPUT_FILES:
            p = os.path.join(out_dir, name)
            if os.path.isfile(p):
                os.remove(p)
    except OSError as exc:
        raise ReportError(f"--out: cannot write to {out_dir!r}: {exc.strerror or exc}") from None
    if not os.access(out_dir, os.W_OK):
        raise ReportError(f"--out: cannot write to {out_dir!r}: permission denied")


def build_report(sources: list[Source], out_dir: str, args) -> dict[str, Any]:
    with style.context():
        return _build_report(sources, out_dir, args)


def _build_report(sources: list[Source], out_dir: str, args) -> dict[str, Any]:
    records: list[RunRecord] = []
    summaries: list[Any] = []
    for i, src in enumerate(sources):
        recs, summ = load_runs(src.client, src.experiment.experiment_id, src.name, i)
        records += recs
        summaries.append(summ)
    records.sort(key=lambda r: (r.start_time, r.run_id))
    org = organise(records)
    reference = org.find_train(args.reference)
    if args.fig2_algorithm is not None and not args.no_fig2:
        fig2_record(org, args.fig2_algorithm)  # a bad name fails here, before anything is written
    prepare_out_dir(out_dir)
    history = mlflow_history(sources)
    notes: list[str] = []
    if reference is None:
        notes.append(f"No training runs of the reference algorithm {args.reference!r}: no improvement table.")
    bar = progress(2 * sum(1 for r in records if r.kind == "train") + 4, "report")
    tables = write_tables(org, reference, args.reference, out_dir)
    tables.update(write_learning_table(org, history, out_dir))
    bar.update(1)

    def counted(record, key):
        bar.update(1)
        return history(record, key)

    figures, captions, fig_notes = draw_figures(org, counted, out_dir, args)
    notes += fig_notes
    agg = write_aggregates(org, reference, out_dir)
    tables.update(agg)
    notes += agg["notes"]
    if agg["files"]:
        figures["fig_profile"] = agg["files"]
    captions["fig_profile"] = agg["caption"]
    bar.update(2)
    marl, mnotes = marl_eval_data(org, history)
    write_marl_eval(os.path.join(out_dir, MARL_EVAL_FILE), marl)
    notes += mnotes
    if len(sources) > 1:
        notes.append(f"{len(sources)} experiments joined; the outputs are not logged to MLflow (no single experiment owns them).")
    bar.update(1)
    bar.close()
    report_path = os.path.join(out_dir, "report.md")
    with open(report_path, "w") as fh:
        fh.write(report_markdown(sources, records, org, notes, figures, captions, tables, reference, args))
    return {"report": report_path, "figures": figures, "warnings": org.warnings, "notes": notes,
            "summaries": summaries, "rows": tables["rows"], "improvements": tables["improvements"],
            "paper": tables["paper"], "open_loop": tables["open_loop"], "learning": tables["learning"],
            "aggregate": tables["aggregate"], "improvement_probability": tables["improvement_probability"],
            "n_runs": len(records)}


def write_tables(org, reference: str | None, requested: str, out_dir: str) -> dict[str, Any]:
    """table_ee, table_improvement and table_paper as CSV and Markdown; their rows and Markdown."""
    rows, imp_rows, p_rows = ee_table(org, reference), improvement_table(org, reference), paper_rows(org)
    ol_rows = open_loop_table(org)
    write_csv(os.path.join(out_dir, "table_open_loop.csv"), TABLE_OPEN_LOOP_COLUMNS, ol_rows)
    write_csv(os.path.join(out_dir, "table_ee.csv"), TABLE_EE_COLUMNS, rows)
    write_csv(os.path.join(out_dir, "table_improvement.csv"), TABLE_IMP_COLUMNS, imp_rows)
    write_csv(os.path.join(out_dir, "table_paper.csv"), PAPER_COLUMNS, p_rows)
    md = {"table_ee.md": ee_table_md(rows, reference), "table_improvement.md": improvement_md(imp_rows, reference or requested),
          "table_paper.md": paper_md(p_rows), "table_open_loop.md": open_loop_md(ol_rows)}
    for name, text in md.items():
        with open(os.path.join(out_dir, name), "w") as fh:
            fh.write(text + "\n")
    return {"rows": rows, "improvements": imp_rows, "paper": p_rows, "open_loop": ol_rows, "md": md}


def write_learning_table(org, history, out_dir: str) -> dict[str, Any]:
    """table_learning (CSV and Markdown): the learning verdicts, which read each run's evaluation curve."""
    rows = learning_table(org, history)
    write_csv(os.path.join(out_dir, "table_learning.csv"), TABLE_LEARNING_COLUMNS, rows)
    md = learning_md(rows)
    with open(os.path.join(out_dir, "table_learning.md"), "w") as fh:
        fh.write(md + "\n")
    return {"learning": rows, "md_learning": md}


def write_aggregates(org, reference: str | None, out_dir: str) -> dict[str, Any]:
    """table_aggregate, table_improvement_probability (CSV and Markdown), the performance profile
    (fig_profile.{png,svg} and its CSV): rows, Markdown, files, caption and notes."""
    sets = score_sets(org)
    agg_rows = aggregate_table(org, sets)
    poi_rows = improvement_probability_table(org, sets, reference)
    write_csv(os.path.join(out_dir, "table_aggregate.csv"), TABLE_AGGREGATE_COLUMNS, agg_rows)
    write_csv(os.path.join(out_dir, "table_improvement_probability.csv"), TABLE_POI_COLUMNS, poi_rows)
    md = {"md_aggregate": aggregate_md(agg_rows), "md_improvement_probability": improvement_probability_md(poi_rows, reference)}
    for name, key in (("table_aggregate.md", "md_aggregate"), ("table_improvement_probability.md", "md_improvement_probability")):
        with open(os.path.join(out_dir, name), "w") as fh:
            fh.write(md[key] + "\n")
    taus, profiles = performance_profiles(org, sets, reference)
    files, notes, caption = fig_profile(taus, profiles, sets, org, looks(org.algorithms()), out_dir)
    if files:
        write_csv(os.path.join(out_dir, "fig_profile.csv"), PROFILE_COLUMNS, profile_rows(sets, taus, profiles))
    note = mixed_scenarios_note(agg_rows)
    return {"aggregate": agg_rows, "improvement_probability": poi_rows, **md, "files": files, "caption": caption,
            "notes": notes + ([note] if note else [])}


def draw_figures(org, history, out_dir: str, args) -> tuple[dict[str, list[str]], dict[str, str], list[str]]:
    """Fig. 3a (and its CSV), 3b, 3c and 2: ({key: files}, {key: caption}, notes)."""
    notes: list[str] = []
    figures: dict[str, list[str]] = {}
    curve_sets = {}
    for metric in CURVE_METRICS:
        # the execution curve needs 2+ points (a lone point is the final evaluation, no curve)
        smooth = args.smooth if metric == RETURN_METRIC else 0.0
        curve_sets[metric], cnotes = curves(history, org, metric, smooth, args.points, 2 if metric == EVAL_CURVE else 1)
        notes += cnotes
    lk = looks(org.algorithms() + [a for cs in curve_sets.values() for s in cs.values() for a in s])
    files, n3a, cap3a = fig3a(curve_sets[EVAL_CURVE], curve_sets[RETURN_METRIC], org, lk, out_dir, args.smooth)
    notes += n3a
    if files:
        figures["fig3a"] = files
        write_curves_csv(curve_sets, org, os.path.join(out_dir, "fig3a_curves.csv"))
    captions = {"fig3a": cap3a}
    for axis, stem, label in (("n_eds", "fig3b", "Fig. 3b"), ("n_uavs", "fig3c", "Fig. 3c")):
        files, snotes, captions[stem] = fig_sweep(org, axis, lk, out_dir, stem, label)
        if files:
            figures[stem] = files
        notes += snotes
    if args.no_fig2:
        notes.append("Fig. 2 skipped (--no-fig2).")
        return figures, captions, notes
    try:
        figures["fig2"], captions["fig2"], n2 = fig2(org, args.fig2_algorithm, out_dir, args.fig2_seed)
        captions["fig2"] = f"Source: {captions['fig2']}"
        notes += n2
    except ReportError:
        raise
    except Exception as exc:  # noqa: BLE001 - the report must not die on the simulator
        notes.append(f"Fig. 2 skipped: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}")
    return figures, captions, notes


def report_markdown(sources, records, org, notes, figures, captions, tables, reference, args) -> str:
    """report.md: source, warnings, notes, figures with captions, tables, statistics."""
    title = ", ".join(f"`{s.name}`" for s in sources)
    lines = [f"# Report: experiment{'s' if len(sources) > 1 else ''} {title}", "",
             f"Generated {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())} by `python -m analysis.report`.",
             "", "## Source", ""]
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
    lines += ["", "## Execution-phase EE per scenario and algorithm", "",
              f"CSV: [table_ee.csv](table_ee.csv). `(!)`: fewer than {MIN_SEEDS} seeds.", "", md["table_ee.md"], "",
              "## Open-loop check and the reference", "",
              "Per scenario: the reference (the exact per-slot optimum where `optimal` ran, else `greedy`, a lower "
              "bound on it), the upper bound on the per-slot optimum of the same slots (docs/model.md), so the "
              "optimum lies between the two, and `best_fixed`, the best constant action, as a share of the "
              "reference. CSV: [table_open_loop.csv](table_open_loop.csv).", "", md["table_open_loop.md"], "",
              "## Learning verdicts", "",
              "Per learner: its share of the reference, its multiple of the open-loop `best_fixed` (a result "
              "means something only above 1), and whether each seed's greedy policy had settled (its last "
              f"{LAST_EVALS} periodic evaluations within {SWING_LIMIT:.0%} of each other). "
              "CSV: [table_learning.csv](table_learning.csv).", "", tables["md_learning"], "",
              "## Aggregate over seeds and scenarios", "",
              "rliable's statistics (Agarwal et al., NeurIPS 2021) on normalised scores: each seed's execution EE "
              "as a share of its scenario's reference (the denominator of every share above), so that scenarios "
              "compare. Intervals: 95% stratified bootstrap, the seeds resampled within each scenario "
              "(see Statistics). CSV: [table_aggregate.csv](table_aggregate.csv).", "", tables["md_aggregate"], "",
              f"Probability of improvement: the chance that a seed of {reference or args.reference} scores higher than "
              "a seed of the other algorithm in the same scenario, averaged over the scenarios both ran (0.5: no "
              "difference; an interval containing 0.5 is no evidence either way). "
              "CSV: [table_improvement_probability.csv](table_improvement_probability.csv).", "",
              tables["md_improvement_probability"], "",
              "The performance profile is under Figures.", "",
              f"## Improvement of {reference or args.reference}", "",
              "CSV: [table_improvement.csv](table_improvement.csv).", "", md["table_improvement.md"], "",
              "## The paper side by side (Fig. 3b, U = 2)", "",
              "The paper's reported improvements (three seeds) beside ours. CSV: [table_paper.csv](table_paper.csv).", "",
              md["table_paper.md"], "",
              "## Machine-readable results", "",
              f"[{MARL_EVAL_FILE}]({MARL_EVAL_FILE}): marl-eval's raw-data JSON (environment `uavlora`, task `v<V>_u<U>`, "
              "one run per seed; steps = the periodic greedy-policy evaluations, absolute_metrics = the final one).", "",
              "## Statistics", "",
              STATS_TEXT.format(ref=reference or args.reference, smooth=args.smooth, points=args.points,
                                open_loop=OPEN_LOOP_SHARE, boot=stats.BOOTSTRAP_RESAMPLES,
                                agg_boot=stats.AGGREGATE_RESAMPLES, prof_boot=stats.PROFILE_RESAMPLES), ""]
    return "\n".join(lines)


def _local_path(uri: str) -> str | None:
    p = urlparse(uri)
    if p.scheme in ("", "file"):
        return p.path if p.scheme == "file" else uri
    return None


REPORT_ARTIFACT_DIR = "report"  # the report's folder among the grid parent run's artifacts


def _clear_local_artifacts(artifact_uri: str, sub: str = "") -> None:
    """Remove a run's previous artifacts (under `sub`) when they are stored locally, so that a new
    report replaces the old one instead of mixing with it (servers overwrite same-named files)."""
    local = _local_path(artifact_uri or "")
    target = os.path.join(local, sub) if local and sub else local
    if not target or not os.path.isdir(target):
        return
    for name in os.listdir(target):
        p = os.path.join(target, name)
        shutil.rmtree(p) if os.path.isdir(p) else os.remove(p)


def _tag_report(client, run_id: str, result: dict[str, Any]) -> None:
    client.set_tag(run_id, "report_generated_utc", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    client.set_tag(run_id, "report_runs", str(result["n_runs"]))
    client.set_tag(run_id, "report_warnings", str(len(result["warnings"])))


def log_summary(client, exp, summaries, out_dir: str, result: dict[str, Any]) -> str:
    """Log out_dir as artifacts of the grid's parent run (folder report/; the oldest parent when
    several) or, in an experiment without one, of its summary run (the newest is reused, older
    ones are deleted, the reused run's previous artifacts are removed when stored locally)."""
    parents = [r for r in summaries if r.data.tags.get("kind") == GRID_KIND]
    if parents:
        run_id = parents[0].info.run_id
        _clear_local_artifacts(parents[0].info.artifact_uri, REPORT_ARTIFACT_DIR)
        _tag_report(client, run_id, result)
        for name in OUTPUT_FILES:
            path = os.path.join(out_dir, name)
            if os.path.isfile(path):
                client.log_artifact(run_id, path, REPORT_ARTIFACT_DIR)
        return run_id  # its status is the grid's (FINISHED, KILLED, ...): left as it is
    summaries = [r for r in summaries if r.data.tags.get("kind") != GRID_KIND]
    if summaries:
        run_id = summaries[0].info.run_id
        for extra in summaries[1:]:
            client.delete_run(extra.info.run_id)
        _clear_local_artifacts(summaries[0].info.artifact_uri)
        client.update_run(run_id, status="RUNNING")
    else:
        run_id = client.create_run(exp.experiment_id, run_name="summary", tags={"kind": SUMMARY_KIND}).info.run_id
    client.set_tag(run_id, "kind", SUMMARY_KIND)
    _tag_report(client, run_id, result)
    for name in OUTPUT_FILES:
        path = os.path.join(out_dir, name)
        if os.path.isfile(path):
            client.log_artifact(run_id, path)
    client.set_terminated(run_id, "FINISHED")
    return run_id


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m analysis.report", description=__doc__.split("\n\n")[0])
    p.add_argument("--experiment", action="append", required=True,
                   help="MLflow experiment name or shell glob; repeat to join several")
    p.add_argument("--tracking-uri", action="append", default=None,
                   help="MLflow tracking URI; repeat to read several stores (default sqlite:///mlflow.db)")
    p.add_argument("--out", default=None, help="output folder (default reports/<experiment>)")
    p.add_argument("--reference", default="mappo", help="algorithm whose improvement is reported (default mappo)")
    p.add_argument("--smooth", type=float_in(0.0, 1.0, high_open=True), default=0.6, help="EMA weight of the training-return curves in [0, 1) (default 0.6)")
    p.add_argument("--points", type=int_in(2), default=200, help="env-step grid points of Fig. 3a (default 200)")
    p.add_argument("--fig2-seed", type=seed, default=0, help="evaluation episode of Fig. 2 (seed offset, default 0)")
    p.add_argument("--fig2-algorithm", default=None, help="learner that plays Fig. 2 (default: the best by execution EE)")
    p.add_argument("--no-fig2", action="store_true", help="skip Fig. 2 (no simulation)")
    p.add_argument("--no-log", action="store_true", help="do not log the outputs to MLflow (the grid's parent run, or a summary run)")
    return p


def default_out(sources: list[Source]) -> str:
    names = list(dict.fromkeys(s.name for s in sources))
    return os.path.join("reports", "+".join(names)[:120])


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        sources = resolve_sources(args.tracking_uri or ["sqlite:///mlflow.db"], args.experiment)
        out_dir = args.out or default_out(sources)
        result = build_report(sources, out_dir, args)
        logged = ""
        if not args.no_log and len(sources) == 1:
            try:
                run_id = log_summary(sources[0].client, sources[0].experiment, result["summaries"][0], out_dir, result)
            except Exception as exc:  # noqa: BLE001 - e.g. a read-only store: the files are written already
                raise ReportError(f"the report is in {out_dir}, but logging it to MLflow failed "
                                  f"({type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}); "
                                  "rerun with --no-log to skip logging") from None
            logged = f"; logged to MLflow run {run_id}"
    except UsageError as exc:  # ReportError and the parser's errors
        return fail(exc, "report")
    except OSError as exc:  # the output folder filled up or vanished while writing
        print(f"report: error: cannot write the report: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("report: interrupted; the output folder may hold a partial report", file=sys.stderr)
        return 130
    figs = ", ".join(sorted(result["figures"])) or "none"
    print(f"report: {result['report']} ({result['n_runs']} runs from {len(sources)} experiment(s), figures: {figs}, "
          f"{len(result['warnings'])} warning(s)){logged}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
