"""Writing one report into its folder: the tables, the figures, the aggregates, the marl-eval JSON
and report.md, from the runs of one or more MLflow experiments."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
from collections.abc import Iterator
from typing import Any

from analysis import style
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
from analysis.cost import TABLE_COST_COLUMNS, cost_md, cost_table
from analysis.data import (
    CURVE_METRICS,
    EVAL_CURVE,
    RETURN_METRIC,
    curves,
    mlflow_history,
    organise,
)
from analysis.export import MARL_EVAL_FILE, marl_eval_data, write_marl_eval
from analysis.figures import fig2, fig2_record, fig3a, fig_profile, fig_sweep, looks, write_curves_csv
from analysis.paper import PAPER_COLUMNS, paper_md, paper_rows
from analysis.report_md import report_markdown
from analysis.runs import ReportError, RunRecord, Source, check_writable_folder, load_runs
from analysis.tables import (
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
from analysis.verdicts import TABLE_LEARNING_COLUMNS, learning_md, learning_table, stopped_before_budget
from uavlora_rllib.experiment.driver_lock import pid_alive

# Every file the report may write (nothing else in --out is touched or logged).
OUTPUT_FILES = tuple(
    [
        f"{stem}.{ext}"
        for stem in ("fig2", "fig3a", "fig3a_all", "fig3b", "fig3c", "fig_profile")
        for ext in ("png", "svg")
    ]
    + [
        "fig3a_curves.csv",
        "table_ee.csv",
        "table_ee.md",
        "table_improvement.csv",
        "table_improvement.md",
        "table_paper.csv",
        "table_paper.md",
        "table_open_loop.csv",
        "table_open_loop.md",
        "table_learning.csv",
        "table_learning.md",
        "table_aggregate.csv",
        "table_aggregate.md",
        "table_improvement_probability.csv",
        "table_improvement_probability.md",
        "table_cost.csv",
        "table_cost.md",
        "fig_profile.csv",
        "results_marl_eval.json",
        "report.md",
    ]
)


def progress(total: int, desc: str):
    """A tqdm bar on stderr (shown on a terminal only: off in logs and pipes)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="step", disable=None, leave=False)


STAGING = ".report-partial"  # inside --out: the report being written, `<STAGING>-<host>-<pid>` (`staged_out_dir`)


@contextlib.contextmanager
def staged_out_dir(out_dir: str) -> Iterator[str]:
    """Create the output folder (ReportError when it is a file or cannot be created) and yield an
    empty staging folder inside it, where the report is written; on success `publish` moves it into
    place, on an error or Ctrl+C it is removed, so a report stopped while writing (killed outright:
    all but the hidden staging folder) leaves the previous one whole."""
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise ReportError(f"--out: {out_dir!r} is a file; expected a folder (existing or new)")
    check_writable_folder(out_dir, "--out")
    mine = f"{STAGING}-{socket.gethostname()}-"  # a report writing into the same --out keeps its own
    staging = os.path.join(out_dir, f"{mine}{os.getpid()}")
    try:
        for name in os.listdir(out_dir):  # this host's reports killed outright (their process is gone)
            pid = name[len(mine) :] if name.startswith(mine) else ""
            if pid.isdigit() and not pid_alive(int(pid)):
                shutil.rmtree(os.path.join(out_dir, name), ignore_errors=True)
        shutil.rmtree(staging, ignore_errors=True)
        os.makedirs(staging)
    except OSError as exc:
        raise ReportError(f"--out: cannot write to {out_dir!r}: {exc.strerror or exc}") from None
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    publish(staging, out_dir)


def publish(staging: str, out_dir: str) -> None:
    """Replace the previous report's files with the staged ones (renames within one filesystem) and
    remove those the new report did not write, so stale outputs cannot survive; nothing else in
    out_dir is touched."""
    for name in OUTPUT_FILES:
        new, old = os.path.join(staging, name), os.path.join(out_dir, name)
        if os.path.isfile(new):
            os.replace(new, old)
        elif os.path.isfile(old):
            os.remove(old)
    shutil.rmtree(staging, ignore_errors=True)


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
    # a name given must have training runs; the default may lack them (report.md then notes it)
    if reference is None and args.reference_given:
        learners = ", ".join(org.algorithms("train")) or "none"
        raise ReportError(f"--reference: {args.reference!r} has no training runs; learners: {learners}")
    if args.fig2_algorithm is not None and not args.no_fig2:
        fig2_record(org, args.fig2_algorithm)  # a bad name fails here, before anything is written
    with staged_out_dir(out_dir) as staging:
        result = _write_report(sources, records, org, reference, staging, args)
    result["summaries"] = summaries
    result["report"] = os.path.join(out_dir, "report.md")
    result["figures"] = {
        k: [os.path.join(out_dir, os.path.basename(f)) for f in v] for k, v in result["figures"].items()
    }
    return result


def _write_report(
    sources: list[Source], records: list[RunRecord], org, reference, out_dir: str, args
) -> dict[str, Any]:
    """Every file of the report into out_dir (the staging folder); the report's contents."""
    history = mlflow_history(sources)
    notes: list[str] = []
    if reference is None:
        configs = [a for a in org.algorithms("train") if a.startswith(f"{args.reference}[")]
        notes.append(
            f"No training runs of the reference algorithm {args.reference!r}: no improvement table."
            + (
                f" A sweep's configurations of it are cells of their own ({', '.join(configs[:3])}"
                f"{', ...' if len(configs) > 3 else ''}): pass one as --reference."
                if configs
                else ""
            )
        )
    notes += stopped_before_budget(org, history)
    bar = progress(2 * sum(1 for r in records if r.kind == "train") + 4, "report")
    tables = write_tables(org, reference, args.reference, out_dir)
    tables.update(write_learning_table(org, history, out_dir))
    tables.update(write_cost_table(records, out_dir))
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
        notes.append(
            f"{len(sources)} experiments joined; the outputs are not logged to MLflow (no single experiment owns them)."
        )
    bar.update(1)
    bar.close()
    with open(os.path.join(out_dir, "report.md"), "w") as fh:
        fh.write(report_markdown(sources, records, org, notes, figures, captions, tables, reference, args))
    return {
        "figures": figures,
        "warnings": org.warnings,
        "notes": notes,
        "rows": tables["rows"],
        "improvements": tables["improvements"],
        "paper": tables["paper"],
        "open_loop": tables["open_loop"],
        "learning": tables["learning"],
        "aggregate": tables["aggregate"],
        "improvement_probability": tables["improvement_probability"],
        "cost": tables["cost"],
        "n_runs": len(records),
    }


def write_tables(org, reference: str | None, requested: str, out_dir: str) -> dict[str, Any]:
    """table_ee, table_improvement and table_paper as CSV and Markdown; their rows and Markdown."""
    rows, imp_rows, p_rows = ee_table(org, reference), improvement_table(org, reference), paper_rows(org)
    ol_rows = open_loop_table(org)
    write_csv(os.path.join(out_dir, "table_open_loop.csv"), TABLE_OPEN_LOOP_COLUMNS, ol_rows)
    write_csv(os.path.join(out_dir, "table_ee.csv"), TABLE_EE_COLUMNS, rows)
    write_csv(os.path.join(out_dir, "table_improvement.csv"), TABLE_IMP_COLUMNS, imp_rows)
    write_csv(os.path.join(out_dir, "table_paper.csv"), PAPER_COLUMNS, p_rows)
    md = {
        "table_ee.md": ee_table_md(rows, reference),
        "table_improvement.md": improvement_md(imp_rows, reference or requested),
        "table_paper.md": paper_md(p_rows),
        "table_open_loop.md": open_loop_md(ol_rows),
    }
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


def write_cost_table(records, out_dir: str) -> dict[str, Any]:
    """table_cost (CSV and Markdown): what the runs took, measured (analysis/cost.py)."""
    rows = cost_table(records)
    write_csv(os.path.join(out_dir, "table_cost.csv"), TABLE_COST_COLUMNS, rows)
    md = cost_md(rows)
    with open(os.path.join(out_dir, "table_cost.md"), "w") as fh:
        fh.write(md + "\n")
    return {"cost": rows, "md_cost": md}


def write_aggregates(org, reference: str | None, out_dir: str) -> dict[str, Any]:
    """table_aggregate, table_improvement_probability (CSV and Markdown), the performance profile
    (fig_profile.{png,svg} and its CSV): rows, Markdown, files, caption and notes."""
    sets = score_sets(org)
    agg_rows = aggregate_table(org, sets)
    poi_rows = improvement_probability_table(org, sets, reference)
    write_csv(os.path.join(out_dir, "table_aggregate.csv"), TABLE_AGGREGATE_COLUMNS, agg_rows)
    write_csv(os.path.join(out_dir, "table_improvement_probability.csv"), TABLE_POI_COLUMNS, poi_rows)
    md = {
        "md_aggregate": aggregate_md(agg_rows),
        "md_improvement_probability": improvement_probability_md(poi_rows, reference),
    }
    for name, key in (
        ("table_aggregate.md", "md_aggregate"),
        ("table_improvement_probability.md", "md_improvement_probability"),
    ):
        with open(os.path.join(out_dir, name), "w") as fh:
            fh.write(md[key] + "\n")
    taus, profiles = performance_profiles(org, sets, reference)
    files, notes, caption = fig_profile(taus, profiles, sets, org, looks(org.algorithms()), out_dir)
    if files:
        write_csv(os.path.join(out_dir, "fig_profile.csv"), PROFILE_COLUMNS, profile_rows(sets, taus, profiles))
    note = mixed_scenarios_note(agg_rows)
    return {
        "aggregate": agg_rows,
        "improvement_probability": poi_rows,
        **md,
        "files": files,
        "caption": caption,
        "notes": notes + ([note] if note else []),
    }


def draw_figures(org, history, out_dir: str, args) -> tuple[dict[str, list[str]], dict[str, str], list[str]]:
    """Fig. 3a (and its CSV), 3b, 3c and 2: ({key: files}, {key: caption}, notes)."""
    notes: list[str] = []
    figures: dict[str, list[str]] = {}
    curve_sets = {}
    for metric in CURVE_METRICS:
        # the execution curve needs 2+ points (a lone point is the final evaluation, no curve)
        smooth = args.smooth if metric == RETURN_METRIC else 0.0
        ev = metric == EVAL_CURVE  # divided by the reference: over the seeds it ran
        curve_sets[metric], cnotes = curves(history, org, metric, smooth, args.points, 2 if ev else 1, matched=ev)
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
