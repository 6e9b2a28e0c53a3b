"""COMA's typed hyperparameters (grid YAML `algorithms.coma:`), declared to the registry without Ray or
torch (registry.spec: grid checks, --dry-run, --list-hparams)."""

from __future__ import annotations

from typing import Annotated, ClassVar, Literal

from pydantic import Field
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common.hparams import (
    MAX_EPISODES,
    MAX_UPDATE_COUNT,
    MAX_UPDATES,
    MAX_WIDTH,
    ActorHeads,
    check_actor_heads,
    check_per_ed_heads,
)
from uavlora_rllib.algorithms.common.registry import Resources, declare
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

NAME = "coma"
ACTION_MODES = ("per_uav", "per_device")


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class COMAHParams:
    """COMA's hyperparameters; defaults from the paper's training table where it has them."""

    # change what is learned, not how long a step or an update takes (gamma does: at 0 the target
    # critic is skipped): a calibration record with other values of these prices a trial
    # (experiment/calibration.py, Store.nearest)
    SPEED_NEUTRAL: ClassVar[frozenset[str]] = frozenset(
        {
            "lr_actor",
            "lr_critic",
            "td_lambda",
            "entropy_coeff",
            "grad_clip",
            "tau",
            "target_hard_update_every",
            "ratio_clip",
            "normalize_advantages",
            "reward_scale",
        }
    )

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
        default=16,
        ge=1,
        le=MAX_EPISODES,
        description="whole episodes per update [episodes] (paper: batch 16); a multiple of all envs",
    )
    tau: float = Field(
        default=0.01, gt=0, le=1, description="Polyak weight of the target critic per update [-] (paper)"
    )
    target_hard_update_every: int = Field(
        default=0,
        ge=0,
        le=MAX_UPDATE_COUNT,
        description="> 0: hard target copy every K updates instead of Polyak [updates]",
    )
    actor_hidden: int = Field(
        default=128, ge=1, le=MAX_WIDTH, description="width of the actor's ReLU layer before the GRU [units]"
    )
    gru_hidden: int = Field(default=128, ge=1, le=MAX_WIDTH, description="GRU width of the actor [units] (paper)")
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
    critic_hidden: tuple[Annotated[int, Field(ge=1, le=MAX_WIDTH)], ...] = Field(
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
    critic_branch_fraction: float = Field(
        default=1.0,
        gt=0,
        le=1,
        description="per_device: share of the critic's (UAV, branch) rows whose TD loss each update trains, drawn "
        "at random per update [-]; the advantage always reads every row (docs/model.md#coma-per-device); 1: all",
    )
    critic_steps: int = Field(
        default=4,
        ge=0,
        le=MAX_UPDATES,
        description="critic-only gradient steps on each batch before the joint step [steps] (critic first, as in the paper)",
    )
    updates_per_iteration: int = Field(
        default=8,
        ge=1,
        le=MAX_UPDATES,
        description="learner updates (critic steps + joint step + target move) on each sampled batch [updates]; "
        "> 1 turns the actor's term into PPO's clipped surrogate, since from the second update on the batch is "
        "off-policy; 1: COMA's plain on-policy gradient (docs/model.md#training-defaults)",
    )
    ratio_clip: float = Field(
        default=0.2, gt=0, le=1, description="clip of each UAV's probability ratio when updates_per_iteration > 1 [-]"
    )
    critic_warmup_updates: int = Field(
        default=0, ge=0, le=MAX_UPDATE_COUNT, description="first updates that train the critic only [updates]; 0: off"
    )
    normalize_advantages: bool = Field(
        default=False, description="standardise the advantages over the batch [bool] (not in COMA)"
    )
    reward_scale: float = Field(default=1.0, gt=0, description="factor on the rewards in the critic targets [-]")
    taken_value: Literal["critic", "return"] = Field(
        default="critic",
        description="first term of the advantage: the critic's Q(s, a) (COMA) or the TD(lambda) return the critic "
        "regresses (unbiased whatever the critic; the counterfactual baseline stays) "
        "(docs/model.md#coma-per-device)",
    )

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


declare(NAME, COMAHParams, ACTION_MODES)
