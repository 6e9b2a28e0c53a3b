"""MAPPO (centralised critic) and IPPO (local critics) on RLlib's new API stack.

Registered as "mappo" and "ippo" (`registry.register_algorithm`). Both sample through the team
view (`team_env`, env "uavlora_team") with RLlib's `SingleAgentEnvRunner` over ONE vectorised
`BatchCore` per env runner (`gym_env_vectorize_mode="vector_entry_point"`), learn with
`MAPPOTorchLearner` (per-agent clipped PPO, per-agent GAE, see `mappo_learner`) and act with
the recurrent decentralised actor of `mappo_module` (common `RecurrentAgentNet`):

* MAPPO: shared GRU actor on each UAV's LOCAL observation row (+ agent id); critic
  V(s, u) on the global state s = info["state"] (learner only; env runners hold the actor).
* IPPO: the same actor; critic V(o_u, u) on the agent's own observation.

Execution: the registry's policy (common/policy.py): the actor alone, greedy (argmax per
agent) or sampled, GRU state carried across slots and cleared in `reset`.

Hyperparameters: `MAPPOHParams` (`--list-hparams mappo`). MAPPOConfig is a PPOConfig (PPO's
sample -> update -> sync loop) whose learner is not PPO's: the PPO features that learner
does not implement (KL loss, entropy schedules, PPO's value clipping, no-GAE) are rejected by
`MAPPOConfig.validate` rather than silently ignored.

Per-iteration env-runner metrics (result["env_runners"], common/metrics.py): `ee_sys_mean`
and `success_rate`, besides RLlib's episode_return_mean.
Learner metrics (result["learners"]["default_policy"]): policy_loss, vf_loss, entropy,
clip_fraction, approx_kl.
"""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as typed_dataclass
from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common.config import ActorHeads, HParamsConfig, check_actor_heads, check_per_ed_heads
from uavlora_rllib.algorithms.common.registry import Resources, register_algorithm
from uavlora_rllib.algorithms.mappo.mappo_learner import MAPPOTorchLearner
from uavlora_rllib.algorithms.mappo.mappo_module import MAPPOTorchRLModule
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig


@typed_dataclass(config=ConfigDict(extra="forbid", frozen=True))
class MAPPOHParams:
    """MAPPO / IPPO hyperparameters (grid YAML `algorithms.mappo:` / `algorithms.ippo:`).

    Defaults: the paper's training table where it gives one, else this project's decision
    (docs/model.md#training-defaults)."""

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
    num_epochs: int = Field(default=15, ge=1, description="passes over each train batch [epochs] (paper)")
    batch_episodes: int = Field(
        default=16,
        ge=1,
        description="train batch [episodes]: 16 x episode_len env steps, each holding all U agents (paper)",
    )
    num_minibatches: int = Field(
        default=4,
        ge=1,
        description="minibatches per epoch [-]: minibatch = train batch / this (docs/model.md#training-defaults)",
    )
    max_seq_len: int = Field(
        default=32,
        ge=1,
        description="GRU backprop window [slots]; each window starts from the GRU state recorded during the "
        "rollout (docs/model.md#training-defaults)",
    )
    gru_hidden: int = Field(default=128, ge=1, description="GRU width of the actor [units] (paper)")
    fc_hidden: int = Field(
        default=128, ge=1, description="width of the actor's ReLU layers before and after the GRU [units]"
    )
    critic_hidden: int = Field(
        default=128, ge=1, description="width of the critic's two ReLU layers [units] (decision)"
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
    actor_heads: ActorHeads = "flat"
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


class MAPPOConfig(HParamsConfig, PPOConfig):
    """PPOConfig whose defaults are MAPPO's module and learner (central critic)."""

    hparams_cls = MAPPOHParams
    module_class = MAPPOTorchRLModule
    learner_class = MAPPOTorchLearner
    default_critic = "central"

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or MAPPO)
        # MAPPO clips values by `value_clip` (its own units); PPO's vf_clip_param is unused.
        self.vf_clip_param = float("inf")
        self.use_kl_loss = False
        self.kl_coeff = 0.0

    @override(HParamsConfig)
    def apply_hparams(self, h: MAPPOHParams, scenario: ScenarioConfig) -> dict:
        train_batch = h.batch_episodes * scenario.episode_len
        self.training(
            lr=h.lr,
            gamma=h.gamma,
            lambda_=h.lambda_,
            clip_param=h.clip_param,
            num_epochs=h.num_epochs,
            train_batch_size_per_learner=train_batch,
            minibatch_size=train_batch // h.num_minibatches,
            shuffle_batch_per_epoch=True,
            entropy_coeff=h.entropy_coeff,
            vf_loss_coeff=h.vf_loss_coeff,
            grad_clip=h.grad_clip,
            grad_clip_by="global_norm",
        )
        return {"critic": h.critic or self.default_critic}

    @override(HParamsConfig)
    def env_runner_settings(self, scenario: ScenarioConfig) -> dict:
        # fragments sized by RLlib to fill the train batch evenly over runners and envs
        return {"rollout_fragment_length": "auto"}

    @override(PPOConfig)
    def validate(self) -> None:
        # PPO features MAPPOTorchLearner does not implement: refuse them instead of ignoring them.
        unsupported = {
            "use_kl_loss": self.use_kl_loss,
            "kl_coeff": self.kl_coeff != 0.0,
            "entropy_coeff (schedule)": isinstance(self.entropy_coeff, (list, tuple)),
            "vf_clip_param": self.vf_clip_param != float("inf"),
            "use_gae=False": not self.use_gae,
            "use_critic=False": not self.use_critic,
        }
        bad = [k for k, v in unsupported.items() if v]
        if bad:
            raise ConfigError(
                f"MAPPOConfig: {', '.join(bad)}: not supported by MAPPO's learner (per-agent clipped PPO with "
                "GAE, a constant entropy_coeff and MAPPOHParams.value_clip); leave them at MAPPOConfig's defaults"
            )
        super().validate()


class IPPOConfig(MAPPOConfig):
    """MAPPO's config with local critics V(o_u, u)."""

    default_critic = "local"


class MAPPO(PPO):
    """PPO's sample -> learner update -> weight sync loop, with MAPPO's module and learner."""

    @classmethod
    @override(PPO)
    def get_default_config(cls) -> MAPPOConfig:
        return MAPPOConfig()


register_algorithm("mappo", MAPPOConfig, ("per_uav", "per_device"))
register_algorithm("ippo", IPPOConfig, ("per_uav", "per_device"))

__all__ = ["MAPPO", "MAPPOConfig", "IPPOConfig", "MAPPOHParams"]
