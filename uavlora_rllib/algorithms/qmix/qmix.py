"""QMIX and VDN (value decomposition) on RLlib 2.60's new API stack, through the team view.

Sampling: env "uavlora_team" (team_env.py): one RLlib "agent" = the whole UAV team, obs
[U, obs_dim] (row u = UAV u's LOCAL observation), action MultiDiscrete([A] * U) (per_uav mode
only), the shared reward, the global state in info["state"]. Env runners hold only the agent
Q-network (inference-only module) and act decentralised: UAV u's action is the epsilon-greedy
argmax of its own Q-values, computed from its own observation history (GRU state carried by
RLlib's connectors, zero at every episode start).

One training iteration (`QMIX.training_step`):
  1. sample rollout_fragment_length = episode_len steps on every env of every env runner:
     num_envs_per_env_runner x max(1, num_env_runners) whole episodes;
  2. store them in the episode replay (|D| = buffer_size_episodes whole episodes);
  3. once the replay holds learning_starts_episodes episodes: updates_per_iteration times,
     sample batch_size_episodes whole episodes and run one TD update on the learner (the GRU
     is unrolled over whole episodes from a zero state: no burn-in, no truncated sequences,
     T = 150 is short enough), followed by a soft target update with tau;
  4. push the agent network's weights to the env runners.

Hyperparameters: `QMIXHParams` (one class for both names; `mixer` is fixed by the name:
"qmix" -> monotonic hypernetwork mixer, "vdn" -> sum). Defaults follow SPEC.md's training
table; the epsilon schedule is linear from epsilon_start to epsilon_end over
epsilon_anneal_fraction x t_max_env_steps env steps (SPEC.md: 5% of T_max = 2M).

Checkpoints (save_to_path / from_checkpoint) hold the config, the learner (agent net, mixer,
their targets, Adam state) and the env runners' weights. The replay buffer is NOT saved: a
restored run refills it (learning resumes after learning_starts_episodes new episodes).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from pydantic import Field, model_validator
from pydantic.dataclasses import dataclass as typed_dataclass

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig, NotProvided
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.execution.rollout_ops import synchronous_parallel_sample
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    SYNCH_WORKER_WEIGHTS_TIMER,
    TIMERS,
)

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.qmix.qmix_learner import QMIXTorchLearner
from uavlora_rllib.algorithms.qmix.qmix_module import AgentQNet, QMixModule, linear_epsilon
from uavlora_rllib.algorithms.qmix.qmix_replay import EpisodeReplay
from uavlora_rllib.algorithms.common.recurrent_policy import RecurrentPolicy, argmax_actions
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.envs.multi_agent import STATE_KEY, scenario_from
from uavlora_rllib.sim.scenario import ScenarioConfig

MIXERS = ("qmix", "vdn")


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class QMIXHParams:
    """QMIX/VDN hyperparameters (grid YAML `algorithms.qmix:` / `algorithms.vdn:`)."""

    lr: float = Field(1e-4, gt=0)  # Adam learning rate (paper)
    gamma: float = Field(0.99, ge=0, le=1)  # discount per slot (paper)
    gru_hidden: int = Field(128, ge=1)  # GRU hidden units of the agent network (paper)
    fc_hidden: int = Field(128, ge=1)  # width of the Linear+ReLU layer before the GRU (decision)
    # One agent network for all UAVs (+ one-hot UAV id); False: one network per UAV. Measured:
    # shared nets start (and, for VDN, stay within small budgets) on ONE joint action where
    # both UAVs use the same SF, which the paper's interference model punishes (~0.4x random
    # EE); one net per UAV breaks that symmetry from the start (tests use False).
    share_agent_net: bool = True
    mixing_embed_dim: int = Field(32, ge=1)  # QMIX mixing-network width (Rashid et al.); unused by VDN
    hypernet_embed_dim: int = Field(64, ge=1)  # hidden width of the 2-layer weight hypernetworks; unused by VDN
    double_q: bool = True  # online net picks argmax at t+1, target net evaluates it
    n_step: int = Field(1, ge=1)  # n-step TD targets (truncated at the episode end)
    tau: float = Field(0.01, gt=0, le=1)  # soft target update after every gradient update (paper)
    grad_clip: float = Field(10.0, gt=0)  # global gradient-norm clip (decision)
    batch_size_episodes: int = Field(16, ge=1)  # whole episodes per gradient update (paper)
    buffer_size_episodes: int = Field(32, ge=1)  # replay capacity |D|, whole episodes (paper)
    learning_starts_episodes: int = Field(16, ge=1)  # episodes in the replay before the first update
    updates_per_iteration: int = Field(1, ge=1)  # gradient updates per training iteration
    epsilon_start: float = Field(1.0, ge=0, le=1)
    epsilon_end: float = Field(0.05, ge=0, le=1)
    epsilon_anneal_fraction: float = Field(0.05, ge=0, le=1)  # of t_max_env_steps (SPEC.md: 5%)
    t_max_env_steps: int = Field(2_000_000, ge=1)  # training budget T_max in env steps (team steps)

    @model_validator(mode="after")
    def _check(self) -> "QMIXHParams":
        if self.epsilon_end > self.epsilon_start:
            raise ValueError(f"epsilon_end ({self.epsilon_end}) must be <= epsilon_start ({self.epsilon_start})")
        if self.batch_size_episodes > self.buffer_size_episodes:
            raise ValueError(
                f"batch_size_episodes ({self.batch_size_episodes}) must be <= buffer_size_episodes ({self.buffer_size_episodes})"
            )
        return self

    @property
    def epsilon_anneal_env_steps(self) -> int:
        return int(round(self.epsilon_anneal_fraction * self.t_max_env_steps))


_QMIX_FIELDS = (
    "mixer",
    "gru_hidden",
    "fc_hidden",
    "share_agent_net",
    "mixing_embed_dim",
    "hypernet_embed_dim",
    "double_q",
    "n_step",
    "tau",
    "batch_size_episodes",
    "buffer_size_episodes",
    "learning_starts_episodes",
    "updates_per_iteration",
    "epsilon_start",
    "epsilon_end",
    "epsilon_anneal_env_steps",
    "torch_threads",
)


class QMIXConfig(AlgorithmConfig):
    """AlgorithmConfig of QMIX (mixer="qmix") and VDN (mixer="vdn")."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or QMIX)
        h = QMIXHParams()
        self.lr = h.lr
        self.gamma = h.gamma
        self.grad_clip = h.grad_clip
        self.grad_clip_by = "global_norm"
        self.mixer = "qmix"
        for name in _QMIX_FIELDS[1:-2]:
            setattr(self, name, getattr(h, name))
        self.epsilon_anneal_env_steps = h.epsilon_anneal_env_steps
        self.torch_threads = 1
        self.batch_mode = "truncate_episodes"

    def training(self, **kwargs) -> "QMIXConfig":
        for name in _QMIX_FIELDS:
            if name in kwargs:
                value = kwargs.pop(name)
                if value is not NotProvided:
                    setattr(self, name, value)
        super().training(**kwargs)
        return self

    @property
    def _model_config_auto_includes(self) -> dict[str, Any]:
        cfg = scenario_from(self.env_config) if self.env_config else ScenarioConfig()
        return super()._model_config_auto_includes | {
            "n_agents": cfg.n_uavs,
            "obs_dim": obs_dim(cfg),
            "state_dim": state_dim(cfg),
            "n_actions": cfg.n_joint_actions,
            **{name: getattr(self, name) for name in _QMIX_FIELDS if name not in ("n_step", "tau")},
        }

    def get_default_rl_module_spec(self) -> RLModuleSpec:
        return RLModuleSpec(module_class=QMixModule)

    def get_default_learner_class(self):
        return QMIXTorchLearner

    def validate(self) -> None:
        super().validate()
        if self.mixer not in MIXERS:
            self._value_error(f"mixer: expected one of {list(MIXERS)}, got {self.mixer!r}")
        if self.batch_size_episodes > self.buffer_size_episodes:
            self._value_error("batch_size_episodes must be <= buffer_size_episodes")


class VDNConfig(QMIXConfig):
    """QMIX's algorithm with the sum mixer."""

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or VDN)
        self.mixer = "vdn"


class QMIX(Algorithm):
    @classmethod
    def get_default_config(cls) -> QMIXConfig:
        return QMIXConfig()

    def setup(self, config) -> None:
        super().setup(config)
        cfg = scenario_from(self.config.env_config)
        self._scenario = cfg
        self._replay = EpisodeReplay(
            self.config.buffer_size_episodes,
            cfg.episode_len,
            cfg.n_uavs,
            obs_dim(cfg),
            state_dim(cfg),
            seed=self.config.seed,
        )
        self._pending: dict[str, list] = {}  # episode id -> chunks (only if a runner cut an episode)
        self._episodes_dropped = 0

    # ------------------------------------------------------------------ episodes -> replay
    def _store(self, episodes) -> dict[str, float]:
        """Add every complete episode to the replay; returns the sampled episodes' slot metrics."""
        ee, success = [], []
        t_len = self._scenario.episode_len
        for ep in episodes:
            chunks = self._pending.pop(ep.id_, []) + [ep]
            if not ep.is_done:
                self._pending[ep.id_] = chunks
                continue
            if chunks[0].t_started != 0:  # its start was never seen (e.g. after a restore)
                self._episodes_dropped += 1
                continue
            obs = np.concatenate([np.asarray(chunks[0].get_observations())] + [np.asarray(c.get_observations())[1:] for c in chunks[1:]])
            infos = list(chunks[0].get_infos()) + [i for c in chunks[1:] for i in list(c.get_infos())[1:]]
            actions = np.concatenate([np.asarray(c.get_actions()) for c in chunks])
            rewards = np.concatenate([np.asarray(c.get_rewards()) for c in chunks])
            if len(actions) != t_len:
                self._episodes_dropped += 1
                continue
            state = np.stack([np.asarray(i[STATE_KEY]) for i in infos])
            self._replay.add(obs, actions, rewards, state, terminated=bool(ep.is_terminated))
            ee.append(float(np.mean([i["ee_sys"] for i in infos[1:]])))
            success.append(float(np.mean([i["success_rate"] for i in infos[1:]])))
        if len(self._pending) > 4 * self.config.buffer_size_episodes:  # chunks of abandoned episodes
            self._pending.clear()
        return {"ee_sys": float(np.mean(ee)) if ee else float("nan"), "success_rate": float(np.mean(success)) if success else float("nan"), "n": len(ee)}

    # ------------------------------------------------------------------ the loop
    def training_step(self) -> None:
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            episodes, runner_results = synchronous_parallel_sample(
                worker_set=self.env_runner_group,
                concat=True,
                sample_timeout_s=self.config.sample_timeout_s,
                _uses_new_env_runners=True,
                _return_metrics=True,
            )
        self.metrics.aggregate(runner_results, key=ENV_RUNNER_RESULTS)
        sampled = self._store(episodes)
        env_steps = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        c = self.config
        self.metrics.log_dict(
            {
                "epsilon": linear_epsilon(env_steps, c.epsilon_start, c.epsilon_end, c.epsilon_anneal_env_steps),
                "replay_episodes": len(self._replay),
                "replay_episodes_added_lifetime": self._replay.added,
                "episodes_dropped_lifetime": self._episodes_dropped,
            },
            window=1,
        )
        if sampled["n"]:
            self.metrics.log_dict(
                {"sampled_ee_sys_mean": sampled["ee_sys"], "sampled_success_rate": sampled["success_rate"]}, window=1
            )
        if len(self._replay) < max(c.learning_starts_episodes, 1):
            self.metrics.log_value("num_gradient_updates_lifetime", 0, reduce="lifetime_sum")
            return
        t_len = self._scenario.episode_len
        for _ in range(c.updates_per_iteration):
            data = self._replay.sample(c.batch_size_episodes)
            batch = MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch(data)}, env_steps=c.batch_size_episodes * t_len)
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                learner_results = self.learner_group.update(
                    batch=batch, timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: env_steps}
                )
            self.metrics.aggregate(learner_results, key=LEARNER_RESULTS)
        # lifetime counter in the metrics logger, which checkpoints keep
        self.metrics.log_value("num_gradient_updates_lifetime", c.updates_per_iteration, reduce="lifetime_sum")
        with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
            self.env_runner_group.sync_weights(
                from_worker_or_learner_group=self.learner_group,
                policies=[DEFAULT_MODULE_ID],
                inference_only=True,
            )


class VDN(QMIX):
    @classmethod
    def get_default_config(cls) -> VDNConfig:
        return VDNConfig()


# ---------------------------------------------------------------------- registry glue
class GreedyQPolicy(RecurrentPolicy):
    """Decentralised greedy execution: each UAV's argmax Q over its own observation history."""

    def __init__(self, agent: AgentQNet, name: str):
        agent = copy.deepcopy(agent).cpu()
        zeros = lambda n: torch.zeros(n, agent.n_agents, agent.gru_hidden)  # noqa: E731
        super().__init__(agent, argmax_actions, zeros, name)
        self.agent = agent


def agent_network(algo: Algorithm) -> AgentQNet:
    """The learner's current agent Q-network (a CPU copy)."""
    mc = algo.config.model_config
    net = AgentQNet(mc["n_agents"], mc["obs_dim"], mc["n_actions"], mc["fc_hidden"], mc["gru_hidden"], mc["share_agent_net"])
    weights = algo.learner_group.get_weights([DEFAULT_MODULE_ID])[DEFAULT_MODULE_ID]
    net.load_state_dict({k[len("agent.") :]: torch.as_tensor(v) for k, v in weights.items() if k.startswith("agent.")})
    return net


def _greedy_policy(algo: Algorithm, scenario: ScenarioConfig) -> GreedyQPolicy:
    name = algo.config.env_config.get("uavlora_algorithm", algo.config.mixer)
    return GreedyQPolicy(agent_network(algo), name)


def _build(name: str, config_cls: type):
    def build(scenario: ScenarioConfig, hparams: QMIXHParams, resources: registry.Resources, seed: int) -> QMIXConfig:
        entry = registry.get(name)
        entry.check_scenario(scenario)
        if not isinstance(hparams, QMIXHParams):
            hparams = entry.hparams(hparams)
        from uavlora_rllib.envs.team import sample_through_team_env

        config = (
            sample_through_team_env(
                config_cls(), scenario, resources, name, rollout_fragment_length=scenario.episode_len, batch_mode="truncate_episodes"
            )
            .learners(num_learners=0, num_cpus_per_learner=resources.num_cpus_per_learner)
            .training(
                lr=hparams.lr,
                gamma=hparams.gamma,
                grad_clip=hparams.grad_clip,
                grad_clip_by="global_norm",
                epsilon_anneal_env_steps=hparams.epsilon_anneal_env_steps,
                torch_threads=resources.torch_threads,
                **{f: getattr(hparams, f) for f in _QMIX_FIELDS if f not in ("mixer", "epsilon_anneal_env_steps", "torch_threads")},
            )
            .debugging(seed=seed)
        )
        return config

    return build


for _name, _cls in (("qmix", QMIXConfig), ("vdn", VDNConfig)):
    registry.register(
        registry.AlgorithmEntry(
            name=_name,
            hparams_cls=QMIXHParams,
            action_modes=("per_uav",),
            build=_build(_name, _cls),
            greedy_policy=_greedy_policy,
        )
    )
