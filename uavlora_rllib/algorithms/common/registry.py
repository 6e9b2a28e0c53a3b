"""Algorithms the grid YAML can name, and what each must provide.

An algorithm module registers one `AlgorithmEntry` per name at import time. The Tune
entry point, the evaluate CLI and the tests only go through this registry, so a new
algorithm needs no change anywhere else. Modules are imported lazily (importing RLlib and
torch costs seconds), from `MODULES`.

Adding an algorithm: a typed hyperparameter class and an AlgorithmConfig that follow
common/config.py (hparams_cls, module_class, learner_class, apply_hparams,
env_runner_settings), a team-view RLModule whose forward_inference / forward_exploration
return Columns.ACTIONS (then the default `make_policy` runs it, greedy or sampled), one
`register_algorithm(name, ConfigClass)` call in its module, and a line in
`MODULES`; the typed class goes in a module of its own that imports neither Ray nor torch and
`declare`s it (a line in `HPARAMS_MODULES`), so that a grid is checked, previewed and listed
without importing RLlib (`spec`). tests/test_algorithm_matrix.py then trains, checkpoints, restores and evaluates it
with no new test code. A plugin (a module outside the package, listed under a grid's `plugins:`) calls
`register_algorithm` (after its own `declare`, or with `action_modes`) or, with a builder of its own,
`register(AlgorithmEntry(...))` when imported; it needs no MODULES or HPARAMS_MODULES line, and a name of its
own (`_checked_spec`).
"""

from __future__ import annotations

import dataclasses
import importlib
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field, ValidationError
from pydantic.dataclasses import dataclass as typed_dataclass
from pydantic.dataclasses import is_pydantic_dataclass

from uavlora_rllib.config_errors import ConfigError, build
from uavlora_rllib.sim.scenario import MAX_ENVS, ScenarioConfig

if TYPE_CHECKING:
    from ray.rllib.algorithms import Algorithm, AlgorithmConfig

    from uavlora_rllib.experiment.evaluation import Policy

# name -> module that registers it. Only names whose module exists are offered.
MODULES: dict[str, str] = {
    "mappo": "uavlora_rllib.algorithms.mappo.mappo",
    "ippo": "uavlora_rllib.algorithms.mappo.mappo",
    "qmix": "uavlora_rllib.algorithms.qmix.qmix",
    "vdn": "uavlora_rllib.algorithms.qmix.qmix",
    "coma": "uavlora_rllib.algorithms.coma.coma",
}


# name -> the module that declares its typed hyperparameters and action modes (`declare`) and imports
# neither Ray nor torch: what a grid's validation, `tune --dry-run` and `--list-hparams` read through
# `spec`, so that they answer in about a second (MODULES' modules import RLlib: seconds).
HPARAMS_MODULES: dict[str, str] = {
    "mappo": "uavlora_rllib.algorithms.mappo.hparams",
    "ippo": "uavlora_rllib.algorithms.mappo.hparams",
    "qmix": "uavlora_rllib.algorithms.qmix.hparams",
    "vdn": "uavlora_rllib.algorithms.qmix.hparams",
    "coma": "uavlora_rllib.algorithms.coma.hparams",
}


# `Resources.learner_precision`: float32 everywhere, or the learner's matrix products in bfloat16
LearnerPrecision = Literal["float32", "bfloat16"]


# Most remote env runners or learners one trial may ask for: each is a bundle of the trial's placement
# group (`Resources.bundles`), so a count from a typo (10**9) would be built as a list before Ray saw it.
MAX_ACTORS_PER_TRIAL = 4096
# Most torch threads a process asks for (bench_train's flag too).
MAX_TORCH_THREADS = 1024


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class Resources:
    """How one trial samples and learns (grid YAML `resources:`)."""

    num_env_runners: int = Field(
        default=0,
        ge=0,
        le=MAX_ACTORS_PER_TRIAL,
        description="remote env runners; 0: sample in the trial's own process",
    )
    num_envs_per_env_runner: int = Field(
        default=16, ge=1, le=MAX_ENVS, description="scenarios per env runner, all in one BatchCore"
    )
    num_cpus_per_env_runner: float = Field(default=1.0, gt=0, description="CPUs reserved per remote env runner")
    num_learners: int = Field(
        default=0,
        ge=0,
        le=MAX_ACTORS_PER_TRIAL,
        description="remote learner actors (data-parallel updates); 0: learn in the trial's own process",
    )
    num_gpus_per_learner: float = Field(
        default=0.0, ge=0, description="GPUs per learner (per the trial's own process when num_learners is 0)"
    )
    num_cpus_per_learner: float = Field(
        default=1.0, gt=0, description="CPUs per learner (the trial's process when num_learners is 0)"
    )
    torch_threads: int = Field(default=1, ge=1, le=MAX_TORCH_THREADS, description="torch intra-op threads per process")
    learner_precision: LearnerPrecision = Field(
        default="float32",
        description="number format of the learner's matrix products: 'bfloat16' gives them bfloat16 inputs during "
        "the training update (oneDNN's bfloat16 products on CPUs with AMX, torch.autocast elsewhere; the GRU state, "
        "losses and parameters stay float32); faster on some chips, so measure it with bench_train "
        "(docs/model.md#learner-precision)",
    )

    def bundles(self) -> list[dict[str, float]]:
        """Placement-group bundles of one trial, in RLlib's layout
        (`Algorithm.default_resource_request`, which tests/test_algorithm_matrix.py checks this
        against): the trial's own process (which also learns when num_learners is 0), the
        remote env runners, the remote learners. Zero amounts are left out."""

        def bundle(cpu: float, gpu: float) -> dict[str, float]:
            return {k: float(v) for k, v in (("CPU", cpu), ("GPU", gpu)) if v}

        if self.num_learners == 0:
            main = bundle(max(self.num_cpus_per_learner, 1.0), self.num_gpus_per_learner)
        else:
            main = bundle(1.0, 0.0)
        runners = [bundle(self.num_cpus_per_env_runner, 0.0)] * self.num_env_runners
        learners = [bundle(self.num_cpus_per_learner, self.num_gpus_per_learner)] * self.num_learners
        return [main] + runners + learners


def _team_policy(algo: Algorithm, scenario: ScenarioConfig, explore: bool = False, seed: int = 0) -> Policy:
    from uavlora_rllib.algorithms.common.policy import team_policy

    return team_policy(algo, scenario, explore=explore, seed=seed)


def check_hparams(hparams: Any, scenario: ScenarioConfig, resources: Resources, path: str) -> None:
    """A typed config's cross-checks with the trial's scenario and resources (its `check`, ConfigError naming
    the field), where it has them: a plugin's class may have none."""
    check = getattr(hparams, "check", None)
    if check is not None:
        check(scenario, resources, path)


@dataclass(frozen=True)
class AlgorithmSpec:
    """What a grid is checked against before anything runs: the typed hyperparameters and the
    action modes of algorithm `name`."""

    name: str
    hparams_cls: type  # the algorithm's typed config (pydantic dataclass, see common/config.py)
    action_modes: tuple[str, ...]  # scenario.action_mode values it supports

    def hparams(self, overrides: dict | None, prefix: str | None = None) -> Any:
        return build(self.hparams_cls, overrides or {}, prefix or f"algorithms.{self.name}")

    def check_scenario(self, scenario: ScenarioConfig, prefix: str = "scenario.action_mode") -> None:
        if scenario.action_mode not in self.action_modes:
            raise ConfigError(
                f"{prefix}: algorithm {self.name!r} supports action modes {list(self.action_modes)}, "
                f"got {scenario.action_mode!r}"
            )

    def check_trial(self, scenario: ScenarioConfig, hparams: Any, resources: Resources, seed: int) -> None:
        """The cross-checks of one trial (hyperparameters x scenario x resources), ConfigError naming
        the field: the typed config's `check` where it has one, which `team_config` runs first when it
        builds a trial (a plugin's class may have none)."""
        check_hparams(hparams, scenario, resources, f"algorithms.{self.name}")


@dataclass(frozen=True)
class AlgorithmEntry(AlgorithmSpec):
    """A registered algorithm: its spec, and how to build and play it (imports RLlib)."""

    # (scenario, hparams, resources, seed) -> an RLlib AlgorithmConfig ready for .build_algo()
    build: Callable[[ScenarioConfig, Any, Resources, int], AlgorithmConfig]
    # (built or restored algorithm, scenario, explore, seed) -> the decentralised policy for
    # evaluation: greedy (explore=False, the paper's execution) or sampled (explore=True). The
    # default runs the algorithm's own team-view RLModule (common/policy.py).
    make_policy: Callable[..., Policy] = _team_policy

    def policy(self, algo: Algorithm, scenario: ScenarioConfig, explore: bool = False, seed: int = 0) -> Policy:
        """Greedy (argmax per UAV) or, with explore=True, sampled execution of a trained algorithm."""
        return self.make_policy(algo, scenario, explore=explore, seed=seed)

    def greedy_policy(self, algo: Algorithm, scenario: ScenarioConfig) -> Policy:
        return self.policy(algo, scenario, explore=False)

    def algorithm_config(
        self, scenario: ScenarioConfig, hparams: Any, resources: Resources, seed: int
    ) -> AlgorithmConfig:
        """The trial's AlgorithmConfig from `build`, refused (ConfigError) when its learner cannot run
        `resources.learner_precision`: only a UavLoraLearner applies bfloat16 (docs/model.md#learner-precision),
        and a plugin's plain learner would otherwise train in float32 without a word."""
        from uavlora_rllib.algorithms.common.learner import UavLoraLearner

        config = self.build(scenario, hparams, resources, seed)
        if resources.learner_precision != "float32" and not issubclass(config.learner_class, UavLoraLearner):
            raise ConfigError(
                f"resources.learner_precision: {resources.learner_precision!r} needs a learner built on "
                f"common/learner.py's UavLoraLearner, and algorithm {self.name!r}'s "
                f"{config.learner_class.__name__} is not; allowed: 'float32'"
            )
        return config

    def check_trial(self, scenario: ScenarioConfig, hparams: Any, resources: Resources, seed: int) -> None:
        """Building the trial's AlgorithmConfig (not the algorithm): a plugin's own builder holds its checks."""
        self.algorithm_config(scenario, hparams, resources, seed)


_REGISTRY: dict[str, AlgorithmEntry] = {}
_SPECS: dict[str, AlgorithmSpec] = {}


def _defined_at(cls: type) -> tuple[str, str]:
    return (cls.__module__, cls.__qualname__)


def _checked_spec(name: str, hparams_cls: type, action_modes: Any, known: AlgorithmSpec | None) -> AlgorithmSpec:
    """The spec of a declaration or registration, or TypeError naming what is wrong with it (raised when
    the module is imported: a plugin's then fails in one line, grid.import_plugins): action modes a
    tuple of ScenarioConfig.action_mode values, a typed (pydantic dataclass) hyperparameter class whose
    defaults pass its own constraints, and a name that is neither a built-in's nor taken by another class."""
    where = f"algorithm {name!r}"
    allowed = typing.get_args(typing.get_type_hints(ScenarioConfig)["action_mode"])
    if isinstance(action_modes, str) or not action_modes or any(m not in allowed for m in action_modes):
        raise TypeError(f"{where}: action_modes must be a non-empty tuple of {list(allowed)}, got {action_modes!r}")
    if not (isinstance(hparams_cls, type) and is_pydantic_dataclass(hparams_cls)):
        raise TypeError(f"{where}: hparams_cls must be a pydantic dataclass (common/hparams.py), got {hparams_cls!r}")
    _check_owner(name, hparams_cls.__module__, HPARAMS_MODULES)
    # the same class defined again (its module imported anew) is the same algorithm; another class is not
    if known is not None and _defined_at(known.hparams_cls) != _defined_at(hparams_cls):
        raise TypeError(f"{where} is already taken by {known.hparams_cls.__module__}.{known.hparams_cls.__qualname__}")
    try:
        defaults = hparams_cls()
    except (TypeError, ValidationError):  # pydantic dataclasses raise ValidationError ("Field required")
        missing = [n for n, f in hparams_cls.__pydantic_fields__.items() if f.is_required()]
        raise TypeError(f"{where}: every hyperparameter needs a default; none for {', '.join(missing)}") from None
    # pydantic leaves defaults unchecked: a default outside its field's own constraints fails every grid
    build(hparams_cls, {f.name: getattr(defaults, f.name) for f in dataclasses.fields(hparams_cls)}, where)
    return AlgorithmSpec(name=name, hparams_cls=hparams_cls, action_modes=tuple(action_modes))


def declare(name: str, hparams_cls: type, action_modes: tuple[str, ...]) -> AlgorithmSpec:
    """Declare algorithm `name`'s typed hyperparameters and action modes (from its HPARAMS_MODULES module,
    or a plugin's module that imports neither Ray nor torch); TypeError or ConfigError when they are not
    usable (`_checked_spec`)."""
    _SPECS[name] = _checked_spec(name, hparams_cls, action_modes, _SPECS.get(name))
    return _SPECS[name]


def spec(name: str, path: str = "algorithm") -> AlgorithmSpec:
    """`name`'s hyperparameters and action modes, from its HPARAMS_MODULES module when it has one
    (no Ray, no torch), else from its registered entry (a plugin's: `get`)."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in HPARAMS_MODULES and name not in _SPECS:
        importlib.import_module(HPARAMS_MODULES[name])
    if name in _SPECS:
        return _SPECS[name]
    return get(name, path)


def _check_owner(name: str, module: str, owners: dict[str, str]) -> None:
    """A built-in's name is declared or registered by its own module (`owners`: HPARAMS_MODULES or MODULES)
    only: a plugin reusing its hyperparameter class (or subclassing its config) under that name would
    replace it silently."""
    if name in owners and owners[name].startswith("uavlora_rllib.algorithms.") and module != owners[name]:
        raise TypeError(f"algorithm {name!r} is built in; a plugin takes another name (built in: {built_in()})")


def register(entry: AlgorithmEntry) -> None:
    """Register `entry` under its name (checked as a declaration is: `_checked_spec`; a plain entry's
    owner is the module of its `build`)."""
    if entry.build.__module__ != __name__:  # register_algorithm's entries: checked there
        _check_owner(entry.name, entry.build.__module__, MODULES)
    _checked_spec(
        entry.name, entry.hparams_cls, entry.action_modes, _REGISTRY.get(entry.name) or _SPECS.get(entry.name)
    )
    _REGISTRY[entry.name] = entry


def register_algorithm(name: str, config_cls: type[Any], action_modes: tuple[str, ...] | None = None) -> AlgorithmEntry:
    """Register algorithm `name`, whose trials are `config_cls` (an `HParamsConfig`
    AlgorithmConfig) set up by `config.team_config`; returns its entry. Its action modes are
    those its HPARAMS_MODULES module declared (`declare`), or `action_modes` for a plugin without one."""

    def build(scenario: ScenarioConfig, hparams: Any, resources: Resources, seed: int) -> AlgorithmConfig:
        from uavlora_rllib.algorithms.common.config import team_config

        entry = get(name)
        entry.check_scenario(scenario)
        if not isinstance(hparams, entry.hparams_cls):
            hparams = entry.hparams(hparams)
        return team_config(config_cls(), name, scenario, hparams, resources, seed)

    _check_owner(name, config_cls.__module__, MODULES)
    declared = _SPECS.get(name)
    if declared is not None:
        if declared.hparams_cls is not config_cls.hparams_cls or action_modes is not None:
            raise TypeError(f"register_algorithm({name!r}): its hparams_cls and action modes are its declaration's")
        action_modes = declared.action_modes
    if action_modes is None:
        raise TypeError(f"register_algorithm({name!r}): action_modes needed (no declaration)")
    entry = AlgorithmEntry(name=name, hparams_cls=config_cls.hparams_cls, action_modes=tuple(action_modes), build=build)
    register(entry)
    return entry


def built_in() -> list[str]:
    """The algorithms this package implements, in MODULES' order (a plugin may add a line to MODULES,
    so MODULES alone is not the built-in set)."""
    return [name for name, module in MODULES.items() if module.startswith("uavlora_rllib.algorithms.")]


def available() -> list[str]:
    """Names whose module can be imported (implemented algorithms), then those imported plugins registered."""
    out = []
    for name, module in MODULES.items():
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            continue
        if name in _REGISTRY:
            out.append(name)
    return out + sorted(n for n in _REGISTRY if n not in out)


def check_registered(name: str, path: str) -> None:
    """ConfigError unless a trial of `name` can be built: a built-in (MODULES), or registered by a module
    imported so far (a plugin's); a plugin that only declares its hyperparameters would pass a dry run and
    fail in every trial."""
    if name not in MODULES and name not in _REGISTRY:
        get(name, path)


def known() -> list[str]:
    """Every name a grid may use now: the built-ins, and what plugins imported so far declared or registered."""
    return sorted(set(MODULES) | set(_REGISTRY) | set(_SPECS))


def get(name: str, path: str = "algorithm") -> AlgorithmEntry:
    """`name`'s registered entry: registered already (a plugin's, at its import), or by importing its MODULES module."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name not in MODULES:
        if name in _SPECS:
            raise ConfigError(
                f"{path}: algorithm {name!r} is declared (its hyperparameters) but no imported module registers "
                "it; list the module that calls register_algorithm or registry.register under plugins:"
            )
        raise ConfigError(f"{path}: unknown algorithm {name!r}; allowed: {known()}")
    if name not in _REGISTRY:
        try:
            importlib.import_module(MODULES[name])
        except ModuleNotFoundError as exc:
            if exc.name != MODULES[name]:
                raise
    if name not in _REGISTRY:
        raise ConfigError(f"{path}: algorithm {name!r} is not implemented yet; implemented: {available()}")
    return _REGISTRY[name]


def entry_for_algorithm(algo: Algorithm) -> AlgorithmEntry:
    """The registry entry of a built or restored algorithm (stored in its config)."""
    name = getattr(algo.config, "uavlora_algorithm", None) or algo.config.env_config.get("uavlora_algorithm")
    if name is None:
        raise ConfigError("checkpoint: not a uavlora_rllib algorithm (no 'uavlora_algorithm' in its env_config)")
    return get(name)
