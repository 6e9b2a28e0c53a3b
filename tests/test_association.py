"""ED-UAV association (Eq. association): greedy against a naive sequential reference written
(conftest.reference_greedy) in docs/model.md#association's order, optimal against brute force, and the constraints both must keep."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from conftest import reference_greedy
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uavlora_rllib.sim.association import UNASSOCIATED, associate, greedy_association, optimal_association

SETTINGS = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def total_gain(g: np.ndarray, serving: np.ndarray) -> float:
    return float(sum(g[u, v] for v, u in enumerate(serving) if u != UNASSOCIATED))


def brute_force_best(g: np.ndarray, d: np.ndarray, r_comm: float, quota: int) -> float:
    n_uavs, n_eds = g.shape
    best = 0.0
    for assign in itertools.product(range(-1, n_uavs), repeat=n_eds):
        if any(u >= 0 and d[u, v] > r_comm for v, u in enumerate(assign)):
            continue
        if any(assign.count(u) > quota for u in range(n_uavs)):
            continue
        best = max(best, total_gain(g, assign))
    return best


def check_constraints(serving: np.ndarray, g: np.ndarray, d: np.ndarray, r_comm: float, quota: int) -> None:
    n, n_uavs, n_eds = g.shape
    assert serving.shape == (n, n_eds)
    assert np.issubdtype(serving.dtype, np.integer)
    assert ((serving >= UNASSOCIATED) & (serving < n_uavs)).all()  # one UAV or none, per ED
    for i in range(n):
        for u in range(n_uavs):
            assert (serving[i] == u).sum() <= quota  # quota Lambda_max
        for v in range(n_eds):
            u = serving[i, v]
            if u != UNASSOCIATED:
                assert d[i, u, v] <= r_comm  # never beyond R_comm
            else:  # unassociated only when every in-range UAV is full (both methods, positive gains)
                for w in range(n_uavs):
                    assert d[i, w, v] > r_comm or (serving[i] == w).sum() == quota


# ------------------------------------------------------------------ hand examples
def test_greedy_and_optimal_by_hand_when_the_quota_binds():
    # quota 1. ED0: 10 at UAV0, 9 at UAV1. ED1: 8 at UAV0, 1 at UAV1. ED2: out of range everywhere.
    g = np.array([[[10.0, 8.0, 50.0], [9.0, 1.0, 60.0]]])
    d = np.array([[[1.0, 1.0, 700.0], [1.0, 1.0, 700.0]]])
    # greedy: ED0 (best 10) goes first and takes UAV0; ED1 finds UAV0 full and takes UAV1 -> total 11
    np.testing.assert_array_equal(greedy_association(g, d, 600.0, 1), [[0, 1, -1]])
    # optimal: ED0 -> UAV1 (9), ED1 -> UAV0 (8) -> total 17 > 11
    np.testing.assert_array_equal(optimal_association(g, d, 600.0, 1), [[1, 0, -1]])
    np.testing.assert_array_equal(associate(g, d, 600.0, 1, "greedy"), [[0, 1, -1]])
    with pytest.raises(ValueError, match="association"):
        associate(g, d, 600.0, 1, "auction")


def test_greedy_order_is_by_best_gain_not_by_index():
    # ED2 has the strongest link, so it is served first and takes the only slot of UAV0
    g = np.array([[[3.0, 2.0, 5.0], [1.0, 0.5, 0.1]]])
    d = np.ones_like(g)
    np.testing.assert_array_equal(greedy_association(g, d, 600.0, 1), [[1, -1, 0]])
    # with a quota of 2 ED0 (3.0) beats ED1 (2.0) to UAV0's second slot
    np.testing.assert_array_equal(greedy_association(g, d, 600.0, 2), [[0, 1, 0]])


def test_out_of_range_best_uav_is_skipped():
    # ED0's strongest UAV (1) is beyond R_comm: it takes UAV0, the best in range
    g = np.array([[[1e-9], [1e-8]]])
    d = np.array([[[500.0], [601.0]]])
    np.testing.assert_array_equal(greedy_association(g, d, 600.0, 4), [[0]])
    np.testing.assert_array_equal(optimal_association(g, d, 600.0, 4), [[0]])
    # exactly at R_comm counts as in range
    np.testing.assert_array_equal(greedy_association(g, np.array([[[700.0], [600.0]]]), 600.0, 4), [[1]])


def test_no_ed_in_range():
    g = np.full((2, 3, 5), 1e-9)
    d = np.full((2, 3, 5), 1000.0)
    for method in ("greedy", "optimal"):
        np.testing.assert_array_equal(associate(g, d, 10.0, 2, method), np.full((2, 5), -1))


# ------------------------------------------------------------------ properties
@st.composite
def association_problems(draw, max_uavs=4, max_eds=9, max_batch=3):
    n = draw(st.integers(1, max_batch))
    n_uavs = draw(st.integers(1, max_uavs))
    n_eds = draw(st.integers(1, max_eds))
    quota = draw(st.integers(1, max(1, n_eds)))
    if draw(st.booleans()):  # realistic magnitudes: 60..140 dB path loss
        loss_db = draw(st.lists(st.floats(60.0, 140.0), min_size=n * n_uavs * n_eds, max_size=n * n_uavs * n_eds))
        g = 10.0 ** (-np.array(loss_db) / 10.0)
    else:  # small integers: many ties, in the ED order and between UAVs
        g = np.array(draw(st.lists(st.integers(1, 4), min_size=n * n_uavs * n_eds, max_size=n * n_uavs * n_eds)), float)
    d = np.array(draw(st.lists(st.floats(0.0, 1000.0), min_size=n * n_uavs * n_eds, max_size=n * n_uavs * n_eds)))
    r_comm = draw(st.sampled_from([1.0, 300.0, 600.0, 2000.0]))
    return g.reshape(n, n_uavs, n_eds), d.reshape(n, n_uavs, n_eds), r_comm, quota


@SETTINGS
@given(association_problems())
def test_greedy_equals_the_sequential_reference(problem):
    g, d, r_comm, quota = problem
    serving = greedy_association(g, d, r_comm, quota)
    check_constraints(serving, g, d, r_comm, quota)
    for i in range(g.shape[0]):
        assert serving[i].tolist() == reference_greedy(g[i], d[i], r_comm, quota)


@SETTINGS
@given(association_problems())
def test_optimal_keeps_the_constraints_and_beats_greedy(problem):
    g, d, r_comm, quota = problem
    opt = optimal_association(g, d, r_comm, quota)
    greedy = greedy_association(g, d, r_comm, quota)
    check_constraints(opt, g, d, r_comm, quota)
    for i in range(g.shape[0]):
        assert total_gain(g[i], opt[i]) >= total_gain(g[i], greedy[i]) * (1 - 1e-12)


@settings(max_examples=60, deadline=None)
@given(association_problems(max_uavs=3, max_eds=5, max_batch=1))
def test_optimal_equals_brute_force(problem):
    g, d, r_comm, quota = problem
    opt = optimal_association(g, d, r_comm, quota)
    assert total_gain(g[0], opt[0]) == pytest.approx(brute_force_best(g[0], d[0], r_comm, quota), rel=1e-9)


def test_batch_rows_are_independent():
    rng = np.random.default_rng(7)
    g = 10.0 ** (-rng.uniform(60, 120, size=(6, 3, 12)) / 10)
    d = rng.uniform(0, 900, size=(6, 3, 12))
    for method in ("greedy", "optimal"):
        batch = associate(g, d, 600.0, 3, method)
        for i in range(6):
            np.testing.assert_array_equal(batch[i], associate(g[i : i + 1], d[i : i + 1], 600.0, 3, method)[0])


# ------------------------------------------------------------------ the nearest-UAV path (gain decreasing in d_h)
def test_nearest_uav_on_the_mid_line_equals_the_argmin():
    from uavlora_rllib.sim import physics
    from uavlora_rllib.sim.association import nearest_uav, nearest_uav_on_line
    from uavlora_rllib.sim.scenario import ScenarioConfig

    rng = np.random.default_rng(0)
    for n_uavs in (1, 2, 3, 8):
        cfg = ScenarioConfig(n_uavs=n_uavs)
        uav = physics.uav_positions(cfg)
        s = cfg.area_m / n_uavs
        x = np.concatenate([rng.uniform(0, 1000, 2000), np.arange(n_uavs + 1) * s, [0.0, 1000.0]])  # boundaries: ties
        xy = np.stack([x, rng.uniform(0, 1000, x.size)], axis=-1)
        assert np.array_equal(nearest_uav_on_line(x, s, n_uavs), nearest_uav(xy, uav))


@SETTINGS
@given(
    st.integers(1, 3), st.integers(1, 8), st.integers(1, 30), st.integers(1, 12), st.integers(0, 2**31),
    st.sampled_from([100.0, 300.0, 600.0, 2000.0]),
)  # fmt: skip
def test_greedy_from_nearest_equals_greedy(n, n_uavs, n_eds, quota, seed, r_comm):
    """Positions -> channel of every pair -> greedy_association, against the nearest-UAV path
    (small quotas: the deferred-acceptance fallback runs for the scenarios where one binds)."""
    from uavlora_rllib.sim import physics
    from uavlora_rllib.sim.association import greedy_from_nearest, nearest_uav
    from uavlora_rllib.sim.scenario import ScenarioConfig

    cfg = ScenarioConfig(n_uavs=n_uavs, n_eds=n_eds)
    uav = physics.uav_positions(cfg)
    xy = np.random.default_rng(seed).uniform(0, 1000, (n, n_eds, 2))
    d2 = physics.horizontal_distance_sq(xy, uav)
    gains, d_h = physics.channel_gain_sq(d2, cfg), np.sqrt(d2)
    want = greedy_association(gains, d_h, r_comm, quota)
    for i in range(n):
        assert want[i].tolist() == reference_greedy(gains[i], d_h[i], r_comm, quota)
    near = nearest_uav(xy, uav)
    d_near = np.sqrt(physics.horizontal_distance_sq_to(xy, uav, near))

    def nearest_keys(b):  # the gains as keys
        return np.take_along_axis(gains[b], near[b][:, None, :], axis=1)[:, 0]

    got, counts = greedy_from_nearest(
        near, d_near, r_comm, quota, n_uavs, nearest_keys, lambda e, v: (gains[e, :, v], d_h[e, :, v]),
        return_counts=True,
    )  # fmt: skip
    assert np.array_equal(got, want)
    for u in range(n_uavs + 1):  # EDs served by each UAV, then the unassociated ones
        assert np.array_equal(counts[:, u], (got == (u if u < n_uavs else UNASSOCIATED)).sum(axis=-1))


@pytest.mark.parametrize("quota", [11, 13, 15])
def test_greedy_with_long_rejection_chains_equals_the_reference(quota):
    """The paper's large layout (V=100, U=8) with quotas close to the mean load V / U = 12.5:
    most scenarios have a binding quota, and rejected EDs cascade over several UAVs (the
    deferred-acceptance rounds, incl. the ones that end without a ranking round)."""
    from uavlora_rllib.sim import physics
    from uavlora_rllib.sim.scenario import ScenarioConfig

    cfg = ScenarioConfig(n_uavs=8, n_eds=100)
    xy = np.random.default_rng(quota).uniform(0, 1000, (48, 100, 2))
    d2 = physics.horizontal_distance_sq(xy, physics.uav_positions(cfg))
    gains, d_h = physics.channel_gain_sq(d2, cfg), np.sqrt(d2)
    got = greedy_association(gains, d_h, 600.0, quota)
    moved = 0
    for i in range(len(xy)):
        assert got[i].tolist() == reference_greedy(gains[i], d_h[i], 600.0, quota)
        moved += int((got[i] != gains[i].argmax(axis=0)).sum())
    assert moved > 3 * len(xy)  # many EDs were rejected by their first choice


@pytest.mark.parametrize("descending", [False, True])
@pytest.mark.parametrize("n_groups", [None, 3, 65])
@pytest.mark.parametrize("kind", ["positive", "mixed", "ties"])
def test_group_sort_is_a_stable_sort_by_group_then_value(descending, n_groups, kind):
    """group_sort against np.lexsort (stable), on batches large enough for its key sort, with
    signs, zeros of both signs, infinities, wide ranges and ties (its fallback)."""
    from uavlora_rllib.sim.association import KEY_SORT_MIN, group_sort

    rng = np.random.default_rng(7)
    n, v = KEY_SORT_MIN // 50 + 1, 100
    x = rng.lognormal(0.0, 10.0, (n, v))  # spans many binades: the key truncates
    if kind != "positive":
        x *= rng.choice([-1.0, 1.0], x.shape)
        x[:, :2] = [-np.inf, np.inf]
    if kind == "ties":
        x[:, 1::2] = x[:, 0::2]
        x[:, 2:4] = [0.0, -0.0]
    groups = None if n_groups is None else rng.integers(0, n_groups, (n, v))
    order, got_groups = group_sort(x, groups, n_groups or 1, descending)
    keys = -x if descending else x
    want = np.stack([np.lexsort((keys[i],) if groups is None else (keys[i], groups[i])) for i in range(n)])
    np.testing.assert_array_equal(order, want)
    if groups is not None:
        np.testing.assert_array_equal(got_groups, np.take_along_axis(groups, want, axis=-1))
