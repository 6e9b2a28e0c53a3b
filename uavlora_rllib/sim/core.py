"""The simulator core: N independent scenarios stepped at once with NumPy.

Arrays are shaped [N, ...]: EDs [N, V, 2] (stored as [2, N, V]), channels [N, U, V], actions
[N, U] (per_uav) or [N, U, 2 Lambda + 1] (per_device). No Python loop runs over EDs or UAVs in a
step; the only per-scenario loop refills the random-number buffers every `NOISE_CHUNK` steps
(each scenario owns a numpy Generator, so that scenario i of a batch seeded with s replays
exactly the single scenario seeded with s + i, bit for bit, as in Gymnasium's vector envs).
With the default channel only the serving UAV's channel is computed per step (the max-gain UAV
is the nearest one); every pair's d_h / gains / gain_db are computed on demand. A single
scenario can precompute `lookahead` future slots at once (time as the batch axis), see __init__.

Slot semantics: `reset` places the EDs and associates them (slot 0). `step(actions)`
applies the actions to the CURRENT slot (its positions and association), scores it with
`physics.slot_metrics` (per_uav actions with the default models: `physics.slot_metrics_shared`,
the same equations with each UAV's shared allocation factored out), then moves the EDs,
re-associates them and returns the next slot's observations. After `episode_len` steps the
episode is truncated (never terminated).

Observation o_u (SPEC.md; scaling documented in README "Observations and state"):
Lambda_max rows of (x_v, y_v, d_uv, G_uv) over the EDs u serves, sorted by gain, then 3
per-UAV features (served count / Lambda_max, UAV x, UAV y):
  x, y      -> 2 p / L - 1                         in [-1, 1]
  d_uv      -> d_h / R_comm                        in [0, 1] for served EDs
  G_uv      -> dB gain mapped linearly so that G(d_h = 0) -> 1 and G(d_h = R_comm) -> -1
Padding rows are zeros. `obs` is float32 (computed in float64, rounded once). Global state s
(critics and mixers only, float64): ED positions (2V), gain
features to every UAV (UV, clipped to [-3, 1]), association one-hot (V (U+1), last column =
unassociated), each ED's previous (SF, TP, BW) one-hot (V (n_sf + n_tp + n_bw), zeros when it
was silent), and t / T.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.association import (
    UNASSOCIATED,
    associate,
    greedy_from_nearest,
    group_sort,
    nearest_uav_on_line,
)
from uavlora_rllib.sim.scenario import ScenarioConfig

NOISE_CHUNK = 32  # steps of mobility noise drawn per refill
# per_uav mode: EDs in a batch above which per-UAV table look-ups followed by per-ED gathers
# beat one per-ED look-up in the joint-action decoding table (fewer NumPy calls below it)
PER_UAV_GATHER_MIN = 4096


def scenario_rng(seed: Any = None) -> np.random.Generator:
    """The random-number generator of one scenario: NumPy's SFC64 bit generator (seeded
    through a SeedSequence, like default_rng). It draws the mobility noise's uniforms (see
    gaussian_pairs) and the v-bar re-draws, ~1.8x faster than default_rng's PCG64 for uniforms
    on this machine (BENCHMARKS.md)."""
    return np.random.Generator(np.random.SFC64(seed))


def gaussian_pairs(uniform: np.ndarray, out: np.ndarray, scale: float, scratch: tuple | None = None) -> np.ndarray:
    """Standard normal pairs by the Box-Muller transform, times `scale`: uniform [..., 2, K]
    float32 draws in [0, 1) (u0, u1) -> out [..., 2, K] (float32, or wider),
      out[..., 0, :] = scale r cos(theta),  out[..., 1, :] = scale r sin(theta),
      r = sqrt(-2 ln(1 - u0)),  theta = 2 pi u1.
    Computed in float32, whose log/sqrt/sin/cos NumPy vectorises here (float64 sin is a scalar
    loop, 8 ns): ~3.5 ns per normal with the uniforms, against 8.0 ns for
    Generator.standard_normal's float64 ziggurat. 1 - u0 lies in (0, 1] (no log of 0); with
    24-bit uniforms |w| <= sqrt(48 ln 2) = 5.77, a tail of probability 8e-9 left out.
    `scratch`: three float32 arrays of uniform[..., 0, :]'s shape to compute in."""
    u0, u1 = uniform[..., 0, :], uniform[..., 1, :]
    r, theta, w = scratch if scratch is not None else (np.empty(u0.shape, np.float32) for _ in range(3))
    np.subtract(1.0, u0, out=r)
    np.log(r, out=r)
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)
    r *= np.float32(scale)  # (rounded to float32: the noise's scale to ~6e-8, as its values)
    np.multiply(u1, np.float32(2.0 * np.pi), out=theta)
    np.cos(theta, out=w)
    np.multiply(w, r, out=out[..., 0, :])
    np.sin(theta, out=w)
    np.multiply(w, r, out=out[..., 1, :])
    return out


OBS_ROW = 4  # (x, y, d, G) per served ED
OBS_EXTRA = 3  # served count / quota, UAV x, UAV y


class ActionError(ValueError):
    """An action outside its space; the message names the agent and the allowed range."""


@dataclass
class StepResult:
    obs: np.ndarray  # [N, U, obs_dim] observation of the next slot
    reward: np.ndarray  # [N] shared reward of the slot just played
    truncated: np.ndarray  # [N] bool
    metrics: dict[str, np.ndarray]  # physics.SLOT_METRICS, each [N]


def obs_dim(cfg: ScenarioConfig) -> int:
    return cfg.quota * OBS_ROW + OBS_EXTRA


def state_dim(cfg: ScenarioConfig) -> int:
    v, u = cfg.n_eds, cfg.n_uavs
    return 2 * v + u * v + v * (u + 1) + v * (cfg.n_sf + cfg.n_tp + cfg.n_bw) + 1


def per_device_action_len(cfg: ScenarioConfig) -> int:
    return 2 * cfg.quota + 1


def decode_joint_action(a: np.ndarray, cfg: ScenarioConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """per_uav index -> (sf_idx, tp_idx, bw_idx); index = (sf_idx * n_tp + tp_idx) * n_bw + bw_idx."""
    a = np.asarray(a)
    return a // (cfg.n_tp * cfg.n_bw), (a // cfg.n_bw) % cfg.n_tp, a % cfg.n_bw


def encode_joint_action(sf_idx, tp_idx, bw_idx, cfg: ScenarioConfig) -> np.ndarray:
    return (np.asarray(sf_idx) * cfg.n_tp + np.asarray(tp_idx)) * cfg.n_bw + np.asarray(bw_idx)


class BatchCore:
    """N independent copies of the scenario, stepped together."""

    def __init__(self, cfg: ScenarioConfig, n_envs: int = 1, lookahead: int = 0):
        if n_envs < 1:
            raise ValueError(f"n_envs: must be >= 1, got {n_envs}")
        if lookahead < 0 or (lookahead and n_envs != 1):
            raise ValueError(f"lookahead: must be 0, or >= 1 with n_envs = 1; got {lookahead} with n_envs = {n_envs}")
        self.cfg = cfg
        self.n = n_envs
        self.tables = physics.Tables.from_config(cfg)
        self.uav_xy = physics.uav_positions(cfg)
        self.quota = cfg.quota
        self.obs_dim = obs_dim(cfg)
        self.state_dim = state_dim(cfg)
        g_hi = float(-physics.path_loss_db(0.0, cfg))
        g_lo = float(-physics.path_loss_db(cfg.comm_range_m, cfg))
        self._gain_db_mid = (g_hi + g_lo) / 2.0
        self._gain_db_half = max((g_hi - g_lo) / 2.0, 1e-9)
        v, u = cfg.n_eds, cfg.n_uavs
        # Mobility state, stored by coordinate ([2, N, V]: NumPy's loops over a trailing axis of 2
        # are slow); ed_xy, ed_vel, ed_mean_vel are [N, V, 2] views of it (properties below).
        self._xy = np.zeros((2, n_envs, v))
        self._vel = np.zeros((2, n_envs, v))
        self._mvel = np.zeros((2, n_envs, v))
        self.t = np.zeros(n_envs, dtype=np.int64)
        self._prev_alloc = np.full((n_envs, v, 3), -1, dtype=np.int64)
        self._prev_parts: tuple | None = None  # (sf, tp, bw, actions, associated) of the slot just played
        self._rngs: list[np.random.Generator] = [scenario_rng() for _ in range(n_envs)]
        self._chunk = chunk = NOISE_CHUNK
        # Per scenario, (x, y) and step: the noise of every ED, and the float32 uniforms it is
        # made of (gaussian_pairs; computed in the scratch arrays)
        self._gauss = np.zeros((n_envs, 2, chunk, v), dtype=np.float32)  # (float32: as computed)
        self._uniform = np.zeros((n_envs, 2, chunk * v), dtype=np.float32)
        self._gauss_scratch = tuple(np.zeros((n_envs, chunk * v), dtype=np.float32) for _ in range(3))
        self._tests = np.zeros((n_envs, chunk * v))  # per (step, ED): uniform [0, 1) v-bar re-draw test
        # The re-draws those imply, found once per refill (see _refill): scenario, step in the
        # chunk and flat [N, V] index of each, and the new v-bar there [2, K].
        none = np.zeros(0, dtype=np.int64)
        self._redraws: tuple[np.ndarray, ...] = (none, none, none, np.zeros((2, 0)))
        self._cursor = np.zeros(n_envs, dtype=np.int64)
        self._cursor_same: int | None = 0  # the cursor of every scenario while they agree
        self._noise_scale = cfg.mobility.sigma * float(np.sqrt(1.0 - cfg.mobility.memory**2))
        self._n_joint = cfg.n_joint_actions
        self._seed_source = np.random.SeedSequence()
        self._ready = False
        self.serving = np.full((n_envs, v), UNASSOCIATED, dtype=np.int64)
        self._group_counts: np.ndarray | None = None  # [N, U + 1] EDs per UAV, last: unassociated
        self._env_idx = np.arange(n_envs)
        # Flat index of (scenario e, UAV 0, ED v) in a C-contiguous [N, U, V] array; adding
        # u * V picks UAV u. Used to gather "the value at the serving UAV" with one np.take.
        self._flat_base = (self._env_idx[:, None] * (u * v) + np.arange(v)[None, :]).astype(np.int64)
        self._positions = np.broadcast_to(np.arange(v), (n_envs, v))
        self._obs_extra_xy = 2.0 * self.uav_xy / cfg.area_m - 1.0  # [U, 2], constant
        # Channel/association path. "nearest": greedy association with the paper's SINR and a
        # gain strictly decreasing in d_h, so every ED's max-gain UAV is its nearest one and
        # the channel is needed at the serving UAV only ([N, V] work per step, not [N, U, V]);
        # the per-pair d_h / gains / gain_db are then computed on demand (properties below).
        # Otherwise ("pairs") every pair's channel is computed each step, as the optimal
        # association or the cross_gain SINR need it.
        self._nearest = (
            cfg.association == "greedy"
            and cfg.interference == "paper"
            and physics.gain_decreases_with_distance(cfg)
        )
        self._spacing = cfg.area_m / u
        self._row_base = (self._env_idx * v)[:, None]  # flat index of (e, 0) in an [N, V] array
        self._act_base = (self._env_idx * u)[:, None]  # flat index of (e, 0) in an [N, U] array
        self._grp_base = (self._env_idx * (u + 1))[:, None]  # groups: UAV 0..U-1, U = unassociated
        # Observations are written into a buffer of OBS_ROW-wide rows: per (scenario, UAV) the
        # quota's ED rows, then one row holding the 3 extra features and one pad; obs is the
        # [N, U, obs_dim] view of it. One more row at the end receives unassociated EDs.
        q1 = self.quota + 1
        # (offsets in complex64 units, pairs of float32: a row is OBS_ROW // 2 of them)
        self._obs_rows_base = (self._env_idx * (u * q1 * OBS_ROW // 2))[:, None]
        self._obs_garbage = n_envs * u * q1 * OBS_ROW // 2
        self._obs_buf_shape = (n_envs * u * q1 + 1, OBS_ROW)
        self._obs_scratch: tuple[np.ndarray, np.ndarray] | None = None  # complex128, complex64 [N, V]
        self._pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        # per_uav action index -> (sf_idx, tp_idx, bw_idx), one row per joint action
        self._decode = np.stack(decode_joint_action(np.arange(cfg.n_joint_actions), cfg), axis=-1).astype(np.int64)
        # per_uav action index -> its SF index and (P_W, W_Hz, rho_thr), for _per_uav_values
        sf_a, tp_a, bw_a = self._decode.T
        self._action_values = (sf_a.copy(), *physics.allocation_values(sf_a, tp_a, bw_a, self.tables))
        # per_uav actions with the paper's interference and the Shannon rate: each UAV's EDs share
        # its allocation, and step scores the slot with physics.slot_metrics_shared (fewer
        # per-ED passes), from this table of every action's allocation values
        self._shared = cfg.action_mode == "per_uav" and cfg.interference == "paper" and cfg.rate_model == "shannon"
        self._action_alloc = physics.SharedAllocationTable(sf_a, tp_a, bw_a, self.tables)
        # Lookahead (single scenario): actions change neither mobility nor the association
        # (SPEC.md), so the positions, channels, association and observations of the next
        # `lookahead` slots are computed at once, by a second core whose batch axis is time;
        # step() then does only the action-dependent part. Same numbers as without it.
        self._lookahead = lookahead
        self._observer = BatchCore(cfg, lookahead) if lookahead else None
        self._block: tuple | None = None
        self._block_k = 0

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | Sequence[int | None] | None = None, mask: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes. `seed` int s -> scenario i gets s + i; a sequence gives one seed
        per scenario; None draws fresh entropy. `mask` [N] bool resets only those scenarios."""
        mask = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if not self._ready and not mask.all():
            raise ValueError("the first reset must reset every scenario (mask=None)")
        seeds = self._seeds_for(seed)
        cfg, mob = self.cfg, self.cfg.mobility
        for i in np.flatnonzero(mask):  # per-scenario RNG draws only; no physics here
            rng = scenario_rng(seeds[i])
            self._rngs[i] = rng
            self.ed_xy[i] = rng.uniform(0.0, cfg.area_m, size=(cfg.n_eds, 2))
            self.ed_vel[i] = rng.uniform(-mob.v_max_mps, mob.v_max_mps, size=(cfg.n_eds, 2))
        self._refill(None if mask.all() else np.flatnonzero(mask))
        self._vel[:, mask] = self._clip_speed(self._vel[:, mask])
        self._mvel[:, mask] = mob.mean_velocity_init_mps
        self.t[mask] = 0
        self.prev_alloc[mask] = -1  # (materialises the previous slot's, then clears the reset ones)
        self._cursor_same = 0 if mask.all() else None
        self._ready = True
        self._observe()
        if self._lookahead and mask.all():
            self._ahead = (self._xy, self._vel, self._mvel)  # mobility state of the latest slot computed
            self._block = None
        return self.obs

    def _seeds_for(self, seed: int | Sequence[int | None] | None) -> list:
        if seed is None:
            return [s for s in self._seed_source.spawn(self.n)]
        if isinstance(seed, (int, np.integer)):
            return [int(seed) + i for i in range(self.n)]
        seeds = list(seed)
        if len(seeds) != self.n:
            raise ValueError(f"seed: expected {self.n} seeds, got {len(seeds)}")
        return [s if s is not None else self._seed_source.spawn(1)[0] for s in seeds]

    def _refill(self, rows: np.ndarray | None = None) -> None:
        """The next NOISE_CHUNK steps of noise for the scenarios `rows` (indices; None: all).

        Per scenario the stream is: random(2, chunk v) in float32 (u0, u1 of `gaussian_pairs`:
        the Gauss-Markov noise of each (step, ED), x and y), random(chunk, v) (the v-bar re-draw
        tests), then, for the K re-draws those tests imply, random(K, 2) (their new v-bar, (x, y)
        in (step, ED) order, mapped to [-v_max, v_max) as Generator.uniform does). Drawing the new v-bar values only
        where a re-draw happens (~1% of the EDs per step) skips 2/3 of the uniform draws; the
        draws are per scenario, the transforms batched."""
        idx = range(self.n) if rows is None else rows
        for i in idx:
            rng = self._rngs[i]
            rng.random(out=self._uniform[i], dtype=np.float32)
            rng.random(out=self._tests[i])
        self._find_redraws(rows)
        # stored as sigma sqrt(1 - eth^2) w, the term Eq. (gm) adds
        flat = self._gauss.reshape(self.n, 2, -1)
        if rows is None:
            gaussian_pairs(self._uniform, flat, self._noise_scale, self._gauss_scratch)
            self._cursor[:] = 0
        else:
            fresh = np.empty((len(rows),) + flat.shape[1:], dtype=np.float32)
            flat[rows] = gaussian_pairs(self._uniform[rows], fresh, self._noise_scale)
            self._cursor[rows] = 0

    def _find_redraws(self, rows: np.ndarray | None) -> None:
        """The v-bar re-draws of the fresh chunk of the scenarios `rows` (None: all), where the
        test draw is below the re-draw probability (rare: ~1% of the EDs per step), and their
        new v-bar values (drawn here, see _refill). Finding them once per refill, on the
        buffer's contiguous rows, is cheaper than testing an [N, V] slice of it every step."""
        mob = self.cfg.mobility
        tests = self._tests if rows is None else self._tests[rows]  # [N', chunk V]
        j, kv = np.divmod(np.flatnonzero(tests < mob.mean_resample_prob), tests.shape[1])  # (3-D nonzero: 10x slower)
        k, v = np.divmod(kv, self.cfg.n_eds)
        e = j if rows is None else rows[j]
        ev = e * self.cfg.n_eds + v
        raw = np.empty((len(e), 2))
        counts = np.bincount(j, minlength=len(tests))
        ends = np.cumsum(counts)
        for r in np.flatnonzero(counts):  # row r of tests: its re-draws are raw[ends - count : ends]
            rng = self._rngs[r if rows is None else rows[r]]
            rng.random(out=raw[ends[r] - counts[r] : ends[r]])
        low = -mob.v_max_mps
        new = low + (mob.v_max_mps - low) * raw.T  # Generator.uniform's formula
        if rows is not None:  # keep the other scenarios' re-draws
            other = np.ones(self.n, dtype=bool)
            other[rows] = False
            keep = other[self._redraws[0]]
            old = self._redraws
            e, k, ev = (np.concatenate((a[keep], b)) for a, b in zip(old[:3], (e, k, ev)))
            new = np.concatenate((old[3][:, keep], new), axis=1)
        self._redraws = (e, k, ev, new)

    @property
    def ed_xy(self) -> np.ndarray:
        """ED positions [N, V, 2] (a view: writing into it moves the EDs)."""
        return self._xy.transpose(1, 2, 0)

    @property
    def ed_vel(self) -> np.ndarray:
        """ED velocities [N, V, 2] (a view)."""
        return self._vel.transpose(1, 2, 0)

    @property
    def ed_mean_vel(self) -> np.ndarray:
        """ED mean velocities v-bar [N, V, 2] (a view)."""
        return self._mvel.transpose(1, 2, 0)

    # ------------------------------------------------------------------ dynamics
    def _clip_speed(self, vel: np.ndarray) -> np.ndarray:
        """vel [2, ...] scaled (in place) to speed <= v_max. (Dense: scaling only the ~12% of
        EDs above the limit, through flatnonzero and fancy indexing, measured 20% slower.)"""
        vmax = self.cfg.mobility.v_max_mps
        speed = np.multiply(vel[0], vel[0])
        speed += vel[1] * vel[1]
        np.sqrt(speed, out=speed)
        # min(v_max / speed, 1) as v_max / max(speed, v_max): exactly 1 at or below the limit,
        # one pass fewer, and no division by a zero speed
        physics.at_least(speed, vmax, out=speed)
        factor = np.divide(vmax, speed, out=speed)
        vel *= factor
        return vel

    def _move(self) -> None:
        self._xy, self._vel, self._mvel = self._advance(self._xy, self._vel, self._mvel, keep_mean=False)

    def _advance(
        self, xy: np.ndarray, vel: np.ndarray, mvel: np.ndarray, keep_mean: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. (gm) with SPEC.md's decisions: v-bar re-draw, speed clip, mirror reflection.
        (position, velocity, mean velocity) [2, N, V] -> the next slot's, as new arrays (the
        mean velocity is re-drawn in place when not `keep_mean`: nothing else holds it then)."""
        mob, area = self.cfg.mobility, self.cfg.area_m
        c = self._cursor
        k = self._cursor_same  # the common cursor of all scenarios, None after a partial reset
        if k is None:
            due = np.flatnonzero(c >= self._chunk)
            if due.size:
                self._refill(due)
            if (c == c[0]).all():
                k = self._cursor_same = int(c[0])
        elif k >= self._chunk:
            self._refill()
            k = 0
        re, rk, rev, new = self._redraws
        if k is not None:  # the usual case (no partial reset): views, no gather copies
            gauss = self._gauss[:, :, k]
            self._cursor_same = k + 1
            hit = np.flatnonzero(rk == k)
        else:
            gauss = self._gauss[self._env_idx, :, c]
            hit = np.flatnonzero(rk == c.take(re))
        if hit.size:  # the v-bar re-draws of this step (rare: written where they happen)
            if keep_mean:  # (the lookahead keeps every slot's array)
                mvel = mvel.copy()
            mvel.reshape(2, -1)[:, rev[hit]] = new[:, hit]
        c += 1
        eth = mob.memory
        # vel = eth v + (1 - eth) v-bar + sigma sqrt(1 - eth^2) w, in this order.
        vel = eth * vel
        vel += (1.0 - eth) * mvel
        vel += gauss.transpose(1, 0, 2)  # (already scaled, see _refill)
        vel = self._clip_speed(vel)
        pos = vel * mob.dt_s
        pos += xy
        out = pos < 0.0
        out |= pos > area
        i = np.flatnonzero(out)
        if i.size:  # mirror at the borders (few EDs: only theirs are touched)
            pos_f, vel_f = pos.reshape(-1), vel.reshape(-1)  # new C-contiguous arrays: views
            p = pos_f[i]
            p = np.where(p < 0.0, -p, 2.0 * area - p)
            np.minimum(p, area, out=p)  # guards a step longer than the area itself
            np.maximum(p, 0.0, out=p)
            pos_f[i] = p
            vel_f[i] = -vel_f[i]
        return pos, vel, mvel

    def _next_slot(self) -> None:
        """Move on to the next slot: positions, channels, association, observations."""
        if not self._lookahead:
            self._move()
            self._observe()
            return
        self._block_k += 1
        if self._block is None or self._block_k == self._block_len:
            self._compute_block()
            self._block_k = 0
        (serving, assoc, sidx, g, g_db, d_h, slot, counts, obs, all_assoc, xs, vs, ms) = self._block
        k = self._block_k
        row = slice(k, k + 1)
        self.serving, self.associated, self._serving_idx = serving[row], assoc[row], sidx[row]
        self.g_serving, self.g_db_serving, self.d_h_serving = g[row], g_db[row], d_h[row]
        self.slot_of_ed, self._counts, self.obs = slot[row], counts[row], obs[row]
        self._all_associated = all_assoc[k]
        self._xy, self._vel, self._mvel = xs[k], vs[k], ms[k]
        self._pairs = None

    def _compute_block(self) -> None:
        """The next slots (at most `lookahead`, and none past the end of the episode unless
        the episode is already over): mobility one slot at a time, the rest at once."""
        left = self.cfg.episode_len - int(self.t[0]) + 1  # slots t .. episode_len
        self._block_len = m = min(self._lookahead, left) if left > 0 else self._lookahead
        xy, vel, mvel = self._ahead
        xs, vs, ms = [], [], []
        for _ in range(m):  # the mobility recursion is sequential in time
            xy, vel, mvel = self._advance(xy, vel, mvel)
            xs.append(xy)
            vs.append(vel)
            ms.append(mvel)
        self._ahead = (xy, vel, mvel)
        ob = self._observer
        ob._xy = np.concatenate(xs + xs[-1:] * (self._lookahead - m), axis=1)  # [2, lookahead, V]: time as the batch axis
        ob._observe()
        self._block = (
            ob.serving, ob.associated, ob._serving_idx, ob.g_serving, ob.g_db_serving, ob.d_h_serving,
            ob.slot_of_ed, ob._counts, ob.obs, ob.associated.all(axis=-1).tolist(), xs, vs, ms,
        )  # fmt: skip

    def _observe(self) -> None:
        """Channels, association and the observations of the current slot."""
        self._pairs = None
        if self._nearest:
            self._observe_nearest()
        else:
            self._observe_pairs()
        self._all_associated = bool(self.associated.all())
        self._slots()
        self.obs = self._build_obs()

    def _observe_nearest(self) -> None:
        """Association and serving channels from the nearest UAV (see __init__)."""
        cfg = self.cfg
        near = nearest_uav_on_line(self._xy[0], self._spacing, cfg.n_uavs)
        d2 = physics.horizontal_distance_sq_to(self.ed_xy, self.uav_xy, near)
        d_h = np.sqrt(d2)
        self.serving, self._group_counts = greedy_from_nearest(
            near, d_h, cfg.comm_range_m, self.quota, cfg.n_uavs, lambda b: np.negative(d2[b]), self._pair_keys,
            return_counts=True,
        )  # fmt: skip
        self.associated = self.serving != UNASSOCIATED
        # Where a quota bound, some EDs are served by another UAV than their nearest one.
        moved = np.flatnonzero(self.serving != near)
        moved = moved[self.serving.reshape(-1)[moved] != UNASSOCIATED]
        if moved.size:
            u_moved = near.reshape(-1)[moved] = self.serving.reshape(-1)[moved]
            xy_moved = self._xy.reshape(2, -1)[:, moved].T  # [K, 2]
            d2_moved = physics.horizontal_distance_sq_to(xy_moved, self.uav_xy, u_moved)
            d2.reshape(-1)[moved] = d2_moved
            d_h.reshape(-1)[moved] = np.sqrt(d2_moved)
        self._serving_idx = near  # unassociated EDs: their nearest UAV (any valid index)
        self.g_serving, self.g_db_serving = physics.channel_gain_sq(d2, cfg, with_db=True, d_h=d_h)
        self.d_h_serving = d_h

    def _observe_pairs(self) -> None:
        """Association and serving channels from the channel of every UAV-ED pair."""
        cfg = self.cfg
        d_h, gains, gain_db = self._pair_channels()
        self.serving = associate(gains, d_h, cfg.comm_range_m, self.quota, cfg.association)
        self._group_counts = None
        self.associated = self.serving != UNASSOCIATED
        self._serving_idx = np.where(self.associated, self.serving, 0)
        flat = (self._flat_base + self._serving_idx * cfg.n_eds).reshape(-1)  # into [N, U, V]
        shape = self._serving_idx.shape
        self.d_h_serving = d_h.reshape(-1).take(flat).reshape(shape)
        self.g_serving = gains.reshape(-1).take(flat).reshape(shape)
        self.g_db_serving = gain_db.reshape(-1).take(flat).reshape(shape)

    def _pair_channels(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(d_h, G, G_dB) of every UAV-ED pair [N, U, V] of the current slot (cached)."""
        if self._pairs is None:
            d2 = physics.horizontal_distance_sq(self.ed_xy, self.uav_xy)
            gains, gain_db = physics.channel_gain_sq(d2, self.cfg, with_db=True)
            self._pairs = (np.sqrt(d2, out=d2), gains, gain_db)
        return self._pairs

    def _pair_keys(self, e: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(-d_h^2, d_h) [K, U] of the EDs (e[k], v[k]) to every UAV: the keys greedy_from_nearest
        asks for where a quota binds (with -d_h^2 at the nearest UAV, see _observe_nearest).
        -d_h^2 orders the pairs as their gains do (G strictly decreases with d_h here), which is
        all the greedy matching looks at: no transcendental needed. (Same operations as the
        d_h^2 of the nearest UAV's channel, element by element.)"""
        d2 = physics.horizontal_distance_sq(self._xy[:, e, v].T, self.uav_xy).T  # [K, U]
        return np.negative(d2), np.sqrt(d2)

    @property
    def d_h(self) -> np.ndarray:
        """Horizontal distance of every UAV-ED pair [N, U, V] (current slot)."""
        return self._pair_channels()[0]

    @property
    def gains(self) -> np.ndarray:
        """Linear channel gain of every UAV-ED pair [N, U, V] (current slot)."""
        return self._pair_channels()[1]

    @property
    def gain_db(self) -> np.ndarray:
        """Channel gain in dB of every UAV-ED pair [N, U, V] (current slot)."""
        return self._pair_channels()[2]

    def _slots(self) -> None:
        """slot_of_ed [N, V]: rank of each served ED by gain among its UAV's EDs (ties by ED id;
        -1 if unassociated), and the served counts [N, U]. The EDs are sorted by (serving UAV,
        descending gain, ED id): each UAV's EDs form a run in gain order, and an ED's slot is its
        position minus the start of its UAV's run (an exclusive cumulative sum of the counts)."""
        n, v, u = self.n, self.cfg.n_eds, self.cfg.n_uavs
        grp = self._serving_idx if self._all_associated else np.where(self.associated, self._serving_idx, u)
        # EDs by (serving UAV, descending gain, ED id): each UAV's EDs form a run in gain order
        order, grouped = group_sort(self.g_serving, grp, u + 1, descending=True)
        order += self._row_base  # flat indices into [N, V]
        grouped += self._grp_base
        counts = self._group_counts  # [N, U + 1], last: unassociated (from the association, or:)
        if counts is None:
            counts = np.bincount(grouped.reshape(-1), minlength=n * (u + 1)).reshape(n, u + 1)
        start = np.cumsum(counts, axis=-1)
        start -= counts
        slot = self._positions - start.reshape(-1).take(grouped)
        if not self._all_associated:
            slot[grouped - self._grp_base == u] = -1
        slot_of_ed = np.empty((n, v), dtype=np.int64)
        slot_of_ed.reshape(-1)[order] = slot
        self.slot_of_ed = slot_of_ed
        self._counts = counts[:, :u]

    def _gain_feature(self, gain_db: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        x = np.subtract(gain_db, self._gain_db_mid, out=out)
        return np.divide(x, self._gain_db_half, out=x)

    def _build_obs(self) -> np.ndarray:
        cfg, n, q, n_u = self.cfg, self.n, self.quota, self.cfg.n_uavs
        q1 = q + 1
        # Row of ED v: (e U + u) (quota + 1) + slot; unassociated EDs: the scratch row. A row is
        # two complex64 (8-byte) pairs of float32, (x, y) and (d, G), each written by one flat
        # scatter from a contiguous array (half the scatters of one per feature; NumPy's loops
        # over a trailing axis of 2 or 4 are slow).
        start = self.slot_of_ed * (OBS_ROW // 2)  # complex64 index of the row's (x, y) pair
        start += self._serving_idx * (q1 * OBS_ROW // 2)
        start += self._obs_rows_base
        if not self._all_associated:
            start = np.where(self.associated, start, self._obs_garbage)
        # np.zeros, not a copy of a template: a buffer of this size comes zeroed from the OS
        # (calloc), so this skips reading and copying one (0.05-0.5 ms of ~10 per step at
        # V=100/U=8/N=1024 in A/B runs); the extras are written below.
        buf = np.zeros(self._obs_buf_shape, dtype=np.float32)
        pairs = buf.reshape(-1).view(np.complex64)
        if self._obs_scratch is None or self._obs_scratch[0].shape != start.shape:
            self._obs_scratch = (np.empty(start.shape, np.complex128), np.empty(start.shape, np.complex64))
        # (private, overwritten every step: no fresh 1.6 MB per step). Features are computed
        # in float64 and rounded once to float32 (the same values as casting a float64 obs).
        val, val32 = self._obs_scratch
        for k, part in enumerate((val.real, val.imag)):  # x, y -> 2 p / L - 1
            np.multiply(self._xy[k], 2.0 / cfg.area_m, out=part)
            part -= 1.0
        np.copyto(val32, val, casting="same_kind")
        pairs[start] = val32
        np.divide(self.d_h_serving, cfg.comm_range_m, out=val.real)
        self._gain_feature(self.g_db_serving, out=val.imag)
        np.copyto(val32, val, casting="same_kind")
        start += 1
        pairs[start] = val32
        obs = buf[:-1].reshape(n, n_u, q1 * OBS_ROW)
        np.divide(self._counts, q, out=obs[..., q * OBS_ROW])
        obs[..., q * OBS_ROW + 1 : q * OBS_ROW + OBS_EXTRA] = self._obs_extra_xy
        return obs[..., : q * OBS_ROW + OBS_EXTRA]

    # ------------------------------------------------------------------ actions
    def allocations(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-ED (sf_idx, tp_idx, bw_idx) [N, V] implied by the agents' actions this slot."""
        cfg = self.cfg
        actions = np.asarray(actions)
        if cfg.action_mode == "per_uav":
            self._check_range(actions, (self.n, cfg.n_uavs), self._n_joint)
            idx = self._serving_idx + self._act_base  # flat index of each ED's serving UAV in [N, U]
            if idx.size <= PER_UAV_GATHER_MIN:  # small: one lookup in the decoding table
                alloc = self._decode[actions.reshape(-1).take(idx)]  # [N, V, 3]
                return alloc[..., 0], alloc[..., 1], alloc[..., 2]
            sf, tp, bw = decode_joint_action(actions, cfg)  # [N, U] each, then 3 contiguous gathers
            return sf.reshape(-1).take(idx), tp.reshape(-1).take(idx), bw.reshape(-1).take(idx)
        length = per_device_action_len(cfg)
        highs = np.array([cfg.n_sf, cfg.n_tp] * self.quota + [cfg.n_bw])
        self._check_range(actions, (self.n, cfg.n_uavs, length), highs)
        slot = np.maximum(self.slot_of_ed, 0)
        per_uav = actions[self._env_idx[:, None], self._serving_idx]  # [N, V, length]
        sf = np.take_along_axis(per_uav, (2 * slot)[..., None], axis=-1)[..., 0]
        tp = np.take_along_axis(per_uav, (2 * slot + 1)[..., None], axis=-1)[..., 0]
        return sf, tp, per_uav[..., -1]

    def _check_range(self, actions: np.ndarray, shape: tuple[int, ...], high) -> None:
        if actions.shape != shape:
            raise ActionError(f"actions: expected shape {shape}, got {actions.shape}")
        if actions.dtype.kind not in "iu":  # signed or unsigned integers
            raise ActionError(f"actions: expected integers, got dtype {actions.dtype}")
        if np.isscalar(high) and actions.size:
            if actions.size <= 64:  # small: Python's min/max on a list beat two NumPy reductions
                values = actions.ravel().tolist()
                if 0 <= min(values) and max(values) < high:
                    return
            elif 0 <= actions.min() and actions.max() < high:
                return
        bad = (actions < 0) | (actions >= high)
        if bad.any():
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            limit = high if np.isscalar(high) else int(np.broadcast_to(high, shape)[idx])
            raise ActionError(
                f"action of uav_{idx[1]} (scenario {idx[0]}): {int(actions[idx])} is outside [0, {limit})"
            )

    # ------------------------------------------------------------------ step
    def _per_uav_values(self, actions: np.ndarray) -> tuple[np.ndarray, tuple, tuple]:
        """per_uav mode, large batches: each ED's SF index and (P_W, W_Hz, rho_thr) gathered
        from its serving UAV's values ([N, U]: U table look-ups per scenario instead of V),
        and (actions, flat serving-UAV index), from which prev_alloc gets the TP and BW
        indices when it is read."""
        cfg = self.cfg
        actions = np.asarray(actions)
        self._check_range(actions, (self.n, cfg.n_uavs), self._n_joint)
        idx = self._serving_idx + self._act_base  # flat index of each ED's serving UAV in [N, U]
        sf, *values = (table.take(actions).reshape(-1).take(idx) for table in self._action_values)
        return sf, tuple(values), (actions.copy(), idx)  # (a copy: the caller may reuse its array)

    def step(self, actions: np.ndarray) -> StepResult:
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        metrics, self._prev_parts = self._score_shared(actions) if self._shared else self._score(actions)
        self.t += 1
        self._next_slot()
        return StepResult(self.obs, metrics["reward"], self.t >= self.cfg.episode_len, metrics)

    def _score(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], tuple]:
        """The current slot's metrics under `actions` (physics.slot_metrics), and the parts
        prev_alloc is built from."""
        gains = None if self._nearest else self.gains
        if self.cfg.action_mode == "per_uav" and self._serving_idx.size > PER_UAV_GATHER_MIN:
            sf, values, actions_idx = self._per_uav_values(actions)
            tp = bw = None
        else:
            sf, tp, bw = self.allocations(actions)
            values = actions_idx = None
        metrics = physics.slot_metrics(
            gains, self._serving_idx, self.associated, sf, tp, bw, self.cfg, self.tables, g_serving=self.g_serving,
            values=values,
        )  # fmt: skip
        return metrics, (sf, tp, bw, actions_idx, None if self._all_associated else self.associated)

    def _score_shared(self, actions: np.ndarray) -> tuple[dict[str, np.ndarray], tuple]:
        """_score in the per_uav mode with the paper's interference and the Shannon rate
        (physics.slot_metrics_shared); prev_alloc decodes the actions only when read."""
        cfg = self.cfg
        actions = np.asarray(actions)
        self._check_range(actions, (self.n, cfg.n_uavs), self._n_joint)
        idx = self._serving_idx + self._act_base  # flat index of each ED's serving UAV in [N, U]
        metrics = physics.slot_metrics_shared(
            self.g_serving, self.g_db_serving, idx, self.associated, self._counts, self._action_alloc.take(actions),
            cfg, self.tables,
        )  # fmt: skip
        # (a copy of the actions: the caller may reuse its array)
        return metrics, (None, None, None, (actions.copy(), idx), None if self._all_associated else self.associated)

    @property
    def prev_alloc(self) -> np.ndarray:
        """Each ED's (sf_idx, tp_idx, bw_idx) in the slot just played [N, V, 3]; -1 where it was
        silent or no slot was played since the reset (built on first access)."""
        if self._prev_parts is not None:
            sf, tp, bw, actions_idx, assoc = self._prev_parts
            if tp is None:  # per_uav: decoded from the actions only now
                actions, idx = actions_idx
                sf_u, tp_u, bw_u = decode_joint_action(actions, self.cfg)
                tp, bw = tp_u.reshape(-1).take(idx), bw_u.reshape(-1).take(idx)
                if sf is None:
                    sf = sf_u.reshape(-1).take(idx)
            prev = np.stack((sf, tp, bw), axis=-1)
            if assoc is not None:
                prev[~assoc] = -1
            self._prev_alloc, self._prev_parts = prev, None
        return self._prev_alloc

    # ------------------------------------------------------------------ global state
    def state(self) -> np.ndarray:
        cfg, n = self.cfg, self.n
        pos = 2.0 * self.ed_xy / cfg.area_m - 1.0
        gains = np.clip(self._gain_feature(self.gain_db), -3.0, 1.0)
        assoc = np.zeros((n, cfg.n_eds, cfg.n_uavs + 1))
        np.put_along_axis(assoc, np.where(self.associated, self.serving, cfg.n_uavs)[..., None], 1.0, axis=-1)
        sizes = (cfg.n_sf, cfg.n_tp, cfg.n_bw)
        prev = [
            (self.prev_alloc[..., k, None] == np.arange(size)).astype(np.float64) for k, size in enumerate(sizes)
        ]
        t = (self.t / cfg.episode_len)[:, None]
        return np.concatenate(
            [pos.reshape(n, -1), gains.reshape(n, -1), assoc.reshape(n, -1), *(p.reshape(n, -1) for p in prev), t],
            axis=-1,
        )
