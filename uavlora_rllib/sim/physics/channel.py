"""The ground-to-air channel, Eqs. (plos) and (a2g_pl), and the geometry it needs: UAV
positions and horizontal ED-UAV distances."""

from __future__ import annotations

import numpy as np

from uavlora_rllib.sim.physics.arrays import db_to_lin
from uavlora_rllib.sim.scenario import ScenarioConfig

_DEG_PER_RAD = 180.0 / np.pi
_LN10_OVER_10 = np.log(10.0) / 10.0


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
