"""The per-UAV PettingZoo `ParallelEnv` over one scenario, and the plumbing every env view shares.

Ray-free on purpose: PettingZoo and Gymnasium users (`envs.uavlora_v0`, `gymnasium.make`) get
the simulator without importing Ray (docs/model.md#environments). The RLlib view lives in
`envs.multi_agent`. Agents are the UAV gateways ``uav_0..uav_{U-1}``; they share one reward.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.actions import ActionError, as_integers, per_device_action_len
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig

_NP_INTS = frozenset(
    np.sctypeDict[k] for k in ("int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64")
)
LOOKAHEAD = 32  # slots of positions/channels/association/observations precomputed at once (BatchCore)
STATE_KEY = "state"
# "human": one line per slot on stdout, printed by reset and step (the simulator is headless; Gymnasium's
# human mode may render to "the current display or terminal"); "rgb_array": render() returns the frame
RENDER_MODES = ["human", "rgb_array"]
RENDER_FPS = 2  # frames per second of real time: one slot of the default dt_s = 0.5 s per frame


def check_render_mode(render_mode: str | None) -> str | None:
    """`render_mode` if an env view supports it, else ConfigError (docs/model.md#environments)."""
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ConfigError(
            f"render_mode: {render_mode!r} is not supported; allowed: None, "
            + ", ".join(repr(m) for m in RENDER_MODES)
            + " (for an animation of an episode: python -m analysis.animate)"
        )
    return render_mode


def env_metadata(base: Mapping[str, Any], cfg: ScenarioConfig) -> dict[str, Any]:
    """`base` with render_fps = 1 / dt_s of this scenario (frames in real time; docs/model.md#environments)."""
    return {**base, "render_fps": 1.0 / cfg.mobility.dt_s}


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
    raise ConfigError(f"scenario: expected a ScenarioConfig or a mapping of its fields, got {type(config).__name__}")


def scenario_with(scenario: Any, fields: Mapping[str, Any]) -> ScenarioConfig:
    """`scenario` (as `scenario_from` takes it) with top-level ScenarioConfig `fields` on top,
    validated (the factories' keywords, docs/model.md#environments)."""
    if not fields:
        return scenario_from(scenario)
    return ScenarioConfig.from_dict({**scenario_from(scenario).to_dict(), **fields})


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
            rows.append(as_integers(value, f"action of {a}", what).astype(np.int64).reshape(shape))
        return np.stack(rows)[None]

    def global_state(self) -> np.ndarray:
        return self.core.state()[0].astype(np.float32)

    def _render_rgb(self) -> np.ndarray:
        return render_rgb(self.core, self._last_metrics)

    def _show_human(self) -> None:
        """render_mode "human": print the slot's line (reset and step call it)."""
        if getattr(self, "render_mode", None) == "human":
            print(human_line(self.core, self._last_metrics), flush=True)


def human_line(core: BatchCore, metrics: Mapping[str, float]) -> str:
    """render_mode "human": the slot just played (reward, EE_sys in bit/J, success rate; none
    after a reset) and the association of the current slot, as one terminal line."""
    cfg = core.cfg
    t, serving = int(core.t[0]), core.serving[0]
    per_uav = np.bincount(serving[serving >= 0], minlength=cfg.n_uavs).tolist()
    now = f"slot {t}/{cfg.episode_len}: EDs per UAV {per_uav}, unassociated {int((serving < 0).sum())}"
    if not metrics:
        return f"[uavlora] reset; {now}"
    return (
        f"[uavlora] played slot {t - 1}: reward {metrics['reward']:.4g}, EE_sys {metrics['ee_sys']:.4g} bit/J, "
        f"success {metrics['success_rate']:.3f}; {now}"
    )


def render_rgb(core: BatchCore, metrics: Mapping[str, float]) -> np.ndarray:
    """Scenario 0 of `core` as an [H, W, 3] uint8 image: the association map, slot and EE_sys in the title."""
    from uavlora_rllib.sim.render import association_rgb  # matplotlib: only when drawing

    cfg = core.cfg
    title = f"t={int(core.t[0])}  EE={metrics.get('ee_sys', float('nan')):.0f} bit/J"
    return association_rgb(core.ed_xy[0], core.uav_xy, core.serving[0], cfg.comm_range_m, cfg.area_m, title)


class UavLoraParallelEnv(_SingleScenario, ParallelEnv):
    """PettingZoo ParallelEnv over one scenario."""

    metadata = {"name": "uavlora_v0", "render_modes": RENDER_MODES, "render_fps": RENDER_FPS, "is_parallelizable": True}

    def __init__(self, scenario: ScenarioConfig | Mapping[str, Any] | None = None, render_mode: str | None = None):
        self.render_mode = check_render_mode(render_mode)
        self._setup(scenario_from(scenario))
        self.metadata = env_metadata(type(self).metadata, self.scenario)
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
        self._show_human()
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
        self._show_human()
        return (
            obs,
            {a: reward for a in agents},
            {a: False for a in agents},
            {a: done for a in agents},
            {a: dict(self._last_metrics) for a in agents},
        )

    def state(self) -> np.ndarray:
        return self.global_state()

    def render(self) -> np.ndarray | None:
        """The current slot's frame [H, W, 3] uint8 with render_mode "rgb_array"; None otherwise
        ("human" printed its line in reset/step)."""
        if self.render_mode != "rgb_array":
            return None
        return self._render_rgb()

    def close(self) -> None:
        pass
