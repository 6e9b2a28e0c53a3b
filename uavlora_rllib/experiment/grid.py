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
    evaluation: {episodes: 10}   # execution-phase episodes per trial / baseline run
    storage: ./ray_results       # Ray Tune storage (a shared path on a cluster)
    max_concurrent_trials: null  # optional cap
    plugins: []                  # optional: modules to import that register more algorithms

An algorithm whose hyperparameters have `t_max_env_steps` (QMIX/VDN: the epsilon schedule is
a fraction of T_max) gets `stop.env_steps` there unless its overrides set it.
A plugin module registers entries with `registry.register(...)` and adds each name to
`registry.MODULES` (name -> its own module) so that workers can import it too.

Relative paths (`storage`, a relative sqlite file) are relative to the directory the driver was
launched from (`experiment.cluster.launch_dir`; under `ray job submit` they need
UAVLORA_LAUNCH_DIR or an absolute path).
"""

from __future__ import annotations

import dataclasses
import importlib
import itertools
from dataclasses import dataclass
from typing import Annotated, Any, Mapping

import yaml
from pydantic import Field, field_validator
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.config_errors import ConfigError, build
from uavlora_rllib.sim.scenario import ScenarioConfig

_STRICT = {"extra": "forbid", "frozen": True}
PosInt = Annotated[int, Field(ge=1)]


@typed_dataclass(config=_STRICT)
class StopConfig:
    env_steps: int = Field(gt=0)  # env steps sampled per trial (num_env_steps_sampled_lifetime)


@typed_dataclass(config=_STRICT)
class MlflowConfig:
    tracking_uri: str = "sqlite:///mlflow.db"
    # seconds the driver keeps retrying (with backoff) while MLflow is unreachable, then stops
    # with a clear message; --resume fills in what was not logged (docs/cluster.md)
    retry_timeout_s: float = Field(300.0, gt=0, le=86400)

    @field_validator("tracking_uri")
    @classmethod
    def _check_uri(cls, v: str) -> str:
        if v.startswith("file:") or "://" not in v and not v.startswith("sqlite:"):
            raise ValueError(
                "must be a database or server URI such as sqlite:///mlflow.db or http://host:5000 "
                "(mlflow 3 refuses file stores)"
            )
        return v


@typed_dataclass(config=_STRICT)
class FailureConfig:
    # times Tune restarts a failed trial (e.g. its node died) from its last checkpoint, into the
    # same MLflow run, before the trial counts as failed; 0 disables retries
    max_failures: int = Field(3, ge=0, le=1000)


@typed_dataclass(config=_STRICT)
class EvaluationConfig:
    episodes: int = Field(10, ge=1)  # execution-phase episodes per trial and per baseline run


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
    seeds: list[int] = Field(min_length=1)
    n_eds: list[PosInt] = Field(min_length=1)
    n_uavs: list[PosInt] = Field(min_length=1)
    stop: StopConfig
    baselines: list[str] = dataclasses.field(default_factory=list)
    scenario: dict[str, Any] = dataclasses.field(default_factory=dict)
    checkpoint_every: int = Field(10, ge=1)
    resources: registry.Resources = dataclasses.field(default_factory=registry.Resources)
    mlflow: MlflowConfig = dataclasses.field(default_factory=MlflowConfig)
    evaluation: EvaluationConfig = dataclasses.field(default_factory=EvaluationConfig)
    failure: FailureConfig = dataclasses.field(default_factory=FailureConfig)
    storage: str = Field("./ray_results", min_length=1)
    max_concurrent_trials: int | None = Field(None, ge=1)
    plugins: list[str] = dataclasses.field(default_factory=list)

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
    hparams: Any  # the algorithm's validated hyperparameter dataclass

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

    @property
    def name(self) -> str:
        return run_name(self.baseline, self.n_eds, self.n_uavs, self.seed)


def run_name(algorithm: str, n_eds: int, n_uavs: int, seed: int) -> str:
    return f"{algorithm}-V{n_eds}-U{n_uavs}-s{seed}"


# --------------------------------------------------------------------------- loading
def _read_yaml(path: str) -> Any:
    try:
        with open(path) as fh:
            text = fh.read()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the grid file: {exc.strerror or exc}") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}: {where}YAML syntax error: {problem}") from None


def import_plugins(modules: list[str], prefix: str = "plugins") -> None:
    """Import modules that register extra algorithms (each adds itself to registry.MODULES)."""
    for i, module in enumerate(modules):
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ConfigError(f"{prefix}.{i}: cannot import module {module!r}: {exc}") from None


def algorithm_overrides(grid: GridConfig, name: str, entry: Any) -> dict[str, Any]:
    """The YAML overrides of one algorithm, plus T_max = stop.env_steps for algorithms whose
    hyperparameters have a `t_max_env_steps` field (schedules such as QMIX's epsilon anneal
    over 5% of T_max) unless the YAML sets it."""
    overrides = dict(grid.algorithms.get(name) or {})
    fields = {f.name for f in dataclasses.fields(entry.hparams_cls)}
    if "t_max_env_steps" in fields and "t_max_env_steps" not in overrides:
        overrides["t_max_env_steps"] = grid.stop.env_steps
    return overrides


def scenario_for(grid: GridConfig, n_eds: int, n_uavs: int) -> ScenarioConfig:
    return ScenarioConfig.from_dict({**grid.scenario, "n_eds": n_eds, "n_uavs": n_uavs}, prefix="scenario")


def _validate(grid: GridConfig) -> None:
    """Cross-field checks: algorithms, overrides, every scenario, baselines."""
    for key in ("n_eds", "n_uavs"):
        if key in grid.scenario:
            raise ConfigError(f"scenario.{key}: set by the top-level '{key}' list; remove it from scenario")
    import_plugins(grid.plugins)
    entries = {}
    for name in grid.algorithms:
        entry = registry.get(name, path=f"algorithms.{name}")
        hparams = entry.hparams(algorithm_overrides(grid, name, entry), prefix=f"algorithms.{name}")
        entries[name] = (entry, hparams)

    from uavlora_rllib.baselines.policies import BASELINES, make_baseline

    for i, name in enumerate(grid.baselines):
        if name not in BASELINES:
            raise ConfigError(f"baselines.{i}: unknown baseline {name!r}; allowed: {list(BASELINES)}")
    for n_eds, n_uavs in itertools.product(grid.n_eds, grid.n_uavs):
        where = f" (with n_eds={n_eds}, n_uavs={n_uavs})"
        try:
            scenario = scenario_for(grid, n_eds, n_uavs)
        except ConfigError as exc:
            raise ConfigError(f"{exc}{where}") from None
        for name, (entry, hparams) in entries.items():
            entry.check_scenario(scenario, prefix="scenario.action_mode")
            # the entry's own cross-checks (hyperparameters x resources x scenario); builds
            # only the AlgorithmConfig, not the algorithm
            try:
                entry.build(scenario, hparams, grid.resources, grid.seeds[0])
            except ConfigError as exc:
                raise ConfigError(f"{exc}{where}") from None
        for i, name in enumerate(grid.baselines):
            try:
                make_baseline(name, scenario, seed=0)
            except ConfigError as exc:
                raise ConfigError(f"baselines.{i}: {name!r}{where}: {exc}") from None


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
        entry = registry.get(name, path=f"algorithms.{name}")
        hparams = entry.hparams(algorithm_overrides(grid, name, entry), prefix=f"algorithms.{name}")
        for seed, n_eds, n_uavs in itertools.product(grid.seeds, grid.n_eds, grid.n_uavs):
            out.append(TrialSpec(name, seed, n_eds, n_uavs, scenario_for(grid, n_eds, n_uavs), hparams))
    return out


def baseline_runs(grid: GridConfig) -> list[BaselineSpec]:
    """The product baseline x seed x n_eds x n_uavs (evaluation seed = the grid's seed)."""
    return [
        BaselineSpec(name, seed, n_eds, n_uavs, scenario_for(grid, n_eds, n_uavs))
        for name, seed, n_eds, n_uavs in itertools.product(grid.baselines, grid.seeds, grid.n_eds, grid.n_uavs)
    ]


def hparams_dict(hparams: Any) -> dict[str, Any]:
    """A hyperparameter dataclass as a plain dict (for Ray configs and MLflow params)."""
    if dataclasses.is_dataclass(hparams):
        return dataclasses.asdict(hparams)
    return dict(hparams or {})
