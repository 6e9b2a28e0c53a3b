"""Decentralised execution of a trained team-view RLModule, greedy or sampled.

Every algorithm of the project acts through its RLModule's own public forward passes, the
ones RLlib's env runners call: `forward_inference` (greedy: the argmax action per UAV) and
`forward_exploration` (sampled: an action drawn from the policy that training samples from;
for QMIX/VDN epsilon-greedy at the final epsilon, see qmix_module). The module's outputs hold
Columns.ACTIONS; the GRU state is carried across slots and cleared at each episode start.

Weights come through public RLlib APIs only: the module's architecture from the algorithm's
env runner (`Algorithm.get_module`, inference-only: actor / agent network, no critic or
mixer), its weights from the learners (`LearnerGroup.get_weights`), which works with local
and remote learners alike and is current right after a training step or a restore.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig


def trained_module(algo, module_id: str = DEFAULT_MODULE_ID):
    """A private CPU copy of the algorithm's inference-only RLModule with the learners' weights."""
    module = algo.get_module(module_id)
    if module is None:
        raise ValueError(f"algorithm has no RLModule {module_id!r}")
    module = copy.deepcopy(module.unwrapped()).to("cpu")
    module.set_state(algo.learner_group.get_weights([module_id])[module_id])
    return module.eval()


class ModulePolicy:
    """evaluation.Policy over a team-view RLModule (observation [U, d] per scenario).

    `explore=True` samples; its random stream is the policy's own (seeded by `seed`, kept
    apart from torch's global generator), so an evaluation is reproducible."""

    def __init__(self, module, name: str, explore: bool = False, seed: int = 0):
        self.module, self.name, self.explore = module, name, explore
        self.state: dict[str, torch.Tensor] | None = None
        gen = torch.Generator().manual_seed(int(seed))
        self._rng_state = gen.get_state()

    def reset(self, core: BatchCore) -> None:
        init = self.module.get_initial_state()
        self.state = {k: torch.as_tensor(v).unsqueeze(0).repeat(core.n, *([1] * np.ndim(v))) for k, v in init.items()}

    def act(self, core: BatchCore) -> np.ndarray:
        if self.state is None or next(iter(self.state.values())).shape[0] != core.n:
            self.reset(core)
        # Clipped and float32 exactly as the team env hands observations to the env runners.
        obs = torch.as_tensor(np.clip(core.obs, -1.0, 1.0), dtype=torch.float32).unsqueeze(1)  # [N, 1, U, d]
        batch = {Columns.OBS: obs, Columns.STATE_IN: self.state}
        with torch.no_grad(), torch.random.fork_rng(devices=[]):
            torch.set_rng_state(self._rng_state)
            out = self.module.forward_exploration(batch) if self.explore else self.module.forward_inference(batch)
            self._rng_state = torch.get_rng_state()
        self.state = out[Columns.STATE_OUT]
        return out[Columns.ACTIONS][:, 0].numpy().astype(np.int64)


def check_module_fits(module, scenario: ScenarioConfig) -> None:
    """A trained module runs on a scenario only with the same team spaces (U, obs_dim, actions)."""
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    want_obs, want_act = team_observation_space(scenario), team_action_space(scenario)
    if tuple(module.observation_space.shape) != tuple(want_obs.shape):
        raise ConfigError(
            f"scenario: the trained module expects observations {tuple(module.observation_space.shape)}, "
            f"this scenario gives {tuple(want_obs.shape)} (n_uavs / observation layout differ)"
        )
    if not np.array_equal(np.asarray(module.action_space.nvec), np.asarray(want_act.nvec)):
        raise ConfigError(
            f"scenario.action_mode: the trained module acts in {np.asarray(module.action_space.nvec).tolist()}, "
            f"this scenario needs {np.asarray(want_act.nvec).tolist()} ({scenario.action_mode!r})"
        )


def team_policy(algo, scenario: ScenarioConfig, explore: bool = False, seed: int = 0) -> ModulePolicy:
    """The registry's default policy factory: the trained module, greedy or sampled."""
    module = trained_module(algo)
    check_module_fits(module, scenario)
    name = algo.config.env_config.get("uavlora_algorithm", type(algo).__name__.lower())
    return ModulePolicy(module, name, explore=explore, seed=seed)
