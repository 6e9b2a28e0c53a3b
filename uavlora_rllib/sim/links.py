"""The ED-UAV links of a slot: the channel, the association, and each served ED's row.

A link stage maps the ED positions of N scenarios to `Links`: which UAV serves each ED (the
association of docs/model.md), the channel of that link (d_h, G, G in dB), and each served
ED's rank by gain among its UAV's EDs (its row in the UAV's observation and, in per_device
mode, its part of the UAV's action). Two stages:

- `NearestLinks`: greedy association with the paper's SINR and a gain strictly decreasing in
  d_h (the defaults). Every ED's max-gain UAV is then its nearest one, so the channel is
  computed at the serving UAV only ([N, V] work per slot, not [N, U, V]); the per-pair channel
  is left for whoever asks (`pair_channels`).
- `AllPairLinks`: every pair's channel each slot, as the optimal association, the cross-gain
  SINR or a non-monotone channel need it.

`default_link_stage(cfg, n)` picks NearestLinks wherever it is exact. Where both apply they give
the same trajectories bit for bit (tested).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.association import (
    UNASSOCIATED,
    associate,
    greedy_from_nearest,
    group_sort,
    nearest_uav_on_line,
)
from uavlora_rllib.sim.scenario import ScenarioConfig


class Links:
    """The links of one slot of N scenarios, arrays [N, V] unless noted.

    serving: the serving UAV, UNASSOCIATED (-1) where none; associated: serving != -1, and
    all_associated: whether that holds everywhere (masks are skipped then); serving_idx: the
    serving UAV where associated, any valid UAV index elsewhere (safe to gather with);
    g_serving, g_db_serving, d_h_serving: the channel at serving_idx; slot_of_ed: the ED's rank
    by gain among its UAV's EDs (ties by ED id), -1 if unassociated; counts [N, U]: the EDs each
    UAV serves; pairs: (d_h, G, G_dB) of every pair [N, U, V] when computed, else None."""

    __slots__ = (
        "serving", "associated", "all_associated", "serving_idx", "g_serving", "g_db_serving", "d_h_serving",
        "slot_of_ed", "counts", "pairs",
    )  # fmt: skip

    def __init__(
        self, serving, associated, all_associated, serving_idx, g_serving, g_db_serving, d_h_serving,
        slot_of_ed, counts, pairs=None,
    ):  # fmt: skip
        self.serving, self.associated, self.all_associated = serving, associated, all_associated
        self.serving_idx = serving_idx
        self.g_serving, self.g_db_serving, self.d_h_serving = g_serving, g_db_serving, d_h_serving
        self.slot_of_ed, self.counts, self.pairs = slot_of_ed, counts, pairs

    def row(self, k: int, all_associated: bool) -> Links:
        """The links of scenario k alone, as a batch of one (views; the pair channels left out;
        `all_associated`: whether scenario k's EDs all are, known to the caller). The lookahead
        computes a block of slots as a batch and plays it back one row per slot."""
        r = slice(k, k + 1)
        return Links(
            self.serving[r], self.associated[r], all_associated, self.serving_idx[r], self.g_serving[r],
            self.g_db_serving[r], self.d_h_serving[r], self.slot_of_ed[r], self.counts[r],
        )  # fmt: skip


def pair_channels(ed_xy: np.ndarray, uav_xy: np.ndarray, cfg: ScenarioConfig) -> tuple[np.ndarray, ...]:
    """(d_h, G, G_dB) of every UAV-ED pair [..., U, V] from the ED positions [..., V, 2]."""
    d2 = physics.horizontal_distance_sq(ed_xy, uav_xy)
    gains, gain_db = physics.channel_gain_sq(d2, cfg, with_db=True)
    return np.sqrt(d2, out=d2), gains, gain_db


class LinkStage(ABC):
    """A link stage for N scenarios: called with the ED positions, returns the slot's Links.
    Holds what the stages share: the scenario, the batch size, and the slot ranking (`_rank`).
    A new stage (another channel or association model) subclasses it and sets `all_pairs`."""

    all_pairs = False  # whether Links.pairs is computed (else the pair channels are left to callers)

    def __init__(self, cfg: ScenarioConfig, n_envs: int):
        self.cfg = cfg
        self.n = n_envs
        self.uav_xy = physics.uav_positions(cfg)
        v, u = cfg.n_eds, cfg.n_uavs
        env_idx = np.arange(n_envs)
        self._row_base = (env_idx * v)[:, None]  # flat index of (e, 0) in an [N, V] array
        self._grp_base = (env_idx * (u + 1))[:, None]  # groups: UAV 0..U-1, U = unassociated
        self._positions = np.broadcast_to(np.arange(v), (n_envs, v))

    @abstractmethod
    def __call__(self, xy: np.ndarray) -> Links:
        """The links of the slot whose ED positions are `xy` [2, N, V] (by coordinate)."""

    def _rank(
        self, serving_idx: np.ndarray, associated: np.ndarray, all_associated: bool, g_serving: np.ndarray,
        group_counts: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """slot_of_ed [N, V]: rank of each served ED by gain among its UAV's EDs (ties by ED id;
        -1 if unassociated), and the served counts [N, U]. The EDs are sorted by (serving UAV,
        descending gain, ED id): each UAV's EDs form a run in gain order, and an ED's slot is its
        position minus the start of its UAV's run (an exclusive cumulative sum of the counts).
        `group_counts` [N, U + 1] (last: unassociated), when the association counted them."""
        n, v, u = self.n, self.cfg.n_eds, self.cfg.n_uavs
        grp = serving_idx if all_associated else np.where(associated, serving_idx, u)
        # EDs by (serving UAV, descending gain, ED id): each UAV's EDs form a run in gain order
        order, grouped = group_sort(g_serving, grp, u + 1, descending=True)
        assert grouped is not None  # (groups given)
        order += self._row_base  # flat indices into [N, V]
        grouped += self._grp_base
        counts = group_counts
        if counts is None:
            counts = np.bincount(grouped.reshape(-1), minlength=n * (u + 1)).reshape(n, u + 1)
        start = np.cumsum(counts, axis=-1)
        start -= counts
        slot = self._positions - start.reshape(-1).take(grouped)
        if not all_associated:
            slot[grouped - self._grp_base == u] = -1
        slot_of_ed = np.empty((n, v), dtype=np.int64)
        slot_of_ed.reshape(-1)[order] = slot
        return slot_of_ed, counts[:, :u]


class NearestLinks(LinkStage):
    """Greedy association from each ED's nearest UAV; channel at the serving UAV only."""

    def __init__(self, cfg: ScenarioConfig, n_envs: int):
        super().__init__(cfg, n_envs)
        self._spacing = cfg.area_m / cfg.n_uavs

    def __call__(self, xy: np.ndarray) -> Links:
        cfg = self.cfg
        near = nearest_uav_on_line(xy[0], self._spacing, cfg.n_uavs)
        d2 = physics.horizontal_distance_sq_to(xy.transpose(1, 2, 0), self.uav_xy, near)
        d_h = np.sqrt(d2)

        def pair_keys(e: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            # (-d_h^2, d_h) [K, U] of the EDs (e[k], v[k]) to every UAV, where a quota binds.
            # -d_h^2 orders the pairs as their gains do (G strictly decreases with d_h here),
            # which is all the greedy matching looks at: no transcendental needed. (Same
            # operations as the d_h^2 of the nearest UAV's channel, element by element.)
            d2_all = physics.horizontal_distance_sq(xy[:, e, v].T, self.uav_xy).T  # [K, U]
            return np.negative(d2_all), np.sqrt(d2_all)

        serving, group_counts = greedy_from_nearest(
            near, d_h, cfg.comm_range_m, cfg.quota, cfg.n_uavs, lambda b: np.negative(d2[b]), pair_keys,
            return_counts=True,
        )  # fmt: skip
        associated = serving != UNASSOCIATED
        # Where a quota bound, some EDs are served by another UAV than their nearest one.
        moved = np.flatnonzero(serving != near)
        moved = moved[serving.reshape(-1)[moved] != UNASSOCIATED]
        if moved.size:
            u_moved = near.reshape(-1)[moved] = serving.reshape(-1)[moved]
            xy_moved = xy.reshape(2, -1)[:, moved].T  # [K, 2]
            d2_moved = physics.horizontal_distance_sq_to(xy_moved, self.uav_xy, u_moved)
            d2.reshape(-1)[moved] = d2_moved
            d_h.reshape(-1)[moved] = np.sqrt(d2_moved)
        serving_idx = near  # unassociated EDs: their nearest UAV (any valid index)
        g_serving, g_db_serving = physics.channel_gain_sq(d2, cfg, with_db=True, d_h=d_h)
        all_associated = bool(associated.all())
        slot_of_ed, counts = self._rank(serving_idx, associated, all_associated, g_serving, group_counts)
        return Links(serving, associated, all_associated, serving_idx, g_serving, g_db_serving, d_h, slot_of_ed, counts)


class AllPairLinks(LinkStage):
    """The configured association on the channel of every UAV-ED pair."""

    all_pairs = True

    def __init__(self, cfg: ScenarioConfig, n_envs: int):
        super().__init__(cfg, n_envs)
        v, u = cfg.n_eds, cfg.n_uavs
        # Flat index of (scenario e, UAV 0, ED v) in a C-contiguous [N, U, V] array; adding
        # u * V picks UAV u. Used to gather "the value at the serving UAV" with one np.take.
        self._flat_base = (np.arange(n_envs)[:, None] * (u * v) + np.arange(v)[None, :]).astype(np.int64)

    def __call__(self, xy: np.ndarray) -> Links:
        cfg = self.cfg
        pairs = d_h, gains, gain_db = pair_channels(xy.transpose(1, 2, 0), self.uav_xy, cfg)
        serving = associate(gains, d_h, cfg.comm_range_m, cfg.quota, cfg.association)
        associated = serving != UNASSOCIATED
        serving_idx = np.where(associated, serving, 0)
        flat = (self._flat_base + serving_idx * cfg.n_eds).reshape(-1)  # into [N, U, V]
        shape = serving_idx.shape
        d_h_serving = d_h.reshape(-1).take(flat).reshape(shape)
        g_serving = gains.reshape(-1).take(flat).reshape(shape)
        g_db_serving = gain_db.reshape(-1).take(flat).reshape(shape)
        all_associated = bool(associated.all())
        slot_of_ed, counts = self._rank(serving_idx, associated, all_associated, g_serving, None)
        return Links(
            serving, associated, all_associated, serving_idx, g_serving, g_db_serving, d_h_serving, slot_of_ed,
            counts, pairs,
        )  # fmt: skip


def default_link_stage(cfg: ScenarioConfig, n_envs: int) -> LinkStage:
    """NearestLinks where it is exact (greedy association, the paper's interference, a gain
    strictly decreasing in d_h), AllPairLinks otherwise."""
    nearest = cfg.association == "greedy" and cfg.interference == "paper" and physics.gain_decreases_with_distance(cfg)
    return (NearestLinks if nearest else AllPairLinks)(cfg, n_envs)
