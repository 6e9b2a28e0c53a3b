"""Per-ED allocations scored on a batch of slots: what the per_device references and `best_fixed` share.

A `Slots` holds what scoring a slot needs (the links of N slots: one slot of each scenario of a
batch core, or many recorded slots of a few episodes). An allocation is per ED: SF and TP
indices [..., N, V] and each UAV's BW index [..., N, U]; leading axes are candidates.
`score` is physics.slot_metrics on it (the simulator's own equations; docs/model.md#metrics-and-reward);
`score_ed_moves` scores every single-ED change of (SF, TP) at once with the paper's
interference (tested equal to `score`), which is what makes a per-ED search affordable.

Objectives and the constraint (h), as the per_uav search (baselines/policies.py,
docs/model.md#per-slot-optimum): objective "ee" maximises EE_sys[t] under
rho_v >= rho_thr(SF_v, W_v); in per_device mode (h) separates over the EDs given their UAV's BW,
so an ED that meets it with some (SF, TP) must, an ED that cannot is free, and each UAV keeps
only the BWs with the fewest such violators. Objective "reward" is unconstrained.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

# relative margin by which a move must improve a key to count (rounding of the fast path)
IMPROVE_RTOL = 1e-9


@dataclass
class Slots:
    """The links of N slots, arrays [N, V] (gains [N, U, V] only for interference cross_gain)."""

    g_serving: np.ndarray
    serving_idx: np.ndarray
    associated: np.ndarray
    slot_of_ed: np.ndarray
    gains: np.ndarray | None

    @property
    def n(self) -> int:
        return self.g_serving.shape[0]

    @classmethod
    def of_core(cls, core: BatchCore) -> Slots:
        gains = core.gains if core.cfg.interference != "paper" else None
        return cls(core.g_serving, core.links.serving_idx, core.associated, core.slot_of_ed, gains)


class AllocationScorer:
    """Scores per-ED allocations on `Slots` for one scenario and objective ("ee" or "reward")."""

    def __init__(self, cfg: ScenarioConfig, tables: physics.Tables, objective: str):
        self.cfg, self.tables, self.objective = cfg, tables, objective
        self.n_set = cfg.n_sf * cfg.n_tp  # (SF, TP) settings of one ED, index sf * n_tp + tp
        c = np.arange(self.n_set)
        self.set_sf, self.set_tp = c // cfg.n_tp, c % cfg.n_tp
        # rho_thr [n_sf, n_bw] as the least linear SINR that passes it (score_ed_moves compares without dB)
        self.threshold_lin = physics.db_threshold_lin(tables.threshold_db)

    # ---------------------------------------------------------------- the constraint (h)
    def allowed(self, slots: Slots) -> tuple[np.ndarray, np.ndarray]:
        """(setting_ok [N, V, n_bw, n_set], bw_ok [N, U, n_bw]): what objective "ee" allows (see
        the module docstring); everything for objective "reward" and for unassociated EDs."""
        cfg, t = self.cfg, self.tables
        n, v = slots.g_serving.shape
        if self.objective != "ee":
            return np.ones((n, v, cfg.n_bw, self.n_set), bool), np.ones((n, cfg.n_uavs, cfg.n_bw), bool)
        snr_db = physics.lin_to_db(physics.snr(t.tp_w[self.set_tp], slots.g_serving[..., None], t.noise_w))
        ok = snr_db[:, :, None, :] >= t.threshold_db[self.set_sf].T[None, None]  # [N, V, n_bw, n_set]
        infeasible = ~ok.any(axis=-1) & slots.associated[..., None]  # [N, V, n_bw]
        n_bad = np.stack(
            [physics.group_sum(infeasible[..., b], slots.serving_idx, cfg.n_uavs) for b in range(cfg.n_bw)], -1
        )
        bw_ok = n_bad == n_bad.min(axis=-1, keepdims=True)
        return ok | (infeasible | ~slots.associated[..., None])[..., None], bw_ok

    @staticmethod
    def is_allowed(
        sf_set: np.ndarray, bw: np.ndarray, slots: Slots, setting_ok: np.ndarray, bw_ok: np.ndarray
    ) -> np.ndarray:
        """[..., N] whether an allocation (settings [..., N, V], bw [..., N, U]) is allowed."""
        bw_ed = np.take_along_axis(bw, np.broadcast_to(slots.serving_idx, sf_set.shape), axis=-1)
        n_set = setting_ok.shape[-1]
        flat = setting_ok.reshape(setting_ok.shape[:2] + (-1,))  # [N, V, n_bw * n_set]
        ok_ed = np.take_along_axis(
            np.broadcast_to(flat, sf_set.shape + flat.shape[-1:]), (bw_ed * n_set + sf_set)[..., None], axis=-1
        )[..., 0]
        return np.asarray(ok_ed.all(axis=-1)) & np.take_along_axis(
            np.broadcast_to(bw_ok, bw.shape + bw_ok.shape[-1:]), bw[..., None], axis=-1
        )[..., 0].all(axis=-1)

    # ---------------------------------------------------------------- exact scoring
    def metrics(self, setting: np.ndarray, bw: np.ndarray, slots: Slots) -> dict[str, np.ndarray]:
        """physics.slot_metrics of allocations: settings [..., N, V] (sf * n_tp + tp), bw [..., N, U]."""
        bw_ed = np.take_along_axis(bw, np.broadcast_to(slots.serving_idx, setting.shape), axis=-1)
        return physics.slot_metrics(
            slots.gains, slots.serving_idx, slots.associated, self.set_sf[setting], self.set_tp[setting], bw_ed,
            self.cfg, self.tables, g_serving=slots.g_serving,
        )  # fmt: skip

    def keys(self, m: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(primary, secondary) search keys of slot metrics: (EE_sys, r) for "ee", (r, EE_sys) for "reward"."""
        return (m["ee_sys"], m["reward"]) if self.objective == "ee" else (m["reward"], m["ee_sys"])

    def score(self, setting, bw, slots, setting_ok, bw_ok) -> tuple[np.ndarray, np.ndarray]:
        """(primary, secondary) [..., N]; primary -inf where the allocation is not allowed."""
        p, q = self.keys(self.metrics(setting, bw, slots))
        return np.where(self.is_allowed(setting, bw, slots, setting_ok, bw_ok), p, -np.inf), q

    # ---------------------------------------------------------------- single-ED moves
    def score_ed_moves(
        self, setting: np.ndarray, bw: np.ndarray, slots: Slots, movers: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Keys [N, M, n_set] of the allocation (settings [N, V], bw [N, U]) with ED movers[:, m]
        [N, M] moved to each (SF, TP) setting, the others kept; unconstrained (the caller masks).

        Paper interference: moving ED v changes only the sums of its old and new SF groups
        and its UAV's transmit power, so every candidate is scored from the current group sums
        in O(V) ([N, M, n_set, V] arrays); other interference models score each candidate with
        `metrics` (slower, the same values)."""
        cfg, t = self.cfg, self.tables
        n, v = setting.shape
        m_ = movers.shape[1]
        if cfg.interference != "paper":
            cand = np.broadcast_to(setting, (m_, self.n_set, n, v)).copy()
            ci = np.arange(self.n_set)[None, :, None]
            cand[np.arange(m_)[:, None, None], ci, np.arange(n)[None, None, :], movers.T[:, None, :]] = ci
            p, q = self.keys(self.metrics(cand, np.broadcast_to(bw, (m_, self.n_set) + bw.shape), slots))
            return p.transpose(2, 0, 1), q.transpose(2, 0, 1)
        assoc, sidx = slots.associated, slots.serving_idx
        e = np.arange(n)[:, None]
        sf, tp = self.set_sf[setting], self.set_tp[setting]
        bw_ed = np.take_along_axis(bw, sidx, axis=1)
        w_hz, thr = t.bw_hz[bw_ed], t.threshold_db[sf, bw_ed]
        gain_snr = slots.g_serving / t.noise_w * assoc  # SNR per watt, 0 for silent EDs
        s = t.tp_w[tp] * gain_snr  # [N, V]
        group = physics.group_sum(s, sf, cfg.n_sf)  # [N, K]
        tx_u = physics.group_sum(t.tp_w[tp] * assoc, sidx, cfg.n_uavs)  # [N, U]
        # the mover's new SNR and the group sums after its move: [N, M, C] and [N, M, C, K]
        mv_s, mv_sf, mv_g = s[e, movers], sf[e, movers], gain_snr[e, movers]
        new_s = t.tp_w[self.set_tp] * mv_g[..., None]
        k = np.arange(cfg.n_sf)
        sums = (group[:, None, None, :] - (mv_sf[..., None] == k)[:, :, None, :] * mv_s[..., None, None]
                + (self.set_sf[:, None] == k)[None, None] * new_s[..., None])  # fmt: skip
        # every ED's SINR (Eq. sinr) after the move [N, M, C, V]; the mover's own entry is left out below. Its
        # denominator, interference + 1 = (own group's sum - own SNR + 1) - the mover's old SNR where it
        # shared the ED's SF + its new SNR where it joins it: broadcast sums, no [N, M, C, V] gather.
        base = np.take_along_axis(group, sf, axis=1) - s + 1.0  # [N, V]
        left = base[:, None, :] - (mv_sf[..., None] == sf[:, None, :]) * mv_s[..., None]  # [N, M, V]
        joins = self.set_sf[None, :, None] == sf[:, None, :]  # [N, C, V]
        denom = np.multiply(joins[:, None], new_s[..., None])
        denom += left[:, :, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):  # the mover's own entry (left out below)
            sinr = np.divide(s[:, None, None, :], denom, out=denom)
        mover_interf = np.take_along_axis(sums, self.set_sf[None, None, :, None], axis=-1)[..., 0]
        mover_sinr = new_s / (mover_interf - new_s + 1.0)  # [N, M, C]
        mover_thr = t.threshold_db[self.set_sf[None, None, :], bw_ed[e, movers][..., None]]
        mover_rate = physics.rate_bps(mover_sinr, w_hz[e, movers][..., None], t.sf[self.set_sf][None, None], mover_thr,
                                      cfg.rate_model, cfg.lora_coding_rate)  # fmt: skip
        mi, ci = np.arange(m_)[:, None], np.arange(self.n_set)[None, :]
        mover_at = (e[:, :, None], mi[None], ci[None], movers[:, :, None])  # the mover's own entries
        # decoded (Eq. success) [N, M, C, V], the mover's entry counted below with its new setting
        ok = np.greater_equal(sinr, self.threshold_lin[sf, bw_ed][:, None, None, :], out=np.empty(sinr.shape))
        ok[mover_at] = 0.0
        # each UAV's bits/s and the associated decoded count, one product over the EDs [N, M, C, U + 1]:
        # under the LoRa PHY rate a decoded ED delivers its PHY bit rate, so ok weighs it; the Shannon
        # rate is delivered whatever the threshold (Eq. shannon), so its rates are summed, the count apart
        on_uav = (sidx[..., None] == np.arange(cfg.n_uavs)) & assoc[..., None]  # [N, V, U]
        rows_mc = (n, m_ * self.n_set, v)
        if cfg.rate_model == "lora_phy":
            phy = physics.lora_phy_bit_rate(t.sf[sf], w_hz, cfg.lora_coding_rate)  # [N, V]
            weights = np.concatenate([on_uav * phy[..., None], assoc[..., None]], axis=-1, dtype=np.float64)
            per_uav = np.matmul(ok.reshape(rows_mc), weights)
            bits, count = per_uav[..., :-1], per_uav[..., -1]
        else:
            with np.errstate(invalid="ignore"):
                rate = physics.rate_bps(sinr, w_hz[:, None, None, :], None, thr[:, None, None, :], "shannon")
            rate[mover_at] = 0.0
            bits = np.matmul(rate.reshape(rows_mc), on_uav.astype(np.float64))
            count = np.matmul(ok.reshape(rows_mc), assoc[..., None].astype(np.float64))[..., 0]
        mv_u = sidx[e, movers]
        on_mv_u = (mv_u[..., None] == np.arange(cfg.n_uavs))[:, :, None, :]  # [N, M, 1, U]
        bits = bits.reshape(n, m_, self.n_set, cfg.n_uavs) + on_mv_u * mover_rate[..., None]
        d_tx = (t.tp_w[self.set_tp][None, None] - t.tp_w[tp[e, movers]][..., None]) * assoc[e, movers][..., None]
        tx = tx_u[:, None, None, :] + on_mv_u * d_tx[..., None]
        ee = np.add.reduce(bits / (tx + t.hover_w), axis=-1)  # Eq. (sys_ee) [N, M, C]
        # the reward's other terms: Xi counts every ED, beta changes by the mover's margin points
        mover_thr_lin = self.threshold_lin[self.set_sf[None, None, :], bw_ed[e, movers][..., None]]
        mover_ok = (mover_sinr >= mover_thr_lin) & assoc[e, movers][..., None]  # decoded, as `ok` above
        xi = (count.reshape(n, m_, self.n_set) + mover_ok) / v
        n_assoc = np.maximum(assoc.sum(axis=1), 1)[:, None, None]
        ones = np.ones(new_s.shape + (1,), bool)
        pts_new = physics.margin_score(physics.lin_to_db(new_s)[..., None], mover_thr[..., None], ones)
        pts_old = physics.margin_score(
            physics.lin_to_db(mv_s)[..., None, None], thr[e, movers][..., None, None], ones[..., :1, :]
        )
        beta = physics.margin_score(physics.lin_to_db(s), thr, assoc)[:, None, None]
        beta = beta + (pts_new - pts_old) * assoc[e, movers][..., None] / n_assoc
        p_total = np.add.reduce(tx, axis=-1) + cfg.n_uavs * t.hover_w
        r = physics.reward(ee, xi, beta, p_total, cfg.reward_weights)
        return (ee, r) if self.objective == "ee" else (r, ee)


def lex_better(p1, q1, p2, q2) -> np.ndarray:
    """(p1, q1) lexicographically above (p2, q2) by more than IMPROVE_RTOL (relative)."""
    tol_p = IMPROVE_RTOL * np.maximum(np.abs(p2), 1e-300)
    tol_q = IMPROVE_RTOL * np.maximum(np.abs(q2), 1e-300)
    return (p1 > p2 + tol_p) | ((np.abs(p1 - p2) <= tol_p) & (q1 > q2 + tol_q))


def lex_argmax(p: np.ndarray, q: np.ndarray, axis: int = -1) -> np.ndarray:
    """Index along `axis` of the lexicographic maximum of (p, q); ties: the lowest."""
    top = p == p.max(axis=axis, keepdims=True)
    return np.argmax(np.where(top, q, -np.inf), axis=axis)


def to_actions(cfg: ScenarioConfig, slots: Slots, setting: np.ndarray, bw: np.ndarray) -> np.ndarray:
    """per_device actions [N, U, 2 quota + 1] from per-ED settings [N, V] and BWs [N, U]: ED v
    fills row slot_of_ed[v] of its UAV (docs/model.md#actions); unused rows hold SF, TP index 0."""
    n = setting.shape[0]
    actions = np.zeros((n, cfg.n_uavs, 2 * cfg.quota + 1), dtype=np.int64)
    actions[..., -1] = bw
    e, v = np.nonzero(slots.associated)
    u, k = slots.serving_idx[e, v], slots.slot_of_ed[e, v]
    actions[e, u, 2 * k] = setting[e, v] // cfg.n_tp
    actions[e, u, 2 * k + 1] = setting[e, v] % cfg.n_tp
    return actions
