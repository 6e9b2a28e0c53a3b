"""The report's data: runs grouped into cells (V, U, algorithm), the reference of each scenario,
and the curves of Fig. 3a. No drawing and no file writing here.

A cell holds one value per seed: the newest FINISHED run with execution metrics of that seed.
Runs may come from several experiments (analysis.runs.resolve_sources); cells join them, and a
warning names any cell whose runs differ in budget, episode count or scenario parameters, since
averaging those would mix different experiments.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Collection
from dataclasses import dataclass, field

import numpy as np

from analysis import stats
from analysis.runs import EE_KEY, RunRecord, metric_history
from uavlora_rllib.experiment.evaluation import BOUND_METRIC

PAPER_SCENARIO = (10, 2)  # Fig. 2 and Fig. 3a: V = 10 EDs, U = 2 UAVs
PAPER_FIXED_U = 2  # Fig. 3b
PAPER_FIXED_V = 60  # Fig. 3c
MIN_SEEDS = 3  # below this a cell's statistics are flagged as weak
KINDS = ("train", "baseline")
OPTIMAL, GREEDY = "optimal", "greedy"
REFERENCE_BASELINES = (OPTIMAL, GREEDY)  # the "share of reference" denominator, first present wins
BEST_FIXED = "best_fixed"  # the open-loop check: the best constant action
BOUND_KEY = f"eval/{BOUND_METRIC}"  # the references' upper bound on the per-slot optimum
RETURN_METRIC = "episode_return_mean"  # training return of the sampled (exploring) policy
SAMPLED_PARAM = "hparam."  # a sweep's sampled hyperparameter (run_schema.sampled_params)
# params whose values must agree inside a cell (n_eds / n_uavs are the cell's key already)
_IDENTITY_PARAMS = ("stop.env_steps", "eval.episodes")


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

    @property
    def scenario(self) -> tuple[int, int]:
        return (self.n_eds, self.n_uavs)

    def values(self, metric: str = EE_KEY, seeds: Collection[str] | None = None) -> np.ndarray:
        """The metric per run, of the runs whose seed is in `seeds` (all runs when None)."""
        runs = self.runs if seeds is None else [r for r in self.runs if str(r.seed) in seeds]
        return np.array([r.metrics.get(metric, math.nan) for r in runs], dtype=float)

    def summary(self, metric: str = EE_KEY, seeds: Collection[str] | None = None) -> stats.SeedSummary:
        v = self.values(metric, seeds)
        return stats.summarize(v[np.isfinite(v)])

    def mean_of(self, metric: str, seeds: Collection[str] | None = None) -> float:
        v = self.values(metric, seeds)
        v = v[np.isfinite(v)]
        return float(v.mean()) if v.size else math.nan

    @property
    def seeds(self) -> list[str]:
        return [str(r.seed) for r in self.runs]


@dataclass(frozen=True)
class Reference:
    """The denominator of "share of reference" in one scenario."""

    name: str  # "optimal" or "greedy"
    mean: float  # its seed-mean execution EE
    mode: str = "per_uav"  # the action mode its runs searched (param scenario.action_mode)
    bound: float = math.nan  # seed-mean upper bound on the per-slot optimum of the same slots

    @property
    def label(self) -> str:
        what = "per-slot optimum" if self.name == OPTIMAL else "greedy baseline"
        return f"{what} ({self.mode})"


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

    def kind_of(self, algorithm: str) -> str:
        return next((c.kind for c in self.cells.values() if c.algorithm == algorithm), "train")

    def reference(self, scenario: tuple[int, int], seeds: Collection[str] | None = None) -> Reference | None:
        """The optimum where the scenario has `optimal` baseline runs, else the greedy baseline,
        else None; in either action mode (its runs' scenario.action_mode labels it). With `seeds`,
        its mean is over those seeds only, so that a learner is divided by the reference of the
        same evaluation episodes (each seed has its own); None where it has none of them."""
        for name in REFERENCE_BASELINES:
            cell = self.cells.get((*scenario, name))
            if cell is not None and cell.kind == "baseline" and cell.runs:
                m = cell.summary(seeds=seeds).mean
                if math.isfinite(m) and m > 0:
                    modes = sorted({r.params.get("scenario.action_mode", "per_uav") for r in cell.runs})
                    return Reference(name, m, "/".join(modes), cell.mean_of(BOUND_KEY, seeds))
        return None

    def matched_seeds(self, cell: Cell, *baselines: str) -> list[str]:
        """The cell's seeds that the scenario's reference and each named baseline also ran, on the
        same task (`same_task`): the seeds on which a share or ratio compares the same evaluation
        episodes of one scenario (joined experiments may hold another rate model or reward at one V, U)."""
        ref = self.reference(cell.scenario)
        names = ([ref.name] if ref is not None else []) + list(baselines)
        own = {str(r.seed): r for r in cell.runs}
        have = [
            {str(r.seed) for r in c.runs if str(r.seed) in own and same_task(r, own[str(r.seed)])}
            for n in names
            if (c := self.cells.get((*cell.scenario, n))) is not None
        ]
        return [s for s in cell.seeds if all(s in h for h in have)]

    def normalised(self, cell: Cell) -> np.ndarray:
        """The cell's per-seed execution EE as a share of its scenario's reference over the same
        seeds (the denominator of every "share of reference" of the report); empty without one."""
        seeds = self.matched_seeds(cell)
        ref = self.reference(cell.scenario, seeds)
        if ref is None:
            return np.empty(0)
        v = cell.values(seeds=seeds)
        return v[np.isfinite(v)] / ref.mean

    def baseline_mean(self, scenario: tuple[int, int], name: str, seeds: Collection[str] | None = None) -> float:
        """Seed-mean execution EE of baseline `name` in the scenario (over `seeds` only, when
        given); NaN where it has no such runs."""
        cell = self.cells.get((*scenario, name))
        return (
            cell.summary(seeds=seeds).mean if cell is not None and cell.kind == "baseline" and cell.runs else math.nan
        )

    def find_train(self, name: str) -> str | None:
        """The learner called `name` (case-insensitive), or None."""
        return next((a for a in self.algorithms("train") if a.lower() == name.lower()), None)


def cell_name(r: RunRecord) -> str:
    """The cell a run joins: its algorithm, and for a trial of a sweep its sampled values
    (params ``hparam.<name>``, experiment/sweep.py): ``mappo[entropy_coeff=0.01,lr=0.000316]``,
    so that the seeds of one sampled configuration are averaged and different ones are not."""
    from uavlora_rllib.experiment.sweep import variant_label

    sampled = {k[len(SAMPLED_PARAM) :]: _as_number(v) for k, v in r.params.items() if k.startswith(SAMPLED_PARAM)}
    return f"{r.algorithm}[{variant_label(sampled)}]" if sampled and r.kind == "train" else str(r.algorithm)


def _as_number(text: str):
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text


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
        name = cell_name(r)
        if r.kind == "baseline" and name in train_names:
            name = f"{name} (baseline)"  # a baseline named like a learner must not join its cell
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
            seed = r.seed_key
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
            warnings.append(
                f"{where}: seed {r.seed} has several finished runs; the newest is used, left out: {r.label}"
            )
        mixed = _mixed_params(cell.runs)
        if mixed:
            warnings.append(
                f"{where}: its runs differ in {mixed}; they are averaged together (check the joined experiments)"
            )
    org = Organised(cells, warnings, records)
    for scenario in org.scenarios():  # a share divides by the reference: both must see the same episodes
        for key, groups in _params_across_cells(org.cells_of(scenario)):
            where = f"V={scenario[0]} U={scenario[1]}"
            if key == "eval.episodes":
                warnings.append(
                    f"{where}: its runs were evaluated on different numbers of episodes "
                    f"(eval.episodes {groups}), so its shares of the reference compare different episodes "
                    "(check the joined experiments)"
                )
            else:  # another action mode, episode length, channel or reward: other episodes, another task
                warnings.append(
                    f"{where}: its algorithms ran different scenarios ({key} {groups}), so its shares of the "
                    "reference compare different tasks (check the joined experiments)"
                )
    for key in sorted(cells):
        cell, ref = cells[key], org.reference(key[:2])
        unmatched = [s for s in cell.seeds if s not in org.matched_seeds(cell)] if ref is not None else []
        if unmatched:
            warnings.append(
                f"V={cell.n_eds} U={cell.n_uavs} {cell.algorithm} ({cell.kind}): seed(s) {', '.join(unmatched)} have no "
                f"{ref.name} run on their evaluation episodes (that seed, the same scenario.* settings); left out of "
                "every share of the reference"
            )
    return org


def same_task(a: RunRecord, b: RunRecord) -> bool:
    """Whether two runs of one (V, U) ran one task: equal scenario.* params where both logged them (a run
    logged before a param existed ran its default, which a later run may not have changed)."""
    keys = {k for k in a.params.keys() & b.params.keys() if k.startswith("scenario.")}
    return all(a.params[k] == b.params[k] for k in keys)


def _scenario_keys(runs: list[RunRecord]) -> set[str]:
    """The scenario.* params the runs logged, but V and U (which key the cells)."""
    return {
        k
        for r in runs
        for k in r.params
        if k.startswith("scenario.") and k not in ("scenario.n_eds", "scenario.n_uavs")
    }


def _params_across_cells(cells: list[Cell]) -> list[tuple[str, str]]:
    """(param, "value: algorithms; ...") for eval.episodes and every scenario.* param (but V and U)
    whose value differs between the algorithms of one scenario."""
    keys = {"eval.episodes"} | _scenario_keys([r for cell in cells for r in cell.runs])
    found = []
    for key in sorted(keys, key=lambda k: (k != "eval.episodes", k)):
        by_value: dict[str, set[str]] = defaultdict(set)
        for cell in cells:
            for r in cell.runs:
                by_value[r.params.get(key, "<unset>")].add(cell.algorithm)
        if len(by_value) > 1:
            found.append((key, "; ".join(f"{v}: {', '.join(sorted(names))}" for v, names in sorted(by_value.items()))))
    return found


def _mixed_params(runs: list[RunRecord]) -> str:
    """'param (values), ...' for identity params (budget, episodes, scenario.*) that differ."""
    keys = set(_IDENTITY_PARAMS) | _scenario_keys(runs)
    parts = []
    for k in sorted(keys):
        vals = sorted({r.params.get(k, "<unset>") for r in runs})
        if len(vals) > 1:
            parts.append(f"{k} ({' / '.join(vals)})")
    return ", ".join(parts)


def pick_fixed(counter: Counter, preferred: int) -> int | None:
    """The most common value (the paper's where it ties for most common)."""
    if not counter:
        return None
    top = max(counter.values())
    best = sorted(k for k, v in counter.items() if v == top)
    return preferred if preferred in best else best[0]


# ---------------------------------------------------------------- curves (Fig. 3a)
@dataclass
class Curve:
    """One algorithm's curve in one scenario: mean over seeds on a common env-step grid, with a
    95% percentile-bootstrap band over seeds (lo = hi = mean for one seed)."""

    steps: np.ndarray
    mean: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    seeds: tuple[str, ...]  # the runs' seeds, one series each

    @property
    def n_seeds(self) -> int:
        return len(self.seeds)


EVAL_CURVE = EE_KEY  # the greedy policy's execution EE per slot, logged during training
CURVE_METRICS = (EVAL_CURVE, RETURN_METRIC)


def curves(
    history, org: Organised, metric: str, smooth: float, points: int, min_points: int = 1, matched: bool = False
):
    """{scenario: {algorithm: Curve}} of `metric`'s history (x = env steps) over the train runs,
    and notes. `history(record, key)` -> (steps, values). One run per seed: the tables' where they have
    the seed (the newest FINISHED one with execution metrics), else the newest; FINISHED runs only, unless
    an algorithm has none (then all its runs). Runs with fewer than `min_points` logged points are
    left out (the execution curve needs the periodic evaluation: one point is the final one).
    With `matched`, a scenario with a reference keeps only the seeds the reference also ran, so a
    curve divided by the reference over its seeds compares the same episodes (Organised.normalised)."""
    notes: list[str] = []
    out: dict[tuple[int, int], dict[str, Curve]] = {}
    groups: dict[tuple[int, int, str], list[RunRecord]] = defaultdict(list)
    for r in org.records:
        if r.kind == "train" and r.algorithm and r.scenario_key is not None:
            groups[(r.n_eds, r.n_uavs, cell_name(r))].append(r)
    for (v, u, alg), runs in sorted(groups.items()):
        finished = [r for r in runs if r.status == "FINISHED"]
        # one run per seed: the newest (runs are in start order), the tables' run where the cell has the seed
        by_seed = {r.seed_key: r for r in finished or runs}
        cell = org.cells.get((v, u, alg))
        by_seed.update({r.seed_key: r for r in (cell.runs if cell else [])})
        use = list(by_seed.values())
        if not finished:
            notes.append(f"V={v} U={u} {alg}: no FINISHED run; its {metric} curve uses unfinished runs")
        ref = org.reference((v, u)) if matched else None
        if ref is not None:
            # the seeds every share of the reference uses (the same seed and task: Organised.matched_seeds)
            ran = set(org.matched_seeds(cell)) if cell is not None else set(org.cells[(v, u, ref.name)].seeds)
            if dropped := sorted({str(r.seed) for r in use} - ran):
                notes.append(
                    f"V={v} U={u} {alg}: seed(s) {', '.join(dropped)} left out of its {metric} curve: "
                    f"the {ref.name} reference has no run of them on the same task"
                )
            use = [r for r in use if str(r.seed) in ran]
        series, seeds = [], []
        for r in use:
            steps, vals = history(r, metric)
            if len(steps) >= min_points:
                series.append((np.asarray(steps), stats.ema(vals, smooth)))
                seeds.append(str(r.seed))
        if not series:
            continue
        grid = stats.common_grid([(s[0], s[-1]) for s, _ in series], points)
        if grid.size == 0:
            notes.append(f"V={v} U={u} {alg}: the seeds' env-step ranges of {metric} do not overlap; no curve")
            continue
        y = stats.interpolate(series, grid)
        mean, lo, hi = stats.bootstrap_ci95(y)
        out.setdefault((v, u), {})[alg] = Curve(grid, mean, lo, hi, tuple(seeds))
    return out, notes


def mlflow_history(sources):
    """history(record, key) reading each record's own tracking store, each (run, metric) once: the
    learning table, the early-stop notes and Fig. 3a all read the execution curve (one request
    each to a remote server otherwise)."""
    cache: dict[tuple[int, str, str], tuple[list[float], list[float]]] = {}

    def history(record: RunRecord, key: str):
        k = (record.source, record.run_id, key)
        if k not in cache:
            cache[k] = metric_history(sources[record.source].client, record.run_id, key)
        return cache[k]

    return history


def main_scenario(available: dict) -> tuple[tuple[int, int] | None, str | None]:
    """The paper's scenario if it has curves, else the one with the most seeds; and a note."""
    if not available:
        return None, None
    if PAPER_SCENARIO in available:
        return PAPER_SCENARIO, None
    main = max(available, key=lambda s: (sum(c.n_seeds for c in available[s].values()), -s[0], -s[1]))
    return main, f"the paper's scenario V=10, U=2 has no curves; drawn for V={main[0]}, U={main[1]}"
