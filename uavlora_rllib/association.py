"""ED-UAV association, the paper's Eq. (association), for a batch of scenarios.

Both functions take channel gains [N, U, V] and horizontal distances [N, U, V] and return
`serving` [N, V] (UAV index, or -1 when the ED is unassociated this slot).

greedy (the paper's channel-aware matching, SPEC.md order): EDs are taken in descending
order of their best in-range gain; each takes its max-gain in-range UAV with free quota.
That is a serial dictatorship with one common priority order over the EDs, and with a
common priority order the ED-proposing deferred-acceptance algorithm yields exactly the
serial-dictatorship matching. Deferred acceptance runs in rounds that are vectorised over
the batch, the EDs and the UAVs: each round every unmatched ED proposes to its next
preferred UAV, and each UAV keeps its Lambda_max highest-priority candidates. Scenarios
where no quota binds (the default layout) skip it: there every ED simply takes its best
in-range UAV (one argmax). At most V * U rounds, usually <= U. Cost per round O(N V) plus
O(U) per rejected ED (its keys to every UAV are asked for only then), and one O(N V log V)
sort; a scenario leaves the rounds once none of its EDs is rejected, found without a ranking
round where the EDs just rejected fit in the quotas left at their next UAVs (most scenarios
need one ranking round).

optimal (extension): the assignment that maximises the total linear gain under the quota,
solved per scenario with scipy's linear_sum_assignment on min(Lambda_max, V) replicated
slots per UAV (a rectangular problem: EDs left without a slot, or given an out-of-range
one, which is worth 0, stay unassociated).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment

from uavlora_rllib import physics

UNASSOCIATED = -1


def in_range_mask(d_h: np.ndarray, comm_range_m: float) -> np.ndarray:
    return d_h <= comm_range_m


def greedy_association(gains: np.ndarray, d_h: np.ndarray, comm_range_m: float, quota: int) -> np.ndarray:
    ok = in_range_mask(d_h, comm_range_m)  # [N, U, V]
    g = np.where(ok, gains, -np.inf)
    # Fast path: where every ED's first choice fits in its UAV's quota, the matching is just
    # the per-ED argmax (first index on ties, as the stable sort below) and no order matters.
    first = np.argmax(g, axis=1)  # [N, V]
    reachable = ok.any(axis=1)
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

    Usually one np.sort (SIMD; an argsort costs ~3.5x more) of an int64 key that carries the
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
    order += row_base  # flat indices into [N, V] (flat takes: much faster than fancy indexing here)
    candidate = first.reshape(-1).take(order)  # first choices, in priority order
    candidate[best.reshape(-1).take(order) == -np.inf] = UNASSOCIATED
    tried = np.zeros((n * n_eds, n_uavs), dtype=bool)  # per priority position: UAVs that rejected it
    pos = np.arange(n_eds)
    # Each round's sort key: (candidate UAV, priority position) in one small integer, sorted by
    # np.sort (SIMD; positions are distinct, so any sort is stable here).
    id_bits = max(int(n_eds - 1).bit_length(), 1)
    key_type = np.int16 if (n_uavs + 1) << id_bits <= 1 << 15 else np.int64
    key_pos = pos.astype(key_type)
    group_base = (np.arange(n) * (n_uavs + 1))[:, None]
    held_all = np.empty((n, n_eds), dtype=np.int64)  # the final matching, in priority order
    active = np.arange(n)  # scenarios still with rejected EDs (the others are done)
    while True:
        # A UAV keeps a candidate iff fewer than `quota` of its candidates come earlier in the
        # priority order (the columns): rank each candidate within its UAV by sorting
        # (UAV id (U = none), position), as in BatchCore._slots.
        m = len(active)
        key = np.where(candidate == UNASSOCIATED, n_uavs, candidate).astype(key_type)
        key <<= id_bits
        key |= key_pos
        key.sort(axis=-1)
        by = (key & ((1 << id_bits) - 1)).astype(np.int64)
        by += row_base[:m]
        uav_sorted = key >> id_bits
        grouped = uav_sorted.astype(np.int64)
        grouped += group_base[:m]  # flat (row, UAV) group of each sorted entry
        counts = np.bincount(grouped.reshape(-1), minlength=m * (n_uavs + 1)).reshape(m, n_uavs + 1)
        start = np.cumsum(counts, axis=-1)
        start -= counts  # first sorted position of each group within its row
        kept_sorted = uav_sorted < n_uavs
        kept_sorted &= pos - start.reshape(-1).take(grouped) < quota
        kept = np.empty_like(kept_sorted)
        kept.reshape(-1)[by.reshape(-1)] = kept_sorted.reshape(-1)
        held = np.where(kept, candidate, UNASSOCIATED)
        rejected = (candidate != UNASSOCIATED) & ~kept
        going = rejected.any(axis=-1)
        n_held = np.minimum(counts[:, :n_uavs], quota)  # [m, U] candidates each UAV keeps
        if not going.all():  # scenarios without a rejection are matched; later rounds skip them
            held_all[active[~going]] = held[~going]
            if not going.any():
                break
            active, held, rejected, candidate, n_held = (x[going] for x in (active, held, rejected, candidate, n_held))
        e, i = np.nonzero(rejected)  # proposers and displaced EDs move on to their next choice
        at = active[e] * n_eds + i  # their priority rows
        tried[at, candidate[e, i]] = True
        keys = rows(active[e], order.reshape(-1).take(at) - row_base[active[e], 0])  # [K, U]
        keys[tried[at]] = -np.inf
        nxt = np.argmax(keys, axis=-1)
        has_next = keys[np.arange(len(e)), nxt] > -np.inf
        candidate = held
        e, i, nxt = e[has_next], i[has_next], nxt[has_next]
        candidate[e, i] = nxt
        # A scenario whose new proposals fit in the quotas left is matched: the next ranking
        # round would keep every candidate (most scenarios end here, after one ranking round).
        n_held += np.bincount(e * n_uavs + nxt, minlength=n_held.size).reshape(n_held.shape)
        again = (n_held > quota).any(axis=-1)
        if not again.all():
            held_all[active[~again]] = candidate[~again]
            if not again.any():
                break
            active, candidate = active[again], candidate[again]
    serving = np.empty_like(held_all)
    serving.reshape(-1)[order] = held_all
    return serving


def nearest_uav(ed_xy: np.ndarray, uav_xy: np.ndarray) -> np.ndarray:
    """Index of each ED's horizontally nearest UAV [..., V] (ties: the lowest index)."""
    return np.argmin(physics.horizontal_distance_sq(ed_xy, uav_xy), axis=-2)


def nearest_uav_on_line(ed_x: np.ndarray, spacing: float, n_uavs: int) -> np.ndarray:
    """`nearest_uav` for UAVs at x_i = (i + 0.5) spacing on one horizontal line (SPEC.md's
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
