"""Non-learning policies for the execution phase: random, fixed, LoRaWAN ADR, greedy, per-slot optimum."""

from uavlora_rllib.baselines.policies import BASELINES, OBJECTIVES, make_baseline

__all__ = ["BASELINES", "OBJECTIVES", "make_baseline"]
