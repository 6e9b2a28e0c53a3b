"""QMIX and VDN (value decomposition) on RLlib 2.60's new API stack, through the team view.

Sampling: env "uavlora_team" (envs/team.py): one RLlib "agent" = the whole UAV team, obs
[U, obs_dim] (row u = UAV u's LOCAL observation), action MultiDiscrete([A] * U) in per_uav mode
or MultiDiscrete [U, 2 quota + 1] in per_device mode, the shared reward, the global state in
info["state"]. Env runners hold only the agent Q-network (inference-only module) and act
decentralised: UAV u's action is the epsilon-greedy argmax of its own Q-values (per_device: of
each action branch, branching.py), computed from its own observation history (GRU state
carried by RLlib's connectors, zero at every episode start).

One training iteration (the common `EpisodeAlgorithm` loop, with QMIX's hooks):
  1. sample rollout_fragment_length = episode_len steps on every env of every env runner:
     num_envs_per_env_runner x max(1, num_env_runners) whole episodes;
  2. store them in the episode replay (|D| = buffer_size_episodes whole episodes);
  3. once the replay holds learning_starts_episodes episodes: updates_per_episode x the episodes
     stored in step 2 times (the fraction carries over to the next iteration; an explicit
     updates_per_iteration overrides it), sample batch_size_episodes whole episodes and run one TD update on the learner (the GRU
     is unrolled over whole episodes from a zero state: no burn-in, no truncated sequences,
     T = 150 is short enough), followed by a soft target update with tau;
  4. push the agent network's weights to the env runners.

Hyperparameters: `QMIXHParams` (`--list-hparams qmix`) and `VDNHParams`, its subclass that
differs in one default (updates_per_episode 1.0 against QMIX's 0.25); the mixer
is fixed by the name: "qmix" -> monotonic hypernetwork mixer, "vdn" -> sum; both add V(s) unless
state_bias is false, see qmix_module.py). Defaults follow
the paper's training table (docs/model.md); the epsilon schedule is linear from
epsilon_start to epsilon_end over epsilon_anneal_fraction x t_max_env_steps env steps (5% of
T_max = 2M).

Execution (common/policy.py): greedy = each UAV's argmax Q (per_device: per branch). Sampled = epsilon-greedy at
epsilon_end, the behaviour policy training converges to: a softmax over Q would need a
temperature on the scale of the returns, which nothing in the paper fixes, while epsilon_end
is the paper's own exploration setting (see `QMixModule._forward_exploration`).

Checkpoints (save_to_path / from_checkpoint) hold the config, the learner (agent net, mixer,
their targets, Adam state) and the env runners' weights. The replay buffer is NOT saved: a
restored run refills it (learning resumes after learning_starts_episodes new episodes).
"""

from __future__ import annotations

import numpy as np
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.annotations import override
from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.config import HParamsConfig
from uavlora_rllib.algorithms.common.episode_algorithm import EpisodeAlgorithm
from uavlora_rllib.algorithms.qmix.branching_module import BranchingQMixModule
from uavlora_rllib.algorithms.qmix.hparams import QMIXHParams, VDNHParams
from uavlora_rllib.algorithms.qmix.qmix_learner import QMIXTorchLearner
from uavlora_rllib.algorithms.qmix.qmix_module import QMixModule, linear_epsilon
from uavlora_rllib.algorithms.qmix.qmix_replay import EpisodeReplay
from uavlora_rllib.sim.actions import per_device_action_len
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig

MIXERS = ("qmix", "vdn")


class QMIXConfig(HParamsConfig, AlgorithmConfig):
    """AlgorithmConfig of QMIX (mixer="qmix") and VDN (mixer="vdn"); hyperparameters: QMIXHParams."""

    hparams_cls = QMIXHParams
    module_class = QMixModule
    learner_class = QMIXTorchLearner
    mixer = "qmix"

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or QMIX)
        self.hparams = QMIXHParams()
        self.torch_threads = 1
        self.batch_mode = "truncate_episodes"

    @override(HParamsConfig)
    def get_default_rl_module_spec(self) -> RLModuleSpec:
        """QMixModule in per_uav mode, BranchingQMixModule (factored agent network) in per_device mode."""
        per_device = self.model_config.get("action_mode") == "per_device"
        return RLModuleSpec(module_class=BranchingQMixModule if per_device else QMixModule)

    @override(HParamsConfig)
    def apply_hparams(self, h: QMIXHParams, scenario: ScenarioConfig) -> dict:
        self.training(lr=h.lr_schedule, gamma=h.gamma, grad_clip=h.grad_clip, grad_clip_by="global_norm")
        return {
            "mixer": self.mixer,
            "epsilon_anneal_env_steps": h.epsilon_anneal_env_steps,
            "action_mode": scenario.action_mode,
        }

    @override(HParamsConfig)
    def env_runner_settings(self, scenario: ScenarioConfig) -> dict:
        # one episode per env and sampling round: the replay stores whole episodes
        return {"rollout_fragment_length": scenario.episode_len, "batch_mode": "truncate_episodes"}


class VDNConfig(QMIXConfig):
    """QMIX's algorithm with the sum mixer (plus V(s) with state_bias: VDN-S); hyperparameters: VDNHParams."""

    hparams_cls = VDNHParams
    mixer = "vdn"

    def __init__(self, algo_class=None):
        super().__init__(algo_class=algo_class or VDN)
        self.hparams = VDNHParams()


class QMIX(EpisodeAlgorithm):
    """EpisodeAlgorithm over the episode replay: one sampling round of every env per
    iteration, updates_per_episode updates per episode added, each on batch_size_episodes
    episodes drawn from the replay."""

    @classmethod
    @override(Algorithm)
    def get_default_config(cls) -> QMIXConfig:
        return QMIXConfig()

    @override(EpisodeAlgorithm)
    def setup(self, config) -> None:
        super().setup(config)
        cfg = self.scenario
        self.replay = EpisodeReplay(
            self.config.hparams.buffer_size_episodes,
            cfg.episode_len,
            cfg.n_uavs,
            obs_dim(cfg),
            state_dim(cfg),
            seed=self.config.seed,
            action_len=per_device_action_len(cfg) if cfg.action_mode == "per_device" else None,
        )
        self._pending: dict[str, list] = {}  # episode id -> chunks (only if a runner cut an episode)
        self._episodes_dropped = 0
        # updates owed but not yet run (< 1): with updates_per_episode 0.25 and 2 episodes per
        # iteration, every second iteration runs one update. Not checkpointed: a restore forgets < 1 update.
        self._update_credit = 0.0

    @override(EpisodeAlgorithm)
    def episodes_per_runner(self) -> int:
        return self.config.num_envs_per_env_runner

    @override(EpisodeAlgorithm)
    def add_episodes(self, episodes: list) -> int:
        added = self._store(episodes)
        c = self.config.hparams
        env_steps = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        self.metrics.log_dict(
            {
                "epsilon": linear_epsilon(env_steps, c.epsilon_start, c.epsilon_end, c.epsilon_anneal_env_steps),
                "replay_episodes": len(self.replay),
                "replay_episodes_added_lifetime": self.replay.added,
                "episodes_dropped_lifetime": self._episodes_dropped,
            },
            window=1,
        )
        if len(self.replay) < c.learning_starts_episodes:
            return 0
        return c.updates_per_iteration if c.updates_per_iteration is not None else self._updates_due(added)

    @override(EpisodeAlgorithm)
    def next_batch(self) -> MultiAgentBatch:
        n = self.config.hparams.batch_size_episodes
        data = self.replay.sample(n)
        return MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch(data)}, env_steps=n * self.scenario.episode_len)

    def _updates_due(self, episodes_added: int) -> int:
        """Gradient updates this iteration, updates_per_episode per episode added (see setup)."""
        self._update_credit += episodes_added * self.config.hparams.updates_per_episode
        n = int(self._update_credit + 1e-9)  # 1e-9: 4 x 0.25 adds up to exactly 1, never 0.999...
        self._update_credit = max(self._update_credit - n, 0.0)
        return n

    def _store(self, episodes) -> int:
        """Add every complete episode to the replay (chunks of a cut episode are joined first);
        returns how many were added."""
        t_len = self.scenario.episode_len
        added = 0
        for ep in episodes:
            chunks = self._pending.pop(ep.id_, []) + [ep]
            if not ep.is_done:
                self._pending[ep.id_] = chunks
                continue
            if chunks[0].t_started != 0:  # its start was never seen (e.g. after a restore)
                self._episodes_dropped += 1
                continue
            obs = np.concatenate(
                [np.asarray(chunks[0].get_observations())] + [np.asarray(c.get_observations())[1:] for c in chunks[1:]]
            )
            infos = list(chunks[0].get_infos()) + [i for c in chunks[1:] for i in list(c.get_infos())[1:]]
            actions = np.concatenate([np.asarray(c.get_actions()) for c in chunks])
            rewards = np.concatenate([np.asarray(c.get_rewards()) for c in chunks])
            if len(actions) != t_len:
                self._episodes_dropped += 1
                continue
            state = np.stack([np.asarray(i[GLOBAL_STATE]) for i in infos])
            self.replay.add(obs, actions, rewards, state, terminated=bool(ep.is_terminated))
            added += 1
        if len(self._pending) > 4 * self.config.hparams.buffer_size_episodes:  # chunks of abandoned episodes
            self._pending.clear()
        return added


class VDN(QMIX):
    @classmethod
    @override(QMIX)
    def get_default_config(cls) -> VDNConfig:
        return VDNConfig()


registry.register_algorithm("qmix", QMIXConfig)
registry.register_algorithm("vdn", VDNConfig)
