"""Hyperparameter sweeps in the grid YAML: Tune search spaces, a scheduler, a search algorithm.

Any algorithm hyperparameter may be a Tune search space instead of one value::

    algorithms:
      mappo:
        lr: {loguniform: [1.0e-5, 1.0e-3]}      # float fields: uniform, loguniform
        entropy_coeff: {choice: [0.0, 0.001, 0.01]}
        num_epochs: {randint: [5, 16]}          # int fields: lo <= x < hi (Ray Tune's randint)
        share_actor: {grid_search: [true, false]}  # every value, one trial each

and the grid may name a scheduler and a search algorithm, with `num_samples`::

    num_samples: 8                 # samples of the spaces per grid point (default 1)
    scheduler: {type: asha, grace_period: 20000, reduction_factor: 3}
    search_alg: {type: optuna, seed: 0}

Every candidate and bound is validated against the field's type and range when the grid is
loaded, with the algorithm's other (fixed) hyperparameters, so a bad sweep is one line and exit
code 2 before Ray starts (`split_overrides`).

The metric of every scheduler and search algorithm is the periodic greedy evaluation,
`eval/ee_sys_mean` (mode max), never the training return (which is the exploring policy's,
see experiment/periodic_eval.py). Tune reads a scheduler's metric from every result, and the
greedy policy is evaluated only every `evaluation.interval_env_steps`, so the trainable reports
the latest evaluation in every result as `SWEEP_METRIC` (``eval_latest/ee_sys_mean``, not
logged to MLflow: the ``eval/ee_sys_mean`` series there keeps one point per evaluation). A
scheduler or search algorithm therefore needs periodic evaluation (`evaluation.interval_env_steps`
not 0), and its intervals are in env steps (Tune's `time_attr` is the trial's env-step count).

What each combination may grid over (`check_sweep`): a scheduler compares trials of one
scenario, so it needs one `n_eds` and one `n_uavs` (the EE of different scenarios is not
comparable); PBT copies checkpoints between trials, so it also needs one algorithm; a search
algorithm suggests one configuration per trial and cannot expand a grid, so it needs one
algorithm, one seed, one `n_eds`, one `n_uavs`, and no `grid_search` space (use `choice`).

Ray Tune itself is imported only when the Tuner is built (`tune_space`, `make_scheduler`,
`make_search_alg`), so `--dry-run` and `--help` stay fast.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.config_errors import ConfigError, build

SPACE_KINDS = ("grid_search", "choice", "uniform", "loguniform", "randint")
METRIC = "eval/ee_sys_mean"  # what every scheduler and search algorithm maximises
SWEEP_METRIC = "eval_latest/ee_sys_mean"  # the latest METRIC, in every result (module docstring)
MODE = "max"
TIME_ATTR = "env_steps"  # run_schema.ENV_STEPS: the schedulers' clock
HPARAM_PREFIX = "hparam/"  # result / MLflow metric of a sampled hyperparameter's current value
MAX_CHECKED_COMBINATIONS = 64  # combinations of sampled values checked together at load time

_STRICT = ConfigDict(extra="forbid", frozen=True)
EnvSteps = Annotated[int, Field(ge=1, le=10**12)]


# --------------------------------------------------------------------------- search spaces
@dataclass(frozen=True)
class SearchSpace:
    """One hyperparameter's search space, validated (`parse_space`)."""

    kind: str  # one of SPACE_KINDS
    values: tuple  # the candidates (grid_search, choice) or the bounds [lo, hi]

    @property
    def representatives(self) -> tuple:
        """The values checked against the hyperparameter class: every candidate, or the bounds
        (randint's upper bound is exclusive)."""
        if self.kind == "randint":
            return (self.values[0], self.values[1] - 1)
        return self.values

    def describe(self) -> str:
        return f"{self.kind}{list(self.values)}"

    def to_tune(self) -> Any:
        from ray import tune

        if self.kind == "grid_search":
            return tune.grid_search(list(self.values))
        if self.kind == "choice":
            return tune.choice(list(self.values))
        return getattr(tune, self.kind)(*self.values)

    def to_mutation(self) -> Any:
        """PBT's `hyperparam_mutations` entry: a list (shifted or resampled) or a Domain."""
        if self.kind in ("grid_search", "choice"):
            return list(self.values)
        return self.to_tune()


def _base_type(hint: Any) -> Any:
    """float / int / bool / other of a field annotation (Annotated and `| None` removed)."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Annotated:
        return _base_type(args[0])
    if origin in (typing.Union, types.UnionType):
        options = [a for a in args if a is not type(None)]
        if len(options) == 1:
            return _base_type(options[0])
        if set(options) <= {int, float}:
            return float
        return object
    return hint


def is_space(value: Any, hint: Any) -> bool:
    """Whether a hyperparameter's YAML value is meant as a search space: a one-key mapping given
    for a field that is not itself a mapping."""
    base = _base_type(hint)
    return isinstance(value, Mapping) and base is not dict and typing.get_origin(base) is not dict


def _check_value(hparams_cls: type, fixed: Mapping[str, Any], name: str, value: Any, where: str, prefix: str) -> None:
    """`value` for field `name`, with the fixed hyperparameters, builds; else ConfigError at `where`."""
    field_path = f"{prefix}.{name}"
    try:
        build(hparams_cls, {**fixed, name: value}, prefix)
    except ConfigError as exc:
        text = str(exc)
        if text.startswith(f"{field_path}:"):
            raise ConfigError(f"{where}:{text[len(field_path) + 1 :]}") from None
        raise ConfigError(f"{text} (with {where} = {value!r})") from None


def parse_space(hparams_cls: type, fixed: Mapping[str, Any], name: str, spec: Mapping, prefix: str) -> SearchSpace:
    """A YAML search space for field `name` -> SearchSpace; ConfigError naming the bad part."""
    path = f"{prefix}.{name}"
    allowed = ", ".join(SPACE_KINDS)
    if len(spec) != 1:
        raise ConfigError(f"{path}: a search space is a mapping with one key, one of {allowed}; got {dict(spec)!r}")
    kind, arg = next(iter(spec.items()))
    if kind not in SPACE_KINDS:
        raise ConfigError(f"{path}: unknown search space {kind!r}; allowed: {allowed}")
    where = f"{path}.{kind}"
    hint = typing.cast(Any, hparams_cls).__pydantic_fields__[name].annotation
    base = _base_type(hint)
    if not isinstance(arg, list):
        shape = "a list of candidate values" if kind in ("grid_search", "choice") else "a list [lo, hi]"
        raise ConfigError(f"{where}: expected {shape}, got {arg!r}")
    if kind in ("grid_search", "choice"):
        if not arg:
            raise ConfigError(f"{where}: expected a non-empty list of candidate values, got []")
        seen: list[Any] = []
        for i, value in enumerate(arg):
            if any(type(value) is type(s) and value == s for s in seen):
                raise ConfigError(f"{where}.{i}: values must be distinct, repeated: {value!r}")
            seen.append(value)
            _check_value(hparams_cls, fixed, name, value, f"{where}.{i}", prefix)
        return SearchSpace(kind, tuple(arg))
    # ranges
    if kind == "randint":
        if base is not int:
            raise ConfigError(
                f"{where}: randint samples integers and {path} is {_type_name(base)}; "
                "allowed: uniform or loguniform (float fields), choice or grid_search (any field)"
            )
    elif base is not float:
        raise ConfigError(
            f"{where}: {kind} samples floats and {path} is {_type_name(base)}; allowed: "
            f"{'randint, ' if base is int else ''}choice or grid_search"
        )
    if len(arg) != 2:
        raise ConfigError(f"{where}: expected a list [lo, hi] of two numbers, got {arg!r}")
    for i, value in enumerate(arg):
        _check_value(hparams_cls, fixed, name, value, f"{where}.{i}", prefix)
    lo, hi = arg
    if kind == "randint":
        if not hi > lo:
            raise ConfigError(
                f"{where}: expected lo < hi (randint samples lo <= x < hi, as Ray Tune's), got [{lo}, {hi}]"
            )
        _check_value(hparams_cls, fixed, name, hi - 1, f"{where}.1", prefix)  # the largest sample
    elif not hi > lo:
        raise ConfigError(f"{where}: expected lo < hi, got [{lo!r}, {hi!r}]")
    if kind == "loguniform" and not lo > 0:
        raise ConfigError(f"{where}.0: loguniform needs a lower bound > 0, got {lo!r}")
    return SearchSpace(kind, (float(lo), float(hi)) if kind != "randint" else (int(lo), int(hi)))


def _type_name(base: Any) -> str:
    if base is float:
        return "a float field"
    if base is int:
        return "an integer field"
    if base is bool:
        return "a true/false field"
    return "not numeric"


def split_overrides(hparams_cls: type, overrides: Mapping[str, Any] | None, prefix: str) -> tuple[dict, dict]:
    """An algorithm's YAML overrides -> (fixed values, {name: SearchSpace}); every space is
    validated, and combinations of the sampled values (up to MAX_CHECKED_COMBINATIONS of
    candidates and bounds) are built together with the fixed values."""
    overrides = dict(overrides or {})
    fields = getattr(hparams_cls, "__pydantic_fields__", {})
    fixed = {k: v for k, v in overrides.items() if not (k in fields and is_space(v, fields[k].annotation))}
    build(hparams_cls, fixed, prefix)  # unknown fields, bad fixed values, cross-field checks
    spaces = {k: parse_space(hparams_cls, fixed, k, v, prefix) for k, v in overrides.items() if k not in fixed}
    for combo in representative_combinations(spaces):
        if len(combo) < 2:
            break  # one sampled field: every candidate was built with the fixed values already
        try:
            build(hparams_cls, {**fixed, **combo}, prefix)
        except ConfigError as exc:
            together = ", ".join(f"{k}={v!r}" for k, v in combo.items())
            raise ConfigError(f"{exc} (sampled together: {together})") from None
    return fixed, spaces


def representative_combinations(spaces: Mapping[str, SearchSpace]) -> list[dict[str, Any]]:
    """Combinations of every space's candidates / bounds (at most MAX_CHECKED_COMBINATIONS)."""
    if not spaces:
        return [{}]
    names = list(spaces)
    combos = itertools.islice(itertools.product(*(spaces[n].representatives for n in names)), MAX_CHECKED_COMBINATIONS)
    return [dict(zip(names, c)) for c in combos]


def grid_search_size(spaces: Mapping[str, SearchSpace]) -> int:
    """Trials per sample of one grid point: the product of the grid_search spaces' sizes."""
    return math.prod(len(s.values) for s in spaces.values() if s.kind == "grid_search")


# --------------------------------------------------------------------------- scheduler, search algorithm
@typed_dataclass(config=_STRICT)
class SchedulerConfig:
    """Grid YAML `scheduler:`. Intervals are env steps; null: 2 x the periodic-evaluation interval."""

    type: Literal["asha", "pbt", "median_stopping"]
    # asha and median_stopping: env steps before a trial can be stopped
    grace_period: EnvSteps | None = None
    # asha: keep 1/reduction_factor of the trials at each rung
    reduction_factor: float = Field(default=3.0, gt=1, le=100)
    # asha: number of brackets (Hyperband's)
    brackets: int = Field(default=1, ge=1, le=10)
    # median_stopping: trials compared before one is stopped
    min_samples_required: int = Field(default=3, ge=1, le=100_000)
    # median_stopping: true stops a trial below the median, false pauses it
    hard_stop: bool = True
    # pbt: env steps between exploit/explore steps of a trial
    perturbation_interval: EnvSteps | None = None
    # pbt: env steps before the first perturbation
    burn_in_period: int = Field(default=0, ge=0, le=10**12)
    # pbt: share of the population in the bottom (copies) and top (is copied) quantiles
    quantile_fraction: float = Field(default=0.25, gt=0, le=0.5)
    # pbt: probability of resampling a mutated value from its space instead of perturbing it
    resample_probability: float = Field(default=0.25, ge=0, le=1)
    # pbt: the factors a continuous value is multiplied by (then clamped into its space)
    perturbation_factors: tuple[float, float] = (1.2, 0.8)
    # pbt: perturb all trials together at each interval (synchronous PBT)
    synch: bool = False

    def check(self, grid: Any, interval: int, prefix: str = "scheduler") -> None:
        """Options that only apply to another scheduler, and intervals shorter than the
        periodic evaluation's (the metric would not have been measured again)."""
        own = {
            "asha": {"grace_period", "reduction_factor", "brackets"},
            "median_stopping": {"grace_period", "min_samples_required", "hard_stop"},
            "pbt": {
                "perturbation_interval",
                "burn_in_period",
                "quantile_fraction",
                "resample_probability",
                "perturbation_factors",
                "synch",
            },
        }
        defaults = SchedulerConfig(type=self.type)
        for f in dataclasses.fields(self):
            if f.name != "type" and f.name not in own[self.type] and getattr(self, f.name) != getattr(defaults, f.name):
                users = [k for k, v in own.items() if f.name in v]
                raise ConfigError(
                    f"{prefix}.{f.name}: an option of {' and '.join(users)}, not of {self.type}; "
                    f"allowed for {self.type}: {', '.join(sorted(own[self.type]))}"
                )
        for name in ("grace_period", "perturbation_interval"):
            value = getattr(self, name)
            if value is not None and name in own[self.type] and value < interval:
                raise ConfigError(
                    f"{prefix}.{name}: {value} env steps is shorter than the periodic evaluation interval "
                    f"({interval} env steps, evaluation.interval_env_steps), so the metric {METRIC} would not "
                    f"be measured again in between; allowed: at least {interval}"
                )
        if self.type == "pbt" and any(not (0 < f < 10) for f in self.perturbation_factors):
            raise ConfigError(
                f"{prefix}.perturbation_factors: expected two factors in (0, 10), got {list(self.perturbation_factors)}"
            )

    def interval(self, eval_interval: int) -> int:
        value = self.perturbation_interval if self.type == "pbt" else self.grace_period
        return int(value) if value is not None else 2 * eval_interval


@typed_dataclass(config=_STRICT)
class SearchAlgConfig:
    """Grid YAML `search_alg:`: Ray Tune's OptunaSearch."""

    type: Literal["optuna"]
    # optuna's sampler: tpe (TPESampler), random (RandomSampler), cmaes (CmaEsSampler)
    sampler: Literal["tpe", "random", "cmaes"] = "tpe"
    # the sampler's seed (null: unseeded)
    seed: int | None = Field(default=None, ge=0, le=2**32 - 1)


def check_sweep(grid: Any, spaces: Mapping[str, Mapping[str, SearchSpace]], interval: int) -> None:
    """Cross-field checks of a sweep (see the module docstring); `spaces`: algorithm -> spaces."""
    needs_metric = [k for k in ("scheduler", "search_alg") if getattr(grid, k) is not None]
    if needs_metric and interval < 1:
        raise ConfigError(
            f"{needs_metric[0]}: needs periodic evaluation of the greedy policy (its metric is {METRIC}); "
            "evaluation.interval_env_steps is 0; allowed: null (budget / 20) or a positive number of env steps"
        )
    # a scheduler acts on the metric during a trial (a search algorithm only reads the final evaluation's)
    if grid.scheduler is not None and interval >= grid.stop.env_steps:
        raise ConfigError(
            f"evaluation.interval_env_steps: {interval} is not below stop.env_steps ({grid.stop.env_steps}), so "
            f"the scheduler never sees {METRIC} before a trial ends; allowed: null (budget / 20) or fewer "
            "env steps than the budget"
        )
    if grid.num_samples > 1 and not any(spaces.values()) and grid.search_alg is None:
        raise ConfigError(
            f"num_samples: {grid.num_samples} samples of a grid with no search space are {grid.num_samples} identical "
            "trials; allowed: 1, or give search spaces (e.g. algorithms.<algo>.lr: {loguniform: [1.0e-5, 1.0e-3]}), "
            "or more seeds"
        )
    if grid.scheduler is not None:
        grid.scheduler.check(grid, interval)
        _single(
            grid,
            "scheduler",
            ("n_eds", "n_uavs") + (("algorithms",) if grid.scheduler.type == "pbt" else ()),
            "it compares trials" if grid.scheduler.type != "pbt" else "it copies checkpoints between trials",
        )
        if grid.scheduler.type == "pbt" and not any(spaces.values()):
            raise ConfigError(
                "scheduler: pbt mutates the hyperparameters given as search spaces, and the grid has none; "
                "allowed: e.g. algorithms.<algo>.lr: {loguniform: [1.0e-5, 1.0e-3]}"
            )
    if grid.search_alg is not None:
        _single(
            grid,
            "search_alg",
            ("algorithms", "seeds", "n_eds", "n_uavs"),
            "it suggests one configuration per trial and cannot expand a grid",
        )
        for algo, algo_spaces in spaces.items():
            for name, space in algo_spaces.items():
                if space.kind == "grid_search":
                    raise ConfigError(
                        f"algorithms.{algo}.{name}.grid_search: {grid.search_alg.type} cannot sample a "
                        "grid_search; allowed: choice, uniform, loguniform, randint"
                    )
        if not any(spaces.values()):
            raise ConfigError(
                f"search_alg: {grid.search_alg.type} needs at least one search space and the grid has "
                "none; allowed: e.g. algorithms.<algo>.lr: {loguniform: [1.0e-5, 1.0e-3]}"
            )


def _single(grid: Any, what: str, keys: tuple[str, ...], why: str) -> None:
    for key in keys:
        n = len(getattr(grid, key))
        if n != 1:
            raise ConfigError(
                f"{key}: {what} {getattr(grid, what).type} needs exactly one value here ({why}), "
                f"got {n}; sweep the others in separate grids"
            )


# --------------------------------------------------------------------------- Tune objects
def make_scheduler(grid: Any, spaces: Mapping[str, SearchSpace], eval_interval: int):
    """The Tune scheduler of `grid.scheduler` (None: FIFO)."""
    s = grid.scheduler
    if s is None:
        return None
    from ray.tune import schedulers

    interval = s.interval(eval_interval)
    common = {"time_attr": TIME_ATTR, "metric": SWEEP_METRIC, "mode": MODE}
    if s.type == "asha":
        return schedulers.ASHAScheduler(
            max_t=grid.stop.env_steps,
            grace_period=min(interval, grid.stop.env_steps),
            reduction_factor=s.reduction_factor,
            brackets=s.brackets,
            **common,
        )
    if s.type == "median_stopping":
        return schedulers.MedianStoppingRule(
            grace_period=interval, min_samples_required=s.min_samples_required, hard_stop=s.hard_stop, **common
        )
    pbt = {
        "perturbation_interval": interval,
        "burn_in_period": s.burn_in_period,
        "hyperparam_mutations": {"trial": {"overrides": {k: v.to_mutation() for k, v in spaces.items()}}},
        "quantile_fraction": s.quantile_fraction,
        "resample_probability": s.resample_probability,
        "perturbation_factors": tuple(s.perturbation_factors),
        "custom_explore_fn": ClampToSpaces(spaces),
        **common,
    }
    if s.synch:  # Ray's, less a race that stops a trial early (experiment/synch_pbt.py)
        from uavlora_rllib.experiment.synch_pbt import SynchronousPBT

        return SynchronousPBT(**pbt)
    return schedulers.PopulationBasedTraining(synch=False, **pbt)


class ClampToSpaces:
    """PBT's custom_explore_fn: a perturbed value (x 1.2, x 0.8) stays inside its space's bounds,
    so a mutated trial never leaves the range the grid validated."""

    def __init__(self, spaces: Mapping[str, SearchSpace]):
        self.bounds = {
            k: s.representatives for k, s in spaces.items() if s.kind in ("uniform", "loguniform", "randint")
        }

    def __call__(self, config: dict) -> dict:
        overrides = config.get("trial", {}).get("overrides", {})
        for name, (lo, hi) in self.bounds.items():
            if name in overrides:
                value = min(max(overrides[name], lo), hi)
                overrides[name] = int(value) if isinstance(lo, int) else float(value)
        return config


def make_search_alg(grid: Any):
    """Tune's OptunaSearch for `grid.search_alg` (None: Tune's grid / random variant generator)."""
    s = grid.search_alg
    if s is None:
        return None
    import optuna
    from ray.tune.search.optuna import OptunaSearch

    sampler = {
        "tpe": lambda: optuna.samplers.TPESampler(seed=s.seed),
        "random": lambda: optuna.samplers.RandomSampler(seed=s.seed),
        "cmaes": lambda: optuna.samplers.CmaEsSampler(seed=s.seed),
    }[s.sampler]()
    return OptunaSearch(metric=SWEEP_METRIC, mode=MODE, sampler=sampler)


def sampled_values(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A resolved trial config's sampled hyperparameters: {name: value}."""
    overrides = cfg.get("overrides") or {}
    return {k: overrides[k] for k in cfg.get("sampled", ()) if k in overrides}


def variant_label(values: Mapping[str, Any]) -> str:
    """'lr=0.000316,entropy_coeff=0.01': a trial's sampled values, short (names, report)."""

    def show(v: Any) -> str:
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    return ",".join(f"{k}={show(v)}" for k, v in sorted(values.items()))
