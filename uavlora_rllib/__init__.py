"""uavlora-rllib: multi-agent RL for UAV-assisted LoRa networks on Ray RLlib."""

from uavlora_rllib.scenario import ScenarioConfig

__all__ = ["ScenarioConfig"]
__version__ = "0.1.0"
