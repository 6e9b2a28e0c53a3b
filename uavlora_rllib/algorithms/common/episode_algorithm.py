"""The training loop of the algorithms that learn from whole episodes (QMIX/VDN, COMA).

One iteration, `EpisodeAlgorithm.training_step`:
  1. every env runner samples `episodes_per_runner()` x episode_len env steps: whole episodes,
     since all envs of a runner start together and every episode lasts exactly episode_len
     slots (truncation);
  2. `add_episodes` takes them (QMIX/VDN: into the replay; COMA: the next train batch) and
     returns how many learner updates are due;
  3. that many times: `update_learners(next_batch())`;
  4. the learners' weights go to the env runners (their inference-only modules), unless no
     update ran.
The hooks are what differs between the algorithms; everything else is here.
"""

from __future__ import annotations

import abc
from typing import Any

import tree
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.policy.sample_batch import MultiAgentBatch
from ray.rllib.utils.annotations import override
from ray.rllib.utils.metrics import (
    ENV_RUNNER_RESULTS,
    ENV_RUNNER_SAMPLING_TIMER,
    LEARNER_RESULTS,
    LEARNER_UPDATE_TIMER,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    SYNCH_WORKER_WEIGHTS_TIMER,
    TIMERS,
)

from uavlora_rllib.envs.multi_agent import scenario_from

# lifetime count of learner updates, in the metrics logger (which checkpoints keep)
NUM_GRADIENT_UPDATES_LIFETIME = "num_gradient_updates_lifetime"


class EpisodeAlgorithm(Algorithm, abc.ABC):
    """sample whole episodes -> add_episodes -> N x update_learners(next_batch()) -> sync weights."""

    @override(Algorithm)
    def setup(self, config) -> None:
        super().setup(config)
        self.scenario = scenario_from(self.config.env_config)

    @override(Algorithm)
    def training_step(self) -> None:
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            episodes, runner_metrics = self.sample_episodes()
        self.metrics.aggregate(runner_metrics, key=ENV_RUNNER_RESULTS)
        n_updates = self.add_episodes(episodes)
        timesteps = {
            NUM_ENV_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
                (ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0
            )
        }
        if n_updates:
            # one timer entry per iteration, as RLlib's own algorithms log it (the timer is an EMA
            # over entries: bench_train reads one iteration's learning time back from it,
            # experiment/training_rate.this_iteration)
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                for _ in range(n_updates):
                    learner_results = self.update_learners(self.next_batch(), timesteps)
                    self.metrics.aggregate(learner_results, key=LEARNER_RESULTS)
        self.metrics.log_value(NUM_GRADIENT_UPDATES_LIFETIME, n_updates, reduce="lifetime_sum")
        if n_updates:
            with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
                self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group, inference_only=True)

    def sample_episodes(self) -> tuple[list, list]:
        """The episodes of one sampling round on every env runner, and the runners' metrics.

        Each runner is asked for `episodes_per_runner()` x episode_len TIMESTEPS rather than
        `num_episodes`: RLlib 2.60's `sample(num_episodes=...)` re-resets every env with the
        runner's fixed seed on every call, which would replay the same scenarios in every
        iteration, while a timestep count that ends on an episode boundary continues with
        fresh seeds on the next call."""
        steps = self.episodes_per_runner() * self.scenario.episode_len
        out = self.env_runner_group.foreach_env_runner(
            lambda runner: (runner.sample(num_timesteps=steps, explore=True), runner.get_metrics()),
            local_env_runner=self.env_runner_group.num_remote_workers() <= 0,
        )
        return tree.flatten([o[0] for o in out]), [o[1] for o in out]

    @abc.abstractmethod
    def episodes_per_runner(self) -> int:
        """Episodes each env runner samples per iteration (a multiple of its envs)."""

    @abc.abstractmethod
    def add_episodes(self, episodes: list) -> int:
        """Take this iteration's episodes; return how many learner updates are due now."""

    @abc.abstractmethod
    def next_batch(self) -> MultiAgentBatch:
        """The train batch of the next learner update."""

    def update_learners(self, batch: MultiAgentBatch, timesteps: dict[str, Any]) -> Any:
        """One learner update on `batch`; returns the learners' results."""
        return self.learner_group.update(batch=batch, timesteps=timesteps)
