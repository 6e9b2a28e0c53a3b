"""Trajectory fingerprints of the simulator core, compared with a tolerance so that they hold
on any CPU: 120 steps of several layouts (the paper's V=10/U=2 and V=100/U=8, both action
modes, the all-pairs channel path, binding quotas, the large-batch per_uav scoring path, the
single-env lookahead), with truncations and partial resets.

Every array a step exposes is reduced to two float64 numbers, S = sum(w x) and A = sum(w |x|),
with fixed positive pseudo-random weights w (a permutation or a changed entry moves S), and
checked against tests/data/sim_regression.npz as |S - S0| <= RTOL A0. NumPy's float32 SIMD
kernels (log/sin/cos in the Box-Muller noise) differ between instruction sets and CPU vendors
by a few ulp (~1e-7 relative); RTOL = 1e-5 sits two orders above that and an order below
what a 1e-4 relative change of one physics constant moves (the last tests below show both).

A change that alters trajectories on purpose (a new random stream, a model fix) re-records the
file with `python tests/test_sim_regression.py --record` and says so in its commit.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # conftest's helpers when run as a script

from conftest import make_cfg, random_actions  # noqa: E402

from uavlora_rllib.sim.core import BatchCore  # noqa: E402
from uavlora_rllib.sim.scenario import ScenarioConfig  # noqa: E402

GOLDEN = Path(__file__).resolve().parent / "data" / "sim_regression.npz"
RTOL = 1e-5
STEPS = 120
# name -> (scenario fields, N, lookahead). episode_len 50: every layout crosses truncations
# (and the lookahead its episode-end blocks) within the 120 steps.
LAYOUTS: dict[str, tuple[dict, int, int]] = {
    "v10u2_per_uav": ({}, 4, 0),
    "v10u2_per_device": ({"action_mode": "per_device"}, 4, 0),
    "v100u8_per_uav": ({"n_eds": 100, "n_uavs": 8}, 3, 0),
    "v100u8_per_device": ({"n_eds": 100, "n_uavs": 8, "action_mode": "per_device"}, 2, 0),
    # N V > PER_UAV_GATHER_MIN and a rate model without the shared factoring: the gathered path
    "v100u8_per_uav_lora_phy_n48": ({"n_eds": 100, "n_uavs": 8, "rate_model": "lora_phy"}, 48, 0),
    "quota_binding": ({"n_eds": 30, "max_eds_per_uav": 4, "comm_range_m": 300.0}, 3, 0),
    "all_pairs_optimal": ({"association": "optimal", "interference": "cross_gain", "n_eds": 12, "n_uavs": 3}, 2, 0),
    "lookahead_v10u2_per_uav": ({}, 1, 32),
    "lookahead_v100u8_per_device": ({"n_eds": 100, "n_uavs": 8, "action_mode": "per_device"}, 1, 32),
}


class Fingerprint:
    """Per array fed: a label (step, name, dtype, shape), checked exactly, and (S, A)."""

    def __init__(self) -> None:
        self.labels: list[str] = []
        self.sums: list[tuple[float, float]] = []
        self._weights: dict[int, np.ndarray] = {}

    def _w(self, size: int) -> np.ndarray:
        if size not in self._weights:  # fixed stream, independent of the simulator's
            self._weights[size] = np.random.default_rng(size).uniform(0.5, 1.5, size)
        return self._weights[size]

    def feed(self, step: int, **arrays) -> None:
        for name, a in arrays.items():
            a = np.asarray(a)
            x = a.astype(np.float64).ravel()
            if not np.isfinite(x).all():  # inf/nan would make S meaningless: record where
                x = np.where(np.isfinite(x), x, 0.0) + np.isnan(x) * 7.0 + np.isposinf(x) * 11.0 - np.isneginf(x) * 13.0
            w = self._w(x.size)
            self.labels.append(f"{step}:{name}:{a.dtype.str}{a.shape}")
            self.sums.append((float(w @ x), float(w @ np.abs(x))))


def trajectory(fields: dict, n: int, lookahead: int, steps: int = STEPS, seed: int = 0) -> Fingerprint:
    """`steps` steps: actions from a fixed stream; after each step the truncated scenarios, and
    a few at random (3% per step), are reset with fresh seeds (partial resets; a single
    scenario resets whole). Feeds obs, reward, truncated, every metric, positions, velocities,
    v-bar, serving, slots, t, the decoded allocations, and (every other step, so that the
    lazily decoded previous allocation is also skipped) prev_alloc and the state."""
    cfg: ScenarioConfig = make_cfg(episode_len=50, **fields)
    core = BatchCore(cfg, n, lookahead=lookahead)
    rng = np.random.default_rng(seed + 1000)
    fp = Fingerprint()
    fp.feed(-1, reset_obs=core.reset(seed), state=core.state())
    for step in range(steps):
        a = random_actions(cfg, n, rng)
        sf, tp, bw = core.allocations(a)
        fp.feed(step, alloc_sf=sf, alloc_tp=tp, alloc_bw=bw)
        res = core.step(a)
        fp.feed(step, obs=res.obs, reward=res.reward, truncated=res.truncated)
        fp.feed(step, **{f"metric_{k}": res.metrics[k] for k in sorted(res.metrics)})
        fp.feed(step, ed_xy=core.ed_xy, ed_vel=core.ed_vel, ed_mean_vel=core.ed_mean_vel)
        fp.feed(step, serving=core.serving, slot_of_ed=core.slot_of_ed, t=core.t)
        if step % 2:
            fp.feed(step, prev_alloc=core.prev_alloc, state=core.state())
        mask = res.truncated | (rng.random(n) < 0.03)
        if mask.any():
            seeds = [int(s) for s in rng.integers(0, 2**31, size=n)]
            fp.feed(step, reset_obs=core.reset(seeds, mask=None if n == 1 else mask))
    return fp


def mismatch(name: str, fp: Fingerprint, golden) -> str | None:
    """None when `fp` matches the recorded layout `name`; else the first differing array."""
    labels = [str(s) for s in golden[f"{name}/labels"]]
    if labels != fp.labels:
        first = next((i for i, (a, b) in enumerate(zip(labels, fp.labels)) if a != b), min(len(labels), len(fp.labels)))
        return f"array #{first}: recorded {labels[first : first + 1]}, now {fp.labels[first : first + 1]}"
    s0, a0 = golden[f"{name}/sums"].T
    s = np.array(fp.sums)[:, 0]
    bad = np.flatnonzero(np.abs(s - s0) > RTOL * a0)
    if bad.size:
        i = int(bad[0])
        return f"{bad.size} arrays differ; first {labels[i]}: S {s[i]!r} vs {s0[i]!r} (A {a0[i]:.6g}, rtol {RTOL})"
    return None


@pytest.fixture(scope="module")
def golden():
    with np.load(GOLDEN) as f:
        return {k: f[k] for k in f.files}


@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_trajectory_unchanged(name, golden):
    assert mismatch(name, trajectory(*LAYOUTS[name]), golden) is None


def test_check_catches_a_physics_constant_moved_by_1e_4(golden):
    """The tolerance is tight enough to see a 1e-4 relative change of one constant."""
    for field in ("carrier_hz", "noise_dbm"):
        fields, n, lookahead = LAYOUTS["v10u2_per_uav"]
        value = getattr(ScenarioConfig(), field) * (1 + 1e-4)
        assert mismatch("v10u2_per_uav", trajectory({**fields, field: value}, n, lookahead), golden) is not None, field


def test_check_catches_another_random_stream(golden):
    fields, n, lookahead = LAYOUTS["v10u2_per_device"]
    assert mismatch("v10u2_per_device", trajectory(fields, n, lookahead, seed=1), golden) is not None


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python tests/test_sim_regression.py --record   (re-records " + str(GOLDEN) + ")")
    out = {}
    for key in sorted(LAYOUTS):
        fp = trajectory(*LAYOUTS[key])
        out[f"{key}/labels"] = np.array(fp.labels)
        out[f"{key}/sums"] = np.array(fp.sums)
    np.savez_compressed(GOLDEN, **out)
    print(f"recorded {len(LAYOUTS)} layouts in {GOLDEN}")
