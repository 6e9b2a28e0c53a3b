"""COMA (Foerster et al., AAAI 2018): counterfactual multi-agent policy gradients, as an RLlib
Algorithm on the new API stack, registered as "coma".

Sampling goes through the team view ("uavlora_team": observation [U, obs_dim], action
MultiDiscrete([90] * U), shared reward, global state in info["state"]); each env runner steps
N scenarios through one vectorised BatchCore. One training iteration:
  1. sample `batch_episodes` whole episodes (T = episode_len steps each) with the current
     policy (see `_sample_episodes` for why it asks for timesteps, not episodes),
  2. one learner update (`updates_per_iteration` of them on the same batch): critic TD(lambda)
     loss + counterfactual actor loss (coma_learner.py),
  3. target critic update after each update (soft tau per update, or hard every K updates),
  4. sync the actor's weights to the env runners (inference-only: they never hold the critic).
Networks: coma_module.py. Hyperparameters: `COMAHParams` (grid YAML `algorithms.coma`,
`--list-hparams coma`). Execution (common/policy.py): greedy = argmax of each UAV's actor
logits; sampled = a draw from the actor's softmax, the stochastic policy COMA trains.
Only the per_uav action mode is supported (the critic outputs one Q per action of a UAV,
which needs a single Discrete action per agent).

Choices beyond the paper (each a COMAHParams field, documented there): the critic trains
`critic_steps` = 4 extra steps on each batch before the joint actor + critic step (the paper
trains the critic first); TD(lambda) with lambda 0.8; the critic's lr is 5e-4; a dueling,
SF/TP/BW-factored Q head; per-UAV actor output layers. Evidence in tests/test_coma.py.
"""

from __future__ import annotations

import torch
import tree
from pydantic import Field
from pydantic.dataclasses import dataclass as typed_dataclass
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
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

from uavlora_rllib.algorithms.coma.coma_learner import COMAEpisodeBatch, COMATorchLearner
from uavlora_rllib.algorithms.coma.coma_module import COMATorchRLModule
from uavlora_rllib.algorithms.common.config import HParamsConfig, team_config
from uavlora_rllib.algorithms.common.registry import AlgorithmEntry, Resources, register
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

NAME = "coma"


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class COMAHParams:
    """COMA's hyperparameters; defaults from the paper's training table where it has them."""

    lr_actor: float = Field(1e-4, gt=0, le=1, description="Adam step size of the actor [1/update] (paper: lr 1e-4)")
    lr_critic: float = Field(
        5e-4,
        gt=0,
        le=1,
        description="Adam step size of the critic [1/update] (decision: pymarl's COMA critic lr; the paper's "
        "1e-4 is the actor's, and the critic must track the policy within ~830 updates)",
    )
    gamma: float = Field(0.99, gt=0, le=1, description="discount per slot [-]")
    td_lambda: float = Field(0.8, ge=0, le=1, description="lambda of the critic's TD(lambda) targets [-] (Foerster et al.)")
    entropy_coeff: float = Field(0.01, ge=0, description="weight of the mean per-agent policy entropy in the actor loss [1/nat]")
    grad_clip: float = Field(10.0, gt=0, description="max global L2 gradient norm, per optimizer (actor, critic) [-]")
    batch_episodes: int = Field(
        16, ge=1, description="whole episodes per update [episodes] (paper: batch 16); a multiple of all envs"
    )
    tau: float = Field(0.01, gt=0, le=1, description="Polyak weight of the target critic per update [-] (paper)")
    target_hard_update_every: int = Field(
        0, ge=0, description="> 0: hard target copy every K updates instead of Polyak [updates]"
    )
    actor_hidden: int = Field(128, ge=1, description="width of the actor's ReLU layer before the GRU [units]")
    gru_hidden: int = Field(128, ge=1, description="GRU width of the actor [units] (paper)")
    actor_agent_heads: bool = Field(
        True, description="each UAV also gets its own linear output layer, added to the shared one [bool]"
    )
    critic_hidden: tuple[int, ...] = Field((128, 128), description="ReLU layer widths of the critic MLP [units]")
    critic_use_obs: bool = Field(True, description="also give the critic UAV u's own observation row [bool]")
    critic_factored_actions: bool = Field(
        True,
        description="use the (SF, TP, BW) structure of an action in the critic: other UAVs' actions also as "
        "one-hot SF/TP/BW, and u's outputs share per-SF/TP/BW terms [bool]",
    )
    critic_dueling: bool = Field(
        True, description="Q = V + (D - mean D) head: untried actions start at the state's value [bool]"
    )
    critic_steps: int = Field(
        4, ge=0, description="critic-only gradient steps on each batch before the joint step [steps] (critic first, as in the paper)"
    )
    updates_per_iteration: int = Field(
        8,
        ge=1,
        description="learner updates (critic steps + joint step + target move) on each sampled batch [updates]; "
        "> 1 turns the actor's term into PPO's clipped surrogate r A (r = pi / pi_sampling per UAV, clipped at "
        "1 +- ratio_clip), because from the second update on the batch is off-policy; 1: COMA's plain "
        "on-policy gradient (decision: 1 -> 8 took greedy EE from 0.63 to 1.000 of the optimum at V=10/U=2 "
        "within 60k env steps and from 0.73 to 0.998 of the greedy baseline at V=60/U=4; BENCHMARKS.md "
        "'Learning at scale')",
    )
    ratio_clip: float = Field(
        0.2, gt=0, le=1, description="clip of each UAV's probability ratio when updates_per_iteration > 1 [-]"
    )
    critic_warmup_updates: int = Field(0, ge=0, description="first updates that train the critic only [updates]; 0: off")
    normalize_advantages: bool = Field(False, description="standardise the advantages over the batch [bool] (not in COMA)")
    reward_scale: float = Field(1.0, gt=0, description="factor on the rewards in the critic targets [-]")

    def check(self, scenario: ScenarioConfig, resources: Resources, path: str) -> None:
        """COMA learns from whole episodes, sampled in whole rounds of all envs of all runners."""
        runners = max(1, resources.num_env_runners)
        if self.batch_episodes % (runners * resources.num_envs_per_env_runner):
            raise ConfigError(
                f"{path}.batch_episodes: {self.batch_episodes} is not a multiple of num_env_runners "
                f"({runners}) x num_envs_per_env_runner ({resources.num_envs_per_env_runner}); COMA learns from "
                "whole episodes, sampled in whole rounds of all envs"
            )


def _coma_learner_connector(obs_space, act_space) -> list:
    return [COMAEpisodeBatch()]


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
        # COMA's batch is whole episodes stacked by COMAEpisodeBatch, not RLlib's chunking.
        self.add_default_connectors_to_learner_pipeline = False
        self.learners(learner_connector=_coma_learner_connector)

    @override(HParamsConfig)
    def apply_hparams(self, h: COMAHParams, scenario: ScenarioConfig) -> dict:
        self.training(
            lr=h.lr_actor,
            gamma=h.gamma,
            grad_clip=h.grad_clip,
            grad_clip_by="global_norm",
            train_batch_size_per_learner=h.batch_episodes * scenario.episode_len,
        )
        factors = [scenario.n_sf, scenario.n_tp, scenario.n_bw] if h.critic_factored_actions else []
        return {"action_factors": factors, "critic_hidden": list(h.critic_hidden)}


class COMA(Algorithm):
    @classmethod
    @override(Algorithm)
    def get_default_config(cls) -> COMAConfig:
        return COMAConfig()

    @override(Algorithm)
    def setup(self, config) -> None:
        torch.set_num_threads(int(getattr(config, "torch_threads", 1) or 1))
        super().setup(config)

    @override(Algorithm)
    def training_step(self) -> None:
        with self.metrics.log_time((TIMERS, ENV_RUNNER_SAMPLING_TIMER)):
            episodes, runner_metrics = self._sample_episodes()
        self.metrics.aggregate(runner_metrics, key=ENV_RUNNER_RESULTS)
        self.metrics.log_value("num_episodes_trained", len(episodes), reduce="sum")

        # updates_per_iteration > 1: the same episodes again (the learner clips the actor's
        # probability ratio to the policy that sampled them, their ACTION_LOGP)
        for _ in range(self.config.hparams.updates_per_iteration):
            with self.metrics.log_time((TIMERS, LEARNER_UPDATE_TIMER)):
                learner_results = self.learner_group.update(
                    episodes=episodes,
                    timesteps={
                        NUM_ENV_STEPS_SAMPLED_LIFETIME: self.metrics.peek(
                            (ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0
                        )
                    },
                )
            self.metrics.aggregate(learner_results, key=LEARNER_RESULTS)
        # lifetime counter in the metrics logger, which checkpoints keep (as QMIX's)
        self.metrics.log_value(
            "num_gradient_updates_lifetime", self.config.hparams.updates_per_iteration, reduce="lifetime_sum"
        )

        with self.metrics.log_time((TIMERS, SYNCH_WORKER_WEIGHTS_TIMER)):
            self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group, inference_only=True)

    def _sample_episodes(self):
        """`batch_episodes` whole episodes, split evenly over the env runners.

        Asks each runner for (its episodes x T) TIMESTEPS rather than `num_episodes`: RLlib
        2.60's `sample(num_episodes=...)` re-resets every env with the runner's fixed seed on
        every call, which would replay the same scenarios in every iteration. All envs of a
        runner start together and every episode lasts exactly T steps (truncation), so
        (episodes per runner) x T timesteps end exactly at an episode boundary: the runner
        returns whole episodes only and continues with fresh seeds on the next call."""
        cfg = self.config
        runners = max(1, cfg.num_env_runners)
        steps = cfg.hparams.batch_episodes // runners * self._episode_len
        out = self.env_runner_group.foreach_env_runner(
            lambda runner: (runner.sample(num_timesteps=steps, explore=True), runner.get_metrics()),
            local_env_runner=self.env_runner_group.num_remote_workers() <= 0,
        )
        episodes = [ep for ep in tree.flatten([o[0] for o in out]) if ep.is_done]
        return episodes, [o[1] for o in out]

    @property
    def _episode_len(self) -> int:
        return ScenarioConfig.from_dict(self.config.env_config["scenario"]).episode_len


# ------------------------------------------------------------------ registry
def build(scenario: ScenarioConfig, hparams: COMAHParams | dict | None, resources: Resources, seed: int) -> COMAConfig:
    if not isinstance(hparams, COMAHParams):
        hparams = ENTRY.hparams(hparams)
    ENTRY.check_scenario(scenario)
    return team_config(COMAConfig(), NAME, scenario, hparams, resources, seed)


ENTRY = AlgorithmEntry(name=NAME, hparams_cls=COMAHParams, action_modes=("per_uav",), build=build)
register(ENTRY)
