"""uavlora-rllib: multi-agent RL for UAV-assisted LoRa networks on Ray RLlib.

The main public names are importable from here. The env classes pull in Ray and RLlib (seconds
to import), so they are resolved on first use rather than at package import.
"""

from __future__ import annotations

import importlib
from typing import Any

from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

_LAZY = {
    "UavLoraParallelEnv": "uavlora_rllib.envs.multi_agent",
    "UavLoraMultiAgentEnv": "uavlora_rllib.envs.multi_agent",
}

__all__ = ["BatchCore", "ScenarioConfig", "UavLoraMultiAgentEnv", "UavLoraParallelEnv"]
__version__ = "0.1.0"


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'uavlora_rllib' has no attribute {name!r}")
