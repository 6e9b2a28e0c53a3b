"""MAPPO (centralised critic) and IPPO (local critics) on RLlib's new API stack.

Registered as "mappo" and "ippo" (`registry.AlgorithmEntry`). Both sample through the team
view (`team_env`, env "uavlora_team") with RLlib's `SingleAgentEnvRunner` over ONE vectorised
`BatchCore` per env runner (`gym_env_vectorize_mode="vector_entry_point"`), learn with
`MAPPOTorchLearner` (per-agent clipped PPO, per-agent GAE, see `mappo_learner`) and act with
the recurrent decentralised actor of `mappo_module` / `gru_actor`:

* MAPPO: shared GRU actor on each UAV's LOCAL observation row (+ agent id); critic
  V(s, u) on the global state s = info["state"] (learner only; env runners hold the actor).
* IPPO: the same actor; critic V(o_u, u) on the agent's own observation.

Execution (`greedy_policy`): the actor alone, on CPU under torch.no_grad, argmax per agent,
GRU state carried across slots and cleared in `reset`.

Per-iteration env-runner metrics (result["env_runners"]): `ee_sys_mean` (per-slot EE_sys
averaged over each sampled episode, then over the episodes that ended in the iteration,
bits/J) and `success_rate` (Xi, same averaging), besides RLlib's episode_return_mean.
Learner metrics (result["learners"]["default_policy"]): policy_loss, vf_loss, entropy,
clip_fraction, approx_kl.
"""

from __future__ import annotations

import copy
from typing import Literal

from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as typed_dataclass
from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from uavlora_rllib.algorithms.common.gru_actor import ActionHead, GRUActor
from uavlora_rllib.algorithms.mappo.mappo_learner import MAPPOTorchLearner
from uavlora_rllib.algorithms.mappo.mappo_module import MAPPOTorchRLModule
from uavlora_rllib.algorithms.common.recurrent_policy import RecurrentPolicy
from uavlora_rllib.algorithms.common.registry import AlgorithmEntry, Resources, register
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.observation import state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig
from uavlora_rllib.envs.team import sample_through_team_env, team_action_space, team_observation_space


@typed_dataclass(config=ConfigDict(extra="forbid", frozen=True))
class MAPPOHParams:
    """MAPPO / IPPO hyperparameters (grid YAML `algorithms.mappo:` / `algorithms.ippo:`).

    Defaults: SPEC.md "Training defaults" (the paper's table) where it gives one, else the
    decision noted. Units in brackets.

    lr               1e-4   Adam step size (paper)
    gamma            0.99   discount per slot (paper)
    lambda_          0.95   GAE lambda (decision, SPEC.md)
    clip_param       0.2    PPO ratio clip epsilon, per agent (paper)
    num_epochs       15     passes over each train batch (paper)
    batch_episodes   16     train batch in EPISODES: train_batch_size = 16 x episode_len env
                            steps (paper's "batch 16"); each env step holds all U agents
    num_minibatches  4      minibatches per epoch [-] (decision: minibatch_size = train_batch_size /
                            num_minibatches env steps; RLlib counts the zero-padded slots, so a
                            batch of 16 chunks x 160 slots gives 15 x 2560 / 600 = 64 Adam steps. One
                            minibatch, MAPPO's reference default, runs ~1.3x faster per env step
                            but at lr 1e-4 learned far less in 150k env steps: 43% vs 100% of
                            the per-slot optimum, BENCHMARKS.md)
    max_seq_len      32     GRU BPTT window [slots] (decision: an episode chunk of T = 150 slots
                            plus RLlib's bootstrap step is 151 = 4 x 32 + 23, 6 % padding; each
                            window starts from the GRU state recorded during the rollout, so
                            only gradients are truncated. MAPPO's reference data_chunk_length 10
                            runs ~1.2x faster here but learned less: 94% of the EE of 32-slot
                            windows, mean of 4 learning-check runs, BENCHMARKS.md)
    gru_hidden       128    GRU width (paper)
    fc_hidden        128    ReLU layer before and after the GRU (paper: ReLU; width a decision)
    critic_hidden    128    width of the critic's two ReLU layers (decision)
    entropy_coeff    0.01   entropy bonus (decision, SPEC.md)
    vf_loss_coeff    1.0    weight of the value loss (actor and critic share the optimizer)
    grad_clip        10.0   global gradient-norm clip (decision, SPEC.md)
    share_actor      True   one actor for all UAVs (+ agent-id one-hot); False: one per UAV
    critic           "central" (MAPPO: V(s, u) on the global state) | "local" (IPPO: V(o_u, u));
                     None = the algorithm's own ("central" for mappo, "local" for ippo)
    value_norm       True   running mean/std normalisation of value targets (MAPPO's ValueNorm)
    value_clip       0.2    value-loss clipping around the old prediction [normalised units]; None: off
    """

    lr: float = Field(1e-4, gt=0.0)
    gamma: float = Field(0.99, ge=0.0, le=1.0)
    lambda_: float = Field(0.95, ge=0.0, le=1.0)
    clip_param: float = Field(0.2, gt=0.0)
    num_epochs: int = Field(15, ge=1)
    batch_episodes: int = Field(16, ge=1)
    num_minibatches: int = Field(4, ge=1)
    max_seq_len: int = Field(32, ge=1)
    gru_hidden: int = Field(128, ge=1)
    fc_hidden: int = Field(128, ge=1)
    critic_hidden: int = Field(128, ge=1)
    entropy_coeff: float = Field(0.01, ge=0.0)
    vf_loss_coeff: float = Field(1.0, ge=0.0)
    grad_clip: float | None = Field(10.0, gt=0.0)
    share_actor: bool = True
    critic: Literal["central", "local"] | None = None
    value_norm: bool = True
    value_clip: float | None = Field(0.2, gt=0.0)


class MAPPOConfig(PPOConfig):
    """PPOConfig whose defaults are MAPPO's module and learner."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or MAPPO)

    def get_default_rl_module_spec(self) -> RLModuleSpec:
        return RLModuleSpec(module_class=MAPPOTorchRLModule)

    def get_default_learner_class(self):
        return MAPPOTorchLearner


class MAPPO(PPO):
    """PPO's sample -> learner update -> weight sync loop, with MAPPO's module and learner."""

    @classmethod
    def get_default_config(cls) -> MAPPOConfig:
        return MAPPOConfig()


# ------------------------------------------------------------------ env-runner metrics
def _on_episode_step(*, episode, **kwargs) -> None:
    info = episode.get_infos(-1)
    if "ee_sys" in info:
        data = episode.custom_data
        data["ee_sum"] = data.get("ee_sum", 0.0) + float(info["ee_sys"])
        data["xi_sum"] = data.get("xi_sum", 0.0) + float(info["success_rate"])
        data["slots"] = data.get("slots", 0) + 1


def _on_episode_end(*, episode, metrics_logger=None, **kwargs) -> None:
    data = episode.custom_data
    n = data.get("slots", 0)
    if n and metrics_logger is not None:
        metrics_logger.log_value("ee_sys_mean", data["ee_sum"] / n, reduce="mean")
        metrics_logger.log_value("success_rate", data["xi_sum"] / n, reduce="mean")


# ------------------------------------------------------------------ build
def _build(name: str):
    default_critic = "central" if name == "mappo" else "local"

    def build(scenario: ScenarioConfig, hparams: MAPPOHParams, resources: Resources, seed: int) -> MAPPOConfig:
        if not isinstance(hparams, MAPPOHParams):
            hparams = ENTRIES[name].hparams(hparams)
        ENTRIES[name].check_scenario(scenario)
        critic = hparams.critic or default_critic
        train_batch = hparams.batch_episodes * scenario.episode_len
        minibatch = train_batch // hparams.num_minibatches
        if minibatch < min(hparams.max_seq_len, scenario.episode_len):
            raise ConfigError(
                f"algorithms.{name}.num_minibatches: {hparams.num_minibatches} minibatches of "
                f"{hparams.batch_episodes} x {scenario.episode_len} env steps are shorter than one GRU "
                f"sequence (max_seq_len {hparams.max_seq_len}); use fewer minibatches or more batch_episodes"
            )
        cfg = (
            sample_through_team_env(MAPPOConfig(), scenario, resources, name, rollout_fragment_length="auto")
            .framework("torch")
            .learners(
                num_learners=0,
                num_cpus_per_learner=resources.num_cpus_per_learner,
                learner_config_dict={"critic": critic, "value_clip": hparams.value_clip},
            )
            .training(
                lr=hparams.lr,
                gamma=hparams.gamma,
                lambda_=hparams.lambda_,
                clip_param=hparams.clip_param,
                num_epochs=hparams.num_epochs,
                train_batch_size_per_learner=train_batch,
                minibatch_size=minibatch,
                shuffle_batch_per_epoch=True,
                entropy_coeff=hparams.entropy_coeff,
                vf_loss_coeff=hparams.vf_loss_coeff,
                grad_clip=hparams.grad_clip,
                grad_clip_by="global_norm",
                use_kl_loss=False,
                kl_coeff=0.0,
            )
            .rl_module(
                model_config={
                    "gru_hidden": hparams.gru_hidden,
                    "fc_hidden": hparams.fc_hidden,
                    "critic_hidden": hparams.critic_hidden,
                    "share_actor": hparams.share_actor,
                    "critic": critic,
                    "state_dim": state_dim(scenario),
                    "value_norm": hparams.value_norm,
                    "max_seq_len": hparams.max_seq_len,
                    "torch_threads": resources.torch_threads,
                }
            )
            .callbacks(on_episode_step=_on_episode_step, on_episode_end=_on_episode_end)
            .debugging(seed=seed)
        )
        return cfg

    return build


# ------------------------------------------------------------------ execution
class RecurrentGreedyPolicy(RecurrentPolicy):
    """evaluation.Policy running a copy of the trained actor (CPU, no grad, argmax)."""

    def __init__(self, actor: GRUActor, head: ActionHead, cfg: ScenarioConfig, name: str):
        super().__init__(actor, head.greedy, actor.initial_state, name)
        self.actor, self.head, self.cfg = actor, head, cfg


def actor_from_module(module: MAPPOTorchRLModule) -> tuple[GRUActor, ActionHead]:
    actor = copy.deepcopy(module.actor).to("cpu")
    return actor, module.head


def _greedy_policy(name: str):
    def greedy_policy(algo, scenario: ScenarioConfig) -> RecurrentGreedyPolicy:
        # The local learner's module holds the freshest weights; with remote learners, the
        # env runners' (synced after every update, actor only).
        learner = getattr(algo.learner_group, "_learner", None)
        module = learner.module[DEFAULT_MODULE_ID] if learner is not None else algo.get_module(DEFAULT_MODULE_ID)
        module = module.unwrapped() if hasattr(module, "unwrapped") else module
        expected = team_observation_space(scenario).shape
        if (module.n_agents, module.obs_dim) != expected:
            raise ValueError(f"scenario: the trained actor expects observations {(module.n_agents, module.obs_dim)}, got {expected}")
        if module.per_device != (scenario.action_mode == "per_device"):
            raise ValueError(f"scenario.action_mode: {scenario.action_mode!r} differs from the trained actor's")
        actor, head = actor_from_module(module)
        return RecurrentGreedyPolicy(actor, head, scenario, name)

    return greedy_policy


ENTRIES: dict[str, AlgorithmEntry] = {}
for _name in ("mappo", "ippo"):
    ENTRIES[_name] = AlgorithmEntry(
        name=_name,
        hparams_cls=MAPPOHParams,
        action_modes=("per_uav", "per_device"),
        build=_build(_name),
        greedy_policy=_greedy_policy(_name),
    )
    register(ENTRIES[_name])

__all__ = ["MAPPO", "MAPPOConfig", "MAPPOHParams", "RecurrentGreedyPolicy", "ENTRIES", "team_action_space"]
