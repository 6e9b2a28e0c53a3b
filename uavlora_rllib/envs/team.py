"""The team view: all UAVs of a scenario as one Gymnasium env, and N scenarios as one vector env.

Centralised-training algorithms (a mixer, a joint critic, a centralised value function)
need every agent's observation and action and the global state at the same time step.
The team view gives them exactly that without RLlib's agent grouping (which has known bugs
on 2.60, see docs/model.md#environments): observation [U, obs_dim] (row u is agent u's LOCAL
observation; decentralised actors read only their own row), action MultiDiscrete of U
entries (per_uav) or [U, 2 Lambda + 1] (per_device), the shared reward, and the global state
under info["state"].

`UavLoraTeamVectorEnv` steps N scenarios with ONE `BatchCore`, so RLlib's env runners sample
through the vectorised core (config.env_runners(num_envs_per_env_runner=N,
gym_env_vectorize_mode="vector_entry_point")). It follows Gymnasium's NEXT_STEP autoreset,
which RLlib's SingleAgentEnvRunner expects: the step after an episode ends resets that
scenario and ignores its action.

Ray-free: `gymnasium.make("UavLora-v0", n_eds=..., n_uavs=...)` and
`gymnasium.make_vec("UavLora-v0", num_envs=N, vectorization_mode="vector_entry_point")` build
them without importing Ray (docs/model.md#environments).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.envs.parallel import (
    RENDER_FPS,
    RENDER_MODES,
    STATE_KEY,
    check_render_mode,
    env_metadata,
    human_line,
    observation_space,
    render_rgb,
    scenario_from,
    scenario_with,
    state_space,
)
from uavlora_rllib.sim.actions import as_integers, per_device_action_len
from uavlora_rllib.sim.core import BatchCore, check_n_envs
from uavlora_rllib.sim.scenario import ScenarioConfig

TEAM_ENV_NAME = "uavlora_team"  # its name in Tune's registry (registered by envs.multi_agent, which imports Ray)
GYM_ID = "UavLora-v0"  # its Gymnasium id (registered by `import uavlora_rllib`)


def team_observation_space(cfg: ScenarioConfig) -> gym.spaces.Box:
    single = observation_space(cfg)
    return gym.spaces.Box(-1.0, 1.0, shape=(cfg.n_uavs, single.shape[0]), dtype=np.float32)


def team_action_space(cfg: ScenarioConfig) -> gym.spaces.MultiDiscrete:
    if cfg.action_mode == "per_uav":
        return gym.spaces.MultiDiscrete(np.full(cfg.n_uavs, cfg.n_joint_actions, dtype=np.int64))
    row = [cfg.n_sf, cfg.n_tp] * cfg.quota + [cfg.n_bw]
    assert len(row) == per_device_action_len(cfg)
    return gym.spaces.MultiDiscrete(np.tile(np.asarray(row, dtype=np.int64), (cfg.n_uavs, 1)))


def _obs32(obs: np.ndarray) -> np.ndarray:
    return np.clip(obs, -1.0, 1.0).astype(np.float32)


class UavLoraTeamEnv(gym.Env):
    """One scenario, all UAVs as one agent-team (a thin view of BatchCore with N = 1).

    The class is also the env specifier the algorithms give RLlib
    (`config.environment(UavLoraTeamEnv, ...)`): when RLlib's env runner asks for a vector
    env it calls the class with `num_envs` in the config, and gets a `UavLoraTeamVectorEnv`
    (one BatchCore for all N scenarios). Passing the class rather than a registered name
    keeps working across Ray sessions in one process, where Tune's env registry does not.
    """

    metadata = {"render_modes": RENDER_MODES, "render_fps": RENDER_FPS}

    def __new__(cls, config: Mapping[str, Any] | ScenarioConfig | None = None, *args: Any, **kwargs: Any):
        if isinstance(config, Mapping) and config.get("num_envs") is not None:
            settings = dict(config)
            return UavLoraTeamVectorEnv(settings, num_envs=int(settings.pop("num_envs")))
        return super().__new__(cls)

    def __init__(self, config: Mapping[str, Any] | ScenarioConfig | None = None, render_mode: str | None = None):
        self.render_mode = check_render_mode(render_mode)
        self.scenario = scenario_from(config)
        self.metadata = env_metadata(type(self).metadata, self.scenario)
        self.core = BatchCore(self.scenario, 1)
        self.observation_space = team_observation_space(self.scenario)
        self.action_space = team_action_space(self.scenario)
        self.state_space = state_space(self.scenario)
        self._last_metrics: dict[str, float] = {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs = self.core.reset(seed)  # checks the seed (a ConfigError naming it), before gymnasium's own message
        super().reset(seed=seed)
        self._last_metrics = {}
        self._show_human()
        return _obs32(obs[0]), {STATE_KEY: self.core.state()[0].astype(np.float32)}

    def step(self, action):
        res = self.core.step(as_integers(np.asarray(action), "action", "integers")[None])
        info = {k: float(v[0]) for k, v in res.metrics.items()}
        self._last_metrics = dict(info)
        self._show_human()
        info[STATE_KEY] = self.core.state()[0].astype(np.float32)
        return _obs32(res.obs[0]), float(res.reward[0]), False, bool(res.truncated[0]), info

    def render(self) -> np.ndarray | None:
        """The association map as an [H, W, 3] uint8 frame (render_mode "rgb_array"), else None
        ("human" printed its line in reset/step)."""
        if self.render_mode != "rgb_array":
            return None
        return render_rgb(self.core, self._last_metrics)

    def _show_human(self) -> None:
        if self.render_mode == "human":
            print(human_line(self.core, self._last_metrics), flush=True)


class UavLoraTeamVectorEnv(gym.vector.VectorEnv):
    """N scenarios stepped by one BatchCore; Gymnasium vector API with NEXT_STEP autoreset."""

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}

    def __init__(self, config: Mapping[str, Any] | ScenarioConfig | None = None, num_envs: int = 1):
        self.scenario = scenario_from(config)
        self.num_envs = check_n_envs(num_envs, "num_envs")
        self.core = BatchCore(self.scenario, self.num_envs)
        self.single_observation_space = team_observation_space(self.scenario)
        self.single_action_space = team_action_space(self.scenario)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.state_space = state_space(self.scenario)
        self._needs_reset = np.zeros(self.num_envs, dtype=bool)
        self._seeds = np.random.SeedSequence()  # episodes' seeds after the first reset (docs/model.md#seeds)

    def _infos(self, metrics: Mapping[str, np.ndarray] | None, live: np.ndarray) -> dict[str, np.ndarray]:
        """Gymnasium's dict-of-arrays infos; metrics only for scenarios that really stepped."""
        infos: dict[str, np.ndarray] = {STATE_KEY: self.core.state().astype(np.float32)}
        infos["_" + STATE_KEY] = np.ones(self.num_envs, dtype=bool)
        if metrics is not None:
            for key, value in metrics.items():
                infos[key] = value
                infos["_" + key] = live.copy()
        return infos

    def reset(self, *, seed: int | list[int] | None = None, options: dict | None = None):
        """seed s: scenario i gets s + i, and later episodes children of SeedSequence(s); a list (Gymnasium's
        vector API): one seed per scenario, later episodes children of SeedSequence(list); None continues that
        stream (Gymnasium's seeding contract; fresh entropy before any seed)."""
        if seed is not None:
            obs = self.core.reset(seed)  # checks each seed, before SeedSequence's own message
            self._seeds = np.random.SeedSequence(seed)
        else:
            obs = self.core.reset(list(self._seeds.spawn(self.num_envs)))
        self._needs_reset[:] = False
        return _obs32(obs), self._infos(None, np.zeros(self.num_envs, dtype=bool))

    def step(self, actions):
        actions = as_integers(np.asarray(actions), "action", "integers")
        restart = self._needs_reset.copy()
        if restart.any():
            # NEXT_STEP autoreset: these scenarios ignore their action and start a new episode.
            # Their placeholder action (0) is valid, so the whole batch can still step below.
            actions = np.where(restart.reshape((-1,) + (1,) * (actions.ndim - 1)), 0, actions)
        if restart.all():
            seeds = [s for s in self._seeds.spawn(self.num_envs)]
            obs = self.core.reset(seeds)
            self._needs_reset[:] = False
            zeros = np.zeros(self.num_envs)
            false = np.zeros(self.num_envs, dtype=bool)
            return _obs32(obs), zeros, false, false.copy(), self._infos(None, false)
        res = self.core.step(actions)
        rewards = np.where(restart, 0.0, res.reward)
        truncated = np.where(restart, False, res.truncated)
        if restart.any():
            restart_seeds: list[np.random.SeedSequence | None] = [None] * self.num_envs
            for i, s in zip(np.flatnonzero(restart), self._seeds.spawn(int(restart.sum()))):
                restart_seeds[i] = s
            self.core.reset(restart_seeds, mask=restart)
        self._needs_reset = truncated.copy()
        terminated = np.zeros(self.num_envs, dtype=bool)
        return _obs32(self.core.obs), rewards, terminated, truncated, self._infos(res.metrics, ~restart)


def make_team_env(config: Mapping[str, Any] | None = None):
    """Env creator (registered with Tune as "uavlora_team"): a vector env when `num_envs` is given."""
    return UavLoraTeamEnv(dict(config or {}))


def gym_env(
    scenario: Mapping[str, Any] | ScenarioConfig | None = None, render_mode: str | None = None, **fields: Any
) -> UavLoraTeamEnv:
    """`gymnasium.make("UavLora-v0", ...)`'s entry point: ScenarioConfig fields as keywords or
    `scenario` (docs/model.md#environments); a bad field is one ConfigError naming it."""
    return UavLoraTeamEnv(scenario_with(scenario, fields), render_mode=render_mode)


def gym_vector_env(
    num_envs: int = 1,
    scenario: Mapping[str, Any] | ScenarioConfig | None = None,
    render_mode: str | None = None,
    **fields: Any,
) -> UavLoraTeamVectorEnv:
    """`gymnasium.make_vec("UavLora-v0", num_envs=N, vectorization_mode="vector_entry_point")`:
    N scenarios in one BatchCore (docs/model.md#environments); frames are not drawn for N > 1."""
    if render_mode is not None:
        raise ConfigError(f"render_mode: the vector env draws no frames; allowed: None, got {render_mode!r}")
    return UavLoraTeamVectorEnv(scenario_with(scenario, fields), num_envs=num_envs)


def sample_through_team_env(
    config: Any, scenario: ScenarioConfig, resources: Any, algorithm: str, **env_runner_settings: Any
) -> Any:
    """`config` (an RLlib AlgorithmConfig) set to sample the team view: N scenarios per env
    runner in ONE BatchCore (`gym_env_vectorize_mode="vector_entry_point"`), with the trial's
    `registry.Resources`. The algorithm's own env-runner settings (fragment length, batch mode)
    pass through `env_runner_settings`."""
    from uavlora_rllib.envs.team_connectors import team_env_to_module, team_module_to_env  # imports Ray

    # one connector piece each way instead of RLlib's 5 + 6 (docs/model.md#acting-connectors); an
    # algorithm's own env_runner_settings may set its connectors instead
    connectors = {
        "env_to_module_connector": team_env_to_module,
        "add_default_connectors_to_env_to_module_pipeline": False,
        "module_to_env_connector": team_module_to_env,
        "add_default_connectors_to_module_to_env_pipeline": False,
    }
    return config.environment(
        UavLoraTeamEnv, env_config={"scenario": scenario.to_dict(), "uavlora_algorithm": algorithm}
    ).env_runners(
        num_env_runners=resources.num_env_runners,
        num_envs_per_env_runner=resources.num_envs_per_env_runner,
        num_cpus_per_env_runner=resources.num_cpus_per_env_runner,
        gym_env_vectorize_mode="vector_entry_point",
        **{**connectors, **env_runner_settings},
    )
