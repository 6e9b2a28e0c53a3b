"""An upper bound on the per-slot optimum of EE_sys[t], computed from the slot's channel alone
(docs/model.md#an-upper-bound-on-the-per-slot-optimum).

Valid in both action modes (per_uav allocations are per-ED allocations with constraints) and
for both objectives' optima (the constraint (h) only shrinks the set maximised over).
"""

from __future__ import annotations

import numpy as np

from uavlora_rllib.baselines.slots import Slots
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig


def _weights(cfg: ScenarioConfig, tables: physics.Tables, slots: Slots) -> np.ndarray:
    """1 / (P_hover + n_u P_min) [N, U], 1/W: the most one bit/s of UAV u's EDs adds to EE_sys
    (its n_u EDs transmit at least the smallest TP each)."""
    n_u = physics.group_count(np.where(slots.associated, slots.serving_idx, cfg.n_uavs), cfg.n_uavs + 1)[:, :-1]
    return 1.0 / (tables.hover_w + n_u * tables.tp_w.min())


def water_filled_log_sum(x: np.ndarray, k: int) -> np.ndarray:
    """max of sum_i log2(1 + z_i) over the K-vector z that every sorted vector of K group sums
    of the items x [N, V] (>= 0) majorizes: z = (x_(1), .., x_(j), L, .., L), the j largest items
    and the rest spread evenly, L = (sum x - top j) / (K - j), j the least with x_(j+1) <= L."""
    n, v = x.shape
    xs = -np.sort(-x, axis=1)
    if v < k:
        xs = np.concatenate([xs, np.zeros((n, k - v))], axis=1)
    total = xs.sum(axis=1, keepdims=True)
    top = np.concatenate([np.zeros((n, 1)), np.cumsum(xs[:, : k - 1], axis=1)], axis=1)  # X_j, j = 0 .. K-1
    j = np.arange(k)
    level = (total - top) / (k - j)  # [N, K]
    fits = xs[:, :k] <= level * (1 + 1e-12)  # x_(j+1) <= L_j; true at j = K - 1
    j_star = np.argmax(fits, axis=1)
    logs = np.concatenate([np.zeros((n, 1)), np.cumsum(np.log2(1.0 + xs[:, : k - 1]), axis=1)], axis=1)
    rows = np.arange(n)
    return logs[rows, j_star] + (k - j_star) * np.log2(1.0 + level[rows, j_star])


def upper_bound_ee(cfg: ScenarioConfig, tables: physics.Tables, slots: Slots) -> np.ndarray:
    """Upper bound [N] on max EE_sys[t] over every per-ED allocation of the slot, bit/J.

    Every ED's bit/s is weighted at most 1 / (P_hover + n_u P_min), n_u the EDs of its UAV. Shannon rate: interference-free, each ED's rate is at most
    W log2(1 + x_v), x_v its SNR at the largest TP; with the paper's interference the EDs of one
    SF group together get at most log2(1 + their summed SNR) (treating interference as noise
    never beats the multiple-access sum rate) and there are n_sf groups, which the water-filled
    sum bounds. The smaller of the two. LoRa-PHY rate: each ED at most its fastest SF that its
    SNR at the largest TP decodes, without interference.
    """
    c_u = _weights(cfg, tables, slots)
    c_ed = np.take_along_axis(c_u, slots.serving_idx, axis=1) * slots.associated  # [N, V]
    x = tables.tp_w.max() * slots.g_serving / tables.noise_w * slots.associated
    if cfg.rate_model != "shannon":
        sf, w, thr = tables.sf[:, None], tables.bw_hz[None, :], tables.threshold_db  # every (SF, BW)
        phy = physics.rate_bps(np.full(thr.shape, np.inf), w, sf, thr, cfg.rate_model, cfg.lora_coding_rate)
        decodes = physics.lin_to_db(x)[..., None, None] >= thr  # [N, V, n_sf, n_bw]
        best = np.where(decodes, phy, 0.0).max(axis=(-2, -1))  # bit/s
        return np.add.reduce(c_ed * best, axis=-1)
    w_max = tables.bw_hz.max()
    free = np.add.reduce(c_ed * w_max * np.log2(1.0 + x), axis=-1)
    if cfg.interference != "paper":
        return free
    grouped = c_u.max(axis=-1) * w_max * water_filled_log_sum(x, cfg.n_sf)
    return np.minimum(free, grouped)


def upper_bound_of_core(core: BatchCore) -> np.ndarray:
    """upper_bound_ee of the core's current slot [N]."""
    return upper_bound_ee(core.cfg, core.tables, Slots.of_core(core))
