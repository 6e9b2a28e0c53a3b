"""Array helpers the equations share: gathers at the serving UAV, per-group sums (one
np.bincount over a batch), clipping, and unit and dB conversions."""

from __future__ import annotations

import functools

import numpy as np

# Floor used wherever a ratio is shown in dB, so that "no signal" is a finite, very low value.
DB_FLOOR = -200.0
_FLOOR_LIN = 10.0 ** (DB_FLOOR / 10.0)  # 1e-20


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


def group_index(groups: np.ndarray, n_groups: int, shape: tuple[int, ...]) -> np.ndarray:
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
    idx = group_index(groups, n_groups, shape)
    w = values.reshape(-1) if values.shape == shape else np.broadcast_to(values, shape).reshape(-1)
    n_bins = (idx.size // shape[-1]) * n_groups if idx.size else 0
    return np.bincount(idx, weights=w, minlength=n_bins).reshape(shape[:-1] + (n_groups,))


def group_count(groups: np.ndarray, n_groups: int) -> np.ndarray:
    """sum_v [groups_v == g] along the last axis, as int64: [..., V] -> [..., n_groups] (one
    unweighted np.bincount, faster than group_sum with boolean weights)."""
    idx = group_index(groups, n_groups, groups.shape)
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


def db_threshold_lin(threshold_db: np.ndarray) -> np.ndarray:
    """The smallest float64 x with lin_to_db(x) >= threshold_db, elementwise, so that `x >= it` decides
    `lin_to_db(x) >= threshold_db` without a logarithm per element (lin_to_db is non-decreasing). For a
    small table of thresholds (e.g. rho_thr per SF and BW): each entry is 10^(thr/10) moved by ulps."""
    thr = np.asarray(threshold_db, dtype=np.float64)
    out = np.empty_like(thr)
    for i, t in np.ndenumerate(thr):
        if t <= DB_FLOOR:  # every x passes, zero and below included
            out[i] = -np.inf
            continue
        x = float(db_to_lin(t))
        while lin_to_db(np.nextafter(x, -np.inf)) >= t:  # down while the float below still passes
            x = np.nextafter(x, -np.inf)
        while lin_to_db(x) < t:  # up until it passes
            x = np.nextafter(x, np.inf)
        out[i] = x
    return out


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
