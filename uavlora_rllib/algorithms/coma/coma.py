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

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.coma.coma_learner import COMATorchLearner, episode_batch
from uavlora_rllib.algorithms.coma.coma_module import TD_TARGETS, COMATorchRLModule
from uavlora_rllib.algorithms.coma.hparams import NAME, COMAHParams
from uavlora_rllib.algorithms.common.config import HParamsConfig
from uavlora_rllib.algorithms.common.episode_algorithm import EpisodeAlgorithm
from uavlora_rllib.algorithms.common.registry import register_algorithm
from uavlora_rllib.sim.scenario import ScenarioConfig


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
        has seen the batch. The joint update's batch carries the critic-only steps' TD(lambda)
        targets (TD_TARGETS): the target critic has not moved in between."""
        if self.config.hparams.critic_steps:
            results = list(self.learner_group.foreach_learner(lambda learner: learner.train_critic(batch)))
            for result in results:
                if not result.ok:  # a remote learner's error (a local one raises here directly)
                    raise result.get()
            # every learner trained on the whole batch against the same target critic: the first one's
            # TD(lambda) targets become the joint step's (its module then skips the target critic)
            targets = results[0].get()
            batch = MultiAgentBatch(
                {
                    mid: SampleBatch({**b, TD_TARGETS: targets[mid]}) if mid in targets else b
                    for mid, b in batch.policy_batches.items()
                },
                env_steps=batch.env_steps(),
            )
        return super().update_learners(batch, timesteps)


register_algorithm(NAME, COMAConfig)
