"""The simulator core: N independent scenarios stepped at once with NumPy.

A step, top to bottom (`BatchCore.step`), each stage in its own module:
  1. score the current slot: the agents' actions on the slot's links -> metrics and the
     shared reward (`scoring`, with the action checks and decoding of `actions`);
  2. move the EDs one slot (`mobility`: Gauss-Markov, Eq. (gm), per-scenario random stream);
  3. link them for the next slot: channel, association and each served ED's row (`links`);
  4. observe the next slot: each UAV's observation (`observation`; the global state on request).
`reset` draws new scenarios (`mobility`) and does 3 and 4 for slot 0. After `episode_len`
steps an episode is truncated (never terminated).

Arrays are shaped [N, ...]: EDs [N, V, 2] (stored as [2, N, V]), channels [N, U, V], actions
[N, U] (per_uav) or [N, U, 2 quota + 1] (per_device). No Python loop runs over EDs or UAVs in a
step; the only per-scenario loop refills the random-number buffers every NOISE_CHUNK steps, so
that scenario i of a batch seeded s replays the single scenario seeded s + i bit for bit.

Since actions change neither mobility nor the links (docs/model.md), a single scenario can
compute stages 3 and 4 of `lookahead` future slots at once, with time as the batch axis; a
step then only scores (`BatchCore(cfg, 1, lookahead=K)`, used by the env views; the same
numbers as stepping slot by slot).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import ActionDecoder
from uavlora_rllib.sim.links import Links, LinkStage, default_link_stage, pair_channels
from uavlora_rllib.sim.mobility import GaussMarkovMobility
from uavlora_rllib.sim.observation import Observer, obs_dim, state_dim
from uavlora_rllib.sim.scenario import MAX_ENVS, ScenarioConfig
from uavlora_rllib.sim.scoring import SlotScorer

Seed = int | np.random.SeedSequence | None  # one scenario's seed (None: from the unseeded stream)


def check_seed(seed: Any, name: str = "seed") -> int | None:
    """A reset seed as a non-negative int or None; ConfigError naming `name` otherwise (NumPy's own message,
    'expected non-negative integer', names no field). No upper bound: SeedSequence takes any size, and the
    evaluation's seeds (EVAL_SEED_BASE + seed x 10,000 + k) pass 2^32 for a grid's large seeds."""
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"{name}: expected a non-negative integer or None, got {seed!r}")
    return int(seed)


def check_n_envs(n_envs: Any, name: str = "n_envs") -> int:
    """A scenario count as an int in [1, MAX_ENVS]; ConfigError naming `name` otherwise."""
    if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or not 1 <= n_envs <= MAX_ENVS:
        raise ConfigError(f"{name}: expected an integer in [1, {MAX_ENVS}], got {n_envs!r}")
    return int(n_envs)


@dataclass
class StepResult:
    obs: np.ndarray  # [N, U, obs_dim] observation of the next slot
    reward: np.ndarray  # [N] shared reward of the slot just played
    truncated: np.ndarray  # [N] bool
    metrics: dict[str, np.ndarray]  # physics.SLOT_METRICS, each [N]


class BatchCore:
    """N independent copies of the scenario, stepped together.

    `link_stage`: the link stage's factory, (cfg, n) -> stage (sim.links; by default the fastest
    exact one for the scenario). The current slot: `links` (sim.links.Links), `obs`, `t`; the ED
    state through `ed_xy`, `ed_vel`, `ed_mean_vel` (views: writing into `ed_xy` moves the EDs,
    then `observe()` re-derives the slot)."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        n_envs: int = 1,
        lookahead: int = 0,
        link_stage: Callable[[ScenarioConfig, int], LinkStage] = default_link_stage,
    ):
        n_envs = check_n_envs(n_envs)
        if lookahead < 0 or (lookahead and n_envs != 1):
            raise ValueError(f"lookahead: must be 0, or >= 1 with n_envs = 1; got {lookahead} with n_envs = {n_envs}")
        self.cfg = cfg
        self.n = n_envs
        self.tables = physics.Tables.from_config(cfg)
        self.uav_xy = physics.uav_positions(cfg)
        self.quota = cfg.quota
        self.obs_dim = obs_dim(cfg)
        self.state_dim = state_dim(cfg)
        self.t = np.zeros(n_envs, dtype=np.int64)
        # the stages
        self.mobility = GaussMarkovMobility(cfg, n_envs)
        self.link_stage = link_stage(cfg, n_envs)
        self.observer = Observer(cfg, n_envs)
        self.decoder = ActionDecoder(cfg, n_envs, self.tables)
        self.scorer = SlotScorer(cfg, self.decoder, self.tables)
        # every pair's gain for the scoring: only the all-pairs models read it
        self._score_needs_gains = self.link_stage.all_pairs and not self.scorer.shared
        self.links: Links = None  # type: ignore[assignment]  # set by reset()
        self.obs: np.ndarray = None  # type: ignore[assignment]  # set by reset()
        self._prev_alloc = np.full((n_envs, cfg.n_eds, 3), -1, dtype=np.int64)
        self._prev_parts: tuple | None = None  # what the scoring kept of the slot just played
        self._seed_source = np.random.SeedSequence()
        self._ready = False
        # Lookahead (single scenario): stages 3 and 4 for the next `lookahead` slots at once,
        # with their own stages whose batch axis is time: _block = (links, whether all EDs are
        # associated, observations, mobility states), each entry k being slot k of the block.
        self._lookahead = lookahead
        if lookahead:
            self._ahead_links = link_stage(cfg, lookahead)
            self._ahead_observer = Observer(cfg, lookahead)
        self._block: tuple[Any, ...] | None = None
        self._block_k = 0

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | Sequence[Seed] | None = None, mask: np.ndarray | None = None) -> np.ndarray:
        """Start new episodes. `seed` int s -> scenario i gets s + i; a sequence gives one seed
        per scenario; None continues the stream of the last integer seed (fresh entropy before
        any). `mask` [N] bool resets only those scenarios."""
        mask = np.ones(self.n, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if not self._ready and not mask.all():
            raise ValueError("the first reset must reset every scenario (mask=None)")
        self.mobility.reset(mask, self._seeds_for(seed))
        self.t[mask] = 0
        self.prev_alloc[mask] = -1  # (materialises the previous slot's, then clears the reset ones)
        self._ready = True
        self.observe()
        if self._lookahead and mask.all():
            mob = self.mobility
            self._ahead = (mob.xy, mob.vel, mob.mvel)  # mobility state of the latest slot computed
            self._block = None
        return self.obs

    def _seeds_for(self, seed: int | Sequence[Seed] | None) -> list:
        """Each scenario's seed. An integer seed s also restarts the stream of the unseeded resets
        that follow (children spawned from SeedSequence(s), as the team vector env's autoresets
        are): Gymnasium's contract that reset() after reset(seed=s) continues the seeded stream
        (docs/model.md#seeds)."""
        if seed is None:
            return [s for s in self._seed_source.spawn(self.n)]
        if isinstance(seed, np.ndarray) or (isinstance(seed, Sequence) and not isinstance(seed, str)):
            seeds = list(seed)
            if len(seeds) != self.n:
                raise ValueError(f"seed: expected {self.n} seeds, got {len(seeds)}")
            spawn = self._seed_source.spawn
            return [
                spawn(1)[0] if s is None else s if isinstance(s, np.random.SeedSequence) else check_seed(s)
                for s in seeds
            ]
        start = check_seed(seed)  # one seed for all: scenario i gets seed + i
        assert start is not None  # (None was answered above)
        self._seed_source = np.random.SeedSequence(start)
        return [start + i for i in range(self.n)]

    # ------------------------------------------------------------------ step
    def step(self, actions: np.ndarray) -> StepResult:
        """Play the current slot with `actions` ([N, U] per_uav, [N, U, 2 quota + 1] per_device;
        ActionError outside the space) and move on to the next one."""
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        gains = self.gains if self._score_needs_gains else None
        metrics, self._prev_parts = self.scorer.score(actions, self.links, gains)  # 1. score
        self.t += 1
        self._next_slot()  # 2.-4. move, link, observe
        return StepResult(self.obs, metrics["reward"], self.t >= self.cfg.episode_len, metrics)

    def _next_slot(self) -> None:
        """Move on to the next slot: positions, links, observations."""
        if not self._lookahead:
            self.mobility.move()
            self.observe()
            return
        self._block_k += 1
        if self._block is None or self._block_k == len(self._block[3]):
            self._compute_block()
            self._block_k = 0
        assert self._block is not None  # (computed just above)
        k, (links, every, obs, states) = self._block_k, self._block
        self.links, self.obs = links.row(k, every[k]), obs[k : k + 1]
        mob = self.mobility
        mob.xy, mob.vel, mob.mvel = states[k]

    def observe(self) -> None:
        """Link and observe the current slot from the ED positions (reset and step do; call it
        after moving EDs through the `ed_xy` view)."""
        xy = self.mobility.xy
        self.links = self.link_stage(xy)
        self.obs = self.observer.observe(self.links, xy)

    def _compute_block(self) -> None:
        """The next slots (at most `lookahead`, and none past the end of the episode unless
        the episode is already over): mobility one slot at a time, links and observations at
        once, for the slots as a batch."""
        left = self.cfg.episode_len - int(self.t[0]) + 1  # slots t .. episode_len
        m = min(self._lookahead, left) if left > 0 else self._lookahead
        xy, vel, mvel = self._ahead
        states = []
        for _ in range(m):  # the mobility recursion is sequential in time
            xy, vel, mvel = self.mobility.advance(xy, vel, mvel)
            states.append((xy, vel, mvel))
        self._ahead = (xy, vel, mvel)
        xs = [s[0] for s in states]
        block_xy = np.concatenate(xs + xs[-1:] * (self._lookahead - m), axis=1)  # [2, lookahead, V]
        links = self._ahead_links(block_xy)
        obs = self._ahead_observer.observe(links, block_xy)
        self._block = (links, links.associated[:m].all(axis=-1).tolist(), obs, states)

    # ------------------------------------------------------------------ actions
    def allocations(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-ED (sf_idx, tp_idx, bw_idx) [N, V] implied by the agents' actions this slot."""
        return self.decoder.allocations(actions, self.links)

    @property
    def prev_alloc(self) -> np.ndarray:
        """Each ED's (sf_idx, tp_idx, bw_idx) in the slot just played [N, V, 3]; -1 where it was
        silent or no slot was played since the reset (built on first access)."""
        if self._prev_parts is not None:
            self._prev_alloc, self._prev_parts = self.decoder.previous_allocation(self._prev_parts), None
        return self._prev_alloc

    # ------------------------------------------------------------------ the current slot
    @property
    def ed_xy(self) -> np.ndarray:
        """ED positions [N, V, 2] (a view: writing into it moves the EDs)."""
        return self.mobility.xy.transpose(1, 2, 0)

    @property
    def ed_vel(self) -> np.ndarray:
        """ED velocities [N, V, 2] (a view)."""
        return self.mobility.vel.transpose(1, 2, 0)

    @property
    def ed_mean_vel(self) -> np.ndarray:
        """ED mean velocities v-bar [N, V, 2] (a view)."""
        return self.mobility.mvel.transpose(1, 2, 0)

    @property
    def serving(self) -> np.ndarray:
        """Each ED's serving UAV [N, V], UNASSOCIATED (-1) where none."""
        return self.links.serving

    @property
    def associated(self) -> np.ndarray:
        """serving != UNASSOCIATED [N, V]."""
        return self.links.associated

    @property
    def slot_of_ed(self) -> np.ndarray:
        """Each served ED's rank by gain among its UAV's EDs [N, V], -1 if unassociated."""
        return self.links.slot_of_ed

    @property
    def g_serving(self) -> np.ndarray:
        """Each ED's linear channel gain at its serving UAV [N, V] (nearest UAV if unassociated)."""
        return self.links.g_serving

    def _pair_channels(self) -> tuple[np.ndarray, ...]:
        """(d_h, G, G_dB) of every UAV-ED pair [N, U, V] of the current slot (computed once)."""
        links = self.links
        if links.pairs is None:
            links.pairs = pair_channels(self.ed_xy, self.uav_xy, self.cfg)
        return links.pairs

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

    def state(self) -> np.ndarray:
        """The global state [N, state_dim] of the current slot (critics and mixers)."""
        return self.observer.global_state(self.ed_xy, self.gain_db, self.links, self.prev_alloc, self.t)
