"""Every registered learner learns a policy whose GREEDY execution beats random and does not
collapse onto one action shared by all UAVs (issue 13), and in per_device mode beats the
open-loop best constant action (issue 23).

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

import json
import time

import numpy as np
import pytest
import torch

import tune_stock_ppo  # noqa: F401  (registers stock_ppo, a per_uav-only plugin, for the CLI refusal below)

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
_Q_CI = {"updates_per_iteration": 16, "lr": 1e-3, "gamma": 0.5, "t_max_env_steps": 8_000, "epsilon_anneal_fraction": 0.25,
         "batch_size_episodes": 8, "buffer_size_episodes": 32, "learning_starts_episodes": 8}
# the project's learners: every algorithm registered from this package (a plugin that another
# test module registers, such as tests/tune_stock_ppo.py, is not a learner of this project)
LEARNERS = [n for n in registry.available() if registry.MODULES[n].startswith("uavlora_rllib.algorithms.")]
CI: dict[str, tuple[dict, int]] = {
    # mappo: 80 x 8 episodes x 20 slots = 12,800 env steps
    "mappo": (_PPO_CI, 80),
    "ippo": (_PPO_CI, 40),  # 6,400 env steps
    "qmix": (_Q_CI, 100),  # 100 x 4 episodes x 20 slots = 8,000 env steps
    "vdn": (_Q_CI, 100),
    "coma": ({"lr_actor": 3e-4, "lr_critic": 1e-3}, 40),  # 40 x 16 episodes x 20 slots = 12,800 env steps, 8 updates each
}
# per_device: one SF/TP per served ED, one BW per UAV. V = 12, U = 3 rather than SMALL: at V = 4, U = 2
# the best constant is already the per-slot optimum in per_device mode too (the open-loop check
# could not fail), so the premise below is asserted on this scenario.
PER_DEVICE = ScenarioConfig(n_eds=12, n_uavs=3, episode_len=20, action_mode="per_device")
# the learners that act per ED, and their CI budgets there: (overrides, training iterations)
PER_DEVICE_LEARNERS = [n for n in LEARNERS if "per_device" in registry.get(n).action_modes]
PER_DEVICE_CI: dict[str, tuple[dict, int]] = {
    "mappo": (_PPO_CI, 160),  # 160 x 8 episodes x 20 slots = 25,600 env steps
    "ippo": (_PPO_CI, 80),
    "qmix": (_Q_CI, 200),  # 200 x 4 episodes x 20 slots = 16,000 env steps
}
# per_device learners whose CI-sized training does not yet beat best_fixed here, and why; they keep
# the other learning tests, and the issue that asks for it stays open (results: BENCHMARKS.md#per_device-learning-benchmark)
PER_DEVICE_NOT_YET: dict[str, str] = {
    "vdn": "the branching Q-network at _Q_CI stays below best_fixed up to 200 iterations",
    "coma": "the factored actor's entropy collapses early onto a poor setting; a larger entropy bonus helps but stays below",
}
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
def ray_session(tmp_path_factory):
    import ray

    # address="local": a private cluster, never somebody else's `ray start` one.
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


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
        algo = entry.build(scenario, entry.hparams(overrides), registry.Resources(num_envs_per_env_runner=ENVS), 0).build_algo()
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
    reference = run_episodes(make_baseline("greedy", PER_DEVICE), PER_DEVICE, EVAL_EPISODES, EVAL_SEED).mean("ee_sys_mean")
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


# ---------------------------------------------------------------- the benchmark's CLI (no training)
@pytest.mark.parametrize(
    "argv, message",
    [
        (["--scenarios", "60x"], "--scenarios: expected VxU"),
        (["--learners", "nope"], "--learners: unknown algorithm 'nope'"),
        (["--learners", "mappo", "--set", "mappo.nope=1"], "--set mappo.nope: unknown field"),
        (["--learners", "mappo", "--set", "qmix.lr=1"], "--set: 'qmix' is not one of the learners run"),
        (["--learners", "stock_ppo", "--action-mode", "per_device"], "--action-mode: algorithm 'stock_ppo' supports action modes"),
        (["--target", "1.5"], "--target: expected a number in (0, 1]"),
        (["--env-steps", "0"], "--env-steps: must be a positive integer"),
    ],
)
def test_bench_learn_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    from uavlora_rllib import bench_learn

    assert bench_learn.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err


def test_bench_learn_steps_to_target_and_table(tmp_path, capsys):
    from uavlora_rllib import bench_learn

    curve = [{"env_steps": 10_000, "greedy_share": 0.5}, {"env_steps": 20_000, "greedy_share": 0.95}, {"env_steps": 30_000, "greedy_share": 0.85}]
    assert bench_learn.steps_to_share(curve, 0.9) == 20_000  # the first crossing, even if it falls back
    assert bench_learn.steps_to_share(curve, 0.99) is None
    row = {"learner": "mappo", "n_eds": 60, "n_uavs": 4, "action_mode": "per_uav", "seed": 0, "tag": "t", "env_steps": 30_000,
           "greedy_ee": 8_500.0, "greedy_share": 0.85, "sampled_share": None, "env_steps_to_target": 20_000, "target": 0.9,
           "reference": "greedy", "reference_ee": 10_000.0, "random_ee": 5_000.0, "train_s": 12.0, "wall_s": 15.0,
           "budget_env_steps": 30_000, "curve": curve}
    path = tmp_path / "r.jsonl"
    path.write_text(json.dumps(row) + "\n")
    assert bench_learn.main(["--table", str(path)]) == 0
    out = capsys.readouterr().out
    assert "| 60 | 4 | per_uav | mappo | t | 0 | 30,000 | 0.850 | - | 20,000 (90%) | 1.70 | greedy 10,000 | 0.500 |" in out
    # one seed at 30k: no verdict on the 3-seed, 200k target
    assert out.strip().splitlines()[-1].startswith("| 60 | 4 | per_uav | mappo | t | 30,000 | 0 | 0.850 | 0.850 | - | 0.85 | n/a |")
    # three seeds at 200k: the mean decides (U=4: 0.85), and V=10/U=2 also at 60k (0.9)
    rows = [dict(row, seed=s, budget_env_steps=200_000, greedy_share=g) for s, g in ((0, 0.95), (1, 0.9), (2, 0.6))]
    rows += [dict(row, n_eds=10, n_uavs=2, seed=s, budget_env_steps=200_000, greedy_share=1.0,
                  curve=[{"env_steps": 60_000, "greedy_share": g}, {"env_steps": 200_000, "greedy_share": 1.0}])
             for s, g in ((0, 0.95), (1, 0.9), (2, 0.8))]
    lines = bench_learn.summary_table(rows[::-1]).splitlines()  # seeds and scenarios in any order
    # the scenario order (U, then V), seeds ascending
    assert lines[2].startswith("| 10 | 2 |") and lines[2].endswith("| 0,1,2 | 1.000 | 1.000 | - | 0.95 | met | 0.883 missed |")
    assert lines[3].startswith("| 60 | 4 |") and lines[3].endswith("| 0,1,2 | 0.817 | 0.600 | - | 0.85 | missed | - |")
    # evaluated at 40k only before 60k: a share below 0.9 there is no miss of "0.9 within 60k"
    early = [dict(r, curve=[{"env_steps": 40_000, "greedy_share": 0.8}, {"env_steps": 200_000, "greedy_share": 1.0}])
             for r in rows[3:]]
    assert bench_learn.summary_table(early).splitlines()[2].endswith("| met | 0.800 at 40,000: n/a |")
    assert bench_learn.summary_table([dict(r, curve=[dict(p, greedy_share=0.95) for p in r["curve"]]) for r in early]
                                     ).splitlines()[2].endswith("| met | 0.950 met |")
    # a seed with no evaluation by 60k: no mean over the others in its place
    gap = [dict(early[0], curve=[{"env_steps": 81_600, "greedy_share": 1.0}])] + early[1:]
    assert bench_learn.summary_table(gap).splitlines()[2].endswith("| met | - |")


def test_bench_learn_trial_row_records_what_ran(tmp_path, capsys):
    """One tiny end-to-end trial: the JSON row carries the reference, the curve and every
    hyperparameter the trial ran with (the override applied), so it stays readable after a
    later registry change."""
    from uavlora_rllib import bench_learn

    out = tmp_path / "r.jsonl"
    argv = ["--scenarios", "10x2", "--learners", "vdn", "--env-steps", "2400", "--eval-every", "1200",
            "--eval-episodes", "1", "--envs-per-runner", "8", "--set", "vdn.state_bias=false", "--tag", "tiny",
            "--out", str(out)]  # 8 envs x 150 slots: 1,200 env steps per iteration
    assert bench_learn.main(argv) == 0
    (row,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert (row["learner"], row["n_eds"], row["n_uavs"], row["reference"], row["tag"]) == ("vdn", 10, 2, "optimal", "tiny")
    assert row["hparams"]["state_bias"] is False and row["hparams"]["lr"] == 1e-4  # override + paper default
    assert row["overrides"] == {"state_bias": False}
    assert [p["env_steps"] for p in row["curve"]] == [1200, 2400]
    assert row["greedy_share"] == pytest.approx(row["greedy_ee"] / row["reference_ee"])
    assert 0 < row["random_ee"] < row["reference_ee"]  # the optimum beats random actions
    assert len(row["git_commit"]) == 40 or row["git_commit"] == "unknown"
    assert "| 10 | 2 | per_uav | vdn | tiny | 0 | 2,400 |" in capsys.readouterr().out


def test_bench_learn_per_device_trial_uses_the_per_uav_reference_as_scale(tmp_path):
    """per_device has no tractable optimum: the row names the per_uav reference it is scaled by,
    and random is the per_device random policy (the benchmark judges per_device against it)."""
    from uavlora_rllib import bench_learn

    out = tmp_path / "r.jsonl"
    argv = ["--scenarios", "10x2", "--learners", "mappo", "--action-mode", "per_device", "--env-steps", "1200",
            "--eval-every", "1200", "--eval-episodes", "1", "--envs-per-runner", "8", "--out", str(out)]
    assert bench_learn.main(argv) == 0
    (row,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert (row["action_mode"], row["reference"]) == ("per_device", "optimal (per_uav)")
    assert row["random_ee"] > row["reference_ee"]  # an SF per ED lifts same-SF interference: see BENCHMARKS


def test_bench_learn_inside_a_ray_session_leaves_it_running(ray_session, tmp_path):
    """Called from Python within a Ray session (this module's), bench_learn uses it, no second
    ray.init, and does not shut it down under its caller."""
    import ray

    from uavlora_rllib import bench_learn

    argv = ["--scenarios", "10x2", "--learners", "vdn", "--env-steps", "1200", "--eval-every", "1200",
            "--eval-episodes", "1", "--envs-per-runner", "8", "--out", str(tmp_path / "r.jsonl")]
    assert bench_learn.main(argv) == 0
    assert ray.is_initialized()
    assert len((tmp_path / "r.jsonl").read_text().splitlines()) == 1
