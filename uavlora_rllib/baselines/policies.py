"""Non-learning baselines: random, fixed, ADR, greedy (coordinate ascent) and the per-slot optimum;
best_fixed (baselines/best_fixed.py) and the per_device greedy and optimal (baselines/per_device.py)
are made by the same factory, `make_baseline`.

Every baseline implements `evaluation.Policy`: `reset(core)` after `core.reset()`, and
`act(core)` returns the actions of all N scenarios of the batch core at once. No Python loop
runs over EDs or scenarios; `greedy` loops over the U agents inside a coordinate-ascent round
(see `GreedyPolicy`), and `optimal` loops over chunks of the joint-action space.

Objectives of `greedy` and `optimal` (docs/model.md#per-slot-optimum):

* ``objective="ee"`` (default): maximise EE_sys[t] subject to the paper's SNR constraint (h),
  rho_{a_v,v}[t] >= rho_thr(SF_v, W_v) for every associated ED. In per_uav mode an ED's SNR
  and threshold depend on its own UAV's action only, so (h) separates over the UAVs. Where
  no action of a UAV satisfies (h) for all its EDs, that UAV is restricted to the actions
  with the fewest violating EDs (lexicographic: fewest violators first, then EE). In the
  paper's layout (h) never binds: within R_comm = 600 m the SNR is >= ~24 dB at 2 dBm, far
  above every threshold (<= -7.5 dB), so this equals the unconstrained per-slot maximum.
* ``objective="reward"``: maximise the shared reward r[t], unconstrained (the reward's
  beta term already penalises violations of (h), as the paper says).

Ties in the objective are broken by the other metric (r[t] for "ee", EE_sys[t] for
"reward"): with the Shannon rate EE_sys[t] does not depend on WHICH distinct SFs the UAVs
use, only on which EDs share one, so many joint actions tie exactly; among them the
tie-break picks those with the best success rate and margins instead of the lowest index.

Because actions change neither the mobility nor the association, the per-slot maximum is the
exact optimum of the whole episode (docs/model.md#per-slot-optimum); `optimal` computes it exhaustively over the
joint per_uav action (90^U candidates) and `greedy` approximates it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from uavlora_rllib.config_errors import ConfigError, exception_line
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import decode_joint_action, encode_joint_action, per_device_action_len
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

BASELINES = ("random", "fixed", "adr", "best_fixed", "greedy", "optimal")
OBJECTIVES = ("ee", "reward")
REFERENCES = ("greedy", "optimal")  # the per-slot references (docs/model.md#per-slot-optimum)

# `optimal` refuses joint-action spaces larger than this (90^U with the paper's sets):
# U <= 3 is accepted (729,000 candidates), U >= 4 (65.6 M) is
# refused (docs/model.md#per-slot-optimum).
OPTIMAL_MAX_CANDIDATES = 1_000_000
# Candidate-ED evaluations per chunk of `optimal` (bounds memory: ~ 60 bytes each).
OPTIMAL_CHUNK_ELEMENTS = 1 << 19
GREEDY_MAX_ROUNDS = 20


def _check_objective(objective: str) -> str:
    if objective not in OBJECTIVES:
        raise ConfigError(f"objective: {objective!r} is not one of {list(OBJECTIVES)}")
    return objective


def _require_per_uav(cfg: ScenarioConfig, name: str) -> None:
    if cfg.action_mode != "per_uav":
        raise ConfigError(
            f"scenario.action_mode: baseline {name!r} supports action modes ['per_uav'], got {cfg.action_mode!r}"
        )


def _serving_gain(core: BatchCore) -> np.ndarray:
    """G between each ED and its serving UAV [N, V] (any value where unassociated)."""
    return np.take_along_axis(core.gains, core.links.serving_idx[:, None, :], axis=1)[:, 0, :]


def _snr_db(core: BatchCore, tp_idx: np.ndarray, g_serving: np.ndarray) -> np.ndarray:
    """Measured SNR in dB at the serving UAV with transmit power index tp_idx (broadcasts)."""
    t = core.tables
    return physics.lin_to_db(physics.snr(t.tp_w[tp_idx], g_serving, t.noise_w))


# ---------------------------------------------------------------- random, fixed
class RandomPolicy:
    """Uniform over the action space, from a numpy Generator seeded once at construction."""

    def __init__(self, cfg: ScenarioConfig, seed: int = 0):
        self.name = "random"
        self.cfg = cfg
        self._rng = np.random.default_rng(seed)
        self._high: np.int64 | np.ndarray
        if cfg.action_mode == "per_uav":
            self._high = np.int64(cfg.n_joint_actions)
        else:
            self._high = np.array([cfg.n_sf, cfg.n_tp] * cfg.quota + [cfg.n_bw], dtype=np.int64)

    def reset(self, core: BatchCore) -> None:
        pass

    def act(self, core: BatchCore) -> np.ndarray:
        shape = (core.n, self.cfg.n_uavs) + (() if self.cfg.action_mode == "per_uav" else (self._high.size,))
        return self._rng.integers(0, self._high, size=shape, dtype=np.int64)


class FixedPolicy:
    """Everyone on the smallest SF, the largest TP and the largest BW: SF7, 14 dBm, 500 kHz
    with the paper's sets (with other sets: min(sf_set), max(tp_dbm), max(bw_khz))."""

    def __init__(self, cfg: ScenarioConfig):
        self.name = "fixed"
        self.cfg = cfg
        sf, tp, bw = 0, cfg.n_tp - 1, cfg.n_bw - 1  # the sets are sorted ascending
        if cfg.action_mode == "per_uav":
            self._row = np.full(cfg.n_uavs, int(encode_joint_action(sf, tp, bw, cfg)), dtype=np.int64)
        else:
            self._row = np.array([[sf, tp] * cfg.quota + [bw]] * cfg.n_uavs, dtype=np.int64)

    def reset(self, core: BatchCore) -> None:
        pass

    def act(self, core: BatchCore) -> np.ndarray:
        return np.broadcast_to(self._row, (core.n,) + self._row.shape).copy()


# ---------------------------------------------------------------- ADR
def adr_update(
    sf_idx: np.ndarray, tp_idx: np.ndarray, margin_db: np.ndarray, n_tp: int, step_db: float = 3.0
) -> tuple[np.ndarray, np.ndarray]:
    """Semtech's network-server ADR rule, vectorised over any shape.

    margin = measured SNR - required SNR(SF, BW) - installation margin (done by the caller);
    n_steps = floor(margin / step_db); while n_steps > 0 and SF > min: SF -= 1, n_steps -= 1;
    then while n_steps > 0 and TP > min: TP -= 1 step, n_steps -= 1; while n_steps < 0 and
    TP < max: TP += 1 step, n_steps += 1. SF never rises (as in Semtech's algorithm). One TP
    step is one level of the TP set (3 dB with the paper's set {2, 5, 8, 11, 14} dBm).
    Indices are into the ascending SF and TP sets (0 = SF7 / 2 dBm).
    """
    steps = np.floor(np.asarray(margin_db, dtype=np.float64) / step_db).astype(np.int64)
    down = np.maximum(steps, 0)
    sf_down = np.minimum(down, sf_idx)
    tp_down = np.minimum(down - sf_down, tp_idx)
    tp_up = np.minimum(np.maximum(-steps, 0), n_tp - 1 - tp_idx)
    return sf_idx - sf_down, tp_idx - tp_down + tp_up


class AdrPolicy:
    """LoRaWAN ADR (Semtech's network-server rule, `adr_update`) run on the measured SNR.

    Each slot, before acting, the network server measures the SNR of the EDs at their serving
    UAV with the setting they currently hold (physics.snr, current channel, current TP), runs
    the ADR rule once, and the new setting is used in this slot and kept for the next one
    (a one-slot idealisation of ADR's uplink history). State starts at SF12 / 14 dBm (the
    largest SF and TP of the scenario's sets) at every episode reset; BW is fixed at
    `bw_khz` (default: 125 kHz, LoRaWAN's usual uplink channel width, or the scenario's
    smallest BW when its set has no 125 kHz; an explicit value must be in the scenario's BW
    set). Installation margin `margin_db` = 10 dB (Semtech's default).

    per_uav: one setting per UAV, adapted on the WORST (minimum) margin of the EDs it serves
    this slot, so that every served ED keeps the installation margin (the conservative choice
    for a shared setting). A UAV that serves nobody keeps its setting.
    per_device: one setting per ED (by ED id, so it follows the ED across UAVs and slots),
    placed into the ED's observation slot; unassociated EDs keep their setting.
    """

    def __init__(self, cfg: ScenarioConfig, bw_khz: int | None = None, margin_db: float = 10.0):
        if bw_khz is None:  # the BW sets are sorted ascending: [0] is the narrowest, closest to 125
            bw_khz = 125 if 125 in cfg.bw_khz else cfg.bw_khz[0]
        if bw_khz not in cfg.bw_khz:
            raise ConfigError(f"adr.bw_khz: {bw_khz} is not in the scenario's BW set {list(cfg.bw_khz)}")
        self.name = "adr"
        self.cfg = cfg
        self.bw_idx = cfg.bw_khz.index(bw_khz)
        self.margin_db = float(margin_db)
        self._sf: np.ndarray | None = None
        self._tp: np.ndarray | None = None

    def reset(self, core: BatchCore) -> None:
        width = self.cfg.n_uavs if self.cfg.action_mode == "per_uav" else self.cfg.n_eds
        self._sf = np.full((core.n, width), self.cfg.n_sf - 1, dtype=np.int64)
        self._tp = np.full((core.n, width), self.cfg.n_tp - 1, dtype=np.int64)

    def _margins_per_ed(self, core: BatchCore, sf_ed: np.ndarray, tp_ed: np.ndarray) -> np.ndarray:
        thr = core.tables.threshold_db[sf_ed, self.bw_idx]
        return _snr_db(core, tp_ed, _serving_gain(core)) - thr - self.margin_db

    def act(self, core: BatchCore) -> np.ndarray:
        if self._sf is None or self._sf.shape[0] != core.n:
            self.reset(core)
        assert self._sf is not None and self._tp is not None  # (reset sets them)
        cfg = self.cfg
        assoc = core.associated
        if cfg.action_mode == "per_uav":
            sidx = core.links.serving_idx
            sf_ed = np.take_along_axis(self._sf, sidx, axis=1)
            tp_ed = np.take_along_axis(self._tp, sidx, axis=1)
            m = self._margins_per_ed(core, sf_ed, tp_ed)  # [N, V]
            mine = (sidx[:, None, :] == np.arange(cfg.n_uavs)[None, :, None]) & assoc[:, None, :]  # [N, U, V]
            worst = np.where(mine, m[:, None, :], np.inf).min(axis=-1)  # [N, U]
            serves = mine.any(axis=-1)
            sf_new, tp_new = adr_update(self._sf, self._tp, np.where(serves, worst, 0.0), cfg.n_tp)
            self._sf = np.where(serves, sf_new, self._sf)
            self._tp = np.where(serves, tp_new, self._tp)
            return encode_joint_action(self._sf, self._tp, self.bw_idx, cfg).astype(np.int64)
        m = self._margins_per_ed(core, self._sf, self._tp)  # [N, V]
        sf_new, tp_new = adr_update(self._sf, self._tp, np.where(assoc, m, 0.0), cfg.n_tp)
        self._sf = np.where(assoc, sf_new, self._sf)
        self._tp = np.where(assoc, tp_new, self._tp)
        length = per_device_action_len(cfg)
        actions = np.zeros((core.n, cfg.n_uavs, length), dtype=np.int64)
        actions[..., -1] = self.bw_idx
        e, v = np.nonzero(assoc)
        u, k = core.serving[e, v], core.slot_of_ed[e, v]
        actions[e, u, 2 * k] = self._sf[e, v]
        actions[e, u, 2 * k + 1] = self._tp[e, v]
        return actions


# ---------------------------------------------------------------- per-slot search helpers
class _SlotSearch:
    """Shared by greedy and optimal: scores per_uav joint actions of the current slot."""

    def __init__(self, cfg: ScenarioConfig, objective: str, name: str):
        _require_per_uav(cfg, name)
        self.name = name
        self.cfg = cfg
        self.objective = _check_objective(objective)
        self._metric = "ee_sys" if objective == "ee" else "reward"
        a = np.arange(cfg.n_joint_actions)
        self._sf_a, self._tp_a, self._bw_a = decode_joint_action(a, cfg)  # [A] each

    def reset(self, core: BatchCore) -> None:
        pass

    def _allowed(self, core: BatchCore) -> np.ndarray:
        """[N, U, A] bool: actions of each UAV allowed by the objective (see module docstring)."""
        n, u, a = core.n, self.cfg.n_uavs, self.cfg.n_joint_actions
        if self.objective != "ee":
            return np.ones((n, u, a), dtype=bool)
        snr_db = _snr_db(core, self._tp_a[:, None, None], _serving_gain(core)[None])  # [A, N, V]
        thr = core.tables.threshold_db[self._sf_a, self._bw_a][:, None, None]
        bad = (snr_db < thr) & core.associated[None]  # [A, N, V]
        mine = core.links.serving_idx[:, None, :] == np.arange(u)[None, :, None]  # [N, U, V]
        n_bad = np.einsum("anv,nuv->nua", bad.astype(np.int64), mine.astype(np.int64))
        return n_bad == n_bad.min(axis=-1, keepdims=True)

    def _score(self, core: BatchCore, joint: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(primary, secondary) keys of joint per_uav actions [..., N, U] -> two [..., N] arrays.

        primary: the objective, -inf where a UAV's action is not allowed (`allowed` [..., N]);
        secondary: the tie-break, r[t] for objective "ee" (the EE_sys[t] maximisers differ,
        e.g. by which distinct SFs the UAVs use, and r[t] prefers the robust ones), EE_sys[t]
        for objective "reward".
        """
        shape = joint.shape[:-1] + (self.cfg.n_eds,)
        ed_action = np.take_along_axis(joint, np.broadcast_to(core.links.serving_idx, shape), axis=-1)
        sf, tp, bw = decode_joint_action(ed_action, self.cfg)
        m = physics.slot_metrics(core.gains, core.links.serving_idx, core.associated, sf, tp, bw, self.cfg, core.tables)
        primary = np.where(allowed, m[self._metric], -np.inf)
        return primary, m["reward" if self._metric == "ee_sys" else "ee_sys"]


def _lex_argmax(primary: np.ndarray, secondary: np.ndarray) -> np.ndarray:
    """Index along axis 0 of the lexicographic maximum of (primary, secondary); ties: lowest."""
    top = primary == primary.max(axis=0, keepdims=True)
    return np.argmax(np.where(top, secondary, -np.inf), axis=0)


def _lex_greater(p1: np.ndarray, s1: np.ndarray, p2: np.ndarray, s2: np.ndarray) -> np.ndarray:
    return (p1 > p2) | ((p1 == p2) & (s1 > s2))


class GreedyPolicy(_SlotSearch):
    """Per-slot coordinate ascent on the joint per_uav action.

    Start (documented): UAV u on SF index u mod n_sf (distinct SFs while U <= n_sf, so that no
    two UAVs' EDs interfere), the largest TP and the largest BW. Then rounds: for u = 0..U-1,
    all A = 90 actions of UAV u (the others fixed) are scored at once, slot_metrics broadcast
    over a candidate axis [A, N, V], and u moves to the best one if it STRICTLY improves the
    (objective, tie-break) pair lexicographically (remaining ties: lowest action index).
    Rounds repeat until one makes no move in any scenario, at most `max_rounds`. The loop over u is inherent to Gauss-Seidel coordinate
    ascent (each agent's best response depends on the others' latest moves); everything
    inside it is vectorised over the candidates, the scenarios and the EDs. With U = 1 one
    sweep is exhaustive, so greedy equals optimal there.
    """

    def __init__(self, cfg: ScenarioConfig, objective: str = "ee", max_rounds: int = GREEDY_MAX_ROUNDS):
        super().__init__(cfg, objective, "greedy")
        self.max_rounds = int(max_rounds)
        u = np.arange(cfg.n_uavs)
        self._start = encode_joint_action(u % cfg.n_sf, cfg.n_tp - 1, cfg.n_bw - 1, cfg).astype(np.int64)
        self.rounds_used = 0

    def act(self, core: BatchCore) -> np.ndarray:
        n, n_u, n_a = core.n, self.cfg.n_uavs, self.cfg.n_joint_actions
        allowed = self._allowed(core)  # [N, U, A]
        joint = np.broadcast_to(self._start, (n, n_u)).copy()
        cand_ids = np.arange(n_a)
        rows = np.arange(n)
        for rnd in range(self.max_rounds):
            moved = False
            for u in range(n_u):
                cand = np.broadcast_to(joint, (n_a, n, n_u)).copy()
                cand[:, :, u] = cand_ids[:, None]
                p, q = self._score(core, cand, allowed[:, u, :].T)  # [A, N] each
                best = _lex_argmax(p, q)
                cur = joint[:, u]
                better = _lex_greater(p[best, rows], q[best, rows], p[cur, rows], q[cur, rows])
                if better.any():
                    joint[:, u] = np.where(better, best, joint[:, u])
                    moved = True
            self.rounds_used = rnd + 1
            if not moved:
                break
        return joint


class OptimalPolicy(_SlotSearch):
    """Exhaustive per-slot maximum over the joint per_uav action (A^U candidates, A = 90).

    Candidate c is the mixed-radix number c = sum_u a_u A^u. Candidates are scored in chunks
    of at most OPTIMAL_CHUNK_ELEMENTS candidate-ED pairs per scenario batch, with
    physics.slot_metrics broadcast over the chunk axis; the lexicographic best of (objective,
    tie-break) is kept (remaining ties: lowest c).
    Refused (ConfigError) when A^U > OPTIMAL_MAX_CANDIDATES (U >= 4 with the paper's sets).
    """

    def __init__(self, cfg: ScenarioConfig, objective: str = "ee", max_candidates: int = OPTIMAL_MAX_CANDIDATES):
        super().__init__(cfg, objective, "optimal")
        self.n_candidates = cfg.n_joint_actions**cfg.n_uavs
        if self.n_candidates > max_candidates:
            raise ConfigError(
                f"scenario.n_uavs: baseline 'optimal' searches {cfg.n_joint_actions}^{cfg.n_uavs} = "
                f"{self.n_candidates:,} joint actions, above its limit of {max_candidates:,}; "
                f"use n_uavs <= {_max_uavs(cfg.n_joint_actions, max_candidates)} or the 'greedy' baseline"
            )
        self._radix = cfg.n_joint_actions ** np.arange(cfg.n_uavs, dtype=np.int64)

    def act(self, core: BatchCore) -> np.ndarray:
        n, n_u, n_a = core.n, self.cfg.n_uavs, self.cfg.n_joint_actions
        allowed = self._allowed(core)  # [N, U, A]
        chunk = max(1, OPTIMAL_CHUNK_ELEMENTS // (n * self.cfg.n_eds))
        best_p = np.full(n, -np.inf)
        best_q = np.full(n, -np.inf)
        best_joint = np.zeros((n, n_u), dtype=np.int64)
        rows = np.arange(n)
        for start in range(0, self.n_candidates, chunk):
            c = np.arange(start, min(start + chunk, self.n_candidates), dtype=np.int64)
            per_uav = (c[:, None] // self._radix) % n_a  # [C, U]
            for_u = allowed[:, np.arange(n_u)[None, :], per_uav]  # [N, C, U]
            ok = np.asarray(for_u.all(axis=-1)).T  # [C, N]
            joint = np.broadcast_to(per_uav[:, None, :], (len(c), n, n_u))
            p, q = self._score(core, joint, ok)  # [C, N] each
            i = _lex_argmax(p, q)
            top_p, top_q = p[i, rows], q[i, rows]
            take = _lex_greater(top_p, top_q, best_p, best_q) | (start == 0)
            best_p = np.where(take, top_p, best_p)
            best_q = np.where(take, top_q, best_q)
            best_joint = np.where(take[:, None], per_uav[i], best_joint)
        return best_joint


def _max_uavs(n_actions: int, max_candidates: int) -> int:
    u = 0
    while n_actions ** (u + 1) <= max_candidates:
        u += 1
    return u


# ---------------------------------------------------------------- cost of an evaluation
# Candidate-ED evaluations per second of greedy's and optimal's search on one core [1/s]: an
# estimate only, so that a grid can say beforehand what its baselines cost (the evaluate CLI's
# progress bar shows the real rate).
SEARCH_RATE = 2e6
# Everything else per scenario-slot (simulator step, observations, a cheap policy), per ED.
STEP_SECONDS_PER_ED = 1e-6
# per_device greedy's single-move scoring (AllocationScorer.score_ed_moves): ED-SINR evaluations per
# second [1/s], and the fixed cost of one move over the evaluation batch [s]; fitted at V=10/U=2 and
# V=60/U=8 (batch of 10 scenarios, one idle core: 0.075 s and 3.3 s per slot, 26 and 130 moves per start).
MOVE_SCORING_RATE = 9.5e7
MOVE_OVERHEAD_S = 1.3e-3


def evaluation_seconds(name: str, cfg: ScenarioConfig, episodes: int) -> float:
    """Rough single-core wall-clock estimate of `episodes` episodes of baseline `name` on `cfg`.

    per_uav: optimal searches A^U joint actions per slot; greedy at least 2 rounds of U x A (one
    sweep that moves and one that confirms; up to GREEDY_MAX_ROUNDS). per_device: greedy two starts
    of ~2 (V + U) steepest moves (measured 1.9-2.4), each scoring V x n_sf n_tp single moves over V
    EDs; optimal every candidate.
    best_fixed: its one-off selection (exhaustive or ~3 rounds x 3 starts of coordinate ascent on
    the selection episodes' slots), then constant actions."""
    slots = episodes * cfg.episode_len
    searched = 0
    if name == "best_fixed":
        from uavlora_rllib.baselines.best_fixed import (
            BEST_FIXED_EXHAUSTIVE,
            BEST_FIXED_RESTARTS,
            selection_episodes,
            selection_stride,
        )

        episodes = selection_episodes(cfg)
        sel_slots = episodes * cfg.episode_len // selection_stride(cfg, episodes)
        if cfg.action_mode == "per_uav":
            total = cfg.n_joint_actions**cfg.n_uavs
            cand = (
                total if total <= BEST_FIXED_EXHAUSTIVE else 3 * BEST_FIXED_RESTARTS * cfg.n_uavs * cfg.n_joint_actions
            )
        else:
            cand = (
                3 * (BEST_FIXED_RESTARTS + 1) * (cfg.n_uavs * cfg.quota * cfg.n_sf * cfg.n_tp + cfg.n_uavs * cfg.n_bw)
            )
        return sel_slots * cfg.n_eds * cand / SEARCH_RATE + slots * cfg.n_eds * STEP_SECONDS_PER_ED
    if cfg.action_mode == "per_device" and name in REFERENCES:
        from uavlora_rllib.baselines.per_device import optimal_candidates

        if name == "optimal":
            searched = optimal_candidates(cfg)
        else:
            moves = 2 * 2 * (cfg.n_eds + cfg.n_uavs)
            per_move = cfg.n_eds**2 * cfg.n_sf * cfg.n_tp / MOVE_SCORING_RATE + MOVE_OVERHEAD_S / min(episodes, 32)
            return slots * (moves * per_move + cfg.n_eds * STEP_SECONDS_PER_ED)
    elif name == "optimal":
        searched = cfg.n_joint_actions**cfg.n_uavs
    elif name == "greedy":
        searched = 2 * cfg.n_uavs * cfg.n_joint_actions
    return slots * cfg.n_eds * (searched / SEARCH_RATE + STEP_SECONDS_PER_ED)


# ---------------------------------------------------------------- factory
# name -> factory(scenario, seed) -> Policy: the baselines plugin modules add (`register_baseline`)
_PLUGIN_BASELINES: dict[str, Callable[[ScenarioConfig, int], Any]] = {}


def register_baseline(name: str, factory: Callable[[ScenarioConfig, int], Any]) -> None:
    """Add baseline `name` from a plugin module (listed under a grid's `plugins:`, or `evaluate --plugin`):
    `factory(scenario, seed)` returns an `evaluation.Policy` (`reset(core)`, and `act(core)` the actions of
    all the core's scenarios). TypeError for a name that is not an identifier, a built-in's name, one taken
    by another factory, or a factory that is not callable (the plugin's import then fails in one line)."""
    if not isinstance(name, str) or not name.isidentifier():
        raise TypeError(f"register_baseline: the name must be an identifier, got {name!r}")
    if name in BASELINES:
        raise TypeError(f"baseline {name!r} is built in; a plugin takes another name (built in: {list(BASELINES)})")
    if not callable(factory):
        raise TypeError(f"baseline {name!r}: the factory must be callable (scenario, seed) -> Policy, got {factory!r}")
    known = _PLUGIN_BASELINES.get(name)
    where = (getattr(factory, "__module__", ""), getattr(factory, "__qualname__", ""))
    if known is not None and (known.__module__, known.__qualname__) != where:
        raise TypeError(f"baseline {name!r} is already taken by {known.__module__}.{known.__qualname__}")
    _PLUGIN_BASELINES[name] = factory


def baseline_names() -> list[str]:
    """The built-in baselines, then those the plugins imported so far registered."""
    return [*BASELINES, *sorted(_PLUGIN_BASELINES)]


def make_baseline(name: str, cfg: ScenarioConfig, seed: int = 0, objective: str = "ee"):
    """The baseline policy `name` (one of BASELINES, or a plugin's: `register_baseline`) for scenario `cfg`.

    `seed` drives `random`, and picks `best_fixed`'s selection episodes; `objective` ("ee" or
    "reward") applies to greedy and optimal (and is validated for every name). In per_device
    mode greedy and optimal are baselines/per_device.py's. Raises ConfigError for an unknown
    name or objective, and for optimal beyond its candidate limit.
    """
    _check_objective(objective)
    if name == "random":
        return RandomPolicy(cfg, seed)
    if name == "fixed":
        return FixedPolicy(cfg)
    if name == "adr":
        return AdrPolicy(cfg)
    if name == "best_fixed":
        from uavlora_rllib.baselines.best_fixed import BestFixedPolicy

        return BestFixedPolicy(cfg, seed)
    if name in ("greedy", "optimal") and cfg.action_mode == "per_device":
        from uavlora_rllib.baselines.per_device import PerDeviceGreedy, PerDeviceOptimal

        return (PerDeviceGreedy if name == "greedy" else PerDeviceOptimal)(cfg, objective)
    if name == "greedy":
        return GreedyPolicy(cfg, objective)
    if name == "optimal":
        return OptimalPolicy(cfg, objective)
    if name in _PLUGIN_BASELINES:
        try:
            return _PLUGIN_BASELINES[name](cfg, seed)
        except ConfigError:
            raise
        except Exception as exc:  # a plugin's code: one line naming it, not a traceback
            raise ConfigError(f"baseline {name!r} (a plugin's): {exception_line(exc)}") from None
    raise ConfigError(f"policy: unknown baseline {name!r}; allowed: {baseline_names()}")
