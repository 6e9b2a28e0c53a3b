"""The RLlib `MultiAgentEnv` view of one scenario, and the Tune names ``uavlora`` (this view)
and ``uavlora_team`` (the team view of `envs.team`).

It wraps a `BatchCore` with N = 1 through the plumbing of `envs.parallel` (which also holds the
PettingZoo `UavLoraParallelEnv`, re-exported here) and adds only RLlib's dict-of-agents
conventions: every info carries the slot's metrics (`physics.SLOT_METRICS`) and the global
state under ``info["state"]`` for centralised critics (docs/model.md#environments).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.tune.registry import register_env

from uavlora_rllib.envs.parallel import (  # noqa: F401  (re-exported: the names' old home)
    LOOKAHEAD,
    STATE_KEY,
    UavLoraParallelEnv,
    _SingleScenario,
    action_space,
    agent_ids,
    observation_space,
    scenario_from,
    state_space,
)
from uavlora_rllib.envs.team import TEAM_ENV_NAME, make_team_env
from uavlora_rllib.sim.scenario import ScenarioConfig

ENV_NAME = "uavlora"


class UavLoraMultiAgentEnv(_SingleScenario, MultiAgentEnv):
    """RLlib MultiAgentEnv (new API stack) over one scenario; env config {"scenario": {...}}."""

    def __init__(self, config: Mapping[str, Any] | ScenarioConfig | None = None):
        super().__init__()
        self._setup(scenario_from(config))
        self.agents = list(self.possible_agents)
        self.observation_spaces = {a: self._obs_space for a in self.possible_agents}
        self.action_spaces = {a: self._act_space for a in self.possible_agents}
        self.state_space = self._state_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs = self.core.reset(seed)
        self.agents = list(self.possible_agents)
        state = self.global_state()
        return self._obs_dict(obs), {a: {STATE_KEY: state} for a in self.agents}

    def step(self, action_dict: Mapping[str, Any]):
        res = self.core.step(self._actions_array(action_dict))
        metrics = {k: float(v[0]) for k, v in res.metrics.items()}
        self._last_metrics = metrics
        reward = float(res.reward[0])
        done = bool(res.truncated[0])
        state = self.global_state()
        agents = self.possible_agents
        truncs = {a: done for a in agents}
        truncs["__all__"] = done
        terms = {a: False for a in agents}
        terms["__all__"] = False
        return (
            self._obs_dict(res.obs),
            {a: reward for a in agents},
            terms,
            truncs,
            {a: {**metrics, STATE_KEY: state} for a in agents},
        )

    def render(self) -> np.ndarray:
        return self._render_rgb()


register_env(ENV_NAME, lambda config: UavLoraMultiAgentEnv(config))
register_env(TEAM_ENV_NAME, make_team_env)
