"""A real learner for the Tune/MLflow tests: RLlib's stock PPO on env "uavlora".

Registers the algorithm "stock_ppo" (one policy module shared by all UAVs, RLlib's default
MLP), and the same learner under a second name "stock_ppo_b" so grid tests can expand
several algorithms, through the grid's `plugins:` mechanism (`plugins: [tune_stock_ppo]`), so the Tune infrastructure is tested with a
real `Algorithm` (training, checkpoints, restore, greedy evaluation) before the project's
own algorithms exist. Not a paper algorithm and never offered to users: it lives in tests/.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field
from pydantic.dataclasses import dataclass as typed_dataclass

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.envs.multi_agent import UavLoraMultiAgentEnv

NAMES = ("stock_ppo", "stock_ppo_b")
SHARED = "shared"


@typed_dataclass(config={"extra": "forbid", "frozen": True})
class StockPPOHparams:
    lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate [1]")
    gamma: float = Field(0.99, gt=0, le=1, description="discount factor [1]")
    train_batch_size: int = Field(200, ge=1, description="env steps per training batch [env steps]")
    minibatch_size: int = Field(100, ge=1, description="env steps per minibatch [env steps]")
    num_epochs: int = Field(1, ge=1, description="passes over each batch [epochs]")
    hidden: int = Field(32, ge=1, description="width of each hidden layer [units]")


def _map_to_shared(agent_id, episode, **kwargs):
    return SHARED


def _build(name: str, scenario, hp: StockPPOHparams, resources: registry.Resources, seed: int):
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    from uavlora_rllib.config_errors import ConfigError

    if hp.minibatch_size > hp.train_batch_size:
        # a cross-check in build(), as the project's algorithms do (e.g. coma: batch x resources)
        raise ConfigError(
            f"algorithms.{name}.minibatch_size: {hp.minibatch_size} is larger than the train batch "
            f"({hp.train_batch_size})"
        )

    return (
        PPOConfig()
        .environment(UavLoraMultiAgentEnv, env_config={"scenario": scenario.to_dict(), "uavlora_algorithm": name})
        .multi_agent(policies={SHARED}, policy_mapping_fn=_map_to_shared)
        .env_runners(
            num_env_runners=resources.num_env_runners,
            num_envs_per_env_runner=resources.num_envs_per_env_runner,
            num_cpus_per_env_runner=resources.num_cpus_per_env_runner,
        )
        .learners(
            num_learners=resources.num_learners,
            num_gpus_per_learner=resources.num_gpus_per_learner,
            num_cpus_per_learner=resources.num_cpus_per_learner,
        )
        .rl_module(model_config=DefaultModelConfig(fcnet_hiddens=[hp.hidden]))
        .training(
            lr=hp.lr,
            gamma=hp.gamma,
            train_batch_size_per_learner=hp.train_batch_size,
            minibatch_size=hp.minibatch_size,
            num_epochs=hp.num_epochs,
        )
        .debugging(seed=seed)
    )


class SharedModulePolicy:
    """Decentralised execution: each UAV's own observation -> the shared module's logits ->
    argmax (greedy) or a draw from the softmax (explore=True, from the policy's own generator)."""

    def __init__(self, module, scenario, explore: bool = False, seed: int = 0):
        import torch

        self.name = "stock_ppo_sampled" if explore else "stock_ppo_greedy"
        self.module = module
        self.scenario = scenario
        self.explore = explore
        self.gen = torch.Generator().manual_seed(int(seed))

    def reset(self, core) -> None:
        pass

    def act(self, core) -> np.ndarray:
        import torch

        obs = np.clip(core.obs, -1.0, 1.0).astype(np.float32)  # [N, U, d]
        n, u, d = obs.shape
        with torch.no_grad():
            out = self.module.forward_inference({"obs": torch.from_numpy(obs.reshape(n * u, d))})
        logits = out["action_dist_inputs"]
        if self.explore:
            actions = torch.multinomial(torch.softmax(logits, -1), 1, generator=self.gen)[:, 0]
        else:
            actions = logits.argmax(-1)
        return actions.numpy().reshape(n, u).astype(np.int64)


def make_policy(algo, scenario, explore: bool = False, seed: int = 0):
    # the env runner's module, synced after every update (stock PPO, one local env runner)
    return SharedModulePolicy(algo.get_module(SHARED), scenario, explore=explore, seed=seed)


def _entry(name: str) -> registry.AlgorithmEntry:
    def build(scenario, hp, resources, seed):
        return _build(name, scenario, hp, resources, seed)

    return registry.AlgorithmEntry(
        name=name, hparams_cls=StockPPOHparams, action_modes=("per_uav",), build=build, make_policy=make_policy
    )


for _name in NAMES:
    registry.register(_entry(_name))
