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

from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common.config import HParamsConfig
from uavlora_rllib.algorithms.common.hparams import resolve_actor_heads
from uavlora_rllib.algorithms.common.registry import register_algorithm
from uavlora_rllib.algorithms.mappo.hparams import MAPPOHParams
from uavlora_rllib.algorithms.mappo.mappo_learner import MAPPOTorchLearner
from uavlora_rllib.algorithms.mappo.mappo_module import MAPPOTorchRLModule
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig


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
        return {
            "critic": h.critic or self.default_critic,
            "actor_heads": resolve_actor_heads(h.actor_heads, scenario.action_mode == "per_device"),
        }

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


register_algorithm("mappo", MAPPOConfig)
register_algorithm("ippo", IPPOConfig)

__all__ = ["MAPPO", "MAPPOConfig", "IPPOConfig", "MAPPOHParams"]
