"""The per-slot references in per_device mode: `greedy` (local search with restarts) and `optimal`
(exhaustive for tiny scenarios); docs/model.md#per-slot-optimum.

Both search each associated ED's (SF, TP) and each UAV's BW for the current slot, with the
objectives and the constraint (h) of baselines/slots.py, and return per_device actions.
"""

from __future__ import annotations

import numpy as np

from uavlora_rllib.baselines.slots import AllocationScorer, Slots, lex_argmax, lex_better, to_actions
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

# `optimal` refuses more joint candidates than this: (n_sf n_tp)^V n_bw^U (V <= 3 with the
# paper's sets and U <= 2; larger V with smaller SF/TP sets).
OPTIMAL_MAX_CANDIDATES = 1_000_000
# candidate-ED evaluations per chunk of `optimal` (bounds memory)
OPTIMAL_CHUNK_ELEMENTS = 1 << 19
# single moves per start of `greedy`, as a multiple of V + U (it stops earlier at a local maximum)
GREEDY_MOVES_PER_COORDINATE = 3


class PerDeviceGreedy:
    """Steepest-ascent local search over single moves, from three structured starts; the best
    allocation found (objective, then tie-break) is played.

    A move changes one associated ED's (SF, TP) or one UAV's BW; every move of every ED is scored
    at once (AllocationScorer.score_ed_moves, vectorised over scenarios, EDs and settings), and
    each scenario takes its best allowed move while it strictly improves. Starts, at the widest
    allowed BW: (a) `singletons`, the n_sf - 1 EDs of highest gain alone on SF 0 .. n_sf - 2 at
    the largest TP and the rest sharing the last SF, its strongest ED at the largest TP and the
    others at the smallest (why: with the paper's interference an ED alone on its SF has no
    interferer, EE_sys is a sum of rates, and a shared SF gives almost all its rate to one ED);
    (b) `two_shared`, the same with n_sf - 2 EDs alone and the rest alternating over two shared
    SFs. Starts far from this structure (all EDs of a UAV on one SF) need ~V moves and end
    lower. Violating settings are replaced by an allowed one.
    """

    STARTS = ("singletons", "two_shared")

    def __init__(
        self, cfg: ScenarioConfig, objective: str = "ee", moves_per_coordinate: int = GREEDY_MOVES_PER_COORDINATE
    ):
        self.name = "greedy"
        self.cfg = cfg
        self.objective = objective
        self.max_moves = moves_per_coordinate * (cfg.n_eds + cfg.n_uavs)
        self.moves_used = 0
        self._scorer: AllocationScorer | None = None

    def reset(self, core: BatchCore) -> None:
        pass

    def _start(
        self, kind: str, slots: Slots, setting_ok: np.ndarray, bw_ok: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.cfg
        n, v = slots.g_serving.shape
        # gain rank of each ED among the scenario's associated EDs (0 = highest)
        rank = np.argsort(np.argsort(-np.where(slots.associated, slots.g_serving, -1.0), axis=1, kind="stable"), axis=1)
        alone = cfg.n_sf - (1 if kind == "singletons" else 2)
        shared = np.maximum(rank - alone, 0)  # rank among the EDs that share a SF
        n_groups = cfg.n_sf - alone
        sf = np.where(rank < alone, rank, alone + shared % n_groups)
        # alone: the largest TP; in a shared group its strongest ED the largest TP, the others the smallest
        tp = np.where((rank >= alone) & (shared >= n_groups), 0, cfg.n_tp - 1)
        bw = np.argmax(np.where(bw_ok, np.arange(cfg.n_bw), -1), axis=-1)  # the widest allowed
        bw_ed = np.take_along_axis(bw, slots.serving_idx, axis=1)
        ok = np.take_along_axis(setting_ok, bw_ed[:, :, None, None], axis=2)[:, :, 0]  # [N, V, n_set]
        want = sf * cfg.n_tp + tp
        # an allowed setting closest to the wanted one: same SF first, then higher TP
        s = self._scorer
        assert s is not None  # (search() sets it)
        pref = (s.set_sf[None, None] == sf[..., None]) * 10 * cfg.n_tp + s.set_tp[None, None]
        fallback = np.argmax(np.where(ok, pref, -np.inf), axis=-1)
        wanted_ok = np.take_along_axis(ok, want[..., None], axis=-1)[..., 0]
        return np.where(wanted_ok, want, fallback), bw

    def _ascend(self, setting, bw, slots, setting_ok, bw_ok) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cfg, s = self.cfg, self._scorer
        assert s is not None  # (search() sets it)
        n, v = setting.shape
        rows = np.arange(n)
        movers = np.broadcast_to(np.arange(v), (n, v))
        p0, q0 = s.score(setting, bw, slots, setting_ok, bw_ok)
        for step in range(self.max_moves):
            # every ED's every setting [N, V * n_set], allowed at its UAV's current BW
            pe, qe = s.score_ed_moves(setting, bw, slots, movers)
            bw_ed = np.take_along_axis(bw, slots.serving_idx, axis=1)
            ok = np.take_along_axis(setting_ok, bw_ed[:, :, None, None], axis=2)[:, :, 0] & slots.associated[..., None]
            pe = np.where(ok, pe, -np.inf).reshape(n, -1)
            qe = qe.reshape(n, -1)
            # every UAV's every BW [N, U * n_bw]
            cand_bw = np.broadcast_to(bw, (cfg.n_uavs, cfg.n_bw, n, cfg.n_uavs)).copy()
            cand_bw[np.arange(cfg.n_uavs)[:, None], :, :, np.arange(cfg.n_uavs)[:, None]] = np.arange(cfg.n_bw)[
                None, :, None
            ]
            pb, qb = s.score(np.broadcast_to(setting, (cfg.n_uavs, cfg.n_bw, n, v)), cand_bw, slots, setting_ok, bw_ok)
            p = np.concatenate([pe, pb.reshape(-1, n).T], axis=1)
            q = np.concatenate([qe, qb.reshape(-1, n).T], axis=1)
            best = lex_argmax(p, q)
            move = lex_better(p[rows, best], q[rows, best], p0, q0)
            self.moves_used = step
            if not move.any():
                break
            ed = move & (best < v * s.n_set)
            e, b = rows[ed], best[ed]
            setting[e, b // s.n_set] = b % s.n_set
            e, b = rows[move & ~ed], best[move & ~ed] - v * s.n_set
            bw[e, b // cfg.n_bw] = b % cfg.n_bw
            p0, q0 = s.score(setting, bw, slots, setting_ok, bw_ok)  # exact, for the next comparison
        return setting, bw, p0, q0

    def search(self, slots: Slots, tables) -> tuple[np.ndarray, np.ndarray]:
        """The best (settings [N, V], BWs [N, U]) found for the slots."""
        if self._scorer is None:
            self._scorer = AllocationScorer(self.cfg, tables, self.objective)
        setting_ok, bw_ok = self._scorer.allowed(slots)
        best = None
        for kind in self.STARTS:
            setting, bw, p, q = self._ascend(*self._start(kind, slots, setting_ok, bw_ok), slots, setting_ok, bw_ok)
            if best is None:
                best = [setting, bw, p, q]
                continue
            take = lex_better(p, q, best[2], best[3])
            best[0] = np.where(take[:, None], setting, best[0])
            best[1] = np.where(take[:, None], bw, best[1])
            best[2], best[3] = np.where(take, p, best[2]), np.where(take, q, best[3])
        assert best is not None  # (STARTS is not empty)
        return best[0], best[1]

    def act(self, core: BatchCore) -> np.ndarray:
        slots = Slots.of_core(core)
        setting, bw = self.search(slots, core.tables)
        return to_actions(self.cfg, slots, setting, bw)


def optimal_candidates(cfg: ScenarioConfig) -> int:
    """Joint candidates of per_device `optimal`: (n_sf n_tp)^V settings times n_bw^U BWs."""
    return (cfg.n_sf * cfg.n_tp) ** cfg.n_eds * cfg.n_bw**cfg.n_uavs


class PerDeviceOptimal:
    """The exact per-slot maximum: every (SF, TP) of every ED and every BW of every UAV, scored
    in chunks with physics.slot_metrics (AllocationScorer.score); ties: the lowest candidate.
    Refused (ConfigError) above OPTIMAL_MAX_CANDIDATES candidates."""

    def __init__(self, cfg: ScenarioConfig, objective: str = "ee", max_candidates: int = OPTIMAL_MAX_CANDIDATES):
        self.name = "optimal"
        self.cfg = cfg
        self.objective = objective
        self.n_candidates = optimal_candidates(cfg)
        if self.n_candidates > max_candidates:
            raise ConfigError(
                f"scenario.n_eds: baseline 'optimal' in per_device mode searches (n_sf n_tp)^V n_bw^U = "
                f"{self.n_candidates:,} candidates at V={cfg.n_eds}, U={cfg.n_uavs}, above its limit of "
                f"{max_candidates:,}; use fewer EDs, smaller SF/TP/BW sets, or the 'greedy' baseline"
            )
        n_set = cfg.n_sf * cfg.n_tp
        self._radix = np.array([n_set] * cfg.n_eds + [cfg.n_bw] * cfg.n_uavs, dtype=np.int64)
        self._place = np.concatenate([[1], np.cumprod(self._radix[:-1])]).astype(np.int64)
        self._scorer: AllocationScorer | None = None

    def reset(self, core: BatchCore) -> None:
        pass

    def search(self, slots: Slots, tables) -> tuple[np.ndarray, np.ndarray]:
        if self._scorer is None:
            self._scorer = AllocationScorer(self.cfg, tables, self.objective)
        setting_ok, bw_ok = self._scorer.allowed(slots)
        n, v = slots.g_serving.shape
        chunk = max(1, OPTIMAL_CHUNK_ELEMENTS // (n * v))
        best_p, best_q = np.full(n, -np.inf), np.full(n, -np.inf)
        best = np.zeros((n, v + self.cfg.n_uavs), dtype=np.int64)
        rows = np.arange(n)
        for start in range(0, self.n_candidates, chunk):
            c = np.arange(start, min(start + chunk, self.n_candidates), dtype=np.int64)
            digits = (c[:, None] // self._place) % self._radix  # [C, V + U]
            setting = np.broadcast_to(digits[:, None, :v], (len(c), n, v))
            bw = np.broadcast_to(digits[:, None, v:], (len(c), n, self.cfg.n_uavs))
            p, q = self._scorer.score(setting, bw, slots, setting_ok, bw_ok)  # [C, N]
            i = lex_argmax(p, q, axis=0)
            top_p, top_q = p[i, rows], q[i, rows]
            take = (top_p > best_p) | ((top_p == best_p) & (top_q > best_q)) | (start == 0)
            best_p, best_q = np.where(take, top_p, best_p), np.where(take, top_q, best_q)
            best = np.where(take[:, None], digits[i], best)
        return best[:, :v], best[:, v:]

    def act(self, core: BatchCore) -> np.ndarray:
        slots = Slots.of_core(core)
        setting, bw = self.search(slots, core.tables)
        return to_actions(self.cfg, slots, setting, bw)
