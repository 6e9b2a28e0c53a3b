"""COMA (Foerster et al., AAAI 2018): counterfactual multi-agent policy gradients, as an RLlib
Algorithm on the new API stack, registered as "coma".

Sampling goes through the team view ("uavlora_team": observation [U, obs_dim], action
MultiDiscrete([90] * U), shared reward, global state in info["state"]); each env runner steps
N scenarios through one vectorised BatchCore. One training iteration:
  1. sample `batch_episodes` whole episodes (T = episode_len steps each) with the current
     policy (see `_sample_episodes` for why it asks for timesteps, not episodes),
  2. one learner update: critic TD(lambda) loss + counterfactual actor loss (coma_learner.py),
  3. target critic update (soft tau per update, or hard every K updates),
  4. sync the actor's weights to the env runners (inference-only: they never hold the critic).
Networks: coma_module.py. Hyperparameters: `COMAHParams` (grid YAML `algorithms.coma`).
Only the per_uav action mode is supported (the critic outputs one Q per action of a UAV,
which needs a single Discrete action per agent).

Choices beyond the paper (each a COMAHParams field, documented there): the critic trains
`critic_steps` = 4 extra steps on each batch before the joint actor + critic step (the paper
trains the critic first); TD(lambda) with lambda 0.8; the critic's lr is 5e-4; a dueling,
SF/TP/BW-factored Q head; per-UAV actor output layers. Evidence in tests/test_coma.py.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import tree
from pydantic import Field
from pydantic.dataclasses import dataclass as typed_dataclass
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig, NotProvided
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    SYNCH_WORKER_WEIGHTS_TIMER,
    TIMERS,
)

from uavlora_rllib.algorithms.coma.coma_learner import COMAEpisodeBatch, COMATorchLearner
from uavlora_rllib.algorithms.coma.coma_module import COMAActor, COMATorchRLModule
from uavlora_rllib.algorithms.common.recurrent_policy import RecurrentPolicy, argmax_actions
from uavlora_rllib.algorithms.common.registry import AlgorithmEntry, Resources, register
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig
from uavlora_rllib.envs.team import sample_through_team_env

NAME = "coma"


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class COMAHParams:
    """COMA's hyperparameters; defaults from SPEC.md's training table where it has them."""

    lr_actor: float = Field(1e-4, gt=0)  # Adam step size of the actor (SPEC: lr 1e-4)
    # Adam step size of the critic. SPEC's lr 1e-4 is the actor's; the critic must track the
    # changing policy within the paper's ~830 updates (2M steps / 2,400 per batch), so it
    # gets pymarl's COMA critic lr, 5e-4 (a decision, see the report / docs).
    lr_critic: float = Field(5e-4, gt=0)
    gamma: float = Field(0.99, gt=0, le=1)  # discount per slot
    td_lambda: float = Field(0.8, ge=0, le=1)  # lambda of the critic's TD(lambda) targets (Foerster et al.: 0.8)
    entropy_coeff: float = Field(0.01, ge=0)  # weight of the mean per-agent policy entropy (nats) in the actor loss
    grad_clip: float = Field(10.0, gt=0)  # max global L2 norm of the gradient, per optimizer (actor, critic)
    batch_episodes: int = Field(16, ge=1)  # whole episodes per update (SPEC: batch 16)
    tau: float = Field(0.01, gt=0, le=1)  # Polyak weight of the target critic per update (SPEC: 0.01)
    target_hard_update_every: int = Field(0, ge=0)  # > 0: hard copy every K updates instead of Polyak
    actor_hidden: int = Field(128, ge=1)  # width of the actor's ReLU layer before the GRU
    gru_hidden: int = Field(128, ge=1)  # GRU state size (SPEC: 128)
    # each UAV also gets its own linear output layer (added to the shared head's logits)
    actor_agent_heads: bool = True
    critic_hidden: tuple[int, ...] = (128, 128)  # ReLU layers of the critic MLP
    critic_use_obs: bool = True  # also give the critic UAV u's own observation row
    # use the (SF, TP, BW) structure of an action in the critic: the other UAVs' actions also
    # enter as one-hot SF/TP/BW, and u's 90 outputs share per-SF/TP/BW terms (coma_module.QHead)
    critic_factored_actions: bool = True
    # Q = V + (D - mean D) head (see coma_module.QHead): untried actions start at the state's value
    critic_dueling: bool = True
    # critic-only gradient steps on each batch before the joint critic + actor step (0: joint only)
    # 4: the critic sees each batch 5 times per update and goes first, as in the paper.
    critic_steps: int = Field(4, ge=0)
    # updates (batches) at the start that train the critic only (actor loss zeroed); 0 = off
    critic_warmup_updates: int = Field(0, ge=0)
    normalize_advantages: bool = False  # standardise A over the batch (not in COMA; off by default)
    reward_scale: float = Field(1.0, gt=0)  # rewards are multiplied by this in the critic targets


def _coma_learner_connector(obs_space, act_space) -> list:
    return [COMAEpisodeBatch()]


class COMAConfig(AlgorithmConfig):
    """AlgorithmConfig of COMA; `.coma(hparams)` sets its hyperparameters."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or COMA)
        self.coma_hparams: dict[str, Any] = dict(COMAHParams().__dict__)
        self.torch_threads = 1
        self.uavlora_algorithm = NAME
        self.batch_mode = "complete_episodes"
        self.add_default_connectors_to_learner_pipeline = False
        self._learner_connector = _coma_learner_connector
        self.coma(COMAHParams())

    def coma(self, hparams: COMAHParams | None = NotProvided, torch_threads: int = NotProvided) -> "COMAConfig":
        if hparams is not NotProvided:
            if not isinstance(hparams, COMAHParams):
                raise TypeError(f"hparams: expected COMAHParams, got {type(hparams).__name__}")
            hp = dict(hparams.__dict__)
            self.coma_hparams = hp
            self.gamma = hp["gamma"]
            self.lr = hp["lr_actor"]
            self.grad_clip = hp["grad_clip"]
            self.grad_clip_by = "global_norm"
            self.learner_config_dict = {**self.learner_config_dict, **hp}
        if torch_threads is not NotProvided:
            self.torch_threads = int(torch_threads)
        return self

    def get_default_rl_module_spec(self) -> RLModuleSpec:
        return RLModuleSpec(module_class=COMATorchRLModule)

    def get_default_learner_class(self):
        return COMATorchLearner

    def validate(self) -> None:
        super().validate()
        runners = max(1, self.num_env_runners)
        per_runner, rest = divmod(self.coma_hparams["batch_episodes"], runners)
        if rest or per_runner % self.num_envs_per_env_runner:
            raise ConfigError(
                f"algorithms.coma.batch_episodes: {self.coma_hparams['batch_episodes']} must split into whole rounds "
                f"of all envs: a multiple of num_env_runners ({runners}) x num_envs_per_env_runner "
                f"({self.num_envs_per_env_runner}); COMA learns from whole episodes only"
            )


class COMA(Algorithm):
    @classmethod
    def get_default_config(cls) -> COMAConfig:
        return COMAConfig()

    def setup(self, config) -> None:
        torch.set_num_threads(int(getattr(config, "torch_threads", 1) or 1))
        super().setup(config)

    def training_step(self) -> None:
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            episodes, runner_metrics = self._sample_episodes()
        self.metrics.aggregate(runner_metrics, key=ENV_RUNNER_RESULTS)
        self._log_episode_physics(episodes)

        with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
            learner_results = self.learner_group.update(
                episodes=episodes,
                timesteps={
                    NUM_ENV_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
                        (ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0
                    )
                },
            )
        self.metrics.aggregate(learner_results, key=LEARNER_RESULTS)

        with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
            self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group, inference_only=True)

    def _sample_episodes(self):
        """`batch_episodes` whole episodes, split evenly over the env runners.

        Asks each runner for (its episodes x T) TIMESTEPS rather than `num_episodes`: RLlib
        2.60's `sample(num_episodes=...)` re-resets every env with the runner's fixed seed on
        every call, which would replay the same scenarios in every iteration. All envs of a
        runner start together and every episode lasts exactly T steps (truncation), so
        (episodes per runner) x T timesteps end exactly at an episode boundary: the runner
        returns whole episodes only and continues with fresh seeds on the next call."""
        cfg = self.config
        runners = max(1, cfg.num_env_runners)
        steps = cfg.coma_hparams["batch_episodes"] // runners * self._episode_len
        out = self.env_runner_group.foreach_env_runner(
            lambda runner: (runner.sample(num_timesteps=steps, explore=True), runner.get_metrics()),
            local_env_runner=self.env_runner_group.num_remote_workers() <= 0,
        )
        episodes = [ep for ep in tree.flatten([o[0] for o in out]) if ep.is_done]
        return episodes, [o[1] for o in out]

    @property
    def _episode_len(self) -> int:
        return ScenarioConfig.from_dict(self.config.env_config["scenario"]).episode_len

    def _log_episode_physics(self, episodes) -> None:
        """Per-slot means over the sampled episodes of the paper's metrics (from the infos)."""
        ee, xi = [], []
        for ep in episodes:
            infos = ep.get_infos()[1:]  # infos[0] comes from reset (no slot played yet)
            ee.append(np.mean([i["ee_sys"] for i in infos if "ee_sys" in i]))
            xi.append(np.mean([i["success_rate"] for i in infos if "success_rate" in i]))
        if ee:
            self.metrics.log_value("ee_sys_mean", float(np.mean(ee)), window=1)
            self.metrics.log_value("success_rate", float(np.mean(xi)), window=1)
        self.metrics.log_value("num_episodes_trained", len(episodes), reduce="sum")


# ------------------------------------------------------------------ registry
def build(scenario: ScenarioConfig, hparams: COMAHParams | dict | None, resources: Resources, seed: int) -> COMAConfig:
    entry = ENTRY
    if not isinstance(hparams, COMAHParams):
        hparams = entry.hparams(hparams)
    entry.check_scenario(scenario)
    runners = max(1, resources.num_env_runners)
    if hparams.batch_episodes % (runners * resources.num_envs_per_env_runner):
        raise ConfigError(
            f"algorithms.coma.batch_episodes: {hparams.batch_episodes} is not a multiple of num_env_runners "
            f"({runners}) x num_envs_per_env_runner ({resources.num_envs_per_env_runner}); COMA learns from "
            "whole episodes, sampled in whole rounds of all envs"
        )
    return (
        sample_through_team_env(COMAConfig(), scenario, resources, NAME)
        .framework("torch")
        .learners(num_learners=0, num_cpus_per_learner=resources.num_cpus_per_learner)
        .training(train_batch_size_per_learner=hparams.batch_episodes * scenario.episode_len)
        .coma(hparams, torch_threads=resources.torch_threads)
        .rl_module(
            model_config={
                "state_dim": state_dim(scenario),
                "actor_hidden": hparams.actor_hidden,
                "gru_hidden": hparams.gru_hidden,
                "actor_agent_heads": hparams.actor_agent_heads,
                "critic_hidden": list(hparams.critic_hidden),
                "critic_use_obs": hparams.critic_use_obs,
                "critic_dueling": hparams.critic_dueling,
                "action_factors": (
                    [scenario.n_sf, scenario.n_tp, scenario.n_bw] if hparams.critic_factored_actions else []
                ),
                "torch_threads": resources.torch_threads,
            }
        )
        .debugging(seed=seed)
    )


class COMAGreedyPolicy(RecurrentPolicy):
    """evaluation.Policy: a CPU copy of the trained actor, argmax actions, GRU state per episode.

    `sample_seed` given: sample from the policy instead (the stochastic policy COMA trains),
    from a torch Generator seeded with it; used for diagnostics, not by the registry."""

    def __init__(self, actor: COMAActor, cfg: ScenarioConfig, name: str = NAME, sample_seed: int | None = None):
        pick = argmax_actions if sample_seed is None else _sampler(torch.Generator().manual_seed(sample_seed))
        super().__init__(actor, pick, actor.initial_state, name)
        self.actor, self.cfg = actor, cfg


def _sampler(gen: torch.Generator):
    def pick(logits: torch.Tensor) -> torch.Tensor:
        probs = torch.softmax(logits, dim=-1).reshape(-1, logits.shape[-1])
        return torch.multinomial(probs, 1, generator=gen).reshape(logits.shape[:-1])

    return pick


def actor_from_algo(algo: Algorithm, scenario: ScenarioConfig) -> COMAActor:
    """A CPU copy of the actor with the learner's weights (current after training and restore)."""
    state = algo.learner_group.get_state(components="learner/rl_module")["learner"]["rl_module"]
    weights = next(iter(state.values()))
    mc = algo.config.model_config
    actor = COMAActor(
        obs_dim(scenario),
        scenario.n_uavs,
        scenario.n_joint_actions,
        int(mc["actor_hidden"]),
        int(mc["gru_hidden"]),
        bool(mc.get("actor_agent_heads", False)),
    )
    prefix = "actor."
    actor.load_state_dict({k[len(prefix) :]: torch.as_tensor(v) for k, v in weights.items() if k.startswith(prefix)})
    return actor


def greedy_policy(algo: Algorithm, scenario: ScenarioConfig) -> COMAGreedyPolicy:
    return COMAGreedyPolicy(actor_from_algo(algo, scenario), scenario)


ENTRY = AlgorithmEntry(
    name=NAME, hparams_cls=COMAHParams, action_modes=("per_uav",), build=build, greedy_policy=greedy_policy
)
register(ENTRY)
