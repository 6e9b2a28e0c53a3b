"""Statistics of the analysis step; every definition the report uses lives here.

Across seeds (one value per training seed, e.g. a run's ``eval/ee_sys_mean``):

* ``mean``: arithmetic mean over seeds.
* ``t_ci95``: 95% Student-t confidence interval of that mean,
  mean +- t_{0.975, n-1} * s / sqrt(n), s the sample standard deviation (ddof = 1);
  undefined (NaN) for fewer than 2 seeds.
* ``iqm``: interquartile mean, ``scipy.stats.trim_mean(x, 0.25)`` (cuts int(0.25 n) values
  at each end, so for n <= 3 it equals the mean). The only IQM: the per-cell one and the
  aggregate one below both call it.
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
  (``scipy.stats.bootstrap``: whole seeds resampled with replacement, ``n_boot`` resamples, fixed
  generator seed).

Aggregates over seeds and scenarios (Agarwal et al., "Deep RL at the edge of the statistical
precipice", NeurIPS 2021, the definitions of their ``rliable`` library). A *stratum* is the 1-D
array of one algorithm's normalised scores in one scenario, one value per seed; the scenarios
are rliable's tasks, the seeds its runs:

* ``aggregate_iqm``: rliable's ``aggregate_iqm``, the IQM of all (seed, scenario) scores pooled.
* ``aggregate_mean``: rliable's ``aggregate_mean``, the mean over scenarios of each scenario's
  mean over seeds (every scenario weighs the same, whatever its seed count).
* ``probability_of_improvement``: rliable's, P(X > Y) averaged over the scenarios both ran, each
  scenario's P(X > Y) = the Mann-Whitney U statistic / (n_x n_y): the share of (seed of X, seed
  of Y) pairs where X scores higher, ties counting one half (so 0.5 for identical score sets).
* ``performance_profile``: rliable's score distribution, the fraction of runs scoring above tau,
  averaged over scenarios.
* ``stratified_bootstrap``: the point estimate and a 95% percentile-bootstrap interval of any of
  these (rliable's ``get_interval_estimates`` / ``create_performance_profile`` with their default
  method, percentile, and no task bootstrap): ``scipy.stats.bootstrap`` with every stratum
  resampled with replacement independently of the others (``paired=False``), so each resample
  keeps every scenario with its own seed count. A stratum of one seed cannot be resampled and
  stays fixed; with no stratum of two or more seeds there is no interval (NaN).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats as _st

from uavlora_rllib.experiment.evaluation import t_half_width_95

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
AGGREGATE_RESAMPLES = 10_000  # the aggregates' intervals (rliable's default is 50,000; 2,000 for profiles)
PROFILE_RESAMPLES = 2000  # the performance profile's bands (rliable's default)


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


def iqm(x: Sequence[float] | np.ndarray, axis: int | None = None):
    """Interquartile mean: scipy.stats.trim_mean(x, 0.25) over all values (a float), or along
    `axis` (an array); NaN for no values."""
    a = np.asarray(x, dtype=float)
    if axis is None:
        return float(_st.trim_mean(a, 0.25, axis=None)) if a.size else math.nan
    return _st.trim_mean(a, 0.25, axis=axis)


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
    if y.shape[0] < 2:
        return mean, mean.copy(), mean.copy()
    # whole seeds (rows) are resampled, so every grid point of a resample uses the same seeds
    res = _st.bootstrap(
        (y,), np.mean, axis=0, n_resamples=n_boot, vectorized=True, method="percentile", confidence_level=0.95, rng=seed
    )
    return mean, np.asarray(res.confidence_interval.low, float), np.asarray(res.confidence_interval.high, float)


# ---------------------------------------------------------------- aggregates over scenarios
# Every statistic takes the strata as positional arrays and reduces along `axis` (the seeds), so
# that scipy.stats.bootstrap can call it on a whole batch of resamples at once.
def _pooled(strata: tuple[np.ndarray, ...], axis: int) -> np.ndarray:
    """All scores of all strata in one array (along `axis`)."""
    return np.concatenate([np.asarray(s, dtype=float) for s in strata], axis=axis)


def aggregate_iqm(*strata: np.ndarray, axis: int = -1):
    """IQM of all scores of all strata pooled (rliable's aggregate_iqm)."""
    return iqm(_pooled(strata, axis), axis=axis)


def aggregate_mean(*strata: np.ndarray, axis: int = -1):
    """Mean over strata of each stratum's mean (rliable's aggregate_mean)."""
    return np.mean([np.mean(np.asarray(s, dtype=float), axis=axis) for s in strata], axis=0)


def aggregate_optimality_gap(*strata: np.ndarray, axis: int = -1):
    """1 minus the mean of min(score, 1) over all scores pooled (rliable's aggregate_optimality_gap at
    gamma 1, the reference's level): how far below the reference an algorithm falls, a score above it
    counting as reaching it (lower is better)."""
    return 1.0 - np.mean(np.minimum(_pooled(strata, axis), 1.0), axis=axis)


def _p_greater(x: np.ndarray, y: np.ndarray):
    """P(X > Y) + 0.5 P(X = Y) over all pairs of the last axes: Mann-Whitney U / (n_x n_y)."""
    x, y = np.asarray(x, dtype=float)[..., :, None], np.asarray(y, dtype=float)[..., None, :]
    return np.mean((x > y) + 0.5 * (x == y), axis=(-2, -1))


def _poi(*strata: np.ndarray, axis: int = -1):
    """probability_of_improvement on the strata x_1..x_k, y_1..y_k as one flat argument list."""
    if axis != -1:
        strata = tuple(np.moveaxis(np.asarray(s), axis, -1) for s in strata)
    k = len(strata) // 2
    return np.mean([_p_greater(strata[i], strata[k + i]) for i in range(k)], axis=0)


def probability_of_improvement(x_strata: Sequence[np.ndarray], y_strata: Sequence[np.ndarray]) -> float:
    """P(X > Y) averaged over the scenarios (rliable's probability_of_improvement); the two lists
    hold the same scenarios in the same order, the seed counts may differ."""
    if len(x_strata) != len(y_strata) or not x_strata:
        raise ValueError("probability_of_improvement needs the same, non-empty list of scenarios for X and Y")
    return float(_poi(*x_strata, *y_strata))


def poi_statistic(k: int) -> Callable[..., np.ndarray]:
    """probability_of_improvement as a statistic of 2k strata (x_1..x_k, y_1..y_k) for stratified_bootstrap."""

    def statistic(*strata, axis=-1):
        assert len(strata) == 2 * k
        return _poi(*strata, axis=axis)

    return statistic


def performance_profile(taus: np.ndarray) -> Callable[..., np.ndarray]:
    """The statistic "fraction of runs scoring above tau, averaged over strata" at every tau
    (rliable's score distribution); its result has the taus on the FIRST axis."""
    taus = np.asarray(taus, dtype=float)

    def statistic(*strata, axis=-1):
        fr = [
            np.mean(np.moveaxis(np.asarray(s, dtype=float), axis, -1)[..., None, :] > taus[:, None], axis=-1)
            for s in strata
        ]
        return np.moveaxis(np.mean(fr, axis=0), -1, 0)  # [..., T] -> [T, ...]

    return statistic


def stratified_bootstrap(
    statistic: Callable[..., np.ndarray],
    strata: Sequence[Sequence[float]],
    n_boot: int = AGGREGATE_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    confidence: float = 0.95,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """statistic(*strata) and its percentile-bootstrap interval, every stratum resampled on its
    own (see the module docstring): (point, low, high), arrays shaped like the statistic."""
    data = [np.asarray(s, dtype=float).ravel() for s in strata]
    if not data or any(d.size == 0 for d in data):
        raise ValueError("stratified_bootstrap needs non-empty strata")
    point = np.asarray(statistic(*data, axis=-1), dtype=float)
    free = [i for i, d in enumerate(data) if d.size >= 2]
    if not free:
        nan = np.full_like(point, math.nan)
        return point, nan, nan.copy()

    def resampled(*drawn, axis=-1):
        batch = np.asarray(drawn[0]).shape[:-1]
        full = [np.broadcast_to(d, batch + d.shape) for d in data]
        for i, d in zip(free, drawn):
            full[i] = d
        return statistic(*full, axis=axis)

    res = _st.bootstrap(
        tuple(data[i] for i in free),
        resampled,
        n_resamples=n_boot,
        paired=False,
        vectorized=True,
        method="percentile",
        confidence_level=confidence,
        rng=seed,
    )
    return point, np.asarray(res.confidence_interval.low, float), np.asarray(res.confidence_interval.high, float)
