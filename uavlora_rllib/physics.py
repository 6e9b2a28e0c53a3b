"""The paper's system model, one pure vectorised function per equation.

Every function broadcasts over leading batch dimensions. The simulator core, the
environments, the baselines and the analysis all call these functions; no equation is
written anywhere else. Equation labels refer to the paper's LaTeX source
(``shared/paper/uav-lora-mappo-vtc2026.tex``); where SPEC.md decides something the paper
leaves open, the docstring says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.scenario import SNR_THRESHOLD_TABLE_DB, RewardWeights, ScenarioConfig

# Floor used wherever a ratio is shown in dB, so that "no signal" is a finite, very low value.
DB_FLOOR = -200.0
_DEG_PER_RAD = 180.0 / np.pi


# ---------------------------------------------------------------- gathers
def take_last(arr: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """np.take_along_axis(arr, idx, axis=-1); for 2-D operands with the same number of rows,
    the same gather as one fancy index (without take_along_axis's Python-level set-up)."""
    if arr.ndim == 2 and idx.ndim == 2 and arr.shape[0] == idx.shape[0]:
        return arr[np.arange(arr.shape[0])[:, None], idx]
    return np.take_along_axis(arr, idx, axis=-1)


def at_serving(per_uav: np.ndarray, serving_uav: np.ndarray) -> np.ndarray:
    """per_uav [..., U, V] at each ED's serving UAV serving_uav [..., V] -> [..., V]."""
    if per_uav.ndim == 3 and serving_uav.ndim == 2 and per_uav.shape[0] == serving_uav.shape[0]:
        n, _, v = per_uav.shape
        return per_uav[np.arange(n)[:, None], serving_uav, np.arange(v)[None, :]]
    return np.take_along_axis(per_uav, serving_uav[..., None, :], axis=-2)[..., 0, :]


# ---------------------------------------------------------------- unit conversions
def dbm_to_w(p_dbm: np.ndarray | float) -> np.ndarray:
    return np.power(10.0, (np.asarray(p_dbm, dtype=np.float64) - 30.0) / 10.0)


def db_to_lin(x_db: np.ndarray | float) -> np.ndarray:
    """10^(x/10), on a new array (the input is left untouched)."""
    y = np.divide(x_db, 10.0)
    return np.power(10.0, y, out=y) if isinstance(y, np.ndarray) else np.power(10.0, y)


def lin_to_db(x: np.ndarray | float) -> np.ndarray:
    """10 log10(x), floored at DB_FLOOR for x <= 0."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.maximum(10.0 * np.log10(np.maximum(x, 0.0)), DB_FLOOR)


# ---------------------------------------------------------------- channel, Eqs. (plos), (a2g_pl)
def elevation_deg(d_h: np.ndarray | float, cfg: ScenarioConfig) -> np.ndarray:
    """theta = atan(h / d_h) in degrees (90 deg right under the UAV)."""
    theta = np.arctan2(cfg.altitude_m, np.asarray(d_h, dtype=np.float64))
    # x * (180 / pi) is exactly what np.degrees computes, without its per-element call.
    return np.multiply(theta, _DEG_PER_RAD, out=theta if isinstance(theta, np.ndarray) else None)


def los_probability(theta_deg: np.ndarray | float, cfg: ScenarioConfig) -> np.ndarray:
    """Eq. (plos): P_LoS = 1 / (1 + a exp(-b (theta - a))), theta in degrees (Al-Hourani)."""
    x = np.subtract(np.asarray(theta_deg, dtype=np.float64), cfg.los_a)
    if not isinstance(x, np.ndarray):  # 0-d input: plain scalar arithmetic, same operations
        return 1.0 / (1.0 + cfg.los_a * np.exp(-cfg.los_b * x))
    x *= -cfg.los_b  # in place, same operations and order as the formula
    np.exp(x, out=x)
    x *= cfg.los_a
    x += 1.0
    return np.divide(1.0, x, out=x)


def path_loss_db(d_h: np.ndarray | float, cfg: ScenarioConfig) -> np.ndarray:
    """Eq. (a2g_pl): mean G2A path loss in dB at horizontal distance d_h (m).

    SPEC.md: the free-space term uses the 3-D distance sqrt(d_h^2 + h^2) (the paper writes
    d_h there, which diverges under the UAV).
    """
    d_h = np.asarray(d_h, dtype=np.float64)
    const = 20.0 * np.log10(4.0 * np.pi * cfg.carrier_hz / cfg.speed_of_light_mps)
    if d_h.ndim == 0:
        return path_loss_db(d_h.reshape(1), cfg)[0]
    # fspl = 10 log10(d_h^2 + h^2) + const, then + eta_LoS P + eta_NLoS (1 - P), evaluated in
    # place in exactly the formula's order (the results are bit-identical to the plain form).
    fspl = np.multiply(d_h, d_h)
    fspl += cfg.altitude_m**2
    np.log10(fspl, out=fspl)
    fspl *= 10.0
    fspl += const
    p_los = los_probability(elevation_deg(d_h, cfg), cfg)
    nlos = np.subtract(1.0, p_los)
    nlos *= cfg.eta_nlos_db
    p_los *= cfg.eta_los_db
    fspl += p_los
    fspl += nlos
    return fspl


def channel_gain(d_h: np.ndarray | float, cfg: ScenarioConfig) -> np.ndarray:
    """G = 10^(-L/10), linear power gain."""
    return db_to_lin(-path_loss_db(d_h, cfg))


def horizontal_distance(ed_xy: np.ndarray, uav_xy: np.ndarray) -> np.ndarray:
    """d_h between every UAV and every ED: ed_xy [..., V, 2], uav_xy [U, 2] -> [..., U, V]."""
    ed_xy = np.asarray(ed_xy, dtype=np.float64)
    dx = np.subtract(ed_xy[..., None, :, 0], uav_xy[:, None, 0])  # [..., U, V], contiguous
    dy = np.subtract(ed_xy[..., None, :, 1], uav_xy[:, None, 1])
    dx *= dx
    dy *= dy
    dx += dy
    return np.sqrt(dx, out=dx)


def uav_positions(cfg: ScenarioConfig) -> np.ndarray:
    """SPEC.md: UAVs evenly along the horizontal mid-line, x_i = (i + 0.5) L / U, y = L / 2."""
    i = np.arange(cfg.n_uavs, dtype=np.float64)
    return np.stack([(i + 0.5) * cfg.area_m / cfg.n_uavs, np.full(cfg.n_uavs, cfg.area_m / 2.0)], axis=-1)


# ---------------------------------------------------------------- LoRa thresholds, Table (snr_threshold)
def snr_threshold_db(sf: np.ndarray | int, bw_khz: np.ndarray | int) -> np.ndarray:
    """rho_thr(SF, BW) in dB from the paper's table; raises ConfigError outside the table."""
    sf_a = np.asarray(sf)
    bw_a = np.asarray(bw_khz)
    sfs = np.array(sorted(SNR_THRESHOLD_TABLE_DB))
    bws = np.array([125, 250, 500])
    bad_sf = ~np.isin(sf_a, sfs)
    bad_bw = ~np.isin(bw_a, bws)
    if bad_sf.any():
        raise ConfigError(f"sf: {np.unique(sf_a[bad_sf]).tolist()} not in the allowed set {sfs.tolist()}")
    if bad_bw.any():
        raise ConfigError(f"bw_khz: {np.unique(bw_a[bad_bw]).tolist()} not in the allowed set {bws.tolist()}")
    table = np.array([[SNR_THRESHOLD_TABLE_DB[s][b] for b in bws] for s in sfs])
    return table[np.searchsorted(sfs, sf_a), np.searchsorted(bws, bw_a)]


# ---------------------------------------------------------------- UAV power, Eq. (hover)
def hover_power_w(cfg: ScenarioConfig) -> float:
    """Eq. (hover): P = n W_r^{3/2} (rho^{-1/2} s A^{-1/2} C_T^{-3/2} delta/8 + (1+k)/sqrt(2 rho A))."""
    h = cfg.hover
    w_r = h.weight_n / h.n_rotors
    profile = h.air_density**-0.5 * h.solidity * h.disc_area_m2**-0.5 * h.thrust_coef**-1.5 * h.drag_coef / 8.0
    induced = (1.0 + h.induced_factor) / np.sqrt(2.0 * h.air_density * h.disc_area_m2)
    return float(h.n_rotors * w_r**1.5 * (profile + induced))


# ---------------------------------------------------------------- SNR, SINR (Eq. sinr), rate (Eq. shannon)
def snr(tx_power_w: np.ndarray, gain: np.ndarray, noise_w: float) -> np.ndarray:
    """rho = P G / sigma^2 (linear)."""
    return tx_power_w * gain / noise_w


def _same_sf_onehot(sf_idx: np.ndarray, associated: np.ndarray, n_sf: int) -> np.ndarray:
    """[..., V, n_sf] one-hot of each transmitting ED's SF (zero rows for silent EDs)."""
    return (sf_idx[..., None] == np.arange(n_sf)) & associated[..., None]


def sinr_paper(snr_serving: np.ndarray, sf_idx: np.ndarray, associated: np.ndarray, n_sf: int) -> np.ndarray:
    """Eq. (sinr): SINR_v = rho_v / (sum_{v' != v, same SF, associated} rho_{a_v', v'} + 1).

    The interference of v' is its SNR at ITS OWN serving UAV, as the paper writes it.
    Silent (unassociated) EDs neither transmit nor interfere; their SINR is 0.
    """
    onehot = _same_sf_onehot(sf_idx, associated, n_sf)
    s_tx = np.where(associated, snr_serving, 0.0)
    total = np.einsum("...vn,...v->...n", onehot, s_tx)
    same = take_last(total, sf_idx)
    interference = np.maximum(same - s_tx, 0.0)
    return np.where(associated, s_tx / (interference + 1.0), 0.0)


def sinr_cross_gain(
    tx_power_w: np.ndarray,
    gains: np.ndarray,
    serving_uav: np.ndarray,
    sf_idx: np.ndarray,
    associated: np.ndarray,
    n_sf: int,
    noise_w: float,
) -> np.ndarray:
    """Physical variant: interference at v's serving UAV u is sum_{v'} P_v' G_{u,v'} / sigma^2.

    tx_power_w, serving_uav, sf_idx, associated: [..., V]; gains: [..., U, V].
    """
    onehot = _same_sf_onehot(sf_idx, associated, n_sf)
    p_tx = np.where(associated, tx_power_w, 0.0)
    rx = gains * p_tx[..., None, :]  # [..., U, V] power each UAV receives from each ED
    per_uav_sf = np.einsum("...uv,...vn->...un", rx, onehot)  # [..., U, n_sf]
    u = serving_uav[..., None, :]
    own = np.take_along_axis(rx, u, axis=-2)[..., 0, :]  # [..., V]
    at_serving = np.take_along_axis(per_uav_sf, serving_uav[..., :, None], axis=-2)  # [..., V, n_sf]
    same = np.take_along_axis(at_serving, sf_idx[..., None], axis=-1)[..., 0]
    interference = np.maximum(same - own, 0.0) / noise_w
    return np.where(associated, (own / noise_w) / (interference + 1.0), 0.0)


def rate_bps(
    sinr: np.ndarray,
    bw_hz: np.ndarray,
    sf: np.ndarray,
    threshold_db: np.ndarray,
    model: Literal["shannon", "lora_phy"] = "shannon",
    coding_rate: int = 1,
) -> np.ndarray:
    """Eq. (shannon): R = W log2(1 + SINR), or the LoRa PHY bit rate (SPEC.md extension):
    R = SF W / 2^SF * 4 / (4 + CR), delivered only when SINR_dB >= rho_thr(SF, W)."""
    if model == "shannon":
        return bw_hz * np.log2(1.0 + sinr)
    phy = sf * bw_hz / np.power(2.0, sf) * 4.0 / (4.0 + coding_rate)
    return np.where(lin_to_db(sinr) >= threshold_db, phy, 0.0)


# ---------------------------------------------------------------- EE (Eq. sys_ee) and the reward terms
def energy_efficiency(
    rate: np.ndarray, tx_power_w: np.ndarray, serving_uav: np.ndarray, associated: np.ndarray, hover_w: float, n_uavs: int
) -> np.ndarray:
    """EE_sys[t] = sum_u (sum_v a_uv R_uv) / (sum_v a_uv P_v + P_hover_u), bits per joule, one slot."""
    a_uv = (serving_uav[..., None, :] == np.arange(n_uavs)[:, None]) & associated[..., None, :]
    bits = np.einsum("...uv,...v->...u", a_uv, rate)
    watts = np.einsum("...uv,...v->...u", a_uv, tx_power_w) + hover_w
    return (bits / watts).sum(axis=-1)


def success_rate(sinr_db: np.ndarray, threshold_db: np.ndarray, associated: np.ndarray) -> np.ndarray:
    """Xi[t]: share of ALL V EDs that are associated and decoded (SINR_dB >= rho_thr)."""
    return (associated & (sinr_db >= threshold_db)).mean(axis=-1)


def margin_score(snr_db: np.ndarray, threshold_db: np.ndarray, associated: np.ndarray) -> np.ndarray:
    """beta[t] (SPEC.md): mean over associated EDs of m = SNR_dB - rho_thr scored as
    min(m, 20) / 20 for m >= 0 and max(m / 2, -10) for m < 0; 0 when no ED is associated."""
    m = snr_db - threshold_db
    score = np.where(m >= 0.0, np.minimum(m, 20.0) / 20.0, np.maximum(m / 2.0, -10.0))
    n = associated.sum(axis=-1)
    return np.where(n > 0, np.where(associated, score, 0.0).sum(axis=-1) / np.maximum(n, 1), 0.0)


def total_power_w(tx_power_w: np.ndarray, associated: np.ndarray, hover_w: float, n_uavs: int) -> np.ndarray:
    """P_total[t] = sum of associated EDs' TP (W) + sum_u P_hover_u."""
    return np.where(associated, tx_power_w, 0.0).sum(axis=-1) + n_uavs * hover_w


def reward(ee: np.ndarray, xi: np.ndarray, beta: np.ndarray, p_total: np.ndarray, w: RewardWeights) -> np.ndarray:
    """Eq. (reward): r = w1 EE + w2 Xi + w3 beta - |w4| P_total (w4 is a penalty whatever its sign)."""
    return w.w1 * ee + w.w2 * xi + w.w3 * beta - abs(w.w4) * p_total


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
    def from_config(cls, cfg: ScenarioConfig) -> "Tables":
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


def slot_metrics(
    gains: np.ndarray,
    serving_uav: np.ndarray,
    associated: np.ndarray,
    sf_idx: np.ndarray,
    tp_idx: np.ndarray,
    bw_idx: np.ndarray,
    cfg: ScenarioConfig,
    tables: Tables,
) -> dict[str, np.ndarray]:
    """Everything the paper measures in one slot, given the association and per-ED allocations.

    gains [..., U, V]; the other inputs [..., V] (serving_uav is any valid index where the ED
    is unassociated). Returns the keys of SLOT_METRICS, each shaped [...].
    """
    g_serving = at_serving(gains, serving_uav)
    p_w = tables.tp_w[tp_idx]
    bw_hz = tables.bw_hz[bw_idx]
    thr_db = tables.threshold_db[sf_idx, bw_idx]
    snr_lin = snr(p_w, g_serving, tables.noise_w)
    if cfg.interference == "paper":
        sinr_lin = sinr_paper(snr_lin, sf_idx, associated, cfg.n_sf)
    else:
        sinr_lin = sinr_cross_gain(p_w, gains, serving_uav, sf_idx, associated, cfg.n_sf, tables.noise_w)
    sinr_db = lin_to_db(sinr_lin)
    rate = np.where(
        associated,
        rate_bps(sinr_lin, bw_hz, tables.sf[sf_idx], thr_db, cfg.rate_model, cfg.lora_coding_rate),
        0.0,
    )
    ee = energy_efficiency(rate, p_w, serving_uav, associated, tables.hover_w, cfg.n_uavs)
    xi = success_rate(sinr_db, thr_db, associated)
    beta = margin_score(lin_to_db(snr_lin), thr_db, associated)
    p_total = total_power_w(p_w, associated, tables.hover_w, cfg.n_uavs)
    n_assoc = associated.sum(axis=-1)
    return {
        "reward": reward(ee, xi, beta, p_total, cfg.reward),
        "ee_sys": ee,
        "success_rate": xi,
        "beta": beta,
        "p_total_w": p_total,
        "rate_sum_bps": rate.sum(axis=-1),
        "mean_sinr_db": np.where(n_assoc > 0, np.where(associated, sinr_db, 0.0).sum(axis=-1) / np.maximum(n_assoc, 1), DB_FLOOR),
        "n_unassociated": (~associated).sum(axis=-1).astype(np.float64),
    }
