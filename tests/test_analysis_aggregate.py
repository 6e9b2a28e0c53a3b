"""The report's aggregates over seeds and scenarios (analysis.stats, analysis.aggregate) against
rliable's definitions: the numbers of rliable's own tests (tests/rliable/metrics_test.py and
tests/library_test.py of google-research/rliable 1.2.0), and numbers that rliable 1.2.0 itself
computed on a fixed score matrix (run once beside this project, since rliable does not import on
its pinned pandas: docs/model.md#aggregate-statistics). Then the aggregate rows on hand-made run
records (shares of the scenario's reference; the report's files are tested in test_analysis.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats as st

from analysis import aggregate, stats
from analysis.data import organise
from analysis.runs import EE_KEY
from tests.conftest import finished_record


def strata(m) -> list[np.ndarray]:
    """rliable's score matrix [num_runs, num_tasks] as one stratum (array of runs) per task."""
    m = np.asarray(m, dtype=float)
    return [m[:, j] for j in range(m.shape[1])]


# rliable's tests/rliable/metrics_test.py
RL_X = [[1, 2], [2, 2], [1, 1], [2, 1]]
RL_Y = [[1, 1], [2, 2], [3, 3]]


def test_rliable_metrics_test_numbers():
    assert stats.aggregate_mean(*strata(RL_X)) == 1.5 and stats.aggregate_iqm(*strata(RL_X)) == 1.5
    assert stats.aggregate_mean(*strata(RL_Y)) == 2 and stats.aggregate_iqm(*strata(RL_Y)) == 2
    assert stats.probability_of_improvement(strata(RL_X), strata(RL_Y)) == pytest.approx(1 / 3)


def test_optimality_gap_counts_a_score_above_the_reference_as_reaching_it():
    """rliable's aggregate_optimality_gap at gamma 1: 1 - mean(min(score, 1)) over the pooled scores."""
    gap = stats.aggregate_optimality_gap(np.array([0.5, 1.2]), np.array([0.9, 1.0]))
    assert gap == pytest.approx(1 - (0.5 + 1.0 + 0.9 + 1.0) / 4)
    assert stats.aggregate_optimality_gap(np.array([2.0, 3.0])) == 0.0


def test_probability_of_improvement_of_identical_sets_is_one_half():
    x = strata([[0.1, 0.9], [0.5, 0.7], [0.3, 0.2]])
    assert stats.probability_of_improvement(x, x) == 0.5
    point, lo, hi = stats.stratified_bootstrap(stats.poi_statistic(2), x + x, n_boot=2000)
    assert point == 0.5 and lo < 0.5 < hi
    # ties count one half; one seed against three: a Mann-Whitney U / (n m) per scenario
    assert stats.probability_of_improvement([np.array([2.0])], [np.array([1.0, 2.0, 3.0])]) == pytest.approx(0.5)
    u = st.mannwhitneyu([1.0, 4.0, 4.0], [2.0, 4.0], alternative="greater").statistic / 6
    assert stats.probability_of_improvement([np.array([1.0, 4.0, 4.0])], [np.array([2.0, 4.0])]) == pytest.approx(u)


def test_iqm_is_the_25_percent_trimmed_mean():
    x = np.array([1.0, 2.0, 3.0, 10.0])
    assert stats.iqm(x) == 2.5 == st.trim_mean(x, 0.25)
    # pooled over strata, as rliable's aggregate_iqm(scores) = trim_mean(scores, 0.25, axis=None)
    m = np.arange(80.0).reshape(5, 16)
    assert stats.aggregate_iqm(*strata(m)) == pytest.approx(st.trim_mean(m, 0.25, axis=None))
    assert math.isnan(stats.iqm([]))


def test_rliable_library_test_behaviour():
    """rliable's tests/library_test.py: x = arange(80) as 5 runs x 16 tasks, y = x flipped over runs;
    the CIs of IQM, mean and P(x > y) bracket their point estimates, the profile is non-increasing."""
    x = np.arange(80.0).reshape(5, 16)
    y = np.flip(x, axis=0)
    for fn in (stats.aggregate_iqm, stats.aggregate_mean):
        for m in (x, y):
            point, lo, hi = stats.stratified_bootstrap(fn, strata(m), n_boot=100)
            assert point == fn(*strata(m)) and lo < point < hi
    point, lo, hi = stats.stratified_bootstrap(stats.poi_statistic(16), strata(x) + strata(y), n_boot=100)
    assert point == stats.probability_of_improvement(strata(x), strata(y)) and lo < point < hi
    taus = np.array([0.0, 0.25, 0.5, 1.0])
    prof, lo, hi = stats.stratified_bootstrap(stats.performance_profile(taus), strata(x), n_boot=100)
    assert prof.shape == lo.shape == hi.shape == (4,)
    assert np.all(np.diff(prof) <= 0) and np.all(lo <= prof) and np.all(prof <= hi)


# rliable 1.2.0 (arch 7.2.0, pandas 2.3.3) on this matrix: metrics.aggregate_iqm / aggregate_mean /
# probability_of_improvement, and library.get_interval_estimates (50,000 reps) and
# create_performance_profile (2,000 reps), percentile method, no task bootstrap
RX = [
    [1.069, 1.164, 1.066, 0.739],
    [1.181, 1.089, 0.893, 1.116],
    [1.073, 1.059, 1.006, 1.109],
    [0.853, 0.967, 0.904, 1.12],
    [1.008, 0.942, 0.844, 0.949],
]
RY = [[0.902, 0.817, 1.288, 1.202], [0.087, 0.333, 0.848, 0.773], [0.964, 0.965, 1.535, 0.566]]
RLIABLE = {
    "iqm": (1.0228, 0.9599, 1.0734),
    "mean": (1.00755, 0.95885, 1.05265),
    "poi": (2 / 3, 0.48333, 0.85),
    "taus": [0.5, 0.75, 1.0, 1.25, 1.5],
    "profile": ([1.0, 0.95, 0.6, 0.0, 0.0], [1.0, 0.85, 0.4, 0.0, 0.0], [1.0, 1.0, 0.8, 0.0, 0.0]),
}


def test_matches_rliable_on_a_fixed_matrix():
    for name, fn in (("iqm", stats.aggregate_iqm), ("mean", stats.aggregate_mean)):
        point, lo, hi = stats.stratified_bootstrap(fn, strata(RX), n_boot=50_000)
        p, low, high = RLIABLE[name]
        assert point == pytest.approx(p, abs=1e-4)
        # different generators: the interval ends agree to Monte Carlo error
        assert lo == pytest.approx(low, abs=0.005) and hi == pytest.approx(high, abs=0.005)
    point, lo, hi = stats.stratified_bootstrap(stats.poi_statistic(4), strata(RX) + strata(RY), n_boot=50_000)
    p, low, high = RLIABLE["poi"]
    assert point == pytest.approx(p, abs=1e-4)
    assert lo == pytest.approx(low, abs=0.02) and hi == pytest.approx(high, abs=0.02)
    prof, lo, hi = stats.stratified_bootstrap(
        stats.performance_profile(np.array(RLIABLE["taus"])), strata(RX), n_boot=2000
    )
    want, want_lo, want_hi = RLIABLE["profile"]
    assert prof.tolist() == pytest.approx(want) and lo.tolist() == pytest.approx(want_lo, abs=0.051)
    assert hi.tolist() == pytest.approx(want_hi, abs=0.051)


def test_one_seed_strata_stay_fixed_and_no_interval_without_two_seeds():
    point, lo, hi = stats.stratified_bootstrap(
        stats.aggregate_mean, [np.array([1.0, 3.0]), np.array([10.0])], n_boot=500
    )
    assert point == pytest.approx(6.0) and lo == pytest.approx(5.5) and hi == pytest.approx(6.5)
    point, lo, hi = stats.stratified_bootstrap(stats.aggregate_iqm, [np.array([1.0]), np.array([2.0])])
    assert point == 1.5 and math.isnan(lo) and math.isnan(hi)
    with pytest.raises(ValueError):
        stats.stratified_bootstrap(stats.aggregate_mean, [np.array([])])
    # reproducible: a fixed generator seed
    a = stats.stratified_bootstrap(stats.aggregate_iqm, strata(RX), n_boot=300)
    b = stats.stratified_bootstrap(stats.aggregate_iqm, strata(RX), n_boot=300)
    assert [float(v) for v in a] == [float(v) for v in b]


def _run(i, alg, ee, kind="train", seed="0", scen=(10, 2)):
    params = {"scenario.action_mode": "per_device"}
    return finished_record(i, alg, kind=kind, seed=seed, scen=scen, params=params, metrics={EE_KEY: ee})


def test_rows_use_the_scenarios_reference_shares():
    """Two scenarios whose EE differs 1000-fold: normalised by each scenario's greedy mean they pool."""
    a, b = (10, 2), (60, 4)
    runs, i = [], 0
    for scen, scale in ((a, 1.0), (b, 1000.0)):
        for k, (g, m, p, f) in enumerate(((100, 90, 80, 70), (100, 96, 84, 70), (100, 99, 86, 70))):
            runs += [
                _run(i, "greedy", g * scale, "baseline", str(k), scen),
                _run(i + 1, "mappo", m * scale, seed=str(k), scen=scen),
                _run(i + 2, "ippo", p * scale, seed=str(k), scen=scen),
                _run(i + 3, "best_fixed", f * scale, "baseline", str(k), scen),
            ]
            i += 4
    runs.append(_run(i, "vdn", 50.0, seed="0", scen=a))  # one seed, one scenario
    runs.append(_run(i + 1, "coma", 5.0, seed="0", scen=(99, 9)))  # no reference there: left out
    org = organise(runs)
    sets = aggregate.score_sets(org)
    assert set(sets) == {"greedy", "mappo", "ippo", "best_fixed", "vdn"}
    assert sets["mappo"][b].tolist() == pytest.approx([0.90, 0.96, 0.99])  # the share of greedy's seed mean
    rows = {r["algorithm"]: r for r in aggregate.aggregate_table(org, sets)}
    m = rows["mappo"]
    assert m["n_scenarios"] == 2 and m["n_runs"] == 6 and m["scenarios"] == "V10U2 V60U4"
    assert m["iqm"] == pytest.approx(st.trim_mean([0.9, 0.96, 0.99] * 2, 0.25)) and m["mean"] == pytest.approx(0.95)
    assert m["iqm_ci95_low"] <= m["iqm"] <= m["iqm_ci95_high"]
    assert m["optimality_gap"] == pytest.approx(0.05)  # every share below 1
    assert m["optimality_gap_ci95_low"] <= 0.05 <= m["optimality_gap_ci95_high"]
    assert [r["algorithm"] for r in aggregate.aggregate_table(org, sets)] == [
        "mappo",
        "ippo",
        "vdn",
        "greedy",
        "best_fixed",
    ]
    assert math.isnan(rows["vdn"]["iqm_ci95_low"]) and "1 seed per scenario" in aggregate.aggregate_md([rows["vdn"]])
    poi = {r["other"]: r for r in aggregate.improvement_probability_table(org, sets, "mappo")}
    assert set(poi) == {"ippo", "vdn", "best_fixed"}  # learners and the open-loop floor, not greedy
    assert poi["ippo"]["probability_of_improvement"] == 1.0 and poi["ippo"]["n_scenarios"] == 2
    assert poi["vdn"]["n_scenarios"] == 1 and poi["vdn"]["scenarios"] == "V10U2"
    note = aggregate.mixed_scenarios_note(list(rows.values()))
    assert note and "vdn: V10U2" in note
    taus, prof = aggregate.performance_profiles(org, sets, "mappo")
    assert list(prof) == ["mappo", "ippo", "vdn", "best_fixed"]
    assert taus[0] < 0.5 and taus[-1] > 1.0  # every profile runs from 1 down to 0
    for frac, _lo, _hi in prof.values():
        assert frac[0] == 1.0 and frac[-1] == 0.0 and np.all(np.diff(frac) <= 0)
    md = aggregate.improvement_probability_md(list(poi.values()), "mappo")
    assert "P(mappo > other)" in md and "| ippo | train | 2 (V10U2 V60U4) | 1.000 |" in md
    assert aggregate.improvement_probability_table(org, sets, None) == []
