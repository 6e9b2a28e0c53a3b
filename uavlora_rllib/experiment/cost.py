"""What a grid costs, estimated from the calibration (experiment.calibration): `tune --dry-run`'s
per-trial wall hours, the grid's CPU-hours and its wall-clock time.

Per trial: wall = build + budget / rate + periodic evaluations x one evaluation + the final
evaluation, all as measured for its cell; CPU-hours = wall x the CPUs the trial reserves (its
learner process and env runners). Baseline runs add their own time on one CPU each. The
wall-clock time packs the trials, in the grid's order, onto as many slots as the CPUs (and
max_concurrent_trials) allow. A cell without a record of its own (this code, these
settings) is estimated from its nearest stand-in (calibration.Store.nearest: the same cell
measured with older code, or a record that differs in speed-neutral hyperparameters or scenario
constants only), marked approximate with what differs named; a cell with neither is listed, never
guessed.
"""

from __future__ import annotations

import heapq
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import calibration
from uavlora_rllib.experiment.grid import eval_interval
from uavlora_rllib.experiment.sweep import grid_search_size


@dataclass
class Priced:
    """A cell of the grid and the calibration record that prices it, with how that record differs
    (calibration.Store.nearest); match None: not calibrated."""

    cell: calibration.Cell
    match: calibration.Match | None

    @property
    def record(self) -> dict[str, Any] | None:
        return None if self.match is None else self.match.record

    @property
    def approximate(self) -> bool:
        """Priced by a stand-in: other hyperparameters or scenario constants, or other code."""
        return self.match is not None and (bool(self.match.differs) or self.match.other_code)


@dataclass
class TrialCost(Priced):
    """One row of the trial table: `trials` trials (more than 1 in a sweep) of one cell."""

    index: int  # 1-based, as in the trial table
    name: str
    trials: int
    wall_s: float = math.nan  # one trial


@dataclass
class BaselineCost(Priced):
    """The `runs` baseline runs of one cell (1 CPU each)."""

    runs: int


@dataclass
class GridCost:
    rows: list[TrialCost]
    cpus_per_trial: float
    baselines: list[BaselineCost]
    machine: dict[str, Any]
    version: str
    path: str
    notes: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        return all(p.record is not None for p in [*self.rows, *self.baselines])

    @property
    def approximate(self) -> list[TrialCost]:
        """The rows estimated from a stand-in: other hyperparameters or other code."""
        return [r for r in self.rows if r.approximate]

    def trial_cpu_s(self) -> float:
        return sum(r.wall_s * r.trials * self.cpus_per_trial for r in self.rows if r.record is not None)

    def baseline_cpu_s(self) -> float:
        from uavlora_rllib.experiment.baseline_tasks import BASELINE_CPUS

        return sum(b.record["seconds"] * b.runs * BASELINE_CPUS for b in self.baselines if b.record is not None)

    def records(self) -> list[dict[str, Any]]:
        """The records the estimate uses, trials' then baselines'."""
        return [p.record for p in [*self.rows, *self.baselines] if p.record is not None]


def periodic_evaluations(budget: int, interval: int, steps_per_iteration: float) -> int:
    """Greedy evaluations during one trial (periodic_eval.PeriodicEvalCallback): the first
    iteration's, then one at the first iteration past each multiple of `interval`, over the
    ceil(budget / steps_per_iteration) iterations of the trial; 0 when `interval` is 0."""
    if interval < 1:
        return 0
    steps = max(float(steps_per_iteration), 1.0)
    n_iter = math.ceil(budget / steps)
    return min(n_iter, 1 + math.floor(n_iter * steps / interval))


def trial_seconds(record: Mapping[str, Any], budget: int, interval: int, episodes: int) -> float:
    """One trial's wall seconds from its cell's record (evaluations scaled to `episodes`). Training runs
    whole iterations: the one that crosses the budget ends the trial, so the steps sampled are the
    budget rounded up to an iteration's steps."""
    per_episode = episodes / max(int(record["eval_episodes"]), 1)
    per_iteration = record["env_steps_per_iteration"]
    n_eval = periodic_evaluations(budget, interval, per_iteration)
    return (
        record["build_s"]
        + math.ceil(budget / per_iteration) * per_iteration / record["env_steps_per_s"]
        + (n_eval * record["periodic_eval_s"] + record["final_eval_s"]) * per_episode
    )


def trials_per_spec(grid, specs) -> list[int]:
    """How many Tune trials each grid point runs (a sweep samples several; a search algorithm
    runs num_samples of the first)."""
    if grid.search_alg is not None:
        return [grid.num_samples if i == 0 else 0 for i in range(len(specs))]
    return [grid.num_samples * grid_search_size(s.spaces) for s in specs]


def estimate(grid, specs, store: calibration.Store, machine: Mapping[str, Any], version: str) -> GridCost:
    """The grid's cost from `store`'s records, this code's (`version`) and this machine's first."""
    budget, interval, episodes = grid.stop.env_steps, eval_interval(grid), grid.evaluation.episodes
    rows = []
    for i, (spec, n) in enumerate(zip(specs, trials_per_spec(grid, specs)), 1):
        if n == 0:
            continue
        cell = calibration.train_cell(spec, grid.resources)
        match = store.nearest(cell, machine, version, speed_neutral(spec))  # its own record first
        row = TrialCost(cell, match, i, spec.name, n)
        if match is not None:
            row.wall_s = trial_seconds(match.record, budget, interval, episodes)
        rows.append(row)
    baselines = [
        BaselineCost(cell, store.nearest(cell, machine, version), len(members))
        for cell, members in calibration.grid_baseline_cells(grid).values()
    ]
    cost = GridCost(rows, calibration.trial_cpus(grid.resources), baselines, dict(machine), version, store.path)
    used = cost.records()
    bad = store.unusable()
    if bad:
        cost.notes.append(
            f"note: {bad} record(s) of the calibration file cannot be read (damaged or edited) and are ignored"
        )
    others = {calibration.describe_machine(r["machine"]) for r in used if r["machine"] != dict(machine)}
    for other in sorted(others):
        cost.notes.append(
            f"note: measured on another machine ({other}); this one is {calibration.describe_machine(machine)}"
        )
    scaled = sorted({r.record["eval_episodes"] for r in rows if r.record and r.record["eval_episodes"] != episodes})
    if scaled:
        cost.notes.append(f"note: evaluation times scaled by episodes from {scaled} to the grid's {episodes}")
    early = [r for r in rows if r.record and not r.record.get("learning_started", True)]
    if early:
        cost.notes.append(
            f"note: {len(early)} trial(s) calibrated before their learner updated; their rate is too high"
        )
    cost.notes += _approximate_notes(cost)
    if grid.scheduler is not None:
        cost.notes.append(_scheduler_note(grid.scheduler.type))
    sampled = sorted({name for s in specs for name in s.spaces if name not in speed_neutral(s)})
    if any(s.spaces for s in specs):
        cost.notes.append(
            "note: sampled hyperparameters are calibrated at their defaults"
            + (
                f"; {', '.join(sampled)} change(s) how long a step takes, so trials at other values cost more or less"
                if sampled
                else ""
            )
        )
    if any(b.get("GPU", 0) for b in grid.resources.bundles()):
        cost.notes.append("note: the wall-clock counts CPUs only; trials that reserve GPUs also wait for free GPUs")
    return cost


def speed_neutral(spec) -> frozenset[str]:
    """The hyperparameters of `spec`'s algorithm that change what is learned but not how long a step
    takes (its HParams class's SPEED_NEUTRAL; none declared: none), across which a calibration record
    may stand in for another (calibration.Store.nearest)."""
    return frozenset(getattr(type(spec.hparams), "SPEED_NEUTRAL", ()))


def _scheduler_note(kind: str) -> str:
    """What a Tune scheduler does to the estimate of trials that all run their whole budget."""
    if kind == "pbt":  # it stops no trial; each perturbation checkpoints, restores and rebuilds some
        return "note: the pbt scheduler pauses and rebuilds trials at each perturbation: a lower bound"
    return f"note: the {kind} scheduler stops some trials early: an upper bound"


def _show(value: Any) -> str:
    return value if value == calibration.UNSET else json.dumps(value)


def _stand_in(differs: Mapping[str, tuple[Any, Any]], other_code: bool, code: str = "") -> str:
    """What a stand-in record was measured with, for a note: other code (`code` says which), other
    hyperparameters and other scenario constants, each field with the record's value and the grid's;
    "" for the cell's own."""
    what = []
    if other_code:
        what.append(f"other code ({code})" if code else "other code")
    for kind, fields in (
        ("other hyperparameters", {k: v for k, v in differs.items() if not k.startswith("scenario.")}),
        ("other scenario constants", {k: v for k, v in differs.items() if k.startswith("scenario.")}),
    ):
        if fields:
            what.append(kind + ", " + ", ".join(f"{k} {_show(a)} (now {_show(b)})" for k, (a, b) in fields.items()))
    return "; ".join(what)


def _approximate_notes(cost: GridCost) -> list[str]:
    """One note per group of trials estimated from a stand-in record, naming what differs; one per
    group of baselines."""
    groups: dict[tuple[str, str], list[int]] = {}
    for r in cost.approximate:
        assert r.match is not None
        rec = r.match.record
        code = f"{rec['version']}, {str(rec.get('measured_at', ''))[:10]}; this is {cost.version}"
        why = _stand_in(r.match.differs, r.match.other_code, code)
        algo = str(r.cell.content["algorithm"]) if r.match.differs else ""  # other code alone: one note for all
        groups.setdefault((algo, why), []).append(r.index)
    notes = [
        f"note: approximate for trials {_ranges(ix)}{f' ({algo})' if algo else ''}: measured with {why}"
        for (algo, why), ix in groups.items()
    ]
    kinds: dict[str, list[str]] = {}
    for b in cost.baselines:
        if b.match is not None and b.approximate:
            why = _stand_in(b.match.differs, b.match.other_code)
            kinds.setdefault(why, []).append(str(b.cell.content["baseline"]))
    notes += [
        f"note: approximate baselines ({', '.join(sorted(set(b)))}): measured with {why}" for why, b in kinds.items()
    ]
    return notes


def wall_clock_s(cost: GridCost, cpus: float, max_concurrent: int | None) -> tuple[float, int]:
    """(wall seconds of the whole grid, most trials at once) on `cpus` CPUs; (nan, 0) if a trial
    does not fit. Trials start in order on the first free slot; baselines share the CPUs."""
    slots = math.floor(cpus / cost.cpus_per_trial + 1e-9)
    if max_concurrent is not None:
        slots = min(slots, max_concurrent)
    if slots < 1:
        return math.nan, 0
    free = [0.0] * slots
    for row in cost.rows:
        for _ in range(row.trials):
            heapq.heappush(free, heapq.heappop(free) + row.wall_s)
    busy = (cost.trial_cpu_s() + cost.baseline_cpu_s()) / cpus
    longest_baseline = max((b.record["seconds"] for b in cost.baselines if b.record), default=0.0)
    return max(max(free), busy, longest_baseline), min(slots, sum(r.trials for r in cost.rows))


def _ranges(indices: list[int]) -> str:
    """[1, 2, 3, 7] -> "1-3, 7"."""
    runs: list[list[int]] = []
    for i in sorted(indices):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(str(lo) if lo == hi else f"{lo}-{hi}" for lo, hi in runs)


def _measured(cost: GridCost) -> str:
    """'; measured FIRST to LAST' (UTC days) of the records the estimate uses, or ''."""
    used = cost.records()
    days = sorted(str(r.get("measured_at", ""))[:10] for r in used if r.get("measured_at"))
    if not days:
        return ""
    return f"; measured {days[0]}" + (f" to {days[-1]}" if days[-1] != days[0] else "")


def _minutes(hours: float) -> str:
    """' (N min)' after a figure in hours that would print as 0.0x, else ''."""
    return f" ({hours * 60:.1f} min)" if hours < 0.1 else ""


def report_lines(cost: GridCost, grid, grid_file: str, cpus: float, cpus_given: bool) -> list[str]:
    """The dry run's cost section."""
    lines = [f"cost estimate (calibration {cost.path}, code {cost.version}{_measured(cost)}):"]
    if not cost.records():
        n_cells = len({r.cell.key for r in cost.rows})
        return lines + [
            f"  not calibrated: none of the grid's {n_cells} trial cell(s) and {len(cost.baselines)} "
            "baseline cell(s) is in the calibration",
            f"calibrate with: python -m uavlora_rllib.tune {grid_file} --calibrate",
        ]
    lines += cost.notes + _trial_lines(cost) + _baseline_lines(cost)
    trial_h, base_h = cost.trial_cpu_s() / 3600, cost.baseline_cpu_s() / 3600
    if not cost.complete:
        return (
            lines
            + _missing_lines(cost, grid_file)
            + [
                f"partial: {trial_h + base_h:.2f} CPU-hours for the calibrated part only "
                f"({sum(r.trials for r in cost.rows if r.record)} of {sum(r.trials for r in cost.rows)} trials; "
                "no total until every cell is calibrated)"
            ]
        )
    lines.append(
        f"grid: {trial_h + base_h:.2f} CPU-hours{_minutes(trial_h + base_h)} = {sum(r.trials for r in cost.rows)} "
        f"trials {trial_h:.2f} "
        f"(wall x {cost.cpus_per_trial:g} CPUs each) + baselines {base_h:.2f}"
    )
    if cost.approximate:
        n = sum(r.trials for r in cost.approximate)
        lines.append(
            f"approximate: {n} trial(s) (marked ~) from records measured with other code or other speed-neutral "
            "settings (notes above); "
            f"measure them exactly with: python -m uavlora_rllib.tune {grid_file} --calibrate"
        )
    where = f"{cpus:g} CPUs (--num-cpus)" if cpus_given else f"this machine's {cpus:g} CPUs"
    wall, slots = wall_clock_s(cost, cpus, grid.max_concurrent_trials)
    if slots == 0:
        lines.append(
            f"wall-clock: a trial needs {cost.cpus_per_trial:g} CPUs, more than {where}; "
            "give --num-cpus N to size another machine"
        )
    else:
        capped = grid.max_concurrent_trials is not None and slots == grid.max_concurrent_trials
        lines.append(
            f"wall-clock: about {wall / 3600:.2f} h{_minutes(wall / 3600)} on {where} ({slots} trial(s) at once"
            f"{', max_concurrent_trials' if capped else ''}; the baselines beside them)"
        )
    return lines


def _trial_lines(cost: GridCost) -> list[str]:
    """One row per trial (per grid point in a sweep, with its number of trials)."""
    counts = any(r.trials > 1 for r in cost.rows)
    lines = [
        f"{'#':>4}  {'trial':<24} {'env steps/s':>12} {'wall h':>8} {'CPUs':>5} {'CPU-h':>8}"
        + ("  trials" if counts else "")
    ]
    for r in cost.rows:
        count = f"  x{r.trials}" if counts else ""
        if r.record is None:
            lines.append(f"{r.index:>4}  {r.name:<24} {'not calibrated':>12}{count}")
        else:
            lines.append(
                f"{r.index:>4}  {r.name:<24} {r.record['env_steps_per_s']:>12,.0f} {r.wall_s / 3600:>8.2f} "
                f"{cost.cpus_per_trial:>5g} {r.wall_s * cost.cpus_per_trial / 3600:>8.2f}{count}"
                + ("  ~" if r.approximate else "")
            )
    return lines


def _missing_lines(cost: GridCost, grid_file: str, most: int = 12) -> list[str]:
    """The cells without a measurement, and the command that measures them."""
    by_cell: dict[str, tuple[calibration.Cell, list[int]]] = {}
    for r in cost.rows:
        if r.record is None:
            by_cell.setdefault(r.cell.key, (r.cell, []))[1].append(r.index)
    missing_b = [(b.cell, b.runs) for b in cost.baselines if b.record is None]
    cells = [f"  {cell.label} (trials {_ranges(ix)})" for cell, ix in by_cell.values()] + [
        f"  {cell.label} ({n} baseline runs)" for cell, n in missing_b
    ]
    more = [f"  ... and {len(cells) - most} more"] if len(cells) > most else []
    return (
        [f"not calibrated: {len(by_cell)} trial cell(s), {len(missing_b)} baseline cell(s):"]
        + cells[:most]
        + more
        + [f"calibrate with: python -m uavlora_rllib.tune {grid_file} --calibrate"]
    )


def _baseline_lines(cost: GridCost) -> list[str]:
    """Baseline CPU-hours per kind (seconds per run are measured per cell)."""
    kinds: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for b in cost.baselines:
        if b.record is not None:
            kinds.setdefault(str(b.cell.content["baseline"]), []).append((b.runs, b.record))
    if not kinds:
        return []
    lines = ["baselines (1 CPU per run):"]
    for kind, runs in kinds.items():
        hours = sum(n * rec["seconds"] for n, rec in runs) / 3600
        scaled = [rec for _, rec in runs if rec["timed_episodes"] < rec["episodes"]]
        note = (
            f"; timed on {min(r['timed_episodes'] for r in scaled)} to {max(r['timed_episodes'] for r in scaled)} "
            f"of {scaled[0]['episodes']} episodes and scaled by episodes"
            if scaled
            else ""
        )
        lines.append(f"  {kind:<12} {sum(n for n, _ in runs):>4} runs {hours:>8.3f} CPU-h{note}")
    return lines


def dry_run_report(grid, specs, grid_file: str, num_cpus: int | None, path: str | None = None) -> str:
    """The cost section of `tune --dry-run` (never fails: an unreadable calibration is a note)."""
    path = path or calibration.default_path()
    try:
        store = calibration.Store.load(path)
    except ConfigError as exc:
        store = calibration.Store(path)
        prefix = f"note: {exc}\n"
    else:
        prefix = ""
    cost = estimate(grid, specs, store, calibration.this_machine(), calibration.package_version())
    cpus = float(num_cpus or os.cpu_count() or 1)
    return prefix + "\n".join(report_lines(cost, grid, grid_file, cpus, num_cpus is not None))
