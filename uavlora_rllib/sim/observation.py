"""What the agents see: each UAV's local observation, and the global state of critics and mixers.

Observation o_u (docs/model.md; float32, computed in float64 and rounded once): quota rows of
(x_v, y_v, d_uv, G_uv) over the EDs u serves, sorted by gain (their `slot_of_ed`), then 3
per-UAV features (served count / quota, UAV x, UAV y):
  x, y      -> 2 p / L - 1                         in [-1, 1]
  d_uv      -> d_h / R_comm                        in [0, 1] for served EDs
  G_uv      -> dB gain mapped linearly so that G(d_h = 0) -> 1 and G(d_h = R_comm) -> -1
Padding rows are zeros.

Global state s (float64): ED positions (2V), gain features to every UAV (UV, clipped to
[-3, 1]), association one-hot (V (U+1), last column = unassociated), each ED's previous
(SF, TP, BW) one-hot (V (n_sf + n_tp + n_bw), zeros when it was silent), and t / T.
"""

from __future__ import annotations

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.links import Links
from uavlora_rllib.sim.scenario import ScenarioConfig

OBS_ROW = 4  # (x, y, d, G) per served ED
OBS_EXTRA = 3  # served count / quota, UAV x, UAV y


def obs_dim(cfg: ScenarioConfig) -> int:
    return cfg.quota * OBS_ROW + OBS_EXTRA


def state_dim(cfg: ScenarioConfig) -> int:
    v, u = cfg.n_eds, cfg.n_uavs
    return 2 * v + u * v + v * (u + 1) + v * (cfg.n_sf + cfg.n_tp + cfg.n_bw) + 1


class Observer:
    """Builds the observations [N, U, obs_dim] of N scenarios from their links, and their
    global state [N, state_dim]."""

    def __init__(self, cfg: ScenarioConfig, n_envs: int):
        self.cfg = cfg
        self.n = n_envs
        u, q1 = cfg.n_uavs, cfg.quota + 1
        g_hi = float(-physics.path_loss_db(0.0, cfg))
        g_lo = float(-physics.path_loss_db(cfg.comm_range_m, cfg))
        self._gain_db_mid = (g_hi + g_lo) / 2.0
        self._gain_db_half = max((g_hi - g_lo) / 2.0, 1e-9)
        self._obs_extra_xy = 2.0 * physics.uav_positions(cfg) / cfg.area_m - 1.0  # [U, 2], constant
        # Observations are written into a buffer of OBS_ROW-wide rows: per (scenario, UAV) the
        # quota's ED rows, then one row holding the 3 extra features and one pad; obs is the
        # [N, U, obs_dim] view of it. One more row at the end receives unassociated EDs.
        # (offsets in complex64 units, pairs of float32: a row is OBS_ROW // 2 of them)
        self._obs_rows_base = (np.arange(n_envs) * (u * q1 * OBS_ROW // 2))[:, None]
        self._obs_garbage = n_envs * u * q1 * OBS_ROW // 2
        self._obs_buf_shape = (n_envs * u * q1 + 1, OBS_ROW)
        self._obs_scratch: tuple[np.ndarray, np.ndarray] | None = None  # complex128, complex64 [N, V]

    def gain_feature(self, gain_db: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """G in dB mapped linearly: G(d_h = 0) -> 1, G(d_h = R_comm) -> -1."""
        x = np.subtract(gain_db, self._gain_db_mid, out=out)
        return np.divide(x, self._gain_db_half, out=x)

    def observe(self, links: Links, xy: np.ndarray) -> np.ndarray:
        """The observations of the slot with these links and ED positions xy [2, N, V]
        (a fresh array: callers may keep it)."""
        cfg = self.cfg
        n, q, n_u = self.n, cfg.quota, cfg.n_uavs
        q1 = q + 1
        # Row of ED v: (e U + u) (quota + 1) + slot; unassociated EDs: the scratch row. A row is
        # two complex64 (8-byte) pairs of float32, (x, y) and (d, G), each written by one flat
        # scatter from a contiguous array (half the scatters of one per feature; NumPy's loops
        # over a trailing axis of 2 or 4 are slow).
        start = links.slot_of_ed * (OBS_ROW // 2)  # complex64 index of the row's (x, y) pair
        start += links.serving_idx * (q1 * OBS_ROW // 2)
        start += self._obs_rows_base
        if not links.all_associated:
            start = np.where(links.associated, start, self._obs_garbage)
        # np.zeros, not a copy of a template: a buffer of this size comes zeroed from the OS
        # (calloc), so this skips reading and copying one; the extras are written below.
        buf = np.zeros(self._obs_buf_shape, dtype=np.float32)
        pairs = buf.reshape(-1).view(np.complex64)
        if self._obs_scratch is None or self._obs_scratch[0].shape != start.shape:
            self._obs_scratch = (np.empty(start.shape, np.complex128), np.empty(start.shape, np.complex64))
        # (private, overwritten every step: no fresh 1.6 MB per step). Features are computed
        # in float64 and rounded once to float32 (the same values as casting a float64 obs).
        val, val32 = self._obs_scratch
        for k, part in enumerate((val.real, val.imag)):  # x, y -> 2 p / L - 1
            np.multiply(xy[k], 2.0 / cfg.area_m, out=part)
            part -= 1.0
        np.copyto(val32, val, casting="same_kind")
        pairs[start] = val32
        np.divide(links.d_h_serving, cfg.comm_range_m, out=val.real)
        self.gain_feature(links.g_db_serving, out=val.imag)
        np.copyto(val32, val, casting="same_kind")
        start += 1
        pairs[start] = val32
        obs = buf[:-1].reshape(n, n_u, q1 * OBS_ROW)
        np.divide(links.counts, q, out=obs[..., q * OBS_ROW])
        obs[..., q * OBS_ROW + 1 : q * OBS_ROW + OBS_EXTRA] = self._obs_extra_xy
        return obs[..., : q * OBS_ROW + OBS_EXTRA]

    def global_state(
        self, ed_xy: np.ndarray, gain_db: np.ndarray, links: Links, prev_alloc: np.ndarray, t: np.ndarray
    ) -> np.ndarray:
        """The state [N, state_dim] from the ED positions [N, V, 2], every pair's gain in dB
        [N, U, V], the links, each ED's previous allocation [N, V, 3] and the slot index [N]."""
        cfg, n = self.cfg, self.n
        pos = 2.0 * ed_xy / cfg.area_m - 1.0
        gains = np.clip(self.gain_feature(gain_db), -3.0, 1.0)
        assoc = np.zeros((n, cfg.n_eds, cfg.n_uavs + 1))
        np.put_along_axis(assoc, np.where(links.associated, links.serving, cfg.n_uavs)[..., None], 1.0, axis=-1)
        sizes = (cfg.n_sf, cfg.n_tp, cfg.n_bw)
        prev = [(prev_alloc[..., k, None] == np.arange(size)).astype(np.float64) for k, size in enumerate(sizes)]
        time = (t / cfg.episode_len)[:, None]
        return np.concatenate(
            [pos.reshape(n, -1), gains.reshape(n, -1), assoc.reshape(n, -1), *(p.reshape(n, -1) for p in prev), time],
            axis=-1,
        )
