"""QMIX's and VDN's typed hyperparameters (grid YAML `algorithms.qmix:` / `algorithms.vdn:`), declared to the
registry without Ray or torch (registry.spec: grid checks, --dry-run, --list-hparams)."""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common.hparams import MAX_ENV_STEPS, MAX_EPISODES, MAX_UPDATES, MAX_WIDTH
from uavlora_rllib.algorithms.common.registry import Resources, declare
from uavlora_rllib.sim.scenario import ScenarioConfig

ACTION_MODES = ("per_uav", "per_device")
HYPERNET_EMBED_DIM = 64  # QMIX's default hypernetwork width; VDN, which has none, refuses any other


def _updates_per_episode(default: float):
    """The `updates_per_episode` field: one meaning and range; QMIX and VDN each have their default."""
    return Field(
        default=default,
        gt=0,
        le=64,
        description="gradient updates per episode added to the replay [updates/episode]: the update-to-data "
        "ratio, independent of how many envs and env runners sample (docs/model.md#training-defaults)",
    )


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class QMIXHParams:
    """QMIX/VDN hyperparameters (grid YAML `algorithms.qmix:` / `algorithms.vdn:`)."""

    # change what is learned, not how long a step or an update takes (gamma does: at 0 the target
    # networks are skipped): a calibration record with other values of these prices a trial
    # (experiment/calibration.py, Store.nearest)
    SPEED_NEUTRAL: ClassVar[frozenset[str]] = frozenset(
        {
            "lr",
            "lr_end",
            "negative_td_weight",
            "n_step",
            "tau",
            "grad_clip",
            "buffer_size_episodes",
            "epsilon_start",
            "epsilon_end",
            "epsilon_anneal_fraction",
            "t_max_env_steps",
        }
    )

    lr: float = Field(
        default=1e-4, gt=0, le=1, description="Adam step size, agent network and mixer [1/update] (paper)"
    )
    lr_end: float | None = Field(
        default=None,
        gt=0,
        le=1,
        description="Adam step size reached at t_max_env_steps, linearly from lr [1/update]; null: lr throughout "
        "(paper). A decaying step lets the per-ED utilities settle (docs/model.md#qmix-and-vdn-per-device)",
    )
    gamma: float = Field(default=0.99, ge=0, le=1, description="discount per slot [-] (paper)")
    gru_hidden: int = Field(
        default=128, ge=1, le=MAX_WIDTH, description="GRU width of the agent network [units] (paper)"
    )
    fc_hidden: int = Field(
        default=128, ge=1, le=MAX_WIDTH, description="width of the ReLU layer before the GRU [units] (decision)"
    )
    share_agent_net: bool = Field(
        default=False,
        description="one agent network for all UAVs (+ one-hot UAV id) [bool]; false: one per UAV, which breaks "
        "the symmetry between identical UAVs from the start (docs/model.md#training-defaults)",
    )
    slot_head: Literal["per_slot", "shared"] = Field(
        default="per_slot",
        description="per_device only: each ED slot's (SF, TP) utility head has its own parameters (per_slot) or one "
        "head serves every slot, told apart by the slot's observation row (shared) [-] "
        "(docs/model.md#qmix-and-vdn-per-device)",
    )
    slot_utility: Literal["joint", "additive"] = Field(
        default="joint",
        description="per_device only: a slot's utility has one value per (SF, TP) pair (joint, n_sf n_tp outputs) "
        "or is Q(SF) + Q(TP) (additive, n_sf + n_tp outputs: each SF value learns from every TP tried with it, "
        "as the actor-critic learners' separate SF and TP categoricals) [-] (docs/model.md#qmix-and-vdn-per-device)",
    )
    head_hidden: int = Field(
        default=64,
        ge=1,
        le=MAX_WIDTH,
        description="per_device only: hidden width of every branch head (each slot's and the BW's) [units] "
        "(docs/model.md#qmix-and-vdn-per-device)",
    )
    dueling: bool = Field(
        default=True,
        description="per_device only: the branch heads give advantages around a per-UAV state value V_u, "
        "BDQ's dueling form [bool] (docs/model.md#qmix-and-vdn-per-device)",
    )
    mixing_embed_dim: int = Field(
        default=32,
        ge=1,
        le=MAX_WIDTH,
        description="mixing-network width of QMIX and width of V(s) [units] (Rashid et al.)",
    )
    state_bias: bool = Field(
        default=True,
        description="Q_tot includes a state-value term V(s) (2-layer MLP on the global state) [bool]; VDN with it "
        "is Rashid et al.'s VDN-S, without it Sunehag et al.'s plain sum; execution never reads it "
        "(docs/model.md#training-defaults)",
    )
    reward_norm: bool = Field(
        default=False,
        description="standardise the team reward in the TD targets by its running mean and std (EPyMARL's "
        "standardise_rewards; common/value_norm.py) [bool]: the Q-values are then in those units, the argmax "
        "is unchanged (docs/model.md#qmix-and-vdn-per-device)",
    )
    negative_td_weight: float = Field(
        default=1.0,
        gt=0,
        le=1,
        description="weight of the squared TD error where the target is below Q_tot (1: plain QMIX/VDN) [-]: "
        "below 1 the value follows the better outcomes of a joint action more than the worse ones that other "
        "agents' exploration causes (hysteretic Q-learning; OW-QMIX's weighting) (docs/model.md#qmix-and-vdn-per-device)",
    )
    hypernet_embed_dim: int = Field(
        default=HYPERNET_EMBED_DIM,
        ge=1,
        le=MAX_WIDTH,
        description="hidden width of the 2-layer weight hypernetworks [units]; unused by VDN",
    )
    double_q: bool = Field(
        default=True, description="double Q [bool]: the online net picks argmax at t+1, the target net evaluates it"
    )
    n_step: int = Field(
        default=1, ge=1, le=MAX_UPDATES, description="n of the n-step TD targets [slots] (truncated at the episode end)"
    )
    tau: float = Field(
        default=0.01, gt=0, le=1, description="soft target update weight after every gradient update [-] (paper)"
    )
    grad_clip: float = Field(default=10.0, gt=0, description="global gradient-norm clip [-] (decision)")
    batch_size_episodes: int = Field(
        default=16, ge=1, le=MAX_EPISODES, description="whole episodes per gradient update [episodes] (paper)"
    )
    buffer_size_episodes: int = Field(
        default=32, ge=1, le=MAX_EPISODES, description="replay capacity |D| [episodes] (paper)"
    )
    learning_starts_episodes: int = Field(
        default=16, ge=1, le=MAX_EPISODES, description="episodes in the replay before the first update [episodes]"
    )
    updates_per_episode: float = _updates_per_episode(0.25)
    updates_per_iteration: int | None = Field(
        default=None,
        ge=1,
        le=MAX_UPDATES,
        description="gradient updates per training iteration [updates], overriding updates_per_episode; "
        "null: updates_per_episode x the episodes the iteration added",
    )
    epsilon_start: float = Field(default=1.0, ge=0, le=1, description="exploration epsilon at t = 0 [probability]")
    epsilon_end: float = Field(
        default=0.05,
        ge=0,
        le=1,
        description="exploration epsilon after the anneal, also the sampled execution's [probability]",
    )
    epsilon_anneal_fraction: float = Field(
        default=0.05, ge=0, le=1, description="share of t_max_env_steps over which epsilon anneals linearly [-] (paper)"
    )
    t_max_env_steps: int = Field(
        default=2_000_000,
        ge=1,
        le=MAX_ENV_STEPS,
        description="the paper's training budget T_max [env steps]: the epsilon schedule is a share of it, and "
        "lr_end is reached at it; "
        "independent of a grid's stop.env_steps, so a short run explores as the paper's first env steps do",
    )

    @model_validator(mode="after")
    def _check(self) -> QMIXHParams:
        if self.epsilon_end > self.epsilon_start:
            raise ValueError(f"epsilon_end ({self.epsilon_end}) must be <= epsilon_start ({self.epsilon_start})")
        if self.batch_size_episodes > self.buffer_size_episodes:
            raise ValueError(
                f"batch_size_episodes ({self.batch_size_episodes}) must be <= buffer_size_episodes ({self.buffer_size_episodes})"
            )
        if self.learning_starts_episodes > self.buffer_size_episodes:  # else the replay never fills enough to learn
            raise ValueError(
                f"learning_starts_episodes ({self.learning_starts_episodes}) must be <= buffer_size_episodes "
                f"({self.buffer_size_episodes})"
            )
        return self

    def check(self, scenario: ScenarioConfig, resources: Resources, path: str) -> None:
        """Nothing depends on the scenario or the resources (whole episodes are replayed)."""

    @property
    def epsilon_anneal_env_steps(self) -> int:
        return int(round(self.epsilon_anneal_fraction * self.t_max_env_steps))

    @property
    def lr_schedule(self) -> float | list[list[float]]:
        """RLlib's `lr`: the constant lr, or [[0, lr], [t_max_env_steps, lr_end]] (piecewise linear
        over the sampled env steps, held at lr_end after)."""
        if self.lr_end is None:
            return self.lr
        return [[0, self.lr], [self.t_max_env_steps, self.lr_end]]


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class VDNHParams(QMIXHParams):
    """VDN hyperparameters (grid YAML `algorithms.vdn:`): QMIX's fields; one default differs."""

    updates_per_episode: float = _updates_per_episode(1.0)

    @model_validator(mode="after")
    def _no_hypernetworks(self) -> VDNHParams:
        if (
            self.hypernet_embed_dim != HYPERNET_EMBED_DIM
        ):  # VDN sums the utilities: a width it never builds is a mistake
            raise ValueError("hypernet_embed_dim: unused by VDN (it mixes by a sum, no hypernetworks); leave it out")
        return self


declare("qmix", QMIXHParams, ACTION_MODES)
declare("vdn", VDNHParams, ACTION_MODES)
