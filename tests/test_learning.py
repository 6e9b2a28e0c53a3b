"""Every registered learner learns a policy whose GREEDY execution beats random and does not
collapse onto one action shared by all UAVs (issue 13), and in per_device mode beats the
open-loop best constant action (issue 23) on a scenario with the LoRa PHY rate, where a constant is
not near-optimal.

Scenario: V = 4 EDs, U = 2 UAVs, 20-slot episodes. Its per-slot optimum puts the UAVs on
distinct SFs in most decisions (asserted below as the premise: under the paper's same-SF
interference a shared SF costs EE), and the collapsed policy, both UAVs on one action (the
`fixed` baseline is such a policy), is far below random. In per_device mode the best constant
(`best_fixed`) is well below the per-slot greedy search (asserted as that test's premise), so
beating it shows that a learner uses its observations.

Each learner trains once per mode (module fixtures, one after the other on a private 2-CPU Ray
cluster) with CI-sized step sizes (`CI`, `PER_DEVICE_CI` below), then is evaluated on 16 fresh
episodes. The measured shares are in BENCHMARKS.md.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.baselines import make_baseline
from uavlora_rllib.experiment.evaluation import run_episodes
from uavlora_rllib.sim.actions import decode_joint_action
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

SMALL = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=20)
EVAL_EPISODES, EVAL_SEED = 16, 5
ENVS = 4  # scenarios sampled at once

# Per learner: (hyperparameter overrides, training iterations). The first entries of each are the
# symmetry-breaking choices of BENCHMARKS.md "Learning at scale" (the registry defaults, stated
# here so the test keeps them if a default changes; QMIX at 4 updates per episode); the
# rest only make a CI-sized budget enough (larger step sizes, fewer epochs, a short epsilon
# schedule and a short horizon: the problem is myopic, actions never change the next slot).
_PPO_CI = {"share_actor": False, "lr": 2e-3, "num_epochs": 8, "num_minibatches": 2, "batch_episodes": 8}
_Q_CI = {
    "updates_per_iteration": 16,
    "lr": 1e-3,
    "gamma": 0.5,
    "t_max_env_steps": 8_000,
    "epsilon_anneal_fraction": 0.25,
    "batch_size_episodes": 8,
    "buffer_size_episodes": 32,
    "learning_starts_episodes": 8,
}
# the project's learners (a plugin that another test module registers, such as tests/tune_stock_ppo.py,
# is not a learner of this project)
LEARNERS = registry.built_in()
CI: dict[str, tuple[dict, int]] = {
    # mappo: 80 x 8 episodes x 20 slots = 12,800 env steps
    "mappo": (_PPO_CI, 80),
    "ippo": (_PPO_CI, 40),  # 6,400 env steps
    "qmix": (_Q_CI, 100),  # 100 x 4 episodes x 20 slots = 8,000 env steps
    "vdn": (_Q_CI, 100),
    # 40 x 16 episodes x 20 slots = 12,800 env steps, 8 updates each
    "coma": ({"lr_actor": 3e-4, "lr_critic": 1e-3}, 40),
}
# per_device: one SF/TP per served ED, one BW per UAV, with the LoRa PHY rate. Under the paper's Shannon rate a
# per_device constant earns ~0.96 of the per-slot greedy reference here (n_sf - 1 EDs alone on their SFs, the
# rest on one SF: docs/model.md#decisions), so beating it could show nothing; with `rate_model: lora_phy` each
# ED's (SF, TP) must follow its own gain and it earns 0.64 (the premise below). V = 12, U = 3: at V = 4, U = 2
# the best constant is the per-slot optimum under the Shannon rate.
PER_DEVICE = ScenarioConfig(n_eds=12, n_uavs=3, episode_len=20, action_mode="per_device", rate_model="lora_phy")
# the learners that act per ED, and their CI budgets there: (overrides, training iterations)
PER_DEVICE_LEARNERS = [n for n in LEARNERS if "per_device" in registry.get(n).action_modes]
# Discount 0 where it is set: a slot's action never changes later states, so every discount has the same
# optimal policy, and at 0 the critic regresses the slot's reward alone (docs/model.md#training-defaults).
# A learner gets a budget here once a CI-sized run beats best_fixed on this scenario.
_Q_PER_DEVICE = {**_Q_CI, "gamma": 0.0, "buffer_size_episodes": 512, "epsilon_end": 0.3}  # QMIX's and VDN's, below
PER_DEVICE_CI: dict[str, tuple[dict, int]] = {
    # per-ED heads, their per_device default (docs/model.md#mappo-and-ippo-per-device): each ED's (SF, TP)
    # must follow its own gain here; 100 x 8 episodes x 20 slots = 16,000 env steps. Probes (w1 = 0.1,
    # BENCHMARKS.md): 1.20-1.27x best_fixed from 60 to 160 iterations for both
    "mappo": ({**_PPO_CI, "gamma": 0.0}, 100),
    "ippo": ({**_PPO_CI, "gamma": 0.0}, 100),
    # the return in place of the critic's taken value (docs/model.md#coma-per-device), per-ED heads and MAPPO's
    # actor settings; 80 x 16 episodes x 20 slots = 25,600 env steps. Probe (ci_probe.py, fb33a22): 1.18-1.28x
    # best_fixed from 40 to 120 iterations, where COMA's own advantage at the same settings stays at 1.00-1.04x
    "coma": (
        {
            "gamma": 0.0,
            "entropy_coeff": 0.001,
            "lr_actor": 1e-3,
            "normalize_advantages": True,
            "actor_heads": "shared",
            "actor_agent_heads": False,
            "taken_value": "return",
        },
        80,
    ),
    # a replay of 512 episodes, 16x the paper's, and epsilon 0.3 after the anneal (docs/model.md#qmix-and-vdn-per-device):
    # with the paper's 32 episodes the per-ED utilities fit the last few episodes' noise and stay at 0.83-0.98x best_fixed;
    # 480 x 4 episodes x 20 slots = 38,400 env steps. Probe (ci_probe.py, 2026-12-05): VDN 1.07 / 1.10 / 1.13x at 300 /
    # 420 / 480 iterations, QMIX 1.05 / 1.12 / 1.14x
    "qmix": (_Q_PER_DEVICE, 480),
    "vdn": (_Q_PER_DEVICE, 480),
}
# per_device learners whose CI-sized training does not yet beat best_fixed here, and why; they keep
# the other learning tests, and the issue that asks for it stays open (results: BENCHMARKS.md#per_device-learning-benchmark)
PER_DEVICE_NOT_YET: dict[str, str] = {}
BEAT_BEST_FIXED = 1.02  # greedy EE / the open-loop best constant's on the same episodes, per_device
OPEN_LOOP_MAX = 0.9  # the premise: best_fixed's share of the per_device greedy reference
BEAT_RANDOM = 1.3  # greedy EE / random EE, well below the optimum's and far above the collapsed policy's
MAX_SAME_ACTION = 0.5  # share of decisions where both UAVs pick the same action (collapse: 1.0)
MAX_SAME_SF = 0.5  # share of decisions where both UAVs use the same SF


def _same_action_shares(policy, cfg: ScenarioConfig, episodes: int, seed: int) -> tuple[float, float]:
    """Play the policy on the evaluation episodes; the share of (scenario, slot) decisions in which
    all UAVs chose the same action, and the same SF."""
    from uavlora_rllib.experiment.evaluation import EVAL_SEED_BASE

    core = BatchCore(cfg, episodes)
    core.reset([EVAL_SEED_BASE + seed * 10_000 + k for k in range(episodes)])
    policy.reset(core)
    same_action, same_sf = [], []
    for _ in range(cfg.episode_len):
        a = policy.act(core)  # [N, U]
        sf = decode_joint_action(a, cfg)[0]
        same_action.append(np.all(a == a[:, :1], axis=1))
        same_sf.append(np.all(sf == sf[:, :1], axis=1))
        core.step(a)
    return float(np.mean(same_action)), float(np.mean(same_sf))


@pytest.fixture(scope="module")
def random_ee() -> float:
    return run_episodes(make_baseline("random", SMALL, seed=0), SMALL, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")


def _train_each(scenario: ScenarioConfig, budgets: dict[str, tuple[dict, int]], names) -> dict:
    """name -> (greedy policy, seconds of training): each learner trained on its CI budget, one after the other."""
    out = {}
    for name in names:
        overrides, iters = budgets[name]
        entry = registry.get(name)
        t0 = time.perf_counter()
        algo = entry.build(
            scenario, entry.hparams(overrides), registry.Resources(num_envs_per_env_runner=ENVS), 0
        ).build_algo()
        try:
            for _ in range(iters):
                algo.train()
            out[name] = (entry.greedy_policy(algo, scenario), time.perf_counter() - t0)
        finally:
            algo.stop()
    return out


@pytest.fixture(scope="module")
def trained(ray_session):
    """name -> (greedy policy, seconds of training), for every registered learner."""
    return _train_each(SMALL, CI, LEARNERS)


@pytest.fixture(scope="module")
def best_fixed_per_device_ee() -> float:
    """The open-loop check on the per_device scenario: the best constant action's greedy EE."""
    policy = make_baseline("best_fixed", PER_DEVICE, seed=0)
    return run_episodes(policy, PER_DEVICE, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")


@pytest.fixture(scope="module")
def trained_per_device(ray_session):
    """name -> (greedy policy, seconds of training) in per_device mode, for every learner with a per_device budget."""
    return _train_each(PER_DEVICE, PER_DEVICE_CI, sorted(set(PER_DEVICE_LEARNERS) & set(PER_DEVICE_CI)))


def test_every_registered_learner_has_a_ci_budget():
    assert set(LEARNERS) <= set(CI), sorted(set(LEARNERS) - set(CI))


def test_premise_the_optimum_needs_distinct_sfs(random_ee):
    optimal = make_baseline("optimal", SMALL)
    same_action, same_sf = _same_action_shares(optimal, SMALL, EVAL_EPISODES, EVAL_SEED)
    # the optimum shares an SF only where that costs nothing (e.g. a UAV serving no ED)
    assert same_sf <= 0.2, same_sf
    fixed = run_episodes(make_baseline("fixed", SMALL), SMALL, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")
    assert fixed < 0.5 * random_ee  # and one shared action is far below random


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CI))
def test_greedy_execution_beats_random(trained, random_ee, name):
    if name not in trained:
        pytest.skip(f"{name} is not implemented")
    policy, seconds = trained[name]
    ee = run_episodes(policy, SMALL, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")
    print(f"{name}: greedy EE {ee:.0f} = {ee / random_ee:.2f}x random ({seconds:.0f} s of training)")
    assert ee >= BEAT_RANDOM * random_ee, (ee, random_ee)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CI))
def test_greedy_actions_are_not_one_shared_action(trained, name):
    """Regression (issue 13): shared-parameter actors executed greedily put every UAV on the same
    action in 300 of 300 decisions; a learner must break that symmetry where the optimum needs it."""
    if name not in trained:
        pytest.skip(f"{name} is not implemented")
    same_action, same_sf = _same_action_shares(trained[name][0], SMALL, EVAL_EPISODES, EVAL_SEED)
    print(f"{name}: same action in {same_action:.0%} of decisions, same SF in {same_sf:.0%}")
    assert same_action <= MAX_SAME_ACTION, same_action
    assert same_sf <= MAX_SAME_SF, same_sf


def test_every_per_device_learner_has_a_ci_budget():
    """Each learner that acts per ED has a budget here, or is listed as not yet beating best_fixed."""
    assert not set(PER_DEVICE_CI) & set(PER_DEVICE_NOT_YET)
    missing = set(PER_DEVICE_LEARNERS) - set(PER_DEVICE_CI) - set(PER_DEVICE_NOT_YET)
    assert not missing, sorted(missing)


def test_premise_per_device_open_loop_is_below_the_reference(best_fixed_per_device_ee):
    """The per_device check means something only where a constant is well below the reference."""
    reference = run_episodes(make_baseline("greedy", PER_DEVICE), PER_DEVICE, EVAL_EPISODES, EVAL_SEED).mean(
        "ee_sys_mean"
    )
    assert best_fixed_per_device_ee <= OPEN_LOOP_MAX * reference, (best_fixed_per_device_ee, reference)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(PER_DEVICE_CI))
def test_per_device_greedy_execution_beats_the_best_constant(trained_per_device, best_fixed_per_device_ee, name):
    """Issue 23: in per_device mode (an SF and TP per served ED, a BW per UAV) every learner's
    greedy policy beats the open-loop best constant action on the same evaluation episodes."""
    if name not in trained_per_device:
        pytest.skip(f"{name} does not act in per_device mode")
    policy, seconds = trained_per_device[name]
    ee = run_episodes(policy, PER_DEVICE, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")
    print(f"{name} per_device: greedy EE {ee:.0f} = {ee / best_fixed_per_device_ee:.2f}x best_fixed ({seconds:.0f} s)")
    assert ee >= BEAT_BEST_FIXED * best_fixed_per_device_ee, (ee, best_fixed_per_device_ee)
