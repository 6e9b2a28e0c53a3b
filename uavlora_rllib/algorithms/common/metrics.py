"""The paper's per-slot metrics of the sampled training episodes, one way for every algorithm.

RLlib callbacks on the env runners: each episode sums EE_sys (bits/J) and Xi (success rate)
from its step infos; at its end the per-slot means go into the env runner's metrics, which
every algorithm aggregates into result["env_runners"]: `ee_sys_mean` and `success_rate`
(per-slot mean over an episode, then the mean over the episodes that ended in the iteration).
"""

from __future__ import annotations

from typing import Any

EE_SYS_MEAN = "ee_sys_mean"
SUCCESS_RATE = "success_rate"


def _on_episode_step(*, episode, **kwargs) -> None:
    info = episode.get_infos(-1)
    if "ee_sys" in info:  # not in the reset info (no slot played yet)
        data = episode.custom_data
        data["ee_sum"] = data.get("ee_sum", 0.0) + float(info["ee_sys"])
        data["xi_sum"] = data.get("xi_sum", 0.0) + float(info["success_rate"])
        data["slots"] = data.get("slots", 0) + 1


def _on_episode_end(*, episode, metrics_logger=None, **kwargs) -> None:
    data = episode.custom_data
    n = data.get("slots", 0)
    if n and metrics_logger is not None:
        metrics_logger.log_value(EE_SYS_MEAN, data["ee_sum"] / n, reduce="mean")
        metrics_logger.log_value(SUCCESS_RATE, data["xi_sum"] / n, reduce="mean")


def log_episode_metrics(config: Any) -> Any:
    """`config` (an AlgorithmConfig) with the episode-metric callbacks installed."""
    return config.callbacks(on_episode_step=_on_episode_step, on_episode_end=_on_episode_end)
