"""Scoring a slot: the metrics and the shared reward of the agents' actions on the slot's links.

Two routes to the same equations (docs/model.md):
- `physics.slot_metrics` on per-ED allocations: every action mode and model;
- `physics.slot_metrics_shared` for per_uav actions with the paper's interference and the
  Shannon rate: all EDs of a UAV share its allocation, so its factors come out of the per-ED
  sums (fewer per-ED passes; equal to slot_metrics up to rounding, tested to 1e-12).
"""

from __future__ import annotations

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import PER_UAV_GATHER_MIN, ActionDecoder, check_range
from uavlora_rllib.sim.links import Links
from uavlora_rllib.sim.scenario import ScenarioConfig


class SlotScorer:
    """`score(actions, links, gains)` -> (metrics, parts): physics.SLOT_METRICS, each [N], and
    what ActionDecoder.previous_allocation builds the slot's allocations from (only if asked).
    `gains` [N, U, V]: every pair's gain, read only by the all-pairs models (None with the
    nearest-UAV links)."""

    def __init__(self, cfg: ScenarioConfig, decoder: ActionDecoder, tables: physics.Tables):
        self.cfg = cfg
        self.decoder = decoder
        self.tables = tables
        self.shared = cfg.action_mode == "per_uav" and cfg.interference == "paper" and cfg.rate_model == "shannon"
        # (chosen once: a single-env step is dominated by per-call costs)
        self.score = self._score_shared if self.shared else self._score_per_ed
        # per_uav action index -> the allocation its UAV's EDs share (slot_metrics_shared)
        sf_a, tp_a, bw_a = decoder.joint_table.T
        self._alloc_table = physics.SharedAllocationTable(sf_a, tp_a, bw_a, tables)

    def _score_per_ed(
        self, actions: np.ndarray, links: Links, gains: np.ndarray | None
    ) -> tuple[dict[str, np.ndarray], tuple]:
        """physics.slot_metrics on each ED's allocation."""
        cfg, decoder = self.cfg, self.decoder
        tp: np.ndarray | None
        bw: np.ndarray | None
        values: tuple | None
        actions_idx: tuple | None
        if cfg.action_mode == "per_uav" and links.serving_idx.size > PER_UAV_GATHER_MIN:
            sf, values, actions_idx = decoder.per_uav_values(actions, links)
            tp = bw = None
        else:
            sf, tp, bw = decoder.allocations(actions, links)
            values = actions_idx = None
        metrics = physics.slot_metrics(
            gains, links.serving_idx, links.associated, sf, tp, bw, cfg, self.tables, g_serving=links.g_serving,
            values=values,
        )  # fmt: skip
        return metrics, (sf, tp, bw, actions_idx, None if links.all_associated else links.associated)

    def _score_shared(
        self, actions: np.ndarray, links: Links, gains: np.ndarray | None = None
    ) -> tuple[dict[str, np.ndarray], tuple]:
        """physics.slot_metrics_shared on each UAV's allocation; the per-ED allocations are
        decoded only if asked (previous_allocation)."""
        decoder = self.decoder
        actions = np.asarray(actions)
        check_range(actions, decoder.per_uav_shape, decoder.n_joint)  # (decoder.check_per_uav, one call less)
        idx = links.serving_idx + decoder.act_base  # flat index of each ED's serving UAV in [N, U]
        metrics = physics.slot_metrics_shared(
            links.g_serving, links.g_db_serving, idx, links.associated, links.counts, self._alloc_table.take(actions),
            self.cfg, self.tables,
        )  # fmt: skip
        # (a copy of the actions: the caller may reuse its array)
        return metrics, (None, None, None, (actions.copy(), idx), None if links.all_associated else links.associated)
