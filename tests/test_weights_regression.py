"""Every learner's weights after 3 training iterations match the recorded ones.

Each algorithm trains 3 iterations from a fixed seed on V=10, U=2 (per_uav, 10-slot episodes,
4 scenarios in the trial's own process, one torch thread), with hyperparameters that let every
algorithm run gradient updates within those iterations. The learner module's state (networks,
targets, mixers, value-norm statistics) is summarised per tensor by S = sum(r * w) and
A = sum(r * |w|), r a fixed positive pseudo-random vector, and compared with the golden file
tests/data/weights_after_3_iterations.json as |S - S0| <= RTOL * A0: float rounding on another
CPU passes, a change in what the learners compute does not.

Regenerate the golden file (only when a change of the learned weights is intended), for every
algorithm or only the named ones (the other entries are kept):
    python tests/test_weights_regression.py [ALGO ...]
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
import pytest

GOLDEN = pathlib.Path(__file__).parent / "data" / "weights_after_3_iterations.json"
RTOL = 1e-4
ITERATIONS = 3
SEED = 7
# Small batches so that every algorithm learns in each of the 3 iterations (QMIX/VDN start
# after 4 episodes in the replay, the first iteration's), and enough updates that a 1 % change
# of a learning rate moves the weights beyond RTOL.
_REPLAY = {"learning_starts_episodes": 4, "batch_size_episodes": 4, "updates_per_iteration": 8, "lr": 5e-4}
HPARAMS: dict[str, dict] = {
    "mappo": {"batch_episodes": 8, "num_minibatches": 2},
    "ippo": {"batch_episodes": 8, "num_minibatches": 2},
    "qmix": _REPLAY,
    "vdn": _REPLAY,
    "coma": {"batch_episodes": 4},
}


def train_weights(name: str) -> dict[str, np.ndarray]:
    """The learner module's state after ITERATIONS iterations of algorithm `name`."""
    import torch
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.sim.scenario import ScenarioConfig

    torch.set_num_threads(1)
    scenario = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=10, action_mode="per_uav")
    resources = registry.Resources(num_env_runners=0, num_envs_per_env_runner=4, torch_threads=1)
    entry = registry.get(name)
    algo = entry.build(scenario, entry.hparams(HPARAMS[name]), resources, SEED).build_algo()
    try:
        for _ in range(ITERATIONS):
            algo.train()
        weights = algo.learner_group.get_weights([DEFAULT_MODULE_ID])[DEFAULT_MODULE_ID]
    finally:
        algo.stop()
    return {k: np.asarray(v, dtype=np.float64) for k, v in weights.items()}


def summary(weights: dict[str, np.ndarray]) -> dict[str, list[float]]:
    """Per tensor [S, A]: sums of r * w and r * |w|, r uniform in [0.5, 1.5) from a fixed seed."""
    out = {}
    for key, w in sorted(weights.items()):
        r = np.random.default_rng(12345).uniform(0.5, 1.5, size=w.size)
        flat = w.reshape(-1)
        out[key] = [float(np.dot(r, flat)), float(np.dot(r, np.abs(flat)))]
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(HPARAMS))
def test_weights_after_3_iterations_match_the_golden_file(ray_session, name):
    golden = json.loads(GOLDEN.read_text())[name]
    got = summary(train_weights(name))
    assert sorted(got) == sorted(golden), "the module's parameters and buffers changed"
    bad = {
        key: (s, s0) for key, (s, _) in got.items() for s0, a0 in [golden[key]] if abs(s - s0) > RTOL * max(a0, 1e-12)
    }
    assert not bad, f"{name}: weighted sums off the golden file beyond {RTOL} of sum |w|: {bad}"


if __name__ == "__main__":
    import sys

    names = sys.argv[1:] or sorted(HPARAMS)
    if unknown := sorted(set(names) - set(HPARAMS)):
        print(f"test_weights_regression.py: ALGO: unknown {unknown}; allowed: {sorted(HPARAMS)}", file=sys.stderr)
        sys.exit(2)
    golden = json.loads(GOLDEN.read_text()) if GOLDEN.exists() else {}
    golden.update({name: summary(train_weights(name)) for name in names})
    GOLDEN.parent.mkdir(exist_ok=True)
    GOLDEN.write_text(json.dumps(dict(sorted(golden.items())), indent=1) + "\n")
