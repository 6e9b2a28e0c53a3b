"""MAPPO's and IPPO's typed hyperparameters (grid YAML `algorithms.mappo:` / `algorithms.ippo:`), declared to
the registry without Ray or torch (registry.spec: grid checks, --dry-run, --list-hparams)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common.hparams import (
    MAX_EPISODES,
    MAX_UPDATES,
    MAX_WIDTH,
    ActorHeadsName,
    check_actor_heads,
    check_per_ed_heads,
)
from uavlora_rllib.algorithms.common.registry import Resources, declare
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

ACTION_MODES = ("per_uav", "per_device")


@typed_dataclass(config=ConfigDict(extra="forbid", frozen=True))
class MAPPOHParams:
    """MAPPO / IPPO hyperparameters (grid YAML `algorithms.mappo:` / `algorithms.ippo:`).

    Defaults: the paper's training table where it gives one, else this project's decision
    (docs/model.md#training-defaults)."""

    # change what is learned, not how long a step or an update takes: a calibration record measured
    # with other values of these prices a trial (experiment/calibration.py, Store.nearest)
    SPEED_NEUTRAL: ClassVar[frozenset[str]] = frozenset(
        {"lr", "gamma", "lambda_", "clip_param", "entropy_coeff", "vf_loss_coeff", "grad_clip", "value_clip"}
    )

    lr: float = Field(default=1e-4, gt=0.0, le=1.0, description="Adam step size, actor and critic [1/update] (paper)")
    gamma: float = Field(default=0.99, ge=0.0, le=1.0, description="discount per slot [-] (paper)")
    lambda_: float = Field(
        default=0.0,
        ge=0.0,
        le=1.0,
        description="GAE lambda [-]; 0: the one-step advantage, since a slot's action never changes later "
        "states (docs/model.md#training-defaults)",
    )
    clip_param: float = Field(default=0.2, gt=0.0, le=1.0, description="PPO ratio clip epsilon, per agent [-] (paper)")
    num_epochs: int = Field(
        default=15, ge=1, le=MAX_UPDATES, description="passes over each train batch [epochs] (paper)"
    )
    batch_episodes: int = Field(
        default=16,
        ge=1,
        le=MAX_EPISODES,
        description="train batch [episodes]: 16 x episode_len env steps, each holding all U agents (paper)",
    )
    num_minibatches: int = Field(
        default=4,
        ge=1,
        le=MAX_UPDATES,
        description="minibatches per epoch [-]: minibatch = train batch / this (docs/model.md#training-defaults)",
    )
    max_seq_len: int = Field(
        default=32,
        ge=1,
        le=MAX_UPDATES,
        description="GRU backprop window [slots]; each window starts from the GRU state recorded during the "
        "rollout (docs/model.md#training-defaults)",
    )
    gru_hidden: int = Field(default=128, ge=1, le=MAX_WIDTH, description="GRU width of the actor [units] (paper)")
    fc_hidden: int = Field(
        default=128, ge=1, le=MAX_WIDTH, description="width of the actor's ReLU layers before and after the GRU [units]"
    )
    critic_hidden: int = Field(
        default=128, ge=1, le=MAX_WIDTH, description="width of the critic's two ReLU layers [units] (decision)"
    )
    entropy_coeff: float = Field(
        default=0.001,
        ge=0.0,
        description="weight of the mean per-agent entropy bonus [-] (docs/model.md#training-defaults)",
    )
    vf_loss_coeff: float = Field(
        default=1.0, ge=0.0, description="weight of the value loss [-] (actor and critic share Adam)"
    )
    grad_clip: float | None = Field(
        default=10.0, gt=0.0, description="global gradient-norm clip [-]; null: off (decision)"
    )
    share_actor: bool = Field(
        default=False,
        description="one actor for all UAVs (+ agent-id one-hot) [bool]; false: one actor per UAV, so that "
        "identical UAVs can pick different SFs (docs/model.md#training-defaults)",
    )
    actor_agent_heads: bool = Field(
        default=False,
        description="with share_actor=true: each UAV also gets its own linear output layer on the shared "
        "GRU trunk, added to the shared one (as COMA's actor) [bool]",
    )
    actor_heads: ActorHeadsName | None = Field(
        default=None,
        description="per_device actor output: 'flat' | 'per_slot' | 'shared' (common/hparams.py ActorHeads); null: "
        "'shared' in per_device mode, 'flat' in per_uav (common/hparams.py DEFAULT_ACTOR_HEADS, "
        "docs/model.md#mappo-and-ippo-per-device)",
    )
    critic: Literal["central", "local"] | None = Field(
        default=None,
        description="'central' (V(s, u) on the global state, MAPPO) | 'local' (V(o_u, u), IPPO); "
        "null: the algorithm's own",
    )
    value_norm: bool = Field(
        default=True, description="running mean/std normalisation of the value targets [bool] (MAPPO's ValueNorm)"
    )
    value_clip: float | None = Field(
        default=0.2, gt=0.0, description="value-loss clip around the old prediction [normalised value units]; null: off"
    )

    def check(self, scenario: ScenarioConfig, resources: Resources, path: str) -> None:
        """A minibatch must hold at least one GRU sequence of the scenario's episodes; per-UAV
        heads need the shared actor they sit on."""
        check_actor_heads(self.share_actor, self.actor_agent_heads, path)
        check_per_ed_heads(self.actor_heads, self.actor_agent_heads, scenario, path)
        minibatch = self.batch_episodes * scenario.episode_len // self.num_minibatches
        if minibatch < min(self.max_seq_len, scenario.episode_len):
            raise ConfigError(
                f"{path}.num_minibatches: {self.num_minibatches} minibatches of {self.batch_episodes} x "
                f"{scenario.episode_len} env steps are shorter than one GRU sequence (max_seq_len "
                f"{self.max_seq_len}); use fewer minibatches or more batch_episodes"
            )


declare("mappo", MAPPOHParams, ACTION_MODES)
declare("ippo", MAPPOHParams, ACTION_MODES)
