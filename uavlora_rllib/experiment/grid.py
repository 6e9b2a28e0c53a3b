"""The grid YAML: a typed schema, its loader, and the trials it expands to.

A grid is the product algorithm x seed x n_eds x n_uavs over one scenario, plus the
baselines evaluated (without training) on every seed x n_eds x n_uavs. Everything is
validated when the file is loaded, before Ray starts: every error is one `ConfigError`
whose message starts with the file name and names the YAML path of the bad field, e.g.

    tune_configs/x.yaml: algorithms.mappo.lr: Input should be greater than 0 (got -1)

Schema (see tune_configs/smoke.yaml for a complete example)::

    experiment: smoke            # MLflow experiment name and Ray Tune run name
    algorithms:                  # name -> hyperparameter overrides (or null for defaults)
      mappo: {lr: 3.0e-4}
      ippo: null
    baselines: [random, adr]     # evaluation-only runs (may be empty)
    seeds: [0, 42, 2021]
    n_eds: [10]                  # V values
    n_uavs: [2]                  # U values
    scenario: {episode_len: 150} # ScenarioConfig overrides (not n_eds / n_uavs)
    stop: {env_steps: 2000000}   # training budget per trial
    checkpoint_every: 10         # training iterations between checkpoints
    resources: {num_env_runners: 1, ...}   # registry.Resources, per trial
    mlflow: {tracking_uri: "sqlite:///mlflow.db", retry_timeout_s: 300}
    failure: {max_failures: 3}   # retries of a failed trial (lost node) from its last checkpoint
    evaluation: {episodes: 10}   # execution-phase episodes per trial / baseline run;
                                 # interval_env_steps: greedy-policy curve (null: budget/20, 0: off)
    storage: ./ray_results       # Ray Tune storage (a shared path on a cluster)
    max_concurrent_trials: null  # optional cap
    plugins: []                  # optional: modules to import that register more algorithms
    num_samples: 1               # sweeps (experiment/sweep.py): samples of the search spaces
    scheduler: null              #   {type: asha | pbt | median_stopping, ...}
    search_alg: null             #   {type: optuna, sampler: tpe, seed: 0}

Any algorithm hyperparameter may be a Ray Tune search space instead of one value
(`{grid_search: [...]}`, `{choice: [...]}`, `{uniform: [lo, hi]}`, `{loguniform: [lo, hi]}`,
`{randint: [lo, hi]}`): experiment/sweep.py, which also validates them.

`t_max_env_steps` (QMIX/VDN: the epsilon schedule is a fraction of T_max) is NOT tied to
`stop.env_steps`: it stays at the paper's 2M unless the YAML sets it, so a short grid explores
as the paper's first env steps do (why: docs/model.md#training-defaults).
A plugin module registers its algorithms when imported (`registry.register_algorithm(...)` or
`registry.register(...)`); trials import the grid's plugins too.

Relative paths (`storage`, a relative sqlite file) are relative to the directory the driver was
launched from (`experiment.cluster.launch_dir`; under `ray job submit` they need
UAVLORA_LAUNCH_DIR or an absolute path).

Input is taken strictly (see config_errors.build): no bool or string for a number, no NaN or
inf, seeds in [0, 2^32 - 1], the experiment name a safe identifier (it names a directory
under `storage` and the MLflow experiment), a tracking URI with a scheme MLflow serves
(TRACKING_SCHEMES), `storage` a directory that exists or can be created (or a URI of
STORAGE_SCHEMES), no key twice in one mapping, UTF-8 text.
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
import os
import re
import urllib.parse
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import yaml
from pydantic import ConfigDict, Field, field_validator
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.cli_args import SEED_MAX, write_problem
from uavlora_rllib.config_errors import ConfigError, build
from uavlora_rllib.experiment import sweep
from uavlora_rllib.experiment.sweep import SchedulerConfig, SearchAlgConfig, SearchSpace
from uavlora_rllib.sim.scenario import ScenarioConfig

_STRICT = ConfigDict(extra="forbid", frozen=True)
PosInt = Annotated[int, Field(ge=1)]
Seed = Annotated[int, Field(ge=0, le=SEED_MAX)]

# The experiment name is a directory under `storage` and an MLflow experiment name.
EXPERIMENT_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
# URI schemes MLflow 3 serves as a tracking store (file stores are refused: mlflow 3 warns
# they are going away, and a file store cannot be shared by a cluster's driver and UI).
# SQLAlchemy URIs may name a driver: postgresql+psycopg2://...
TRACKING_SCHEMES = ("sqlite", "postgresql", "mysql", "mssql", "http", "https", "databricks")
# Ray Tune storage URIs (pyarrow file systems); anything else must be a local directory.
STORAGE_SCHEMES = ("s3", "gs", "gcs", "hdfs", "abfs", "abfss", "file")


def _writable_dir_problem(path: str) -> str | None:
    """Why `path` cannot be (or become) a directory this process writes, or None."""
    path = os.path.abspath(os.path.expanduser(path))
    if os.path.exists(path):
        if not os.path.isdir(path):
            return f"{path} exists and is not a directory"
        problem = write_problem(path)
        return f"{path} is not writable ({problem})" if problem else None
    parent = path
    while not os.path.exists(parent):  # the nearest existing ancestor must be a writable directory
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        return f"cannot create {path}: {parent} is not a directory"
    problem = write_problem(parent)
    return f"cannot create {path}: {parent} is not writable ({problem})" if problem else None


def check_storage(value: str) -> str:
    """`storage` (or tune's --storage): a creatable local directory or a URI of STORAGE_SCHEMES."""
    if "://" in value:
        scheme = value.split("://", 1)[0].lower()
        if scheme not in STORAGE_SCHEMES or not value.split("://", 1)[1].strip("/"):
            raise ValueError(
                f"must be a local directory or a URI <scheme>://<bucket/path> with scheme one of "
                f"{list(STORAGE_SCHEMES)}, got {value!r}"
            )
        return value
    if not value.strip() or "\n" in value or "\0" in value:
        raise ValueError(f"must be a directory path, got {value!r}")
    problem = _writable_dir_problem(value)
    if problem:
        raise ValueError(f"must be a directory that exists or can be created: {problem}")
    return value


@typed_dataclass(config=_STRICT)
class StopConfig:
    # env steps sampled per trial (num_env_steps_sampled_lifetime), [1, 1e12]
    env_steps: int = Field(gt=0, le=10**12)


@typed_dataclass(config=_STRICT)
class MlflowConfig:
    tracking_uri: str = "sqlite:///mlflow.db"
    # seconds the driver keeps retrying (with backoff) while MLflow is unreachable, then stops
    # with a clear message; --resume fills in what was not logged (docs/cluster.md)
    retry_timeout_s: float = Field(default=300.0, gt=0, le=86400)
    # MB up to which a finished trial's final checkpoint (on a local or shared filesystem) is
    # uploaded as its run's `checkpoint/` artifact; larger ones, cloud storage, and 0 keep only
    # the `checkpoint` tag pointing at it (docs/cluster.md#mlflow). RLlib checkpoints of the paper's
    # models are ~4 MB
    checkpoint_artifact_max_mb: float = Field(default=50.0, ge=0, le=10**6)

    @field_validator("tracking_uri")
    @classmethod
    def _check_uri(cls, v: str) -> str:
        allowed = (
            f"must be a database or server URI with scheme one of {list(TRACKING_SCHEMES)}, such as "
            "sqlite:///mlflow.db or http://host:5000 (mlflow 3 refuses file stores)"
        )
        scheme, sep, rest = v.partition(":")
        if not sep or scheme.split("+", 1)[0].lower() not in TRACKING_SCHEMES or any(c in v for c in "\n\r\0"):
            raise ValueError(f"{allowed}; got {v!r}")
        scheme = scheme.split("+", 1)[0].lower()
        if scheme in ("http", "https") and not urllib.parse.urlsplit(v).hostname:
            raise ValueError(f"{allowed}; got {v!r} (no host)")
        if scheme == "sqlite":
            if not rest.startswith("///") or rest == "///":
                raise ValueError(f"{allowed}; got {v!r} (a sqlite URI is sqlite:///relative.db or sqlite:////abs.db)")
            db_file = rest[3:]
            if db_file == ":memory:":  # the grid's runs would vanish with the driver
                raise ValueError(f"a grid's runs must outlive the driver: name a sqlite file, got {v!r}")
            if os.path.isdir(db_file):
                raise ValueError(f"the sqlite file {db_file} is a directory; got {v!r}")
            problem = _writable_dir_problem(os.path.dirname(os.path.abspath(db_file)))
            if problem:
                raise ValueError(f"the sqlite file's directory is not usable ({problem}); got {v!r}")
        return v


@typed_dataclass(config=_STRICT)
class FailureConfig:
    # times Tune restarts a failed trial (e.g. its node died) from its last checkpoint, into the
    # same MLflow run, before the trial counts as failed; 0 disables retries
    max_failures: int = Field(default=3, ge=0, le=1000)


@typed_dataclass(config=_STRICT)
class EvaluationConfig:
    # execution-phase episodes per trial and per baseline run, [1, 1e6]
    episodes: int = Field(default=10, ge=1, le=1_000_000)
    # env steps between evaluations of the greedy policy during training (learning curves,
    # experiment/periodic_eval.py); null: stop.env_steps / 20; 0: none
    interval_env_steps: int | None = Field(default=None, ge=0)


def _no_duplicates(v: list) -> list:
    dup = sorted({x for x in v if v.count(x) > 1}, key=str)
    if dup:
        raise ValueError(f"values must be distinct, repeated: {dup}")
    return v


@typed_dataclass(config=_STRICT, kw_only=True)
class GridConfig:
    """One grid YAML, validated field by field (cross-field checks: `load_grid`)."""

    experiment: str = Field(min_length=1)
    algorithms: dict[str, dict[str, Any] | None] = Field(min_length=1)
    seeds: list[Seed] = Field(min_length=1)
    n_eds: list[PosInt] = Field(min_length=1)
    n_uavs: list[PosInt] = Field(min_length=1)
    stop: StopConfig
    baselines: list[str] = dataclasses.field(default_factory=list)
    scenario: dict[str, Any] = dataclasses.field(default_factory=dict)
    checkpoint_every: int = Field(default=10, ge=1, le=10**9)
    resources: registry.Resources = dataclasses.field(default_factory=registry.Resources)
    mlflow: MlflowConfig = dataclasses.field(default_factory=MlflowConfig)
    evaluation: EvaluationConfig = dataclasses.field(default_factory=EvaluationConfig)
    failure: FailureConfig = dataclasses.field(default_factory=FailureConfig)
    storage: str = Field(default="./ray_results", min_length=1)
    max_concurrent_trials: int | None = Field(default=None, ge=1, le=100_000)
    plugins: list[str] = dataclasses.field(default_factory=list)
    num_samples: int = Field(1, ge=1, le=100_000)
    scheduler: SchedulerConfig | None = None
    search_alg: SearchAlgConfig | None = None

    @field_validator("experiment")
    @classmethod
    def _safe_name(cls, v: str) -> str:
        if not EXPERIMENT_NAME.fullmatch(v) or ".." in v:
            raise ValueError(
                "must be 1-64 characters from letters, digits, '_', '.', '-', starting with a letter or "
                f"digit, without '..' (it names a directory under storage); got {v!r}"
            )
        return v

    @field_validator("storage")
    @classmethod
    def _storage(cls, v: str) -> str:
        return check_storage(v)

    @field_validator("plugins")
    @classmethod
    def _module_names(cls, v: list[str]) -> list[str]:
        for i, name in enumerate(v):
            if not all(part.isidentifier() for part in name.split(".")):
                raise ValueError(f"entry {i}: must be a dotted Python module name such as my_pkg.my_algo, got {name!r}")
        return v

    @field_validator("seeds", "n_eds", "n_uavs", "baselines", "plugins")
    @classmethod
    def _distinct(cls, v: list) -> list:
        return _no_duplicates(v)

    @field_validator("algorithms", mode="before")
    @classmethod
    def _list_to_mapping(cls, v: Any) -> Any:
        # `algorithms: [mappo, ippo]` is shorthand for `{mappo: null, ippo: null}`
        if isinstance(v, list) and all(isinstance(x, str) for x in v):
            return {x: None for x in _no_duplicates(v)}
        return v


@dataclass(frozen=True)
class TrialSpec:
    """One training trial of the grid."""

    algorithm: str
    seed: int
    n_eds: int
    n_uavs: int
    scenario: ScenarioConfig
    hparams: Any  # the algorithm's validated hyperparameter dataclass (sampled fields at their defaults)
    # hyperparameters given as Tune search spaces: name -> space (sweep.py); empty: none
    spaces: Mapping[str, SearchSpace] = dataclasses.field(default_factory=dict)

    @property
    def name(self) -> str:
        return run_name(self.algorithm, self.n_eds, self.n_uavs, self.seed)


@dataclass(frozen=True)
class BaselineSpec:
    """One evaluation-only run of a baseline."""

    baseline: str
    seed: int
    n_eds: int
    n_uavs: int
    scenario: ScenarioConfig
    plugins: tuple[str, ...] = ()  # the grid's plugin modules: the task imports them (a plugin's baseline)

    @property
    def name(self) -> str:
        return run_name(self.baseline, self.n_eds, self.n_uavs, self.seed)


def run_name(algorithm: str, n_eds: int, n_uavs: int, seed: int) -> str:
    return f"{algorithm}-V{n_eds}-U{n_uavs}-s{seed}"


def trial_run_name(cfg: Mapping[str, Any], trial_id: str) -> str:
    """The name of a trial (Tune) and of its MLflow run: `run_name`, and in a sweep (the trial
    config's ``sweep``) the trial's number in the experiment too (``-t00003``), since there
    (algorithm, V, U, seed) repeats."""
    name = run_name(cfg["algorithm"], cfg["n_eds"], cfg["n_uavs"], cfg["seed"])
    return f"{name}-t{str(trial_id).rsplit('_', 1)[-1]}" if cfg.get("sweep") else name


# --------------------------------------------------------------------------- loading
class UniqueKeyLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses a key given twice in one mapping (SafeLoader keeps the last
    one silently, so `lr: 1e-3` ... `lr: 1e-2` would train with 1e-2 unnoticed)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *anchor` merges, not a key
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.get(key)
            except TypeError:  # an unhashable key: SafeLoader reports it below
                continue
            if first is not None:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first given on line {first.line + 1})", key_node.start_mark
                )
            seen[key] = key_node.start_mark
        return super().construct_mapping(node, deep)


# YAML 1.1 (PyYAML) reads `3e-4` as the text '3e-4' because its floats need a dot; YAML 1.2 and
# Python read it as a number, and so does every reader of this project's YAML (grids, --set).
UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"), list("-+0123456789")
)


def read_yaml_text(path: str, what: str) -> str:
    """The text of a YAML file as UTF-8; ConfigError '<path>: ...' if unreadable or not UTF-8."""
    try:
        with open(path, "rb") as fh:
            raw = fh.read()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"{path}: the {what} is not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}); "
            "save it as UTF-8"
        ) from None


def parse_yaml(text: str, path: str) -> Any:
    """YAML text -> data (UniqueKeyLoader); ConfigError '<path>: line L, column C: ...'."""
    try:
        return yaml.load(text, Loader=UniqueKeyLoader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        label = "YAML error" if isinstance(exc, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise ConfigError(f"{path}: {where}{label}: {problem}") from None


def _read_yaml(path: str) -> Any:
    return parse_yaml(read_yaml_text(path, "grid file"), path)


def import_plugins(modules: list[str], prefix: str = "plugins") -> None:
    """Import modules that register extra algorithms (each registers its own at import)."""
    for i, module in enumerate(modules):
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ConfigError(f"{prefix}.{i}: cannot import module {module!r}: {exc}") from None
        # A plugin is user code: whatever its import raises (a SyntaxError, any exception, even
        # sys.exit, which would otherwise end the run silently) is a bad grid, not a crash.
        except (Exception, SystemExit) as exc:
            where = f" ({exc.filename}, line {exc.lineno})" if isinstance(exc, SyntaxError) else ""
            detail = " ".join(str(exc).split()) or "(no message)"
            raise ConfigError(
                f"{prefix}.{i}: importing plugin module {module!r} failed: {type(exc).__name__}{where}: {detail}"
            ) from None


def import_grid_plugins(path: str) -> None:
    """Import the `plugins:` of a grid file without validating the rest (`--list-hparams` of a plugin's
    algorithm reads its hyperparameters before the grid that sets them is valid)."""
    data = _read_yaml(path)
    plugins = data.get("plugins") if isinstance(data, dict) else None
    if plugins is None:
        return
    if not isinstance(plugins, list) or not all(isinstance(m, str) and m for m in plugins):
        raise ConfigError(f"{path}: plugins: expected a list of module names, got {plugins!r}")
    import_plugins(plugins, prefix=f"{path}: plugins")


def algorithm_overrides(grid: GridConfig, name: str) -> dict[str, Any]:
    """The YAML overrides of one algorithm (a copy; search spaces included)."""
    return dict(grid.algorithms.get(name) or {})


def algorithm_spaces(grid: GridConfig, entry: Any) -> tuple[dict[str, Any], dict[str, SearchSpace]]:
    """(fixed overrides, search spaces) of one algorithm, validated (sweep.split_overrides)."""
    return sweep.split_overrides(entry.hparams_cls, algorithm_overrides(grid, entry.name), f"algorithms.{entry.name}")


def eval_interval(grid: GridConfig) -> int:
    """periodic_eval.resolve_interval of the grid (env steps between greedy evaluations; 0: none),
    without importing RLlib: null -> stop.env_steps / 20 (at least 1)."""
    interval = grid.evaluation.interval_env_steps
    return max(1, grid.stop.env_steps // 20) if interval is None else int(interval)


def is_sweep(grid: GridConfig, specs: list[TrialSpec]) -> bool:
    """Whether trials are sampled (search spaces, num_samples, scheduler or search algorithm):
    then trial and run names carry the trial's number, since (algorithm, V, U, seed) repeats."""
    return (
        grid.num_samples > 1
        or grid.scheduler is not None
        or grid.search_alg is not None
        or any(s.spaces for s in specs)
    )


def scenario_for(grid: GridConfig, n_eds: int, n_uavs: int) -> ScenarioConfig:
    return ScenarioConfig.from_dict({**grid.scenario, "n_eds": n_eds, "n_uavs": n_uavs}, prefix="scenario")


def _validate(grid: GridConfig) -> None:
    """Cross-field checks: algorithms, overrides, every scenario, baselines."""
    for key in ("n_eds", "n_uavs"):
        if key in grid.scenario:
            raise ConfigError(f"scenario.{key}: set by the top-level '{key}' list; remove it from scenario")
    import_plugins(grid.plugins)
    entries = {}
    spaces = {}
    for name in grid.algorithms:
        entry = registry.spec(name, path=f"algorithms.{name}")  # no RLlib import (dry runs)
        registry.check_registered(name, f"algorithms.{name}")
        fixed, spaces[name] = algorithm_spaces(grid, entry)
        # every checked combination of sampled values (one, the fixed values, without spaces)
        hparams = [
            entry.hparams({**fixed, **combo}, prefix=f"algorithms.{name}")
            for combo in sweep.representative_combinations(spaces[name])
        ]
        entries[name] = (entry, hparams)
    sweep.check_sweep(grid, spaces, eval_interval(grid))

    from uavlora_rllib.baselines.policies import baseline_names, make_baseline

    for i, name in enumerate(grid.baselines):
        if name not in baseline_names():  # a plugin's too (register_baseline)
            raise ConfigError(f"baselines.{i}: unknown baseline {name!r}; allowed: {baseline_names()}")
    for n_eds, n_uavs in itertools.product(grid.n_eds, grid.n_uavs):
        where = f" (with n_eds={n_eds}, n_uavs={n_uavs})"
        try:
            scenario = scenario_for(grid, n_eds, n_uavs)
        except ConfigError as exc:
            raise ConfigError(f"{exc}{where}") from None
        for name, (entry, candidates) in entries.items():
            entry.check_scenario(scenario, prefix="scenario.action_mode")
            # the entry's own cross-checks (hyperparameters x resources x scenario), without RLlib
            # for a built-in (registry.AlgorithmSpec.check_trial)
            for hparams in candidates:
                try:
                    entry.check_trial(scenario, hparams, grid.resources, grid.seeds[0])
                except ConfigError as exc:
                    sampled = ", ".join(f"{k}={getattr(hparams, k)!r}" for k in spaces[name])
                    raise ConfigError(f"{exc}{where}{f' (sampled: {sampled})' if sampled else ''}") from None
        for i, name in enumerate(grid.baselines):
            try:
                make_baseline(name, scenario, seed=0)
            except ConfigError as exc:
                raise ConfigError(f"baselines.{i}: {name!r}{where}: {exc}") from None


def check_local_resources(grid: GridConfig, available_cpus: float) -> None:
    """Refuse a grid one of whose trials needs more CPUs than the local Ray has (Tune would
    wait for them forever). On a cluster (--address) the cluster's size decides instead."""
    r = grid.resources
    bundles = r.bundles()  # the trial's process, then its remote env runners, then its remote learners
    need = sum(b.get("CPU", 0.0) for b in bundles)
    if need <= available_cpus:
        return
    parts = [f"its own process {bundles[0].get('CPU', 0.0):g}"]
    if r.num_env_runners:
        parts.append(f"num_env_runners {r.num_env_runners} x num_cpus_per_env_runner {r.num_cpus_per_env_runner:g}")
    if r.num_learners:
        parts.append(f"num_learners {r.num_learners} x num_cpus_per_learner {r.num_cpus_per_learner:g}")
    field = "resources.num_cpus_per_learner" if r.num_cpus_per_learner > available_cpus else "resources"
    raise ConfigError(
        f"{field}: one trial needs {need:g} CPUs ({' + '.join(parts)}), but the local Ray has {available_cpus:g}; "
        f"allowed: at most {available_cpus:g} in all (or run on a cluster with --address)"
    )


def parse_grid(data: Any) -> GridConfig:
    """Validate a grid given as a mapping (the parsed YAML); raises ConfigError (no file name)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"<top level>: expected a mapping of grid fields, got {type(data).__name__}")
    grid = build(GridConfig, data, "")
    _validate(grid)
    return grid


def load_grid(path: str) -> GridConfig:
    """Read and validate a grid YAML. Raises one ConfigError '<path>: <yaml path>: <problem>'."""
    data = _read_yaml(path)
    try:
        return parse_grid(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------- expansion
def trials(grid: GridConfig) -> list[TrialSpec]:
    """The product algorithm x seed x n_eds x n_uavs, in YAML order."""
    import_plugins(grid.plugins)
    out = []
    for name in grid.algorithms:
        entry = registry.spec(name, path=f"algorithms.{name}")
        fixed, spaces = algorithm_spaces(grid, entry)
        hparams = entry.hparams(fixed, prefix=f"algorithms.{name}")
        for seed, n_eds, n_uavs in itertools.product(grid.seeds, grid.n_eds, grid.n_uavs):
            out.append(TrialSpec(name, seed, n_eds, n_uavs, scenario_for(grid, n_eds, n_uavs), hparams, spaces))
    return out


def trial_count(grid: GridConfig, specs: list[TrialSpec]) -> int:
    """Trials Tune runs: each grid point x its grid_search product x num_samples (a search
    algorithm: num_samples)."""
    if grid.search_alg is not None:
        return grid.num_samples
    return grid.num_samples * sum(sweep.grid_search_size(s.spaces) for s in specs)


def baseline_runs(grid: GridConfig) -> list[BaselineSpec]:
    """The product baseline x seed x n_eds x n_uavs (evaluation seed = the grid's seed)."""
    return [
        BaselineSpec(name, seed, n_eds, n_uavs, scenario_for(grid, n_eds, n_uavs), tuple(grid.plugins))
        for name, seed, n_eds, n_uavs in itertools.product(grid.baselines, grid.seeds, grid.n_eds, grid.n_uavs)
    ]


def hparams_dict(hparams: Any) -> dict[str, Any]:
    """A hyperparameter dataclass as a plain dict (for Ray configs and MLflow params)."""
    if dataclasses.is_dataclass(hparams) and not isinstance(hparams, type):
        return dataclasses.asdict(hparams)
    return dict(hparams or {})
