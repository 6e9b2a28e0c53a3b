"""How an algorithm's hyperparameters are declared, checked, listed and handed to RLlib.

The convention every algorithm follows:

* ONE typed config class, a pydantic dataclass (`MAPPOHParams`, `QMIXHParams`,
  `COMAHParams`) whose every field is `Field(default=default, description="what it does [unit]")`.
  It lives in the algorithm's `hparams.py` (no Ray, no torch: common/hparams.py). The description is
  the documentation: `python -m uavlora_rllib.tune --list-hparams ALGO` prints it with the default
  (see `hparams.describe_hparams`). Checks between its own fields: a
  pydantic `model_validator`. Checks against the scenario and the trial's resources: its
  `check(scenario, resources, path)` method (raises ConfigError naming the field). Each
  check lives in exactly one of those two places.
* ONE way into RLlib: the algorithm's AlgorithmConfig subclass mixes in `HParamsConfig` and
  implements `apply_hparams`, which sets the fields RLlib's own machinery reads (lr, gamma,
  batch sizes, grad_clip, ...), and, where it samples differently from RLlib's defaults,
  `env_runner_settings`. `team_config` builds every trial's config the same way: team env,
  resources, `config.uavlora(hparams, scenario, torch_threads, learner_precision)` (the typed object is kept as
  `config.hparams`, where learners read it; its fields plus the scenario's dimensions become
  the RLModule's model_config, so a module reads every setting as `model_config[name]` and
  states no default of its own), the episode-metric callbacks and the seed.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar

from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.metrics import log_episode_metrics
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig


def module_dims(scenario: ScenarioConfig) -> dict[str, int]:
    """The scenario's sizes an RLModule needs beyond its spaces (the global state's width)."""
    return {
        "n_agents": scenario.n_uavs,
        "obs_dim": obs_dim(scenario),
        "state_dim": state_dim(scenario),
        "n_actions": scenario.n_joint_actions,
    }


class HParamsConfig(abc.ABC):
    """Mixin for an AlgorithmConfig: the one way a typed hyperparameter object reaches RLlib."""

    hparams_cls: ClassVar[type[Any]]  # the typed hyperparameters
    module_class: ClassVar[type]  # the algorithm's RLModule
    learner_class: ClassVar[type]  # the algorithm's Learner
    rl_module: Any  # AlgorithmConfig.rl_module (this class is its mixin)

    @override(AlgorithmConfig)
    def get_default_rl_module_spec(self) -> RLModuleSpec:
        return RLModuleSpec(module_class=self.module_class)

    @property
    @override(AlgorithmConfig)
    def _model_config_auto_includes(self) -> dict[str, Any]:
        """The typed class's defaults, under the model_config a trial sets (`uavlora`): a config
        restored from a checkpoint made before a field existed gets that field's default, which by
        convention is the former behaviour, so the module can still read every setting as
        `model_config[name]` (RLlib merges these under `_model_config`, as PPOConfig does)."""
        return {
            **super()._model_config_auto_includes,  # type: ignore[misc]
            **dataclasses.asdict(self.hparams_cls()),
            "learner_precision": "float32",  # Resources' default (checkpoints made before it existed)
        }

    @override(AlgorithmConfig)
    def get_default_learner_class(self) -> type:
        return self.learner_class

    def uavlora(
        self, hparams: Any, scenario: ScenarioConfig, torch_threads: int = 1, learner_precision: str = "float32"
    ) -> Any:
        if not isinstance(hparams, self.hparams_cls):
            raise TypeError(f"hparams: expected {self.hparams_cls.__name__}, got {type(hparams).__name__}")
        self.hparams = hparams
        self.torch_threads = int(torch_threads)
        resolved = self.apply_hparams(hparams, scenario) or {}
        self.rl_module(
            model_config={
                **module_dims(scenario),
                **dataclasses.asdict(hparams),
                **resolved,
                "torch_threads": self.torch_threads,
                "learner_precision": learner_precision,  # read by the learner (common/learner.py)
            }
        )
        return self

    @abc.abstractmethod
    def apply_hparams(self, hparams: Any, scenario: ScenarioConfig) -> dict[str, Any] | None:
        """Set the AlgorithmConfig fields that RLlib itself reads from `hparams`; return the
        model_config entries the algorithm resolves itself (e.g. a default that depends on it)."""

    def env_runner_settings(self, scenario: ScenarioConfig) -> dict[str, Any]:
        """`AlgorithmConfig.env_runners` arguments of this algorithm's sampling (fragment
        length, batch mode) beyond the trial's resources; none: RLlib's defaults. Connector
        arguments given here replace the team view's (docs/model.md#acting-connectors)."""
        return {}


def apply_resources(config: Any, resources: Any) -> Any:
    """The learner side of a trial's `registry.Resources` (env runners: `sample_through_team_env`)."""
    return config.learners(
        num_learners=resources.num_learners,
        num_gpus_per_learner=resources.num_gpus_per_learner,
        num_cpus_per_learner=resources.num_cpus_per_learner,
    )


def team_config(config: Any, name: str, scenario: ScenarioConfig, hparams: Any, resources: Any, seed: int) -> Any:
    """`config` (a fresh HParamsConfig AlgorithmConfig) set up for one trial of algorithm `name`."""
    from uavlora_rllib.envs.team import sample_through_team_env

    registry.check_hparams(hparams, scenario, resources, f"algorithms.{name}")
    settings = config.env_runner_settings(scenario)
    config = sample_through_team_env(config, scenario, resources, name, **settings).framework("torch")
    config = apply_resources(config, resources).uavlora(
        hparams, scenario, torch_threads=resources.torch_threads, learner_precision=resources.learner_precision
    )
    return log_episode_metrics(config).debugging(seed=seed)


def hparams_model_config(hparams_cls: type, **entries: Any) -> dict[str, Any]:
    """The model_config of an RLModule built without an AlgorithmConfig (tests): the typed
    hyperparameter class's defaults, one torch thread, then `entries` (the scenario's sizes
    and the entries the algorithm's `apply_hparams` resolves)."""
    return {**dataclasses.asdict(hparams_cls()), "torch_threads": 1, "learner_precision": "float32", **entries}
