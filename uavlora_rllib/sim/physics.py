"""The paper's system model, one pure vectorised function per equation.

Every function broadcasts over leading batch dimensions. The simulator core, the
environments, the baselines and the analysis all call these functions; no equation is
written anywhere else. Equation labels, e.g. Eq. (gm), are those of the paper (Ahmed et al.,
VTC2026-Spring), each restated in docs/model.md; where the project decides something the paper
leaves open (docs/model.md#decisions), the docstring says so.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import SNR_THRESHOLD_TABLE_DB, RewardWeights, ScenarioConfig

# Floor used wherever a ratio is shown in dB, so that "no signal" is a finite, very low value.
DB_FLOOR = -200.0
_DEG_PER_RAD = 180.0 / np.pi
_FLOOR_LIN = 10.0 ** (DB_FLOOR / 10.0)  # 1e-20
_LN10_OVER_10 = np.log(10.0) / 10.0


# ---------------------------------------------------------------- gathers
def at_serving(per_uav: np.ndarray, serving_uav: np.ndarray) -> np.ndarray:
    """per_uav [..., U, V] at each ED's serving UAV serving_uav [..., V] -> [..., V]."""
    if per_uav.ndim == 3 and serving_uav.ndim == 2 and per_uav.shape[0] == serving_uav.shape[0]:
        n, _, v = per_uav.shape
        return per_uav[np.arange(n)[:, None], serving_uav, np.arange(v)[None, :]]
    return np.take_along_axis(per_uav, serving_uav[..., None, :], axis=-2)[..., 0, :]


@functools.lru_cache(maxsize=64)
def _row_offsets(lead: tuple[int, ...], n_groups: int) -> np.ndarray:
    """n_groups * (row number) for each row of a [*lead] batch, shaped [*lead, 1] (read-only)."""
    off = (np.arange(int(np.prod(lead)), dtype=np.int64) * n_groups).reshape(lead + (1,))
    off.flags.writeable = False
    return off


def _group_index(groups: np.ndarray, n_groups: int, shape: tuple[int, ...]) -> np.ndarray:
    """Flat bin of each element of `groups` [..., V] (values in [0, n_groups)) in a
    [prod(shape[:-1]) * n_groups] array: row r, group g -> r * n_groups + g."""
    off = _row_offsets(shape[:-1], n_groups)
    if groups.shape != shape:
        groups = np.broadcast_to(groups, shape)
    return np.add(groups, off).reshape(-1)


def group_sum(values: np.ndarray, groups: np.ndarray, n_groups: int) -> np.ndarray:
    """sum_v [groups_v == g] values_v along the last axis: [..., V] x [..., V] -> [..., n_groups].

    One np.bincount over the whole batch (each bin sums its elements in index order, so a
    row's result does not depend on the other rows); `groups` must lie in [0, n_groups)."""
    values, groups = np.asarray(values), np.asarray(groups)
    shape = values.shape if values.shape == groups.shape else np.broadcast_shapes(values.shape, groups.shape)
    idx = _group_index(groups, n_groups, shape)
    w = values.reshape(-1) if values.shape == shape else np.broadcast_to(values, shape).reshape(-1)
    n_bins = (idx.size // shape[-1]) * n_groups if idx.size else 0
    return np.bincount(idx, weights=w, minlength=n_bins).reshape(shape[:-1] + (n_groups,))


def group_count(groups: np.ndarray, n_groups: int) -> np.ndarray:
    """sum_v [groups_v == g] along the last axis, as int64: [..., V] -> [..., n_groups] (one
    unweighted np.bincount, faster than group_sum with boolean weights)."""
    idx = _group_index(groups, n_groups, groups.shape)
    n_bins = (idx.size // groups.shape[-1]) * n_groups if idx.size else 0
    return np.bincount(idx, minlength=n_bins).reshape(groups.shape[:-1] + (n_groups,))


# ---------------------------------------------------------------- unit conversions
def dbm_to_w(p_dbm: np.ndarray | float) -> np.ndarray:
    return np.power(10.0, (np.asarray(p_dbm, dtype=np.float64) - 30.0) / 10.0)


def db_to_lin(x_db: np.ndarray | float) -> np.ndarray:
    """10^(x/10), on a new array (the input is left untouched)."""
    y = np.divide(x_db, 10.0)
    return np.power(10.0, y, out=y) if isinstance(y, np.ndarray) else np.power(10.0, y)


CLIP_MIN = 16384  # elements from which `at_least` / `clip` use np.clip (see at_least)


def at_least(x: np.ndarray, low: float, out: np.ndarray | None = None) -> np.ndarray:
    """max(x, low) elementwise (NaN stays NaN). np.clip with an infinite upper bound gives
    the same values faster per element than np.maximum, but its Python-level wrapper costs
    more per call: it is used from CLIP_MIN elements on."""
    if x.size >= CLIP_MIN:
        return np.clip(x, low, np.inf, out=out)
    return np.maximum(x, low, out=out)


def clip(x: np.ndarray, low: float, high: float, out: np.ndarray | None = None) -> np.ndarray:
    """min(max(x, low), high) elementwise: np.clip from CLIP_MIN elements on (as at_least)."""
    if x.size >= CLIP_MIN:
        return np.clip(x, low, high, out=out)
    y = np.maximum(x, low, out=out)
    return np.minimum(y, high, out=y)


def lin_to_db(x: np.ndarray | float, out: np.ndarray | None = None) -> np.ndarray:
    """10 log10(x), floored at DB_FLOOR for x <= 0 (`out`: an array to write it into).

    Evaluated as max(10 log10(max(x, 10^(DB_FLOOR/10))), DB_FLOOR): for x above the floor's
    linear value that is 10 log10(x); below it (x <= 0 included) both forms give DB_FLOOR, and
    no log of 0 is taken (no floating-point warning to suppress)."""
    if not isinstance(x, np.ndarray) or x.ndim == 0:  # 0-d input
        return np.maximum(10.0 * np.log10(np.maximum(x, _FLOOR_LIN)), DB_FLOOR)
    x = at_least(x, _FLOOR_LIN, out=out)
    np.log10(x, out=x)
    x *= 10.0
    return at_least(x, DB_FLOOR, out=x)


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

    docs/model.md#channel: the free-space term uses the 3-D distance sqrt(d_h^2 + h^2) (the paper writes
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
    """G = 10^(-L/10), linear power gain (the plain formula; see `channel_gain_sq`)."""
    return db_to_lin(-path_loss_db(d_h, cfg))


def channel_gain_sq(d2_h: np.ndarray, cfg: ScenarioConfig, with_db: bool = False, d_h: np.ndarray | None = None):
    """G = 10^(-L/10) of Eq. (a2g_pl) from the SQUARED horizontal distance d2_h = d_h^2, with
    the transcendentals this CPU's NumPy vectorises (sqrt, arctan, exp, log10) instead of
    arctan2 and 10^x. Same value as `channel_gain(sqrt(d2_h))` up to rounding (tested to 1e-12
    relative). Returns G, or (G, G_dB) with G_dB = -L when `with_db`. `d_h`: sqrt(d2_h) when the
    caller has it (sqrt is correctly rounded: the same values, one pass fewer).

    Derivation. With d3^2 = d2_h + h^2 and K0 = 20 log10(4 pi f / c),
      L = 10 log10(d3^2) + K0 + eta_LoS P + eta_NLoS (1 - P)
        = 10 log10(d3^2) + K0 + eta_NLoS - (eta_NLoS - eta_LoS) P,
    so  G = 10^(-L/10) = C / d3^2 * exp(kappa P),  C = (c / (4 pi f))^2 10^(-eta_NLoS/10),
    kappa = (eta_NLoS - eta_LoS) ln(10) / 10.
    Eq. (plos): P = 1 / (1 + a exp(-b (theta - a))), theta = atan(h / d_h) in degrees; for
    d_h >= 0, atan(h / d_h) = pi/2 - atan(d_h / h) (also at d_h = 0), so
      -b (theta - a) = b (a - 90) + b (180/pi) atan(d_h / h).
    """
    d2_h = np.asarray(d2_h, dtype=np.float64)
    if d2_h.ndim == 0:
        out = channel_gain_sq(d2_h.reshape(1), cfg, with_db)
        return (out[0][0], out[1][0]) if with_db else out[0]
    h = cfg.altitude_m
    d3_sq = np.add(d2_h, h * h)
    if d_h is None:
        t = np.sqrt(d2_h)
        t *= 1.0 / h
    else:
        t = np.multiply(d_h, 1.0 / h)
    np.arctan(t, out=t)
    t *= cfg.los_b * _DEG_PER_RAD
    t += cfg.los_b * (cfg.los_a - 90.0)
    np.exp(t, out=t)
    t *= cfg.los_a
    t += 1.0
    p_los = np.divide(1.0, t, out=t)
    c = (cfg.speed_of_light_mps / (4.0 * np.pi * cfg.carrier_hz)) ** 2 * 10.0 ** (-cfg.eta_nlos_db / 10.0)
    p_los *= (cfg.eta_nlos_db - cfg.eta_los_db) * _LN10_OVER_10
    gain = np.exp(p_los, out=p_los)
    np.divide(gain, d3_sq, out=gain)
    gain *= c
    if not with_db:
        return gain
    g_db = np.log10(gain, out=d3_sq)  # G_dB = 10 log10 G = -L
    g_db *= 10.0
    return gain, g_db


def gain_decreases_with_distance(cfg: ScenarioConfig) -> bool:
    """True when G is strictly decreasing in d_h: then "max-gain UAV" = "nearest UAV".

    The free-space term grows with d_h; P_LoS falls with d_h (theta falls, b >= 0), and
    L = ... - (eta_NLoS - eta_LoS) P, so L strictly increases when eta_NLoS >= eta_LoS."""
    return cfg.eta_nlos_db >= cfg.eta_los_db and cfg.los_b >= 0.0 and cfg.los_a >= 0.0


def horizontal_distance_sq(ed_xy: np.ndarray, uav_xy: np.ndarray) -> np.ndarray:
    """d_h^2 between every UAV and every ED: ed_xy [..., V, 2], uav_xy [U, 2] -> [..., U, V]."""
    ed_xy = np.asarray(ed_xy, dtype=np.float64)
    dx = np.subtract(ed_xy[..., None, :, 0], uav_xy[:, None, 0])  # [..., U, V], contiguous
    dy = np.subtract(ed_xy[..., None, :, 1], uav_xy[:, None, 1])
    dx *= dx
    dy *= dy
    dx += dy
    return dx


def horizontal_distance_sq_to(ed_xy: np.ndarray, uav_xy: np.ndarray, uav_idx: np.ndarray) -> np.ndarray:
    """d_h^2 between each ED and ONE UAV each: ed_xy [..., V, 2], uav_idx [..., V] -> [..., V].

    The same operations, element by element, as `horizontal_distance_sq` (so the value equals
    that function's entry [..., uav_idx[v], v] bit for bit)."""
    dx = np.subtract(ed_xy[..., 0], uav_xy[:, 0].take(uav_idx))
    y = uav_xy[:, 1]
    # UAVs on one horizontal line (docs/model.md#scenario layout): the same y for all, no gather needed
    dy = np.subtract(ed_xy[..., 1], y[0] if (y == y[0]).all() else y.take(uav_idx))
    dx *= dx
    dy *= dy
    dx += dy
    return dx


def uav_positions(cfg: ScenarioConfig) -> np.ndarray:
    """docs/model.md#scenario: UAVs evenly along the horizontal mid-line, x_i = (i + 0.5) L / U, y = L / 2."""
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


def _sinr_paper_tx(s_tx: np.ndarray, sf_idx: np.ndarray, n_sf: int, out: np.ndarray | None = None) -> np.ndarray:
    """Eq. (sinr) given s_tx = the SNR of each ED, 0 for silent EDs (see `sinr_paper`);
    `out`: a C-contiguous array of the broadcast shape to write the result into."""
    shape = s_tx.shape if s_tx.shape == sf_idx.shape else np.broadcast_shapes(s_tx.shape, sf_idx.shape)
    idx = _group_index(sf_idx, n_sf, shape)
    s_flat = s_tx.reshape(-1) if s_tx.shape == shape else np.broadcast_to(s_tx, shape).reshape(-1)
    n_bins = (idx.size // shape[-1]) * n_sf if idx.size else 0
    if out is not None:
        _sinr_of_groups(s_flat, idx, n_bins, out=out.reshape(-1))
        return out
    return _sinr_of_groups(s_flat, idx, n_bins).reshape(shape)


def _sinr_of_groups(s_flat: np.ndarray, group: np.ndarray, n_bins: int, out: np.ndarray | None = None) -> np.ndarray:
    """Eq. (sinr) of EDs whose interferers are the EDs of the same group (flat bin per ED:
    scenario and SF): s / (sum of the group's s - s + 1), s_flat and group 1-D."""
    total = np.bincount(group, weights=s_flat, minlength=n_bins)
    interference = total.take(group)  # sum over the ED's own SF, itself included
    interference -= s_flat  # >= 0 exactly: a running sum of terms >= 0 never falls below one of them
    interference += 1.0
    return np.divide(s_flat, interference, out=interference if out is None else out)


def sinr_paper(snr_serving: np.ndarray, sf_idx: np.ndarray, associated: np.ndarray, n_sf: int) -> np.ndarray:
    """Eq. (sinr): SINR_v = rho_v / (sum_{v' != v, same SF, associated} rho_{a_v', v'} + 1).

    The interference of v' is its SNR at ITS OWN serving UAV, as the paper writes it.
    Silent (unassociated) EDs neither transmit nor interfere; their SINR is 0.
    """
    return _sinr_paper_tx(np.where(associated, snr_serving, 0.0), np.asarray(sf_idx), n_sf)


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

    tx_power_w, serving_uav, sf_idx, associated: [..., V]; gains: [..., U, V]. The leading
    axes broadcast against each other (the baselines score candidate actions [C, N, V] against
    the batch's gains [N, U, V] and association [N, V]); the index arrays are broadcast to the
    common shape because take_along_axis needs as many axes in its indices as in its array.
    """
    tx_power_w, sf_idx = np.asarray(tx_power_w), np.asarray(sf_idx)
    associated, serving_uav = np.asarray(associated), np.asarray(serving_uav)
    lead = np.broadcast_shapes(
        tx_power_w.shape, sf_idx.shape, associated.shape, serving_uav.shape, gains.shape[:-2] + gains.shape[-1:]
    )
    sf_idx, associated, serving_uav = (np.broadcast_to(x, lead) for x in (sf_idx, associated, serving_uav))
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
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Eq. (shannon): R = W log2(1 + SINR), or the LoRa PHY bit rate (extension, docs/model.md#rate):
    R = SF W / 2^SF * 4 / (4 + CR), delivered only when SINR_dB >= rho_thr(SF, W).
    `out`: an array of the result's shape for the Shannon rate to be written into."""
    if model == "shannon":
        if out is None:
            return bw_hz * np.log2(np.add(sinr, 1.0))
        np.add(sinr, 1.0, out=out)
        np.log2(out, out=out)
        return np.multiply(bw_hz, out, out=out)
    phy = sf * bw_hz / np.power(2.0, sf) * 4.0 / (4.0 + coding_rate)
    r = np.where(lin_to_db(sinr) >= threshold_db, phy, 0.0)
    if out is not None:
        out[...] = r
        return out
    return r


# ---------------------------------------------------------------- EE (Eq. sys_ee) and the reward terms
def energy_efficiency(
    rate: np.ndarray, tx_power_w: np.ndarray, serving_uav: np.ndarray, associated: np.ndarray, hover_w: float, n_uavs: int
) -> np.ndarray:
    """EE_sys[t] = sum_u (sum_v a_uv R_uv) / (sum_v a_uv P_v + P_hover_u), bits per joule, one slot.

    serving_uav: any valid UAV index where the ED is unassociated."""
    rate_tx, p_tx = np.broadcast_arrays(np.where(associated, rate, 0.0), np.where(associated, tx_power_w, 0.0))
    return _ee_of_tx(rate_tx, p_tx, np.asarray(serving_uav), hover_w, n_uavs)


def _ee_of_tx(
    rate_tx: np.ndarray, p_tx: np.ndarray, serving_uav: np.ndarray, hover_w: float, n_uavs: int
) -> np.ndarray:
    """energy_efficiency from the rate and transmit power [..., V] (same shape), both already 0
    for the unassociated EDs: the per-UAV sums of bits and of watts by a bincount each."""
    shape = rate_tx.shape
    idx = _group_index(serving_uav, n_uavs, shape)
    n_bins = idx.size // shape[-1] * n_uavs
    bits = np.bincount(idx, weights=rate_tx.reshape(-1), minlength=n_bins)
    watts = np.bincount(idx, weights=p_tx.reshape(-1), minlength=n_bins)
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
    return _mean_over(_margin_points(snr_db, threshold_db), associated, np.add.reduce(associated, axis=-1), 0.0)


def _margin_points(snr_db: np.ndarray, threshold_db: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """margin_score's points of each ED; `out` (may be snr_db itself) receives them."""
    return _points_of_margin(np.subtract(snr_db, threshold_db, out=out))


def _points_of_margin(m: np.ndarray) -> np.ndarray:
    """margin_score's points of the margins m = SNR_dB - rho_thr, in place."""
    below = m < 0.0
    clip(m, -20.0, 20.0, out=m)
    divisor = np.multiply(below, 2.0 - 20.0)  # 2 where below, 20 elsewhere (exact; np.where with
    divisor += 20.0  # two scalars is slower)
    m /= divisor
    return m


def _mean_over(x: np.ndarray, associated: np.ndarray | None, n: np.ndarray, empty) -> np.ndarray:
    """Mean of x over the n associated EDs (last axis; x may stack several quantities in front,
    [k, ..., V], each reduced by the one call); `empty` (broadcast) where none is associated.
    associated None: every ED is (the same sums, without the masking pass)."""
    total = np.add.reduce(x if associated is None else np.where(associated, x, 0.0), axis=-1)
    return np.where(n > 0, total / np.maximum(n, 1), empty)


def total_power_w(tx_power_w: np.ndarray, associated: np.ndarray, hover_w: float, n_uavs: int) -> np.ndarray:
    """P_total[t] = sum of associated EDs' TP (W) + sum_u P_hover_u."""
    return _p_total(np.where(associated, tx_power_w, 0.0).sum(axis=-1), hover_w, n_uavs)


def _p_total(tx_sum_w: np.ndarray, hover_w: float, n_uavs: int) -> np.ndarray:
    """total_power_w from the sum of the associated EDs' transmit powers (in place)."""
    tx_sum_w += n_uavs * hover_w
    return tx_sum_w


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
    tp_idx: np.ndarray,
    bw_idx: np.ndarray,
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
        g_serving = at_serving(gains, serving_uav)
    sf_idx = np.asarray(sf_idx)
    p_w, bw_hz, thr_db = allocation_values(sf_idx, tp_idx, bw_idx, tables) if values is None else values
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
        sinr_lin = _sinr_paper_tx(s_tx, sf_idx, cfg.n_sf, out=lin[1])
    else:
        sinr_lin = lin[1]
        sinr_lin[...] = sinr_cross_gain(p_w, gains, serving_uav, sf_idx, associated, cfg.n_sf, tables.noise_w)
    db = lin_to_db(lin)
    snr_db, sinr_db = db[0], db[1]
    # SINR = 0 for silent EDs, so their Shannon rate W log2(1) and their LoRa-PHY rate are 0.
    sf = None if cfg.rate_model == "shannon" else tables.sf[sf_idx]
    rate = rate_bps(sinr_lin, bw_hz, sf, thr_db, cfg.rate_model, cfg.lora_coding_rate, out=np.empty(shape))
    ee = _ee_of_tx(rate, p_tx, serving_uav, tables.hover_w, cfg.n_uavs)  # Eq. (sys_ee)
    rate_sum, p_total = np.add.reduce(rate, axis=-1), np.add.reduce(p_tx, axis=-1)
    p_total = _p_total(p_total, tables.hover_w, cfg.n_uavs)
    xi = success_rate(sinr_db, thr_db, associated)
    _margin_points(snr_db, thr_db, out=db[0])
    return _slot_metrics_of(ee, xi, db, p_total, rate_sum, associated, everyone, cfg.reward)


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
    if everyone:  # (the means' divisor is V: the same values as _mean_over's, fewer calls)
        beta, mean_sinr_db = np.add.reduce(db, axis=-1) / n_eds
        n_unassociated = np.zeros(db.shape[1:-1])
    else:
        n_assoc = np.add.reduce(associated, axis=-1)
        empty = _EMPTY_MEANS.reshape((2,) + (1,) * (db.ndim - 2))
        beta, mean_sinr_db = _mean_over(db, associated, n_assoc, empty)
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
    group = _group_index(alloc.sf_idx, cfg.n_sf, alloc.sf_idx.shape).take(flat)
    sinr = _sinr_of_groups(s_tx, group, n * cfg.n_sf).reshape(n, v)
    # Eq. (shannon) summed per UAV, then Eq. (sys_ee)
    log_term = np.add(sinr, 1.0)
    np.log2(log_term, out=log_term)
    bits = np.bincount(flat, weights=log_term.reshape(-1), minlength=n * n_u).reshape(n, n_u)
    bits *= alloc.bw_hz
    tx_w = np.multiply(counts, alloc.p_w)
    watts = tx_w + tables.hover_w
    ee = np.add.reduce(np.divide(bits, watts, out=watts), axis=-1)
    rate_sum = np.add.reduce(bits, axis=-1)
    p_total = _p_total(np.add.reduce(tx_w, axis=-1), tables.hover_w, n_u)
    # success rate, beta's margin points and the mean SINR (dB), as in slot_metrics
    db = np.empty((2, n, v))  # margin points and SINR (dB), averaged by one reduction
    sinr_db = lin_to_db(sinr, out=db[1])
    xi = success_rate(sinr_db, alloc.threshold_db.take(serving_flat), associated)
    np.add(g_db_serving, alloc.margin_offset_db.take(serving_flat), out=db[0])
    _points_of_margin(db[0])
    return _slot_metrics_of(ee, xi, db, p_total, rate_sum, associated, everyone, cfg.reward)
