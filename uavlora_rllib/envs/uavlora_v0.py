"""The per-UAV env under PettingZoo's naming (`<name>_v<version>`), as `simple_spread_v3` ships it.

    from uavlora_rllib.envs import uavlora_v0
    par = uavlora_v0.parallel_env(n_eds=60, n_uavs=2)   # ParallelEnv (UavLoraParallelEnv)
    aec = uavlora_v0.env(n_eds=60, n_uavs=2)            # AEC: parallel_to_aec, order-enforced
    raw = uavlora_v0.raw_env(n_eds=60, n_uavs=2)        # AEC without PettingZoo's wrappers

Each factory takes ScenarioConfig fields as keywords and/or `scenario` (a ScenarioConfig or a
mapping of its fields), and `render_mode` (None or "rgb_array"). The version suffix changes
whenever the same seed and actions could give different observations or rewards
(docs/model.md#environments). Ray-free.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pettingzoo import AECEnv
from pettingzoo.utils.conversions import parallel_to_aec, parallel_to_aec_wrapper

from uavlora_rllib.envs.parallel import UavLoraParallelEnv, scenario_with
from uavlora_rllib.sim.scenario import ScenarioConfig

metadata = UavLoraParallelEnv.metadata


def parallel_env(
    scenario: ScenarioConfig | Mapping[str, Any] | None = None, render_mode: str | None = None, **fields: Any
) -> UavLoraParallelEnv:
    """The PettingZoo ParallelEnv of one scenario; a bad field or render_mode raises one ConfigError naming it."""
    return UavLoraParallelEnv(scenario_with(scenario, fields), render_mode=render_mode)


def raw_env(
    scenario: ScenarioConfig | Mapping[str, Any] | None = None, render_mode: str | None = None, **fields: Any
) -> AECEnv:
    """The AEC view of `parallel_env` (agents act in turn, the slot is played when the last has acted), unwrapped."""
    return parallel_to_aec_wrapper(parallel_env(scenario, render_mode, **fields))


def env(
    scenario: ScenarioConfig | Mapping[str, Any] | None = None, render_mode: str | None = None, **fields: Any
) -> AECEnv:
    """The AEC view with PettingZoo's order enforcing (`pettingzoo.utils.conversions.parallel_to_aec`)."""
    return parallel_to_aec(parallel_env(scenario, render_mode, **fields))
