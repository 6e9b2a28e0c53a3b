"""Trajectory fingerprints of the simulator core: a SHA-256 over everything a step exposes,
for 120 steps of several layouts (the paper's V=10/U=2 and V=100/U=8, both action modes, the
all-pairs channel path, binding quotas, the large-batch per_uav scoring path, the single-env
lookahead), with truncations and partial resets.

The expected digests were recorded before BatchCore was split into its stage modules
(mobility, links, observation, actions, scoring): a refactoring of the simulator must keep
them. A change that alters trajectories on purpose (a new random stream, a model fix) updates
them, and says so in its commit; `python tests/test_sim_regression.py` prints the current ones.

The digests depend on NumPy's bit generators and its float32 SIMD kernels (log/sin/cos in the
Box-Muller noise), so they are checked only with the NumPy version they were recorded with.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # conftest's helpers when run as a script

from conftest import make_cfg, random_actions  # noqa: E402
from uavlora_rllib.sim.core import BatchCore  # noqa: E402
from uavlora_rllib.sim.scenario import ScenarioConfig  # noqa: E402

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
# Recorded with NumPy 2.4.6 on the commit before the split (ab093f7).
NUMPY_VERSION = "2.4.6"
EXPECTED = {
    "all_pairs_optimal": "839457b7b52f499a7600f2507a0ff7557ad1767d2ed7709e8084506beab0b9be",
    "lookahead_v100u8_per_device": "8c8403f211b680beecf18b7d257819e3a6d9ae6023246572f44b1dd035976ddd",
    "lookahead_v10u2_per_uav": "35469ef264e887eac3ac63f2a8f15ce451bd75129ccf585a35e350d6f6756976",
    "quota_binding": "a443ba5d4f467d4b223a84a04a4425e38e916577ef50e9c5ad3a8cd48f674fac",
    "v100u8_per_device": "2ef417970cd1616b6fd2f074c6f6999004f7245c4d9f6fe1a9c2ba92615bd6e6",
    "v100u8_per_uav": "81d7b78b43079668b1d8fc5707002f6b5cb2016b8557a33b4ecf99aa171508a2",
    "v100u8_per_uav_lora_phy_n48": "395f88d46afd3b6fcd5ec950f8b3cf69852dba741ccd44264d0ed87cae6d7307",
    "v10u2_per_device": "268874c4fa5f961f58c48383d2654d87c7e99537aef1c9dc3456e7424ff0fb40",
    "v10u2_per_uav": "a94f5aa8d28078cff01446542fc948c9cf4bc98396d24a486ab77e560ef17f42",
}


def _feed(h, *arrays) -> None:
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())


def trajectory_digest(fields: dict, n: int, lookahead: int, steps: int = STEPS, seed: int = 0) -> str:
    """SHA-256 of `steps` steps: actions from a fixed stream; after each step the truncated
    scenarios, and a few at random (3% per step), are reset with fresh seeds (partial resets;
    a single scenario resets whole). Hashes obs, reward, truncated, every metric, positions,
    velocities, v-bar, serving, slots, t, the decoded allocations, and (every other step, so
    that the lazily decoded previous allocation is also skipped) prev_alloc and the state."""
    cfg: ScenarioConfig = make_cfg(episode_len=50, **fields)
    core = BatchCore(cfg, n, lookahead=lookahead)
    rng = np.random.default_rng(seed + 1000)
    h = hashlib.sha256()
    _feed(h, core.reset(seed), core.state())
    for step in range(steps):
        a = random_actions(cfg, n, rng)
        _feed(h, *core.allocations(a))
        res = core.step(a)
        _feed(h, res.obs, res.reward, res.truncated, *(res.metrics[k] for k in sorted(res.metrics)))
        _feed(h, core.ed_xy, core.ed_vel, core.ed_mean_vel, core.serving, core.slot_of_ed, core.t)
        if step % 2:
            _feed(h, core.prev_alloc, core.state())
        mask = res.truncated | (rng.random(n) < 0.03)
        if mask.any():
            seeds = [int(s) for s in rng.integers(0, 2**31, size=n)]
            _feed(h, core.reset(seeds, mask=None if n == 1 else mask))
    return h.hexdigest()


@pytest.mark.skipif(np.__version__ != NUMPY_VERSION, reason=f"digests recorded with NumPy {NUMPY_VERSION}")
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_trajectory_digest_unchanged(name):
    assert trajectory_digest(*LAYOUTS[name]) == EXPECTED[name]


if __name__ == "__main__":
    for key in sorted(LAYOUTS):
        print(f'    "{key}": "{trajectory_digest(*LAYOUTS[key])}",')
