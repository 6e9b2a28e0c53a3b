"""ED-UAV association, the paper's Eq. (association), for a batch of scenarios.

Both functions take channel gains [N, U, V] and horizontal distances [N, U, V] and return
`serving` [N, V] (UAV index, or -1 when the ED is unassociated this slot).

greedy (the paper's channel-aware matching, docs/model.md#association order): EDs are taken in descending
order of their best in-range gain; each takes its max-gain in-range UAV with free quota.
That is a serial dictatorship with one common priority order over the EDs, and with a
common priority order the ED-proposing deferred-acceptance algorithm yields exactly the
serial-dictatorship matching. Deferred acceptance runs in rounds that are vectorised over
the batch, the EDs and the UAVs: each round every unmatched ED proposes to its next
preferred UAV, and each UAV keeps its Lambda_max highest-priority candidates. Scenarios
where no quota binds (the default layout) skip it: there every ED simply takes its best
in-range UAV (one argmax). At most V * U rounds, usually <= U. One O(N V log V) sort gives
the priority order; then a round only looks at the candidates of the UAVs over their quota
(O(N V) to find them, a sort of theirs), and costs O(U) per rejected ED (its keys to every
UAV are asked for only then); the rounds end when no UAV is over its quota.

optimal (extension): the assignment that maximises the total linear gain under the quota,
solved per scenario with scipy's linear_sum_assignment on min(Lambda_max, V) replicated
slots per UAV (a rectangular problem: EDs left without a slot, or given an out-of-range
one, which is worth 0, stay unassociated).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment

from uavlora_rllib.sim import physics

UNASSOCIATED = -1


def in_range_mask(d_h: np.ndarray, comm_range_m: float) -> np.ndarray:
    return d_h <= comm_range_m


def greedy_association(gains: np.ndarray, d_h: np.ndarray, comm_range_m: float, quota: int) -> np.ndarray:
    ok = in_range_mask(d_h, comm_range_m)  # [N, U, V]
    g = np.where(ok, gains, -np.inf)
    # Fast path: where every ED's first choice fits in its UAV's quota, the matching is just
    # the per-ED argmax (first index on ties, as the stable sort below) and no order matters.
    first = np.argmax(g, axis=1)  # [N, V]
    reachable = np.asarray(ok.any(axis=1))
    n_uavs = gains.shape[1]
    counts = ((first[:, None, :] == np.arange(n_uavs)[None, :, None]) & reachable[:, None, :]).sum(axis=-1)
    serving = np.where(reachable, first, UNASSOCIATED)
    binding = (counts > quota).any(axis=-1)
    if binding.any():
        g_b = g[binding]
        first_b = first[binding]
        best = np.take_along_axis(g_b, first_b[:, None, :], axis=1)[:, 0]  # = g_b.max(axis=1)
        serving[binding] = _deferred_acceptance(best, first_b, quota, n_uavs, lambda e, v: g_b[e, :, v])
    return serving


def stable_argsort(key: np.ndarray) -> np.ndarray:
    """np.argsort(key, axis=-1, kind="stable") for [N, V]: the (SIMD) quicksort when no row has
    tied keys (then every sort gives the same order), else the stable sort."""
    if key.shape[-1] <= 32 or key.ndim != 2:
        return np.argsort(key, axis=-1, kind="stable")
    order = np.argsort(key, axis=-1)
    if has_ties(key, order):
        return np.argsort(key, axis=-1, kind="stable")
    return order


KEY_SORT_MIN = 2048  # elements from which group_sort's one key sort beats the stable sorts


def group_sort(
    values: np.ndarray, groups: np.ndarray | None = None, n_groups: int = 1, descending: bool = False
) -> tuple[np.ndarray, np.ndarray | None]:
    """Per row of values [N, V] (float64): the indices sorted by (group, value, index), values
    ascending or descending, and the groups [N, V] (int, 0 .. n_groups - 1; None: one group)
    in that order. Ties keep the index order, as a stable sort.

    Usually one np.sort (SIMD; an argsort costs more) of an int64 key that carries the
    index in its low bits: (group, rank part of the value, index). A float64's bit pattern,
    read as an int64, increases with the value for values >= 0 (and, with its low 63 bits
    flipped, for negative ones), so (bits - min) or (max - bits) orders the values; it is
    shifted right by `drop` bits to leave room for the group and the index. Truncation keeps
    the order (never swaps two values), and where no two entries of a group share a
    truncated value the order is exactly that of the full values; where two do (rare, and
    always so for equal values when drop > 0), the stable sorts decide."""
    n, v = values.shape
    if values.size > KEY_SORT_MIN and values.flags.c_contiguous:
        bits = values.view(np.int64)
        lo = int(bits.min())
        if lo < 0:  # negative values (or -0.0): map to an order-preserving pattern
            bits = np.add(values, 0.0).view(np.int64)  # (-0.0 + 0.0 = +0.0: equal values, one key)
            bits ^= (bits >> 63) & 0x7FFF_FFFF_FFFF_FFFF
            lo = int(bits.min())
        hi = int(bits.max())
        id_bits = max(int(v - 1).bit_length(), 1)
        room = 63 - id_bits - (int(n_groups - 1).bit_length() if groups is not None else 0)
        drop = max(0, (hi - lo).bit_length() - room)
        while (hi >> drop) - (lo >> drop) >> room:  # (shifting first: hi - lo may overflow int64)
            drop += 1
        if drop:
            bits = np.right_shift(bits, drop)
            lo, hi = lo >> drop, hi >> drop
        key = np.subtract(hi, bits) if descending else np.subtract(bits, lo)
        if groups is not None:
            key |= np.left_shift(groups.astype(np.int64, copy=False), room)
        key <<= id_bits
        key |= np.arange(v)
        key.sort(axis=-1)
        head = key >> id_bits  # (group, truncated value)
        if drop == 0 or not (head[:, 1:] == head[:, :-1]).any():
            key &= (1 << id_bits) - 1
            return key, None if groups is None else np.right_shift(head, room, out=head)
    order = stable_argsort(np.negative(values) if descending else values)
    if groups is None:
        return order, None
    row_base = (np.arange(n) * v)[:, None]
    order += row_base
    grp_sorted = groups.reshape(-1).take(order)
    # n_groups <= 128 here (U + 1 <= 65): ids fit in int8, whose stable sort is a radix sort.
    by = np.argsort(grp_sorted.astype(np.int8) if v > 32 else grp_sorted, axis=-1, kind="stable")
    by += row_base
    order = order.reshape(-1).take(by)
    order -= row_base
    return order, grp_sorted.reshape(-1).take(by)


def has_ties(key: np.ndarray, order: np.ndarray) -> bool:
    """Whether a row of key [N, V], sorted by order [N, V] (its argsort), has two equal keys.
    (One flat take: np.take_along_axis costs ~6x more here.)"""
    n, v = key.shape
    ks = key.reshape(-1).take(order + (np.arange(n) * v)[:, None])
    return bool((ks[:, 1:] == ks[:, :-1]).any())


def _deferred_acceptance(
    best: np.ndarray, first: np.ndarray, quota: int, n_uavs: int, rows: Callable[[np.ndarray, np.ndarray], np.ndarray]
) -> np.ndarray:
    """ED-proposing deferred acceptance with the common priority order (see module docstring).

    best [N, V]: each ED's highest key (gain, or any strictly increasing function of it) over
    its in-range UAVs, -inf when none is in range; first [N, V]: the UAV that has it (the
    argmax, ties: lowest index); rows(e, v) [K, U]: the keys of the EDs (e[k], v[k]) to every
    UAV, -inf where out of range (asked only for rejected EDs: a few per round). Each round,
    every ED rejected in the previous one proposes to its best in-range UAV not yet tried
    (argmax over the UAVs, ties: lowest index, i.e. the next entry of its preference list);
    EDs held stay candidates of their UAV, and each UAV keeps its `quota` highest-priority
    candidates."""
    n, n_eds = best.shape
    # Priority: descending best in-range key; ties by ED index (stable sort).
    order = group_sort(best, descending=True)[0]  # [N, V] ED ids, best first
    row_base = (np.arange(n) * n_eds)[:, None]
    order += row_base  # flat indices into [N, V] (flat takes: faster than fancy indexing)
    order = order.reshape(-1)
    # The state, per priority position p = row V + j (j-th ED of the row's priority order):
    # the UAV it proposes to / is held by, and that (row, UAV) group, row U + UAV (n U: none).
    candidate = first.reshape(-1).take(order)
    candidate[best.reshape(-1).take(order) == -np.inf] = UNASSOCIATED
    none = n * n_uavs
    group = candidate + np.repeat(np.arange(n) * n_uavs, n_eds)
    group[candidate == UNASSOCIATED] = none
    counts = np.bincount(group, minlength=none + 1)  # candidates per group (last: none)
    tried = np.zeros((n * n_eds, n_uavs), dtype=bool)  # per position: UAVs that rejected it
    while True:
        # Only UAVs with more candidates than their quota reject; their candidates (in priority
        # order within each group: positions ascend within a row) keep the first `quota`.
        counts[none] = 0
        over = np.flatnonzero(counts > quota)
        if not over.size:
            break
        is_over = np.zeros(none + 1, dtype=bool)
        is_over[over] = True
        members = np.flatnonzero(is_over.take(group))  # positions, ascending
        key = group.take(members)
        key *= n_eds
        key += members % n_eds  # (group, j): distinct, so any sort is stable here
        key.sort()
        size = counts.take(over)
        rank = np.arange(key.size) - np.repeat(np.cumsum(size) - size, size)  # rank within the group
        out = key[rank >= quota]  # the rejected: (group, j)
        g, j = np.divmod(out, n_eds)
        r, u = np.divmod(g, n_uavs)
        at = r * n_eds + j  # their positions
        tried[at, u] = True
        keys = rows(r, order.take(at) - r * n_eds)  # [K, U]: their keys to every UAV
        keys[tried[at]] = -np.inf
        nxt = np.argmax(keys, axis=-1)
        has_next = keys[np.arange(len(at)), nxt] > -np.inf
        candidate[at] = np.where(has_next, nxt, UNASSOCIATED)
        group[at] = np.where(has_next, r * n_uavs + nxt, none)
        counts[over] = quota
        counts += np.bincount(group.take(at), minlength=none + 1)
    serving = np.empty(n * n_eds, dtype=np.int64)
    serving[order] = candidate
    return serving.reshape(n, n_eds)


def nearest_uav(ed_xy: np.ndarray, uav_xy: np.ndarray) -> np.ndarray:
    """Index of each ED's horizontally nearest UAV [..., V] (ties: the lowest index)."""
    return np.argmin(physics.horizontal_distance_sq(ed_xy, uav_xy), axis=-2)


def nearest_uav_on_line(ed_x: np.ndarray, spacing: float, n_uavs: int) -> np.ndarray:
    """`nearest_uav` for UAVs at x_i = (i + 0.5) spacing on one horizontal line (docs/model.md#scenario
    layout), from the ED x coordinates alone: UAV i is nearest for x in (i s, (i + 1) s], the
    lower index on the boundary tie, i.e. i = ceil(x / s) - 1 clipped to [0, U - 1]. O(V)."""
    i = np.divide(ed_x, spacing)
    np.ceil(i, out=i)
    i -= 1.0
    np.clip(i, 0.0, n_uavs - 1.0, out=i)
    return i.astype(np.int64)


def greedy_from_nearest(
    nearest: np.ndarray,
    d_h_nearest: np.ndarray,
    comm_range_m: float,
    quota: int,
    n_uavs: int,
    nearest_keys: Callable[[np.ndarray], np.ndarray],
    pair_keys: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    return_counts: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """`greedy_association` where the max-gain UAV is the nearest one (gain strictly decreasing
    in d_h, `physics.gain_decreases_with_distance`), without the per-pair gains.

    Each ED's first choice is its nearest UAV if that one is in range, and no UAV is in range
    otherwise (all others are farther). Where those first choices fit in every quota (the
    default layout) that IS the greedy matching. Scenarios where a quota binds get the full
    greedy matching (deferred acceptance) on keys: nearest_keys(b) [M, V], the key of every ED
    of the scenarios b [M] at its nearest UAV, and pair_keys(e, v) -> (key, d_h) [K, U] each,
    of the EDs (e[k], v[k]) to every UAV (asked, each round, only for the few EDs rejected).
    `key` is the gain or any strictly increasing function of it (the matching depends only on
    the order of the gains), e.g. -d_h^2. With `return_counts`: (serving, counts [N, U + 1]),
    the EDs each UAV serves and, last column, the unassociated ones."""
    reachable = d_h_nearest <= comm_range_m
    everyone = bool(reachable.all())  # (the usual case: then no mask is needed)
    serving = nearest.copy() if everyone else np.where(reachable, nearest, UNASSOCIATED)
    # EDs per first choice, column U: the EDs with no UAV in range
    counts = physics.group_count(nearest if everyone else np.where(reachable, nearest, n_uavs), n_uavs + 1)
    if quota < nearest.shape[-1]:  # otherwise no quota can bind
        binding = (counts[..., :n_uavs] > quota).any(axis=-1)
        if binding.any():
            b = np.flatnonzero(binding)
            best = nearest_keys(b)
            best[~reachable[b]] = -np.inf

            def rows(e_b: np.ndarray, v: np.ndarray) -> np.ndarray:
                key, d = pair_keys(b[e_b], v)
                key[~in_range_mask(d, comm_range_m)] = -np.inf
                return key

            matched = serving[b] = _deferred_acceptance(best, nearest[b], quota, n_uavs, rows)
            counts[b] = physics.group_count(np.where(matched == UNASSOCIATED, n_uavs, matched), n_uavs + 1)
    return (serving, counts) if return_counts else serving


def optimal_association(gains: np.ndarray, d_h: np.ndarray, comm_range_m: float, quota: int) -> np.ndarray:
    n, n_uavs, n_eds = gains.shape
    slots = min(quota, n_eds)
    serving = np.full((n, n_eds), UNASSOCIATED, dtype=np.int64)
    ok = in_range_mask(d_h, comm_range_m)
    for i in range(n):  # one assignment problem per scenario; the solver is C inside
        # Scale so the solver works on O(1) numbers; out-of-range pairs are worth nothing.
        scale = gains[i][ok[i]].max() if ok[i].any() else 1.0
        value = np.where(ok[i], gains[i] / scale, 0.0).T  # [V, U]
        value = np.repeat(value, slots, axis=1)  # [V, U * slots]
        rows, cols = linear_sum_assignment(value, maximize=True)
        uav = cols // slots
        valid = ok[i][uav, rows]
        serving[i, rows[valid]] = uav[valid]
    return serving


def associate(gains: np.ndarray, d_h: np.ndarray, comm_range_m: float, quota: int, method: str) -> np.ndarray:
    if method == "greedy":
        return greedy_association(gains, d_h, comm_range_m, quota)
    if method == "optimal":
        return optimal_association(gains, d_h, comm_range_m, quota)
    raise ValueError(f"association: {method!r} is not one of ['greedy', 'optimal']")
