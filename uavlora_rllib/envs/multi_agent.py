"""The two environment views of one scenario: PettingZoo `ParallelEnv` and RLlib `MultiAgentEnv`.

Both wrap a `BatchCore` with N = 1 and add only the dict-of-agents plumbing; every number
comes from the core (and so from `physics`). Agents are the UAV gateways ``uav_0..uav_{U-1}``;
they share one reward. Every info carries the slot's metrics (`physics.SLOT_METRICS`); the
RLlib view also puts the global state under ``info["state"]`` for centralised critics.
"""

from __future__ import annotations

from typing import Any, Mapping

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv
from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.tune.registry import register_env

from uavlora_rllib.sim.actions import ActionError, per_device_action_len
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.render import association_rgb
from uavlora_rllib.sim.scenario import ScenarioConfig

ENV_NAME = "uavlora"
_NP_INTS = frozenset(np.sctypeDict[k] for k in ("int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64"))
LOOKAHEAD = 32  # slots of positions/channels/association/observations precomputed at once (BatchCore)
STATE_KEY = "state"


def agent_ids(cfg: ScenarioConfig) -> list[str]:
    return [f"uav_{i}" for i in range(cfg.n_uavs)]


def observation_space(cfg: ScenarioConfig) -> gym.spaces.Box:
    return gym.spaces.Box(-1.0, 1.0, shape=(obs_dim(cfg),), dtype=np.float32)


def state_space(cfg: ScenarioConfig) -> gym.spaces.Box:
    return gym.spaces.Box(-3.0, 1.0, shape=(state_dim(cfg),), dtype=np.float32)


def action_space(cfg: ScenarioConfig) -> gym.spaces.Space:
    if cfg.action_mode == "per_uav":
        return gym.spaces.Discrete(cfg.n_joint_actions)
    return gym.spaces.MultiDiscrete([cfg.n_sf, cfg.n_tp] * cfg.quota + [cfg.n_bw])


def scenario_from(config: Any) -> ScenarioConfig:
    """Accept a ScenarioConfig, a mapping of scenario fields, or an env config {"scenario": ...}."""
    if isinstance(config, ScenarioConfig):
        return config
    if config is None:
        return ScenarioConfig()
    if isinstance(config, Mapping):
        inner = config.get("scenario", None) if "scenario" in config else {k: v for k, v in config.items()}
        if isinstance(inner, ScenarioConfig):
            return inner
        return ScenarioConfig.from_dict(inner)
    raise TypeError(f"env config: expected a ScenarioConfig or a mapping, got {type(config).__name__}")


class _SingleScenario:
    """Shared plumbing: one-scenario core, dict <-> array conversion, metric infos."""

    def _setup(self, cfg: ScenarioConfig) -> None:
        self.scenario = cfg
        self.core = BatchCore(cfg, n_envs=1, lookahead=LOOKAHEAD)
        self.possible_agents = agent_ids(cfg)
        self._obs_space = observation_space(cfg)
        self._act_space = action_space(cfg)
        self._state_space = state_space(cfg)
        self._last_metrics: dict[str, float] = {}
        self._per_uav = cfg.action_mode == "per_uav"

    def _obs_dict(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        # cast then clip: the same float32 values as clip then cast (rounding is monotone)
        obs32 = obs[0].astype(np.float32)
        np.maximum(obs32, -1.0, out=obs32)
        np.minimum(obs32, 1.0, out=obs32)
        return dict(zip(self.possible_agents, obs32))

    def _actions_array(self, actions: Mapping[str, Any]) -> np.ndarray:
        # Fast path: exactly the agents, each a plain (numpy) integer, in per_uav mode; the core
        # checks the range. Anything else goes through the checks below.
        if self._per_uav and len(actions) == len(self.possible_agents):
            try:
                values = [actions[a] for a in self.possible_agents]
            except KeyError:
                values = None
            if values is not None and all(type(x) is int or type(x) in _NP_INTS for x in values):
                return np.array(values, dtype=np.int64).reshape(1, -1)
        return self._actions_array_checked(actions)

    def _actions_array_checked(self, actions: Mapping[str, Any]) -> np.ndarray:
        missing = [a for a in self.possible_agents if a not in actions]
        unknown = [a for a in actions if a not in self.possible_agents]
        if missing or unknown:
            raise ActionError(
                f"actions: need one action for each of {self.possible_agents}; missing {missing}, unknown {unknown}"
            )
        if self.scenario.action_mode == "per_uav":
            shape: tuple[int, ...] = ()
            what = "one integer (Discrete)"
        else:
            shape = (per_device_action_len(self.scenario),)
            what = f"{shape[0]} integers (MultiDiscrete)"
        rows = []
        for a in self.possible_agents:
            value = np.asarray(actions[a])
            # Reject (rather than silently truncate or crash on) wrong sizes and non-integer values.
            if value.dtype.kind not in "iuf" or value.size != int(np.prod(shape)):
                raise ActionError(f"action of {a}: expected {what}, got {value.dtype} of shape {value.shape}")
            if value.dtype.kind == "f" and not (np.isfinite(value).all() and (value == np.round(value)).all()):
                raise ActionError(f"action of {a}: expected {what}, got non-integer values {value.tolist()}")
            rows.append(value.astype(np.int64).reshape(shape))
        return np.stack(rows)[None]

    def global_state(self) -> np.ndarray:
        return self.core.state()[0].astype(np.float32)

    def _render_rgb(self) -> np.ndarray:
        c = self.core
        cfg = self.scenario
        title = f"t={int(c.t[0])}  EE={self._last_metrics.get('ee_sys', float('nan')):.0f} bit/J"
        return association_rgb(c.ed_xy[0], c.uav_xy, c.serving[0], cfg.comm_range_m, cfg.area_m, title)


class UavLoraParallelEnv(_SingleScenario, ParallelEnv):
    """PettingZoo ParallelEnv over one scenario."""

    metadata = {"name": "uavlora_v0", "render_modes": ["rgb_array"], "is_parallelizable": True}

    def __init__(self, scenario: ScenarioConfig | Mapping[str, Any] | None = None, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: {render_mode!r} is not one of [None, 'rgb_array']")
        self.render_mode = render_mode
        self._setup(scenario_from(scenario))
        self.agents: list[str] = []

    def observation_space(self, agent: str) -> gym.spaces.Space:
        return self._obs_space

    def action_space(self, agent: str) -> gym.spaces.Space:
        return self._act_space

    @property
    def state_space(self) -> gym.spaces.Space:
        return self._state_space

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs = self.core.reset(seed)
        self.agents = list(self.possible_agents)
        self._last_metrics = {}
        return self._obs_dict(obs), {a: {} for a in self.agents}

    def step(self, actions: Mapping[str, Any]):
        if not self.agents:
            raise RuntimeError("step() after the episode ended; call reset()")
        res = self.core.step(self._actions_array(actions))
        self._last_metrics = {k: float(v[0]) for k, v in res.metrics.items()}
        reward = float(res.reward[0])
        done = bool(res.truncated[0])
        obs = self._obs_dict(res.obs)
        agents = self.agents
        if done:
            self.agents = []
        return (
            obs,
            {a: reward for a in agents},
            {a: False for a in agents},
            {a: done for a in agents},
            {a: dict(self._last_metrics) for a in agents},
        )

    def state(self) -> np.ndarray:
        return self.global_state()

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        return self._render_rgb()

    def close(self) -> None:
        pass


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
