"""One slot end to end: the per-scenario tables, and every metric of a slot from the
association and the allocations (per ED, or shared by each UAV's EDs)."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from uavlora_rllib.sim.physics.arrays import DB_FLOOR, at_serving, dbm_to_w, group_index, lin_to_db
from uavlora_rllib.sim.physics.radio import rate_bps, sinr_cross_gain, sinr_of_groups, sinr_paper_tx, snr_threshold_db
from uavlora_rllib.sim.physics.reward_terms import (
    energy_efficiency_tx,
    hover_power_w,
    margin_points,
    mean_over_associated,
    points_of_margin,
    reward,
    success_rate,
    total_power_of_tx_sum,
)
from uavlora_rllib.sim.scenario import RewardWeights, ScenarioConfig


# ---------------------------------------------------------------- one slot, end to end
@dataclass(frozen=True)
class Tables:
    """Per-scenario constants derived once from a ScenarioConfig (indexable by action indices)."""

    sf: np.ndarray  # [n_sf] spreading factors
    tp_w: np.ndarray  # [n_tp] transmit powers in W
    bw_hz: np.ndarray  # [n_bw] bandwidths in Hz
    threshold_db: np.ndarray  # [n_sf, n_bw] rho_thr
    noise_w: float
    hover_w: float

    @classmethod
    def from_config(cls, cfg: ScenarioConfig) -> Tables:
        sf = np.asarray(cfg.sf_set, dtype=np.int64)
        bw = np.asarray(cfg.bw_khz, dtype=np.int64)
        return cls(
            sf=sf,
            tp_w=dbm_to_w(np.asarray(cfg.tp_dbm)),
            bw_hz=bw.astype(np.float64) * 1e3,
            threshold_db=snr_threshold_db(sf[:, None], bw[None, :]),
            noise_w=float(dbm_to_w(cfg.noise_dbm)),
            hover_w=hover_power_w(cfg),
        )


def allocation_values(
    sf_idx: np.ndarray, tp_idx: np.ndarray, bw_idx: np.ndarray, tables: Tables
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(transmit power in W, bandwidth in Hz, rho_thr(SF, BW) in dB) of allocations given as
    indices into the tables (take: faster than fancy indexing)."""
    thr_db = tables.threshold_db.reshape(-1).take(sf_idx * tables.threshold_db.shape[1] + bw_idx)
    return tables.tp_w.take(tp_idx), tables.bw_hz.take(bw_idx), thr_db


SLOT_METRICS = (
    "reward",
    "ee_sys",
    "success_rate",
    "beta",
    "p_total_w",
    "rate_sum_bps",
    "mean_sinr_db",
    "n_unassociated",
)


_EMPTY_MEANS = np.array([0.0, DB_FLOOR])  # beta and mean SINR (dB) of a slot with no ED associated


def slot_metrics(
    gains: np.ndarray | None,
    serving_uav: np.ndarray,
    associated: np.ndarray,
    sf_idx: np.ndarray,
    tp_idx: np.ndarray | None,
    bw_idx: np.ndarray | None,
    cfg: ScenarioConfig,
    tables: Tables,
    g_serving: np.ndarray | None = None,
    values: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Everything the paper measures in one slot, given the association and per-ED allocations.

    gains [..., U, V]; the other inputs [..., V] (serving_uav is any valid index where the ED
    is unassociated). `g_serving` [..., V], the gain at each ED's serving UAV, may be given
    instead of being gathered from `gains`; `gains` may then be None with the default
    `interference: paper`. `values`: allocation_values(sf_idx, tp_idx, bw_idx, tables) when the
    caller has them (tp_idx and bw_idx are then not used). Returns the keys of SLOT_METRICS,
    each shaped [...].
    """
    if g_serving is None:
        assert gains is not None, "slot_metrics: needs gains or g_serving"
        g_serving = at_serving(gains, serving_uav)
    sf_idx = np.asarray(sf_idx)
    if values is None:
        assert tp_idx is not None and bw_idx is not None, "slot_metrics: needs tp_idx and bw_idx, or values"
        values = allocation_values(sf_idx, tp_idx, bw_idx, tables)
    p_w, bw_hz, thr_db = values
    g_serving, associated, serving_uav = np.asarray(g_serving), np.asarray(associated), np.asarray(serving_uav)
    shape = p_w.shape
    if not (shape == g_serving.shape == associated.shape == sf_idx.shape == serving_uav.shape):
        shape = np.broadcast_shapes(shape, g_serving.shape, associated.shape, sf_idx.shape, serving_uav.shape)
    # Quantities that are reduced the same way are computed into one [2, ...] buffer each, so
    # that each reduction is one NumPy call (a step at N = 1 is dominated by per-call costs).
    lin = np.empty((2,) + shape)  # SNR and SINR (linear) of every ED
    # Every ED associated (the usual case in larger layouts): the masks below are identities,
    # skipped (same values).
    everyone = bool(associated.all())
    if everyone and p_w.shape == shape:
        p_tx = p_w
    else:
        p_tx = np.multiply(p_w, associated)  # silent EDs transmit nothing (P * False = 0)
    s_tx = np.multiply(p_tx, g_serving, out=lin[0])  # = rho_v for associated EDs, 0 for silent ones
    s_tx /= tables.noise_w  # snr(): P G / sigma^2
    if cfg.interference == "paper":
        sinr_lin = sinr_paper_tx(s_tx, sf_idx, cfg.n_sf, out=lin[1])
    else:
        sinr_lin = lin[1]
        assert gains is not None, "slot_metrics: interference 'cross_gain' needs gains"
        sinr_lin[...] = sinr_cross_gain(p_w, gains, serving_uav, sf_idx, associated, cfg.n_sf, tables.noise_w)
    db = lin_to_db(lin)
    snr_db, sinr_db = db[0], db[1]
    # SINR = 0 for silent EDs, so their Shannon rate W log2(1) and their LoRa-PHY rate are 0.
    sf = None if cfg.rate_model == "shannon" else tables.sf[sf_idx]
    rate = rate_bps(sinr_lin, bw_hz, sf, thr_db, cfg.rate_model, cfg.lora_coding_rate, out=np.empty(shape))
    ee = energy_efficiency_tx(rate, p_tx, serving_uav, tables.hover_w, cfg.n_uavs)  # Eq. (sys_ee)
    rate_sum, p_total = np.add.reduce(rate, axis=-1), np.add.reduce(p_tx, axis=-1)
    p_total = total_power_of_tx_sum(p_total, tables.hover_w, cfg.n_uavs)
    xi = success_rate(sinr_db, thr_db, associated)
    margin_points(snr_db, thr_db, out=db[0])
    return _slot_metrics_of(ee, xi, db, p_total, rate_sum, associated, everyone, cfg.reward_weights)


def _slot_metrics_of(
    ee: np.ndarray,
    xi: np.ndarray,
    db: np.ndarray,
    p_total: np.ndarray,
    rate_sum: np.ndarray,
    associated: np.ndarray,
    everyone: bool,
    weights: RewardWeights,
) -> dict[str, np.ndarray]:
    """The SLOT_METRICS dict from a slot's parts; db [2, ..., V]: beta's margin points and the
    SINR in dB of each ED, averaged over the associated EDs in one reduction."""
    n_eds = db.shape[-1]
    if everyone:  # (the means' divisor is V: the same values as mean_over_associated's, fewer calls)
        beta, mean_sinr_db = np.add.reduce(db, axis=-1) / n_eds
        n_unassociated = np.zeros(db.shape[1:-1])
    else:
        n_assoc = np.add.reduce(associated, axis=-1)
        empty = _EMPTY_MEANS.reshape((2,) + (1,) * (db.ndim - 2))
        beta, mean_sinr_db = mean_over_associated(db, associated, n_assoc, empty)
        n_unassociated = np.subtract(n_eds, n_assoc, dtype=np.float64)
    return {
        "reward": reward(ee, xi, beta, p_total, weights),
        "ee_sys": ee,
        "success_rate": xi,
        "beta": beta,
        "p_total_w": p_total,
        "rate_sum_bps": rate_sum,
        "mean_sinr_db": mean_sinr_db,
        "n_unassociated": n_unassociated,
    }


# ---------------------------------------------------------------- one slot, allocations shared per UAV
@dataclass(frozen=True)
class SharedAllocation:
    """The allocation of each UAV, shared by all the EDs it serves (the per_uav action mode),
    as the values slot_metrics_shared needs, each shaped [..., U] (or [A] for a table of A
    actions, indexed by action). Build it with `shared_allocation`."""

    sf_idx: np.ndarray  # index into Tables.sf
    p_w: np.ndarray  # transmit power P (W)
    snr_per_gain: np.ndarray  # P / sigma^2: an ED's SNR is this times its channel gain G
    bw_hz: np.ndarray  # bandwidth W (Hz)
    threshold_db: np.ndarray  # rho_thr(SF, W) (dB)
    margin_offset_db: np.ndarray  # P_dB - sigma^2_dB - rho_thr: SNR_dB - rho_thr = G_dB + this


def shared_allocation(sf_idx: np.ndarray, tp_idx: np.ndarray, bw_idx: np.ndarray, tables: Tables) -> SharedAllocation:
    """SharedAllocation of per-UAV (SF, TP, BW) indices (any shape)."""
    sf_idx = np.asarray(sf_idx)
    p_w, bw_hz, thr_db = allocation_values(sf_idx, np.asarray(tp_idx), np.asarray(bw_idx), tables)
    snr_per_gain = p_w / tables.noise_w
    margin = lin_to_db(snr_per_gain)  # P / sigma^2 in dB (p_w >= 1 mW: no floor)
    margin -= thr_db
    return SharedAllocation(sf_idx, p_w, snr_per_gain, bw_hz, thr_db, margin)


class SharedAllocationTable:
    """The SharedAllocation of each of A actions (1-D index arrays of their SF, TP and BW
    indices), gathered for an array of actions [..., U] by two np.take (per step)."""

    def __init__(self, sf_idx: np.ndarray, tp_idx: np.ndarray, bw_idx: np.ndarray, tables: Tables):
        alloc = shared_allocation(sf_idx, tp_idx, bw_idx, tables)
        self._sf_idx = alloc.sf_idx
        self._names = [f.name for f in fields(SharedAllocation) if f.name != "sf_idx"]  # the float fields
        self._values = np.stack([getattr(alloc, name) for name in self._names])  # [5, A]

    def take(self, actions: np.ndarray) -> SharedAllocation:
        rows = self._values.take(actions, axis=1)
        return SharedAllocation(sf_idx=self._sf_idx.take(actions), **dict(zip(self._names, rows)))


def slot_metrics_shared(
    g_serving: np.ndarray,
    g_db_serving: np.ndarray,
    serving_flat: np.ndarray,
    associated: np.ndarray,
    counts: np.ndarray,
    alloc: SharedAllocation,
    cfg: ScenarioConfig,
    tables: Tables,
) -> dict[str, np.ndarray]:
    """slot_metrics where each UAV's EDs share its allocation (per_uav actions), with the paper's
    interference and the Shannon rate: the same equations, with each UAV's factors taken out of
    its sums (equal to slot_metrics up to rounding; tested to 1e-12), so that fewer per-ED
    passes are made:
      SNR_v = (P_u / sigma^2) G_v,  SNR_dB - rho_thr = G_dB,v + (P_u,dB - sigma^2_dB - rho_thr,u),
      sum_v a_uv R_uv = W_u sum_v a_uv log2(1 + SINR_v),  sum_v a_uv P_v = n_u P_u.

    g_serving, g_db_serving [N, V]: each ED's gain at its serving UAV, linear and in dB
    (any finite value where the ED is unassociated); serving_flat [N, V]: the flat index of
    its serving UAV in [N, U] (any valid one where unassociated); associated [N, V];
    counts [N, U]: the EDs each UAV serves; alloc: [N, U] values."""
    if cfg.interference != "paper" or cfg.rate_model != "shannon":
        raise ValueError("slot_metrics_shared: needs interference 'paper' and rate_model 'shannon'")
    n, v = g_serving.shape
    n_u = counts.shape[-1]
    everyone = bool(associated.all())
    flat = serving_flat.reshape(-1)
    # (ndarray.take without an axis indexes the flattened array: [N, U] tables by serving_flat)
    # SNR of every transmitting ED, 0 for silent ones (which neither transmit nor interfere)
    s_tx = alloc.snr_per_gain.take(flat)
    s_tx *= g_serving.reshape(-1)
    if not everyone:
        s_tx *= associated.reshape(-1)
    # Eq. (sinr): the interferers of an ED are the EDs of its (scenario, SF) group
    group = group_index(alloc.sf_idx, cfg.n_sf, alloc.sf_idx.shape).take(flat)
    sinr = sinr_of_groups(s_tx, group, n * cfg.n_sf).reshape(n, v)
    # Eq. (shannon) summed per UAV, then Eq. (sys_ee)
    log_term = np.add(sinr, 1.0)
    np.log2(log_term, out=log_term)
    bits = np.bincount(flat, weights=log_term.reshape(-1), minlength=n * n_u).reshape(n, n_u)
    bits *= alloc.bw_hz
    tx_w = np.multiply(counts, alloc.p_w)
    watts = tx_w + tables.hover_w
    ee = np.add.reduce(np.divide(bits, watts, out=watts), axis=-1)
    rate_sum = np.add.reduce(bits, axis=-1)
    p_total = total_power_of_tx_sum(np.add.reduce(tx_w, axis=-1), tables.hover_w, n_u)
    # success rate, beta's margin points and the mean SINR (dB), as in slot_metrics
    db = np.empty((2, n, v))  # margin points and SINR (dB), averaged by one reduction
    sinr_db = lin_to_db(sinr, out=db[1])
    xi = success_rate(sinr_db, alloc.threshold_db.take(serving_flat), associated)
    np.add(g_db_serving, alloc.margin_offset_db.take(serving_flat), out=db[0])
    points_of_margin(db[0])
    return _slot_metrics_of(ee, xi, db, p_total, rate_sum, associated, everyone, cfg.reward_weights)
