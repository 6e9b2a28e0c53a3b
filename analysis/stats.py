"""Statistics of the analysis step; every definition the report uses lives here.

Across seeds (one value per training seed, e.g. a run's ``eval/ee_sys_mean``):

* ``mean``: arithmetic mean over seeds.
* ``t_ci95``: 95% Student-t confidence interval of that mean,
  mean +- t_{0.975, n-1} * s / sqrt(n), s the sample standard deviation (ddof = 1);
  undefined (NaN) for fewer than 2 seeds.
* ``iqm``: interquartile mean, ``scipy.stats.trim_mean(x, 0.25)`` (cuts int(0.25 n) values
  at each end, so for n <= 3 it equals the mean).
* ``improvement_pct``: the paper's relative gain, 100 * (a - b) / b, on the seed means.
* ``ratio_ci95``: 95% Fieller interval of mean(a) / mean(b) for two independent sets of seeds
  (the paper table's CI of an improvement is 100 (ratio - 1) over that interval); Student t
  with min(n_a, n_b) - 1 degrees of freedom (conservative), unbounded when mean(b) is not
  significantly different from 0.

Training curves (Fig. 3a):

* ``ema``: TensorBoard-style exponential moving average with debiasing,
  s_k = w s_{k-1} + (1 - w) x_k, s_0 = 0, reported as s_k / (1 - w^(k+1)); w = 0 is no smoothing.
  Applied to each run's logged points before interpolation.
* ``common_grid`` / ``interpolate``: curves of different seeds are linearly interpolated onto
  ``points`` evenly spaced env-step values spanning the range every seed covers.
* ``bootstrap_ci95``: percentile bootstrap of the mean over seeds at every grid point
  (seeds resampled with replacement, ``n_boot`` resamples, fixed generator seed).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st

from uavlora_rllib.experiment.evaluation import t_half_width_95

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0


@dataclass(frozen=True)
class SeedSummary:
    n: int
    mean: float
    std: float  # sample standard deviation (ddof=1), NaN for n < 2
    ci_low: float  # 95% Student-t interval, NaN for n < 2
    ci_high: float
    iqm: float

    @property
    def ci_half(self) -> float:
        return (self.ci_high - self.ci_low) / 2.0


def t_ci95(x: Sequence[float]) -> tuple[float, float]:
    """95% Student-t confidence interval of the mean of `x` (NaN, NaN for fewer than 2 values)."""
    a = np.asarray(x, dtype=float)
    n = a.size
    if n < 2:
        return math.nan, math.nan
    m = float(a.mean())
    half = t_half_width_95(a)
    return m - half, m + half


def iqm(x: Sequence[float]) -> float:
    """Interquartile mean: scipy.stats.trim_mean(x, 0.25)."""
    a = np.asarray(x, dtype=float)
    if a.size == 0:
        return math.nan
    return float(_st.trim_mean(a, 0.25))


def summarize(x: Sequence[float]) -> SeedSummary:
    a = np.asarray(x, dtype=float)
    if a.size == 0:
        return SeedSummary(0, math.nan, math.nan, math.nan, math.nan, math.nan)
    lo, hi = t_ci95(a)
    std = float(a.std(ddof=1)) if a.size > 1 else math.nan
    return SeedSummary(int(a.size), float(a.mean()), std, lo, hi, iqm(a))


def improvement_pct(a: float, b: float) -> float:
    """The paper's relative improvement of a over b: 100 (a - b) / b (NaN when b is 0 or NaN)."""
    if not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return math.nan
    return 100.0 * (a - b) / b


def ratio_ci95(a: Sequence[float], b: Sequence[float]) -> tuple[float, float]:
    """95% Fieller interval of mean(a) / mean(b), independent samples (see the module docstring).

    The set of rho with (mean_a - rho mean_b)^2 <= t^2 (var_a + rho^2 var_b), var_x = s_x^2 / n_x:
    a bounded interval when mean_b^2 > t^2 var_b, else (-inf, inf). NaN, NaN below 2 values a side.
    """
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.size < 2 or y.size < 2:
        return math.nan, math.nan
    t = float(_st.t.ppf(0.975, min(x.size, y.size) - 1))
    ma, mb = float(x.mean()), float(y.mean())
    va, vb = float(x.var(ddof=1)) / x.size, float(y.var(ddof=1)) / y.size
    quad = mb * mb - t * t * vb  # coefficient of rho^2
    if quad <= 0:
        return -math.inf, math.inf
    # the roots of quad rho^2 - 2 ma mb rho + (ma^2 - t^2 va): the discriminant (ma mb)^2 -
    # quad (ma^2 - t^2 va) simplifies to t^2 (va quad + vb ma^2), never negative here
    half = t * math.sqrt(va * quad + vb * ma * ma)
    return (ma * mb - half) / quad, (ma * mb + half) / quad


def ema(values: Sequence[float], weight: float) -> np.ndarray:
    """Debiased exponential moving average (see the module docstring); weight in [0, 1)."""
    if not 0.0 <= weight < 1.0:
        raise ValueError(f"smoothing weight must be in [0, 1), got {weight}")
    x = np.asarray(values, dtype=float)
    if weight == 0.0 or x.size == 0:
        return x.copy()
    out = np.empty_like(x)
    s = 0.0
    for k, v in enumerate(x):
        s = weight * s + (1.0 - weight) * v
        out[k] = s / (1.0 - weight ** (k + 1))
    return out


def common_grid(ranges: Sequence[tuple[float, float]], points: int = 200) -> np.ndarray:
    """`points` evenly spaced values over the span all (first, last) ranges share; empty if none."""
    if not ranges:
        return np.empty(0)
    lo = max(r[0] for r in ranges)
    hi = min(r[1] for r in ranges)
    if hi < lo:
        return np.empty(0)
    if hi == lo:
        return np.array([lo], dtype=float)
    return np.linspace(lo, hi, points)


def interpolate(curves: Sequence[tuple[np.ndarray, np.ndarray]], grid: np.ndarray) -> np.ndarray:
    """Each (steps, values) curve linearly interpolated on `grid`: array [n_curves, len(grid)]."""
    return np.stack([np.interp(grid, np.asarray(s, float), np.asarray(v, float)) for s, v in curves])


def bootstrap_ci95(
    y: np.ndarray, n_boot: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over axis 0 of y [n_seeds, G] and its 95% percentile-bootstrap band (lo, hi)."""
    y = np.asarray(y, dtype=float)
    mean = y.mean(axis=0)
    n = y.shape[0]
    if n < 2:
        return mean, mean.copy(), mean.copy()
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(n_boot, n))
    boot = y[idx].mean(axis=1)  # [n_boot, G]
    lo, hi = np.percentile(boot, [2.5, 97.5], axis=0)
    return mean, lo, hi
