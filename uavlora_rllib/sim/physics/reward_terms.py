"""Energy and the reward: UAV hover power (Eq. hover), system energy efficiency (Eq. sys_ee),
the success rate, the margin score, the total power, and the reward (Eq. reward)."""

from __future__ import annotations

import numpy as np

from uavlora_rllib.sim.physics.arrays import clip, group_index
from uavlora_rllib.sim.scenario import RewardWeights, ScenarioConfig


# ---------------------------------------------------------------- UAV power, Eq. (hover)
def hover_power_w(cfg: ScenarioConfig) -> float:
    """Eq. (hover): P = n W_r^{3/2} (rho^{-1/2} s A^{-1/2} C_T^{-3/2} delta/8 + (1+k)/sqrt(2 rho A))."""
    h = cfg.hover
    w_r = h.weight_n / h.n_rotors
    profile = h.air_density**-0.5 * h.solidity * h.disc_area_m2**-0.5 * h.thrust_coef**-1.5 * h.drag_coef / 8.0
    induced = (1.0 + h.induced_factor) / np.sqrt(2.0 * h.air_density * h.disc_area_m2)
    return float(h.n_rotors * w_r**1.5 * (profile + induced))


# ---------------------------------------------------------------- EE (Eq. sys_ee) and the reward terms
def energy_efficiency(
    rate: np.ndarray,
    tx_power_w: np.ndarray,
    serving_uav: np.ndarray,
    associated: np.ndarray,
    hover_w: float,
    n_uavs: int,
) -> np.ndarray:
    """EE_sys[t] = sum_u (sum_v a_uv R_uv) / (sum_v a_uv P_v + P_hover_u), bits per joule, one slot.

    serving_uav: any valid UAV index where the ED is unassociated."""
    rate_tx, p_tx = np.broadcast_arrays(np.where(associated, rate, 0.0), np.where(associated, tx_power_w, 0.0))
    return energy_efficiency_tx(rate_tx, p_tx, np.asarray(serving_uav), hover_w, n_uavs)


def energy_efficiency_tx(
    rate_tx: np.ndarray, p_tx: np.ndarray, serving_uav: np.ndarray, hover_w: float, n_uavs: int
) -> np.ndarray:
    """energy_efficiency from the rate and transmit power [..., V] (same shape), both already 0
    for the unassociated EDs: the per-UAV sums of bits and of watts by a bincount each."""
    shape = rate_tx.shape
    idx = group_index(serving_uav, n_uavs, shape)
    n_bins = idx.size // shape[-1] * n_uavs
    bits = np.bincount(idx, weights=rate_tx.reshape(-1), minlength=n_bins)
    watts: np.ndarray = np.bincount(idx, weights=p_tx.reshape(-1), minlength=n_bins)  # (float: weighted)
    watts += hover_w
    return np.add.reduce(np.divide(bits, watts, out=watts).reshape(shape[:-1] + (n_uavs,)), axis=-1)


def success_rate(
    sinr_db: np.ndarray, threshold_db: np.ndarray, associated: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """Xi[t]: share of ALL V EDs that are associated and decoded (SINR_dB >= rho_thr)."""
    decoded = np.greater_equal(sinr_db, threshold_db)
    decoded &= associated
    xi = np.add.reduce(decoded, axis=-1, dtype=np.float64, out=out)
    xi /= decoded.shape[-1]
    return xi


def margin_score(snr_db: np.ndarray, threshold_db: np.ndarray, associated: np.ndarray) -> np.ndarray:
    """beta[t] (docs/model.md#metrics-and-reward): mean over associated EDs of m = SNR_dB - rho_thr scored as
    min(m, 20) / 20 for m >= 0 and max(m / 2, -10) for m < 0; 0 when no ED is associated.
    (Evaluated as clip(m, -20, 20) / (20 if m >= 0 else 2): max(m / 2, -10) = max(m, -20) / 2.)"""
    return mean_over_associated(
        margin_points(snr_db, threshold_db), associated, np.add.reduce(associated, axis=-1), 0.0
    )


def margin_points(snr_db: np.ndarray, threshold_db: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """margin_score's points of each ED; `out` (may be snr_db itself) receives them."""
    return points_of_margin(np.subtract(snr_db, threshold_db, out=out))


def points_of_margin(m: np.ndarray) -> np.ndarray:
    """margin_score's points of the margins m = SNR_dB - rho_thr, in place."""
    below = m < 0.0
    clip(m, -20.0, 20.0, out=m)
    divisor = np.multiply(below, 2.0 - 20.0)  # 2 where below, 20 elsewhere (exact; np.where with
    divisor += 20.0  # two scalars is slower)
    m /= divisor
    return m


def mean_over_associated(x: np.ndarray, associated: np.ndarray | None, n: np.ndarray, empty) -> np.ndarray:
    """Mean of x over the n associated EDs (last axis; x may stack several quantities in front,
    [k, ..., V], each reduced by the one call); `empty` (broadcast) where none is associated.
    associated None: every ED is (the same sums, without the masking pass)."""
    total = np.add.reduce(x if associated is None else np.where(associated, x, 0.0), axis=-1)
    return np.where(n > 0, total / np.maximum(n, 1), empty)


def total_power_w(tx_power_w: np.ndarray, associated: np.ndarray, hover_w: float, n_uavs: int) -> np.ndarray:
    """P_total[t] = sum of associated EDs' TP (W) + sum_u P_hover_u."""
    return total_power_of_tx_sum(np.where(associated, tx_power_w, 0.0).sum(axis=-1), hover_w, n_uavs)


def total_power_of_tx_sum(tx_sum_w: np.ndarray, hover_w: float, n_uavs: int) -> np.ndarray:
    """total_power_w from the sum of the associated EDs' transmit powers (in place)."""
    tx_sum_w += n_uavs * hover_w
    return tx_sum_w


def reward(ee: np.ndarray, xi: np.ndarray, beta: np.ndarray, p_total: np.ndarray, w: RewardWeights) -> np.ndarray:
    """Eq. (reward): r = w1 EE + w2 Xi + w3 beta - |w4| P_total (w4 is a penalty whatever its sign);
    `w` resolved (ScenarioConfig.reward_weights: w1 set)."""
    if w.w1 is None:
        raise ValueError("reward: w1 is null; pass ScenarioConfig.reward_weights (w1 resolved by rate model)")
    return w.w1 * ee + w.w2 * xi + w.w3 * beta - abs(w.w4) * p_total
