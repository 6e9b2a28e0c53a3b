"""Non-learning policies for the execution phase: random, fixed, LoRaWAN ADR, the best constant
(best_fixed), greedy, per-slot optimum; and an upper bound on the per-slot optimum (bound)."""

from uavlora_rllib.baselines.policies import BASELINES, OBJECTIVES, baseline_names, make_baseline, register_baseline

__all__ = ["BASELINES", "OBJECTIVES", "baseline_names", "make_baseline", "register_baseline"]
