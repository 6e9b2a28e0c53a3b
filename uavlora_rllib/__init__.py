"""uavlora-rllib: multi-agent RL for UAV-assisted LoRa networks on Ray RLlib.

The main public names are importable from here, resolved on first use rather than at package
import: the simulator pulls in SciPy and the RLlib view Ray (seconds), and every
`python -m uavlora_rllib.<cli> --help` imports this package first. Importing the package
registers the team view with Gymnasium as "UavLora-v0" (`envs.registration`, Gymnasium only).
"""

from __future__ import annotations

import importlib
from typing import Any

from uavlora_rllib.envs.registration import register_gymnasium_ids

_LAZY = {
    "BatchCore": "uavlora_rllib.sim.core",
    "ScenarioConfig": "uavlora_rllib.sim.scenario",
    "UavLoraParallelEnv": "uavlora_rllib.envs.parallel",
    "UavLoraMultiAgentEnv": "uavlora_rllib.envs.multi_agent",
    "UavLoraTeamEnv": "uavlora_rllib.envs.team",
}

__all__ = ["BatchCore", "ScenarioConfig", "UavLoraMultiAgentEnv", "UavLoraParallelEnv", "UavLoraTeamEnv"]
__version__ = "0.1.0"

register_gymnasium_ids()


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'uavlora_rllib' has no attribute {name!r}")
