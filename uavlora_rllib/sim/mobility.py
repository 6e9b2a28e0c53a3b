"""ED mobility: the Gauss-Markov model of Eq. (gm) for N scenarios at once, and its random stream.

docs/model.md fixes the model: per ED and slot
  v <- eta v + (1 - eta) v-bar + sigma sqrt(1 - eta^2) w,  w ~ N(0, I_2),
then the speed is clipped to v_max, the ED moves by v dt and is mirrored back at the area's
borders; v-bar is re-drawn uniformly in [-v_max, v_max]^2 with probability `mean_resample_prob`
per ED and slot.

Each scenario owns a random-number generator (`scenario_rng`), so that scenario i of a batch
seeded s replays the single scenario seeded s + i bit for bit (as in Gymnasium's vector envs).
The noise is drawn per scenario every NOISE_CHUNK slots (the only per-scenario loop of a step)
and transformed for the whole batch at once (`gaussian_pairs`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.scenario import ScenarioConfig

NOISE_CHUNK = 32  # steps of mobility noise drawn per refill


def scenario_rng(seed: Any = None) -> np.random.Generator:
    """The random-number generator of one scenario: NumPy's SFC64 bit generator (seeded
    through a SeedSequence, like default_rng). It draws the mobility noise's uniforms (see
    gaussian_pairs) and the v-bar re-draws: cheaper per uniform than default_rng's PCG64
    (results: docs/history/benchmarks-2026.md#simulator-profile-optimisations-and-the-targets)."""
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


def clip_speed(vel: np.ndarray, v_max: float) -> np.ndarray:
    """vel [2, ...] scaled (in place) to speed <= v_max. (Dense: scaling only the EDs above
    the limit, through flatnonzero and fancy indexing, is slower.)"""
    speed = np.multiply(vel[0], vel[0])
    speed += vel[1] * vel[1]
    np.sqrt(speed, out=speed)
    # min(v_max / speed, 1) as v_max / max(speed, v_max): exactly 1 at or below the limit,
    # one pass fewer, and no division by a zero speed
    physics.at_least(speed, v_max, out=speed)
    factor = np.divide(v_max, speed, out=speed)
    vel *= factor
    return vel


class GaussMarkovMobility:
    """The mobility state of N scenarios and the random stream that drives it.

    State, stored by coordinate ([2, N, V]: NumPy's loops over a trailing axis of 2 are slow):
    `xy` positions, `vel` velocities, `mvel` mean velocities v-bar. `move()` advances it one
    slot; `advance()` computes the next slot's state from any given one without touching
    `xy`/`vel` (the single-scenario lookahead steps several slots ahead with it)."""

    def __init__(self, cfg: ScenarioConfig, n_envs: int):
        self.cfg = cfg
        self.n = n_envs
        v = cfg.n_eds
        self.xy = np.zeros((2, n_envs, v))
        self.vel = np.zeros((2, n_envs, v))
        self.mvel = np.zeros((2, n_envs, v))
        self._rngs: list[np.random.Generator] = [scenario_rng() for _ in range(n_envs)]
        self._chunk = chunk = NOISE_CHUNK
        # Per scenario, (x, y) and step: the noise of every ED, and the float32 uniforms it is
        # made of (gaussian_pairs; computed in the scratch arrays)
        self.gauss = np.zeros((n_envs, 2, chunk, v), dtype=np.float32)  # (float32: as computed)
        self._uniform = np.zeros((n_envs, 2, chunk * v), dtype=np.float32)
        self._gauss_scratch = tuple(np.zeros((n_envs, chunk * v), dtype=np.float32) for _ in range(3))
        self._tests = np.zeros((n_envs, chunk * v))  # per (step, ED): uniform [0, 1) v-bar re-draw test
        # The re-draws those imply, found once per refill (see _refill): scenario, step in the
        # chunk and flat [N, V] index of each, and the new v-bar there [2, K].
        none = np.zeros(0, dtype=np.int64)
        self._redraws: tuple[np.ndarray, ...] = (none, none, none, np.zeros((2, 0)))
        self._cursor = np.zeros(n_envs, dtype=np.int64)
        self._cursor_same: int | None = 0  # the cursor of every scenario while they agree
        # the scale of the noise term, sigma sqrt(1 - eta^2): `gauss` holds it applied
        self.noise_scale = cfg.mobility.sigma * float(np.sqrt(1.0 - cfg.mobility.memory**2))
        self._env_idx = np.arange(n_envs)

    def reset(self, mask: np.ndarray, seeds: list) -> None:
        """New episodes for the scenarios of `mask` [N] bool: each gets a fresh generator from
        its seed, uniform positions in the area and velocities in [-v_max, v_max]^2 (then
        clipped), the initial v-bar, and the first chunk of noise."""
        cfg, mob = self.cfg, self.cfg.mobility
        xy, vel = self.xy.transpose(1, 2, 0), self.vel.transpose(1, 2, 0)  # [N, V, 2] views
        for i in np.flatnonzero(mask):  # per-scenario RNG draws only; no physics here
            rng = scenario_rng(seeds[i])
            self._rngs[i] = rng
            xy[i] = rng.uniform(0.0, cfg.area_m, size=(cfg.n_eds, 2))
            vel[i] = rng.uniform(-mob.v_max_mps, mob.v_max_mps, size=(cfg.n_eds, 2))
        self._refill(None if mask.all() else np.flatnonzero(mask))
        self.vel[:, mask] = clip_speed(self.vel[:, mask], mob.v_max_mps)
        self.mvel[:, mask] = mob.mean_velocity_init_mps
        self._cursor_same = 0 if mask.all() else None

    def move(self) -> None:
        """Advance the state one slot."""
        self.xy, self.vel, self.mvel = self.advance(self.xy, self.vel, self.mvel, keep_mean=False)

    def advance(
        self, xy: np.ndarray, vel: np.ndarray, mvel: np.ndarray, keep_mean: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Eq. (gm) with docs/model.md's decisions: v-bar re-draw, speed clip, mirror reflection.
        (position, velocity, mean velocity) [2, N, V] -> the next slot's, as new arrays (the
        mean velocity is re-drawn in place when not `keep_mean`: nothing else holds it then).
        Consumes one slot of each scenario's noise."""
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
            gauss = self.gauss[:, :, k]
            self._cursor_same = k + 1
            hit = np.flatnonzero(rk == k)
        else:
            gauss = self.gauss[self._env_idx, :, c]
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
        vel = clip_speed(vel, mob.v_max_mps)
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

    def _refill(self, rows: np.ndarray | None = None) -> None:
        """The next NOISE_CHUNK steps of noise for the scenarios `rows` (indices; None: all).

        Per scenario the stream is: random(2, chunk v) in float32 (u0, u1 of `gaussian_pairs`:
        the Gauss-Markov noise of each (step, ED), x and y), random(chunk, v) (the v-bar re-draw
        tests), then, for the K re-draws those tests imply, random(K, 2) (their new v-bar, (x, y)
        in (step, ED) order, mapped to [-v_max, v_max) as Generator.uniform does). Drawing the
        new v-bar values only where a re-draw happens (~1% of the EDs per step) skips 2/3 of the
        uniform draws; the draws are per scenario, the transforms batched."""
        idx = range(self.n) if rows is None else rows
        for i in idx:
            rng = self._rngs[i]
            rng.random(out=self._uniform[i], dtype=np.float32)
            rng.random(out=self._tests[i])
        self._find_redraws(rows)
        # stored as sigma sqrt(1 - eth^2) w, the term Eq. (gm) adds
        flat = self.gauss.reshape(self.n, 2, -1)
        if rows is None:
            gaussian_pairs(self._uniform, flat, self.noise_scale, self._gauss_scratch)
            self._cursor[:] = 0
        else:
            fresh = np.empty((len(rows),) + flat.shape[1:], dtype=np.float32)
            flat[rows] = gaussian_pairs(self._uniform[rows], fresh, self.noise_scale)
            self._cursor[rows] = 0

    def _find_redraws(self, rows: np.ndarray | None) -> None:
        """The v-bar re-draws of the fresh chunk of the scenarios `rows` (None: all), where the
        test draw is below the re-draw probability (rare: ~1% of the EDs per step), and their
        new v-bar values (drawn here, see _refill). Finding them once per refill, on the
        buffer's contiguous rows, is cheaper than testing an [N, V] slice of it every step."""
        mob = self.cfg.mobility
        tests = self._tests if rows is None else self._tests[rows]  # [N', chunk V]
        j, kv = np.divmod(np.flatnonzero(tests < mob.mean_resample_prob), tests.shape[1])  # (a 3-D nonzero is slower)
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
