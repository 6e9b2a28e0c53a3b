"""COMA (Foerster et al., AAAI 2018): counterfactual multi-agent policy gradients, as an RLlib
Algorithm on the new API stack, registered as "coma".

Sampling goes through the team view ("uavlora_team": observation [U, obs_dim], action
MultiDiscrete([90] * U) per_uav or [U, 2 quota + 1] per_device, shared reward, global state in
info["state"]); each env runner steps
N scenarios through one vectorised BatchCore. One training iteration (the common
`EpisodeAlgorithm` loop):
  1. sample `batch_episodes` whole episodes (T = episode_len steps each) with the current
     policy; they are the train batch (`coma_learner.episode_batch`),
  2. `updates_per_iteration` updates on that batch, each: `critic_steps` critic-only steps
     (`COMATorchLearner.train_critic`), then one learner update with the critic's TD(lambda)
     loss + the counterfactual actor loss (coma_learner.py), then the target critic's move
     (soft tau per update, or hard every K updates),
  3. sync the actor's weights to the env runners (inference-only: they never hold the critic).
Networks: coma_module.py. Hyperparameters: `COMAHParams` (grid YAML `algorithms.coma`,
`--list-hparams coma`). Execution (common/policy.py): greedy = argmax of each UAV's actor
logits; sampled = a draw from the actor's softmax, the stochastic policy COMA trains.
Both action modes: per_uav (the critic outputs one Q per action of a UAV) and per_device, a
factored policy with a per-branch counterfactual baseline (branching.py,
docs/model.md#coma-per-device).

Choices beyond the paper (each a COMAHParams field, documented there): the critic trains
`critic_steps` = 4 extra steps on each batch before the joint actor + critic step (the paper
trains the critic first); TD(lambda) with lambda 0.8; the critic's lr is 5e-4; a dueling,
SF/TP/BW-factored Q head; per-UAV actor output layers.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field
from pydantic.dataclasses import dataclass as typed_dataclass
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.coma.coma_learner import COMATorchLearner, episode_batch
from uavlora_rllib.algorithms.coma.coma_module import COMATorchRLModule
from uavlora_rllib.algorithms.common.config import ActorHeads, HParamsConfig, check_actor_heads, check_per_ed_heads
from uavlora_rllib.algorithms.common.episode_algorithm import EpisodeAlgorithm
from uavlora_rllib.algorithms.common.registry import Resources, register_algorithm
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

NAME = "coma"


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class COMAHParams:
    """COMA's hyperparameters; defaults from the paper's training table where it has them."""

    lr_actor: float = Field(
        default=1e-4, gt=0, le=1, description="Adam step size of the actor [1/update] (paper: lr 1e-4)"
    )
    lr_critic: float = Field(
        default=5e-4,
        gt=0,
        le=1,
        description="Adam step size of the critic [1/update] (pymarl's COMA critic lr; the paper's 1e-4 is the "
        "actor's)",
    )
    gamma: float = Field(
        default=0.99, ge=0, le=1, description="discount per slot [-]; 0: the critic regresses the slot's reward alone"
    )
    td_lambda: float = Field(
        default=0.8, ge=0, le=1, description="lambda of the critic's TD(lambda) targets [-] (Foerster et al.)"
    )
    entropy_coeff: float = Field(
        default=0.01, ge=0, description="weight of the mean per-agent policy entropy in the actor loss [1/nat]"
    )
    grad_clip: float = Field(
        default=10.0, gt=0, description="max global L2 gradient norm, per optimizer (actor, critic) [-]"
    )
    batch_episodes: int = Field(
        default=16, ge=1, description="whole episodes per update [episodes] (paper: batch 16); a multiple of all envs"
    )
    tau: float = Field(
        default=0.01, gt=0, le=1, description="Polyak weight of the target critic per update [-] (paper)"
    )
    target_hard_update_every: int = Field(
        default=0, ge=0, description="> 0: hard target copy every K updates instead of Polyak [updates]"
    )
    actor_hidden: int = Field(default=128, ge=1, description="width of the actor's ReLU layer before the GRU [units]")
    gru_hidden: int = Field(default=128, ge=1, description="GRU width of the actor [units] (paper)")
    share_actor: bool = Field(
        default=True,
        description="one actor for all UAVs (+ agent-id one-hot) [bool]; false: one actor per UAV, batched "
        "(docs/model.md#batched-agent-networks)",
    )
    actor_agent_heads: bool = Field(
        default=True,
        description="with share_actor=true: each UAV also gets its own linear output layer, added to the shared one [bool]",
    )
    actor_heads: ActorHeads = "flat"
    critic_hidden: tuple[int, ...] = Field(
        default=(128, 128), description="ReLU layer widths of the critic MLP [units]"
    )
    critic_use_obs: bool = Field(default=True, description="also give the critic UAV u's own observation row [bool]")
    critic_factored_actions: bool = Field(
        default=True,
        description="per_uav: use the (SF, TP, BW) structure of an action in the critic: other UAVs' actions "
        "also as one-hot SF/TP/BW, and u's outputs share per-SF/TP/BW terms [bool] (per_device actions are "
        "factored already: no effect there, docs/model.md#coma-per-device)",
    )
    critic_dueling: bool = Field(
        default=True, description="Q = V + (D - mean D) head: untried actions start at the state's value [bool]"
    )
    critic_steps: int = Field(
        default=4,
        ge=0,
        description="critic-only gradient steps on each batch before the joint step [steps] (critic first, as in the paper)",
    )
    updates_per_iteration: int = Field(
        default=8,
        ge=1,
        description="learner updates (critic steps + joint step + target move) on each sampled batch [updates]; "
        "> 1 turns the actor's term into PPO's clipped surrogate, since from the second update on the batch is "
        "off-policy; 1: COMA's plain on-policy gradient (docs/model.md#training-defaults)",
    )
    ratio_clip: float = Field(
        default=0.2, gt=0, le=1, description="clip of each UAV's probability ratio when updates_per_iteration > 1 [-]"
    )
    critic_warmup_updates: int = Field(
        default=0, ge=0, description="first updates that train the critic only [updates]; 0: off"
    )
    normalize_advantages: bool = Field(
        default=False, description="standardise the advantages over the batch [bool] (not in COMA)"
    )
    reward_scale: float = Field(default=1.0, gt=0, description="factor on the rewards in the critic targets [-]")

    def check(self, scenario: ScenarioConfig, resources: Resources, path: str) -> None:
        """COMA learns from whole episodes, sampled in whole rounds of all envs of all runners;
        the per_device critic (branching.BranchQCritic) needs a hidden layer; per-UAV heads need the
        shared actor they sit on."""
        check_actor_heads(self.share_actor, self.actor_agent_heads, path)
        check_per_ed_heads(self.actor_heads, self.actor_agent_heads, scenario, path)
        if scenario.action_mode == "per_device" and not self.critic_hidden:
            raise ConfigError(
                f"{path}.critic_hidden: per_device needs at least one critic layer (the per-branch critic "
                "sums its action inputs in the first layer)"
            )
        runners = max(1, resources.num_env_runners)
        if self.batch_episodes % (runners * resources.num_envs_per_env_runner):
            raise ConfigError(
                f"{path}.batch_episodes: {self.batch_episodes} is not a multiple of num_env_runners "
                f"({runners}) x num_envs_per_env_runner ({resources.num_envs_per_env_runner}); COMA learns from "
                "whole episodes, sampled in whole rounds of all envs"
            )


class COMAConfig(HParamsConfig, AlgorithmConfig):
    """AlgorithmConfig of COMA; hyperparameters: COMAHParams through `uavlora(...)`."""

    hparams_cls = COMAHParams
    module_class = COMATorchRLModule
    learner_class = COMATorchLearner

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or COMA)
        self.hparams = COMAHParams()
        self.torch_threads = 1
        self.uavlora_algorithm = NAME
        self.batch_mode = "complete_episodes"

    @override(HParamsConfig)
    def apply_hparams(self, h: COMAHParams, scenario: ScenarioConfig) -> dict:
        self.training(
            lr=h.lr_actor,
            gamma=h.gamma,
            grad_clip=h.grad_clip,
            grad_clip_by="global_norm",
            train_batch_size_per_learner=h.batch_episodes * scenario.episode_len,
        )
        per_uav_factors = h.critic_factored_actions and scenario.action_mode == "per_uav"
        factors = [scenario.n_sf, scenario.n_tp, scenario.n_bw] if per_uav_factors else []
        return {"action_factors": factors, "critic_hidden": list(h.critic_hidden)}


class COMA(EpisodeAlgorithm):
    """EpisodeAlgorithm on-policy: each iteration's `batch_episodes` episodes are the train batch
    of its `updates_per_iteration` updates, each one the critic's steps, then the joint step."""

    @classmethod
    @override(Algorithm)
    def get_default_config(cls) -> COMAConfig:
        return COMAConfig()

    @override(EpisodeAlgorithm)
    def episodes_per_runner(self) -> int:
        return self.config.hparams.batch_episodes // max(1, self.config.num_env_runners)

    @override(EpisodeAlgorithm)
    def add_episodes(self, episodes: list) -> int:
        episodes = [ep for ep in episodes if ep.is_done]
        self.batch = MultiAgentBatch(
            {DEFAULT_MODULE_ID: SampleBatch(episode_batch(episodes))},
            env_steps=sum(len(ep) for ep in episodes),
        )
        self.metrics.log_value("num_episodes_trained", len(episodes), reduce="sum")
        return self.config.hparams.updates_per_iteration

    @override(EpisodeAlgorithm)
    def next_batch(self) -> MultiAgentBatch:
        # updates_per_iteration > 1: the same episodes again (the learner clips the actor's
        # probability ratio to the policy that sampled them, their SAMPLED_LOGP)
        return self.batch

    @override(EpisodeAlgorithm)
    def update_learners(self, batch: MultiAgentBatch, timesteps: dict[str, Any]) -> Any:
        """The critic goes first (as in the paper): its critic-only steps on the batch, then the
        joint actor + critic update, so that the actor's advantage comes from the critic that
        has seen the batch."""
        if self.config.hparams.critic_steps:
            for result in self.learner_group.foreach_learner(lambda learner: learner.train_critic(batch)):
                if not result.ok:  # a remote learner's error (a local one raises here directly)
                    raise result.get()
        return super().update_learners(batch, timesteps)


register_algorithm(NAME, COMAConfig, ("per_uav", "per_device"))
