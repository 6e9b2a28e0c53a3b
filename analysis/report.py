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
  drawn as a line at 1 (over the seeds the reference also ran, as every share); (b) the training return of the exploring policy. For the paper's
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
report; a note says so). The files are written in a staging folder inside --out and moved into place
once all are written, so a report stopped midway leaves the previous one whole. Modules: report_files
(writes the folder), report_md (report.md),
report_mlflow (the logging), data (cells, references, curves), tables, figures, paper, export,
stats. Every expected failure (bad flag, unknown experiment, unreachable URI, --out a
file or not writable) prints one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from analysis.report_files import build_report
from analysis.report_mlflow import log_summary
from analysis.runs import ReportError, Source, resolve_sources
from uavlora_rllib.cli_args import Parser, UsageError, fail, float_in, int_in, nonempty_path, seed

DEFAULT_REFERENCE = "mappo"
# Fig. 3a interpolates every run's curves onto a grid of --points env steps: 10^5 is far more than
# a figure can show, and 10^9 exhaust the memory
MAX_POINTS = 100_000


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m analysis.report", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--experiment",
        action="append",
        required=True,
        help="MLflow experiment name or shell glob; repeat to join several",
    )
    p.add_argument(
        "--tracking-uri",
        action="append",
        default=None,
        help="MLflow tracking URI; repeat to read several stores (default sqlite:///mlflow.db)",
    )
    p.add_argument("--out", type=nonempty_path, default=None, help="output folder (default reports/<experiment>)")
    p.add_argument(
        "--reference",
        default=None,
        help=f"learner whose improvement is reported (default {DEFAULT_REFERENCE}, skipped with a note when it has "
        "no training runs; a name given must have some)",
    )
    p.add_argument(
        "--smooth",
        type=float_in(0.0, 1.0, high_open=True),
        default=0.6,
        help="EMA weight of the training-return curves in [0, 1) (default 0.6)",
    )
    p.add_argument(
        "--points",
        type=int_in(2, MAX_POINTS),
        default=200,
        help=f"env-step grid points of Fig. 3a in [2, {MAX_POINTS}] (default 200)",
    )
    p.add_argument("--fig2-seed", type=seed, default=None, help="evaluation episode of Fig. 2 (seed offset, default 0)")
    p.add_argument(
        "--fig2-algorithm", default=None, help="learner that plays Fig. 2 (default: the best by execution EE)"
    )
    p.add_argument("--no-fig2", action="store_true", help="skip Fig. 2 (no simulation)")
    p.add_argument(
        "--no-log",
        action="store_true",
        help="do not log the outputs to MLflow (the grid's parent run, or a summary run)",
    )
    return p


def default_out(sources: list[Source]) -> str:
    names = list(dict.fromkeys(s.name for s in sources))
    return os.path.join("reports", "+".join(names)[:120])


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The parsed flags, with the combinations that would silently do nothing refused (UsageError)."""
    args = build_parser().parse_args(argv)
    if args.no_fig2:
        for flag, value in (("--fig2-algorithm", args.fig2_algorithm), ("--fig2-seed", args.fig2_seed)):
            if value is not None:
                raise UsageError(f"{flag}: applies to Fig. 2, which --no-fig2 skips; drop one of them")
    args.fig2_seed = 0 if args.fig2_seed is None else args.fig2_seed
    args.reference_given = args.reference is not None
    args.reference = DEFAULT_REFERENCE if args.reference is None else args.reference
    return args


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = parse_args(argv)
        sources = resolve_sources(args.tracking_uri or ["sqlite:///mlflow.db"], args.experiment)
        out_dir = args.out or default_out(sources)
        result = build_report(sources, out_dir, args)
        logged = ""
        if not args.no_log and len(sources) == 1:
            try:
                run_id = log_summary(sources[0].client, sources[0].experiment, result["summaries"][0], out_dir, result)
            except Exception as exc:  # noqa: BLE001 - e.g. a read-only store: the files are written already
                raise ReportError(
                    f"the report is in {out_dir}, but logging it to MLflow failed "
                    f"({type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}); "
                    "rerun with --no-log to skip logging"
                ) from None
            logged = f"; logged to MLflow run {run_id}"
    except UsageError as exc:  # ReportError and the parser's errors
        return fail(exc, "report")
    except OSError as exc:  # the output folder filled up or vanished while writing
        print(f"report: error: cannot write the report: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("report: interrupted; the output folder holds the previous report, if any, unchanged", file=sys.stderr)
        return 130
    figs = ", ".join(sorted(result["figures"])) or "none"
    print(
        f"report: {result['report']} ({result['n_runs']} runs from {len(sources)} experiment(s), figures: {figs}, "
        f"{len(result['warnings'])} warning(s)){logged}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
