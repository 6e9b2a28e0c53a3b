"""The grid calibration: what each distinct part of a grid costs on this machine, measured once
(`tune GRID.yaml --calibrate`) and read by `tune --dry-run`'s cost estimate (experiment.cost).

A *cell* is what decides the cost, without the seed: for a trial the algorithm, its resolved
hyperparameters, the whole scenario and the resources that change speed (SPEED_RESOURCES); for a
baseline run the baseline, the scenario and the number of evaluation episodes. Its key is a hash
of that content, so a grid that differs in anything that matters gets new cells, and two grids
that share a cell share its measurement. A cell with no record of its own falls back, for the
estimate only and marked approximate, to the same cell measured with other code or to a record
that differs from it in speed-neutral hyperparameters alone (`Store.nearest`), so a code change or
a new hyperparameter does not throw the earlier measurements away.

The file lives in the user's cache directory (`default_path`; $UAVLORA_CALIBRATION names
another), not in the grid's storage: the numbers describe a machine, not an experiment, one file
serves every grid and every storage (including cloud URIs no plain file can be written to), and a
dry run needs no storage. Each record names the machine (CPU model and count) and the code it was
measured with (`package_version`: the package's sources and the torch and Ray versions); the
estimate prefers this machine's records and this code's, and says when it uses another machine's
or older code's. Every write is atomic (a temporary file renamed over the old one, under a
lock), one record at a time, so a killed calibration keeps what it measured and a rerun
measures only the rest.

Nothing here imports Ray or torch at module level: a dry run reads the file without them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import functools
import hashlib
import json
import math
import os
import stat
import sys
import tempfile
import time
from collections.abc import Collection, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, TextIO

from uavlora_rllib.config_errors import ConfigError

FORMAT = 1
PATH_ENV = "UAVLORA_CALIBRATION"  # another calibration file (a shared one, or a test's)
# Resources fields that change how fast a trial trains (the CPUs reserved do not: Ray does not pin)
SPEED_RESOURCES = (
    "num_env_runners",
    "num_envs_per_env_runner",
    "torch_threads",
    "num_learners",
    "num_gpus_per_learner",
    "learner_precision",
)
DEFAULT_ITERATIONS = 2  # timed training iterations per cell (after the warm-up)
# A baseline whose (unloaded, single-core) cost model, `baselines.policies.evaluation_seconds`,
# exceeds this many seconds is timed on fewer episodes and scaled by episodes (except best_fixed,
# whose one-off selection does not scale with episodes)
BASELINE_MEASURE_S = 20.0
# the installed packages whose version enters the code digest: the learner, Ray and the simulator's numerics
SPEED_DISTRIBUTIONS = ("torch", "ray", "numpy", "scipy", "gymnasium")
ONE_OFF_BASELINES = ("best_fixed",)


# --------------------------------------------------------------------------- cells
@dataclass(frozen=True)
class Cell:
    """What one measurement stands for: `kind` "train" or "baseline", and its content."""

    kind: str
    content: Mapping[str, Any]
    label: str  # for people: "mappo V=60 U=2 per_uav T=150"

    @property
    def key(self) -> str:
        return cell_key(self.kind, self.content)


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def cell_key(kind: str, content: Mapping[str, Any]) -> str:
    """A stable hash of a cell's content (sorted-key JSON, so dict order does not matter)."""
    return hashlib.sha256(_canonical({"kind": kind, **content}).encode()).hexdigest()[:16]


def _scenario_label(scenario: Mapping[str, Any]) -> str:
    return f"V={scenario['n_eds']} U={scenario['n_uavs']} {scenario['action_mode']} T={scenario['episode_len']}"


def train_cell(spec, resources) -> Cell:
    """The cell of a trial (grid.TrialSpec) under `resources` (registry.Resources)."""
    from uavlora_rllib.experiment.grid import hparams_dict

    scenario = spec.scenario.to_dict()
    content = {
        "algorithm": spec.algorithm,
        "hparams": hparams_dict(spec.hparams),
        "scenario": scenario,
        "resources": {k: getattr(resources, k) for k in SPEED_RESOURCES},
    }
    r = content["resources"]
    label = (
        f"{spec.algorithm} {_scenario_label(scenario)} runners={r['num_env_runners']} "
        f"envs/runner={r['num_envs_per_env_runner']}"
    )
    return Cell("train", json.loads(_canonical(content)), label)


def baseline_cell(spec, episodes: int) -> Cell:
    """The cell of a baseline run (grid.BaselineSpec) of `episodes` evaluation episodes."""
    scenario = spec.scenario.to_dict()
    content = {"baseline": spec.baseline, "scenario": scenario, "episodes": int(episodes)}
    return Cell(
        "baseline", json.loads(_canonical(content)), f"{spec.baseline} {_scenario_label(scenario)} {episodes} episodes"
    )


def grid_train_cells(grid, specs) -> dict[str, tuple[Cell, list[int]]]:
    """key -> (cell, indices into `specs` of the trials in it), in the order of `specs`."""
    out: dict[str, tuple[Cell, list[int]]] = {}
    for i, spec in enumerate(specs):
        cell = train_cell(spec, grid.resources)
        out.setdefault(cell.key, (cell, []))[1].append(i)
    return out


def grid_baseline_cells(grid) -> dict[str, tuple[Cell, list]]:
    """key -> (cell, the grid's BaselineSpecs in it), in the grid's order."""
    from uavlora_rllib.experiment.grid import baseline_runs

    out: dict[str, tuple[Cell, list]] = {}
    for spec in baseline_runs(grid):
        cell = baseline_cell(spec, grid.evaluation.episodes)
        out.setdefault(cell.key, (cell, []))[1].append(spec)
    return out


# --------------------------------------------------------------------------- machine
def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux), else what `platform` knows."""
    import platform

    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key, sep, value = line.partition(":")
                if sep and key.strip() in ("model name", "Hardware", "cpu model"):
                    return " ".join(value.split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def this_machine() -> dict[str, Any]:
    return {"cpu_model": cpu_model(), "cpus": os.cpu_count() or 1}


def describe_machine(machine: Mapping[str, Any]) -> str:
    return f"{machine.get('cpu_model', 'unknown CPU')}, {machine.get('cpus', '?')} CPUs"


def package_version() -> str:
    """The code a measurement describes: the package's version and `code_digest`. `__version__` alone
    stays the same while the learners get several times faster, and an old record would then pass
    for an exact one."""
    import uavlora_rllib

    return f"{uavlora_rllib.__version__}+{code_digest()}"


@functools.cache
def code_digest() -> str:
    """12 hex digits of a SHA-256 over the package's Python sources (relative path and bytes, in
    sorted order), the Python version and the installed versions of SPEED_DISTRIBUTIONS, which set a
    trial's speed as much; read from their metadata, so none is imported."""
    from importlib import metadata

    import uavlora_rllib

    root = os.path.dirname(os.path.abspath(uavlora_rllib.__file__))
    digest = hashlib.sha256()
    for directory, subdirs, files in os.walk(root):
        subdirs[:] = sorted(d for d in subdirs if d != "__pycache__")  # a fixed walk order
        for name in sorted(f for f in files if f.endswith(".py") and not f.startswith(".")):
            path = os.path.join(directory, name)
            if not os.path.isfile(path):  # an editor's lock file, a dangling link: not code
                continue
            digest.update(os.path.relpath(path, root).encode() + b"\0")
            with open(path, "rb") as fh:
                digest.update(fh.read() + b"\0")
    for dist in SPEED_DISTRIBUTIONS:
        try:
            installed = metadata.version(dist)
        except metadata.PackageNotFoundError:
            installed = "none"
        digest.update(f"{dist}={installed}\0".encode())
    digest.update(f"python={sys.version_info[0]}.{sys.version_info[1]}".encode())
    return digest.hexdigest()[:12]


def default_path() -> str:
    """$UAVLORA_CALIBRATION if set, else $XDG_CACHE_HOME/uavlora_rllib/calibration.json
    (XDG_CACHE_HOME unset or relative: ~/.cache)."""
    if os.environ.get(PATH_ENV):
        return os.path.abspath(os.path.expanduser(os.environ[PATH_ENV]))
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "uavlora_rllib", "calibration.json")


# --------------------------------------------------------------------------- the file
# the fields the estimate reads, each a finite number: True where it must be above 0 (a rate, a count)
_READ_FIELDS = {
    "train": {
        "env_steps_per_s": True,
        "env_steps_per_iteration": True,
        "eval_episodes": True,
        "seconds_per_iteration": False,
        "build_s": False,
        "periodic_eval_s": False,
        "final_eval_s": False,
    },
    "baseline": {"seconds": False, "timed_episodes": True, "episodes": True},
}


def usable(record: Any) -> bool:
    """Whether a record can price a cell: its identity fields, and the numbers the estimate reads
    (`_READ_FIELDS`) finite, rates and counts above 0. A damaged or hand-edited file may hold others;
    they are skipped (and counted: `Store.unusable`), never a traceback."""
    if not isinstance(record, dict) or record.get("kind") not in _READ_FIELDS:
        return False
    if not all(isinstance(record.get(k), t) for k, t in (("cell_key", str), ("version", str), ("cell", dict))):
        return False
    if not isinstance(record.get("machine"), dict):
        return False
    if not all(isinstance(record["cell"].get(k, {}), dict) for k in ("hparams", "scenario")):
        return False
    for name, positive in _READ_FIELDS[record["kind"]].items():
        value = record.get(name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return False
        if value < 0 or (positive and value == 0):
            return False
    return True


@dataclass(frozen=True)
class Match:
    """The record that prices a cell, and how it differs: hyperparameters (name -> (the record's
    value, the grid's), `hparam_differences`) and whether it was measured with other code."""

    record: dict[str, Any]
    differs: dict[str, tuple[Any, Any]]
    other_code: bool


def _record_id(key: str, machine: Mapping[str, Any], version: str) -> str:
    return f"{key}/{cell_key('machine', machine)}/{version}"


@dataclass
class Store:
    """The calibration file's records: record id (cell key / machine hash / version) -> record."""

    path: str
    records: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    @classmethod
    def load(cls, path: str) -> Store:
        """The file's records (none if it does not exist); ConfigError if it cannot be read."""
        try:
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
        except FileNotFoundError:
            return cls(path)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"calibration file {path}: cannot read it ({exc}); delete it to start over") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("records"), dict):
            raise ConfigError(f"calibration file {path}: not a calibration of format {FORMAT}; delete it to start over")
        return cls(path, dict(data["records"]))

    def unusable(self) -> int:
        """How many of the file's records `usable` rejects."""
        return sum(not usable(r) for r in self.records.values())

    def find(self, key: str, machine: Mapping[str, Any], version: str) -> dict[str, Any] | None:
        """The record of cell `key` for `version`: this machine's, else the newest of another
        machine (its "machine" field tells which)."""
        found = [r for r in self.records.values() if usable(r) and r["cell_key"] == key and r["version"] == version]
        return _own_then_newest(found, machine) if found else None

    def nearest(
        self, cell: Cell, machine: Mapping[str, Any], version: str, neutral: Collection[str] = ()
    ) -> Match | None:
        """The record that prices `cell`: its own (the same content measured with this code), else the
        nearest stand-in, marked approximate: the same content measured with other code, or a record
        that differs from it only in speed-neutral settings, which change what is learned or computed
        but not how long a step takes: the hyperparameters named in `neutral` (a trial's HParams
        SPEED_NEUTRAL) and, for a trial cell, the scenario's (ScenarioConfig.SPEED_NEUTRAL). This code's
        records come first, then the fewest differing fields, this machine's, the newest. None if
        there is none. A code change or a new neutral setting keeps the earlier measurements usable,
        named as approximate, until `--calibrate` measures the cell."""
        from uavlora_rllib.sim.scenario import ScenarioConfig

        # a baseline's cost follows the scenario's every number (its searches loop until nothing improves)
        scenario_neutral = ScenarioConfig.SPEED_NEUTRAL if cell.kind == "train" else frozenset()
        rest, wanted = _speed_parts(cell.content, scenario_neutral)
        found = []
        for r in self.records.values():
            if not usable(r) or r["kind"] != cell.kind:
                continue
            other_rest, scenario = _speed_parts(r["cell"], scenario_neutral)
            if other_rest != rest:
                continue
            diff = hparam_differences(r["cell"].get("hparams", {}), cell.content.get("hparams", {}))
            if any(name not in neutral for name in diff):
                continue
            diff.update({f"scenario.{k}": v for k, v in hparam_differences(scenario, wanted).items()})
            found.append((r["version"] != version, len(diff), r, diff))
        if not found:
            return None
        best = min((other, n) for other, n, _, _ in found)
        group = [(r, diff) for other, n, r, diff in found if (other, n) == best]
        record = _own_then_newest([r for r, _ in group], machine)
        return Match(record, next(diff for r, diff in group if r is record), record["version"] != version)

    def has(self, key: str, machine: Mapping[str, Any], version: str) -> bool:
        """Whether cell `key` is measured on `machine` with this code (`version`)."""
        found = self.find(key, machine, version)
        return found is not None and found.get("machine") == dict(machine)

    def put(self, record: dict[str, Any]) -> None:
        """Add (or replace) one record: the file is re-read, merged and replaced atomically."""
        directory = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(directory, exist_ok=True)
        with _locked(self.path + ".lock"):
            current = Store.load(self.path).records
            current[_record_id(record["cell_key"], record["machine"], record["version"])] = record
            fd, tmp = tempfile.mkstemp(prefix=".calibration-", suffix=".tmp", dir=directory)
            try:
                # the file's own mode, or a new file's under the umask (mkstemp's 0600 would make a
                # shared $UAVLORA_CALIBRATION unreadable to the others after one write)
                os.fchmod(fd, _mode_of(self.path))
                with os.fdopen(fd, "w", encoding="utf-8") as fh:
                    json.dump({"format": FORMAT, "records": current}, fh, indent=1, sort_keys=True)
                    fh.flush()
                    os.fsync(fh.fileno())
                os.replace(tmp, self.path)
            except BaseException:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        self.records = current


def _mode_of(path: str) -> int:
    """The permission bits of `path`, or those a new file gets (0666 less the umask)."""
    try:
        return stat.S_IMODE(os.stat(path).st_mode)
    except OSError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def _own_then_newest(found: list[dict[str, Any]], machine: Mapping[str, Any]) -> dict[str, Any]:
    """This machine's newest record of `found` (not empty), else the newest of another machine's."""
    own = [r for r in found if r.get("machine") == dict(machine)]
    return max(own or found, key=lambda r: str(r.get("measured_at", "")))


UNSET = "unset"  # a hyperparameter one side of a comparison does not have (added or removed since)


def _speed_parts(content: Mapping[str, Any], scenario_neutral: Collection[str]) -> tuple[dict, dict]:
    """A cell's content without its hyperparameters and its scenario's speed-neutral fields (what must
    match for one record to stand in for another), and those scenario fields."""
    scenario = content.get("scenario")
    rest = {k: v for k, v in content.items() if k not in ("hparams", "scenario")}
    if not isinstance(scenario, Mapping):
        return {**rest, "scenario": scenario}, {}
    rest["scenario"] = {k: v for k, v in scenario.items() if k not in scenario_neutral}
    return rest, {k: v for k, v in scenario.items() if k in scenario_neutral}


def hparam_differences(recorded: Mapping[str, Any], wanted: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """name -> (the record's value, the grid's value) for every hyperparameter (or scenario field)
    that differs, UNSET where one side lacks it; sorted by name."""
    names = sorted(set(recorded) | set(wanted))
    return {
        n: (recorded.get(n, UNSET), wanted.get(n, UNSET))
        for n in names
        if n not in recorded or n not in wanted or recorded[n] != wanted[n]
    }


@contextlib.contextmanager
def _locked(path: str) -> Iterator[None]:
    """An exclusive advisory lock on `path`, held while one record is merged into the file."""
    import fcntl

    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


@contextlib.contextmanager
def _one_calibration(path: str) -> Iterator[None]:
    """Held for a whole `--calibrate` into `path`: a second one is refused, since two at once would
    time each other's load and record it as this machine's speed. Also the check, before anything
    is measured, that the file's directory can be written."""
    import fcntl

    directory = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(directory, exist_ok=True)
        with open(path + ".lock", "a"):  # what each write locks (Store.put) ...
            pass
        fd, probe = tempfile.mkstemp(prefix=".calibration-", suffix=".tmp", dir=directory)  # ... and creates
        os.close(fd)
        os.unlink(probe)
        fh = open(path + ".calibrating", "a")  # noqa: SIM115  (held until the end of the block)
    except OSError as exc:
        raise ConfigError(
            f"calibration file {path}: cannot write there ({exc.strerror}); set ${PATH_ENV} to a writable path"
        ) from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ConfigError(
                f"calibration file {path}: another --calibrate is measuring into it; wait for it to end "
                "(two at once would time each other's load)"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _stamp(cell: Cell, machine: Mapping[str, Any], version: str, **fields: Any) -> dict[str, Any]:
    now = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    return {
        "cell_key": cell.key,
        "kind": cell.kind,
        "label": cell.label,
        "cell": dict(cell.content),
        "machine": dict(machine),
        "version": version,
        "measured_at": now,
        "load_1min": load,
        **fields,
    }


# --------------------------------------------------------------------------- measuring
def trial_cpus(resources) -> float:
    """CPUs one trial reserves: its placement group's bundles (learner process, env runners, learners)."""
    return float(sum(b.get("CPU", 0.0) for b in resources.bundles()))


def _evaluation_timer(scenario, episodes: int, seed: int):
    """algo -> (seconds of one periodic evaluation, seconds of the final evaluation), with the code a
    trial runs: periodic_eval.evaluate_policies for both (the trainable's evaluate calls it too)."""

    def run(algo) -> tuple[float, float]:
        from uavlora_rllib.experiment.periodic_eval import PeriodicEvalSettings, evaluate_policies

        evaluate_policies(algo, PeriodicEvalSettings(scenario, 1, 1, seed))  # first-call costs, untimed
        t0 = time.perf_counter()
        evaluate_policies(algo, PeriodicEvalSettings(scenario, 1, episodes, seed))
        t1 = time.perf_counter()
        evaluate_policies(algo, PeriodicEvalSettings(scenario, 0, episodes, seed))
        return t1 - t0, time.perf_counter() - t1

    return run


def measure_train_cell(grid, spec, iterations: int) -> dict[str, Any]:
    """The measured fields of one trial cell (Ray must be running)."""
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.experiment.training_rate import measure_training

    entry = registry.get(spec.algorithm)
    episodes = grid.evaluation.episodes
    m = measure_training(
        entry,
        spec.scenario,
        spec.hparams,
        grid.resources,
        spec.seed,
        iterations,
        warmup_until_learning=True,
        after=_evaluation_timer(spec.scenario, episodes, spec.seed),
    )
    periodic_s, final_s = m.after
    return {
        "env_steps_per_s": m.env_steps_per_s,
        "seconds_per_iteration": m.seconds_per_iteration,
        "env_steps_per_iteration": m.env_steps_per_iteration,
        "build_s": m.build_s,
        "iterations": len(m.rows),
        "warmup_iterations": m.warmup_iterations,
        "learning_started": m.learning_started,
        "periodic_eval_s": periodic_s,
        "final_eval_s": final_s,
        "eval_episodes": episodes,
    }


def baseline_episodes_to_time(name: str, scenario, episodes: int) -> int:
    """Episodes to time a baseline on: all of them, unless its cost model says that is long and its
    cost grows with episodes; then fewer (at least 1), and the time is scaled."""
    from uavlora_rllib.baselines.policies import evaluation_seconds

    if name in ONE_OFF_BASELINES:
        return episodes
    estimate = evaluation_seconds(name, scenario, episodes)
    if estimate <= BASELINE_MEASURE_S:
        return episodes
    return max(1, min(episodes, int(episodes * BASELINE_MEASURE_S / estimate)))


def measure_baseline_cell(spec, episodes: int) -> dict[str, Any]:
    """The measured fields of one baseline cell: one run with the code a baseline task runs."""
    from uavlora_rllib.experiment.baseline_tasks import evaluate_baseline

    timed = baseline_episodes_to_time(spec.baseline, spec.scenario, episodes)
    wall = float(evaluate_baseline(spec, timed)["_wall_s"])
    return {"seconds": wall * episodes / timed, "timed_episodes": timed, "timed_s": wall, "episodes": episodes}


def calibrate(
    grid,
    specs,
    path: str | None = None,
    iterations: int = DEFAULT_ITERATIONS,
    num_cpus: int | None = None,
    out: TextIO | None = None,
) -> int:
    """Measure every cell of the grid not yet recorded for this machine and this code, one
    calibration per file at a time, and record each as soon as it is measured; returns how many
    were measured."""
    out = out or sys.stdout
    path = path or default_path()
    with _one_calibration(path):
        return _calibrate_grid(grid, specs, Store.load(path), iterations, num_cpus, out)


def _calibrate_grid(grid, specs, store: Store, iterations: int, num_cpus: int | None, out: TextIO) -> int:
    machine, version = this_machine(), package_version()
    trains = [(c, specs[ix[0]]) for c, ix in grid_train_cells(grid, specs).values()]
    bases = [(c, members[0]) for c, members in grid_baseline_cells(grid).values()]
    todo_t = [(c, s) for c, s in trains if not store.has(c.key, machine, version)]
    todo_b = [(c, s) for c, s in bases if not store.has(c.key, machine, version)]
    kept = len(trains) + len(bases) - len(todo_t) - len(todo_b)
    print(
        f"calibration: {len(todo_t)} trial cells and {len(todo_b)} baseline cells to measure on "
        f"{describe_machine(machine)} ({kept} already in {store.path})",
        file=out,
        flush=True,
    )
    load, cpus = (os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0), os.cpu_count() or 1
    if (todo_t or todo_b) and load > 0.5 * cpus:  # a 1-minute mean: other work before this one started
        print(
            f"note: load {load:.1f} on {cpus} CPUs: other work shares the cores, so the rates measured now will be "
            "low; calibrate on an idle machine for the figures to plan with",
            file=out,
            flush=True,
        )
    t_start = time.perf_counter()
    if todo_t:
        _calibrate_trials(grid, todo_t, store, machine, version, iterations, num_cpus, out)
    for i, (cell, spec) in enumerate(todo_b, 1):
        fields = measure_baseline_cell(spec, grid.evaluation.episodes)
        if not _put_usable(store, _stamp(cell, machine, version, **fields), f"  [{i}/{len(todo_b)}]", out):
            continue
        scaled = (
            f" (timed on {fields['timed_episodes']} of {fields['episodes']} episodes, scaled)"
            if fields["timed_episodes"] < fields["episodes"]
            else ""
        )
        print(f"  [{i}/{len(todo_b)}] {cell.label}: {fields['seconds']:.1f} s{scaled}", file=out, flush=True)
    print(f"calibration: done in {time.perf_counter() - t_start:.0f} s; written to {store.path}", file=out, flush=True)
    return len(todo_t) + len(todo_b)


def _calibrate_trials(
    grid, todo, store: Store, machine, version: str, iterations: int, num_cpus: int | None, out: TextIO
) -> None:
    """Measure the trial cells in one private local Ray."""
    import ray

    import uavlora_rllib.envs.multi_agent  # noqa: F401  (registers the "uavlora" env)
    from uavlora_rllib.experiment.quiet import SETUP_HOOK

    need = trial_cpus(grid.resources)
    cpus = int(max(num_cpus or os.cpu_count() or 1, math.ceil(need)))
    if need > (os.cpu_count() or 1):
        print(
            f"note: a trial reserves {need:g} CPUs and this machine has {os.cpu_count()}: measured with its "
            "processes sharing the cores",
            file=out,
            flush=True,
        )
    ray.init(
        address="local",
        num_cpus=cpus,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"worker_process_setup_hook": SETUP_HOOK},
    )
    try:
        for i, (cell, spec) in enumerate(todo, 1):
            t0 = time.perf_counter()
            fields = measure_train_cell(grid, spec, iterations)
            if not _put_usable(store, _stamp(cell, machine, version, **fields), f"  [{i}/{len(todo)}]", out):
                continue
            late = "" if fields["learning_started"] else "; the learner had not updated yet (rate too high)"
            print(
                f"  [{i}/{len(todo)}] {cell.label}: {fields['env_steps_per_s']:,.0f} env steps/s, "
                f"{fields['seconds_per_iteration']:.1f} s per iteration; evaluation {fields['periodic_eval_s']:.1f} s "
                f"periodic, {fields['final_eval_s']:.1f} s final ({time.perf_counter() - t0:.0f} s){late}",
                file=out,
                flush=True,
            )
    finally:
        ray.shutdown()


def _put_usable(store: Store, record: dict[str, Any], prefix: str, out: TextIO) -> bool:
    """Store a measured record, unless `usable` rejects it (e.g. no env step was timed): a record
    the estimate cannot read would only hide the cell from the next --calibrate."""
    if usable(record):
        store.put(record)
        return True
    read = {k: record.get(k) for k in _READ_FIELDS[record["kind"]]}
    print(f"{prefix} {record['label']}: not recorded, the measurement is unusable: {read}", file=out, flush=True)
    return False
