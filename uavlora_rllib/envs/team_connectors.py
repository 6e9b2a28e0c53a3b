"""The env runner's connectors for the team view, one piece each way (docs/model.md#acting-connectors).

RLlib's default env-to-module pipeline is five pieces (observations, time rank, recurrent state,
batching, tensors) and its module-to-env pipeline six (get actions, numpy, unbatch, time rank,
clip, listify), each timed and walked item by item per scenario. For the team view, where every
scenario of the vector env is one single-agent episode with the same spaces, each direction is a
few stacked-array operations. These two pieces build exactly what the default pipelines build for
this env and these modules (tests/test_team_connectors.py compares them on every learner), in one
call each way:

* `TeamEnvToModule`: OBS, the last observation of every episode, [N, 1, ...] for a stateful module
  (RLlib's single-step time rank) or [N, ...]; STATE_IN, each episode's last STATE_OUT, or the
  module's initial state where an episode has not stepped yet; as tensors on the runner's device.
* `TeamModuleToEnv`: the module's outputs as numpy, the time rank removed (not from STATE_OUT), one
  item per scenario; ACTIONS stays one [N, ...] array, which the env runner steps the vector env
  with (a module's own ACTIONS_FOR_ENV is dropped: with RLlib's default normalize_actions the
  default pipeline replaces it by ACTIONS). This package's modules return ACTIONS; for a module
  that returns only ACTION_DIST_INPUTS, RLlib's own GetActions samples them first. The team view's
  actions are discrete: nothing to clip.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import tree
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.connectors.module_to_env.get_actions import GetActions
from ray.rllib.core.columns import Columns
from ray.rllib.utils.annotations import override
from ray.rllib.utils.numpy import convert_to_numpy
from ray.rllib.utils.spaces.space_utils import batch as batch_items
from ray.rllib.utils.torch_utils import convert_to_torch_tensor


def _per_episode(data: Any, n: int, squeezed: bool = False) -> list[Any]:
    """A batched column (an array, or a dict of them as STATE_OUT is) -> its n per-scenario items, views as
    RLlib's `unbatch` gives them, at 1/7 of its cost (dm-tree's walk per item). squeezed: the column lost its
    time rank here, and an [N] column's items are then 0-d arrays (np.squeeze's), not scalars."""
    if isinstance(data, dict):
        parts = {k: _per_episode(v, n, squeezed) for k, v in data.items()}
        return [{k: v[i] for k, v in parts.items()} for i in range(n)]
    return [np.asarray(x) for x in data] if squeezed and data.ndim == 1 else list(data)


class TeamEnvToModule(ConnectorV2):
    """Episodes -> {OBS, STATE_IN} tensors for forward_exploration/forward_inference (see module doc)."""

    def __init__(self, input_observation_space=None, input_action_space=None, *, device=None, **kwargs):
        super().__init__(input_observation_space, input_action_space, **kwargs)
        self._device = device

    @override(ConnectorV2)
    def __call__(
        self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], explore=None, shared_data=None, **kwargs
    ) -> Any:
        obs = np.stack([episode.get_observations(-1) for episode in episodes])
        stateful = rl_module.is_stateful()
        # NumpyToTensor's conversion (float64 -> float32, the runner's device)
        batch[Columns.OBS] = convert_to_torch_tensor(obs[:, None] if stateful else obs, device=self._device)
        if stateful:
            init = None
            states = []
            for episode in episodes:
                # AddStatesFromEpisodesToBatch's rule for env runners (Ray 2.60)
                fresh = episode.t_started == 0 and len(episode) == 0
                if fresh or Columns.STATE_OUT not in episode.extra_model_outputs:
                    init = convert_to_numpy(rl_module.get_initial_state()) if init is None else init
                    states.append(init)
                else:
                    states.append(episode.get_extra_model_outputs(key=Columns.STATE_OUT, indices=-1))
            batch[Columns.STATE_IN] = convert_to_torch_tensor(batch_items(states), device=self._device)
        return batch


class TeamModuleToEnv(ConnectorV2):
    """The module's outputs -> what the env runner steps the env with and stores per scenario (module doc)."""

    def __init__(self, input_observation_space=None, input_action_space=None, **kwargs):
        super().__init__(input_observation_space, input_action_space, **kwargs)
        self._get_actions = GetActions()

    @override(ConnectorV2)
    def __call__(
        self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], explore=None, shared_data=None, **kwargs
    ) -> Any:
        if Columns.ACTIONS not in batch:  # a module that returns only its distribution's inputs
            batch = self._get_actions(rl_module=rl_module, batch=batch, episodes=episodes, explore=explore)
        out = convert_to_numpy(batch)
        timed = rl_module.is_stateful()  # TeamEnvToModule gave every input but STATE_IN a time rank of 1
        to_env: dict[str, Any] = {}
        out.pop(Columns.ACTIONS_FOR_ENV, None)  # the env gets ACTIONS, as after the default's normalize/clip
        for column, data in out.items():
            if column == Columns.STATE_OUT:
                to_env[column] = _per_episode(data, len(episodes))
                continue
            data = tree.map_structure(lambda x: x[:, 0], data) if timed else data
            to_env[column] = data if column == Columns.ACTIONS else _per_episode(data, len(episodes), timed)
        return to_env


def team_env_to_module(env: Any = None, spaces: Any = None, device: Any = None) -> TeamEnvToModule:
    """`config.env_runners(env_to_module_connector=...)` for the team view."""
    return TeamEnvToModule(device=device)


def team_module_to_env(env: Any = None, spaces: Any = None) -> TeamModuleToEnv:
    """`config.env_runners(module_to_env_connector=...)` for the team view, whose actions are discrete:
    RLlib's clipping and unsquashing, which this piece leaves out, would have nothing to do."""
    space = getattr(env, "single_action_space", None)
    if space is not None and not isinstance(space, (gym.spaces.Discrete, gym.spaces.MultiDiscrete)):
        raise ValueError(f"team_module_to_env: the env's actions must be discrete (they are not clipped); got {space}")
    return TeamModuleToEnv()
