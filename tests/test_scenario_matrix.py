"""Every documented scenario option works with every baseline and every learner that claims it.

The matrix is interference (paper, cross_gain) x rate_model (shannon, lora_phy) x action_mode
(per_uav, per_device) x association (greedy, optimal): each combination is stepped through
both environments (PettingZoo and RLlib) and every baseline, and every output must be finite.
In per_device mode `optimal` must refuse this scenario (too many candidates) with a ConfigError
naming scenario.n_eds. One training iteration of each learner (slow) runs on the
combination furthest from the default path (cross_gain, lora_phy, optimal association) in each
action mode it claims; the default path is trained by each learner's own tests.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import tune_stock_ppo  # noqa: F401  (its learners join LEARNER_CASES whatever the collection order)
from conftest import random_actions

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.baselines.policies import BASELINES, make_baseline
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.envs.multi_agent import STATE_KEY, UavLoraMultiAgentEnv, UavLoraParallelEnv
from uavlora_rllib.experiment.evaluation import run_episodes
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import decode_joint_action
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

OPTIONS = {
    "interference": ("paper", "cross_gain"),
    "rate_model": ("shannon", "lora_phy"),
    "action_mode": ("per_uav", "per_device"),
    "association": ("greedy", "optimal"),
}
COMBOS = [dict(zip(OPTIONS, values)) for values in itertools.product(*OPTIONS.values())]


def _cfg(**options) -> ScenarioConfig:
    # 9 EDs, 2 UAVs, a 300 m range: quotas bind and some EDs are out of range, so the
    # unassociated paths run too
    return ScenarioConfig(n_eds=9, n_uavs=2, comm_range_m=300.0, max_eds_per_uav=4, episode_len=4, **options)


def _combo_id(c: dict) -> str:
    return "-".join(c.values())


@pytest.mark.parametrize("options", COMBOS, ids=[_combo_id(c) for c in COMBOS])
def test_envs_step_to_finite_values(options):
    cfg = _cfg(**options)
    rng = np.random.default_rng(0)
    pz = UavLoraParallelEnv(cfg)
    obs, _ = pz.reset(seed=3)
    steps = 0
    while pz.agents:
        acts = random_actions(cfg, 1, rng)[0]
        obs, rew, _, _, infos = pz.step(dict(zip(pz.agents, acts)))
        steps += 1
        assert all(np.isfinite(o).all() for o in obs.values())
        assert all(math.isfinite(r) for r in rew.values())
        assert all(math.isfinite(v) for info in infos.values() for v in info.values())
    assert steps == cfg.episode_len

    env = UavLoraMultiAgentEnv({"scenario": cfg.to_dict()})
    env.reset(seed=3)
    for _ in range(cfg.episode_len):
        acts = random_actions(cfg, 1, rng)[0]
        obs, rew, _, truncs, infos = env.step(dict(zip(env.possible_agents, acts)))
        assert all(np.isfinite(o).all() for o in obs.values())
        assert all(math.isfinite(r) for r in rew.values())
        for info in infos.values():
            assert np.isfinite(info[STATE_KEY]).all()
            assert all(math.isfinite(v) for k, v in info.items() if k != STATE_KEY)
    assert truncs["__all__"]


@pytest.mark.parametrize("options", COMBOS, ids=[_combo_id(c) for c in COMBOS])
@pytest.mark.parametrize("baseline", BASELINES)
def test_every_baseline_on_every_combination(options, baseline):
    cfg = _cfg(**options)
    if baseline == "optimal" and cfg.action_mode != "per_uav":
        with pytest.raises(ConfigError, match=r"^scenario\.n_eds: baseline 'optimal' in per_device mode"):
            make_baseline(baseline, cfg)
        return
    summary = run_episodes(make_baseline(baseline, cfg, seed=1), cfg, episodes=2, seed=5).summary()
    for key, value in summary.items():
        if key not in ("ci95", "episodes"):
            assert math.isfinite(value), (key, value)
    assert summary["ee_sys_mean"] > 0.0  # some ED is in range of a UAV in these layouts
    assert 0.0 <= summary["success_rate"] <= 1.0


@pytest.mark.parametrize("rate_model", OPTIONS["rate_model"])
def test_cross_gain_scores_candidates_like_one_at_a_time(rate_model):
    """The baselines score a batch of candidate actions [C, N, U] against the batch's channels
    [N, U, V] in one broadcast slot_metrics call; with cross_gain that must equal scoring each
    candidate alone (the broadcast once crashed in sinr_cross_gain)."""
    cfg = _cfg(interference="cross_gain", rate_model=rate_model, association="optimal")
    core = BatchCore(cfg, 3)
    core.reset(11)
    core.step(random_actions(cfg, 3, np.random.default_rng(0)))
    cand = np.random.default_rng(1).integers(0, cfg.n_joint_actions, size=(5, 3, cfg.n_uavs))

    def score(joint):
        shape = joint.shape[:-1] + (cfg.n_eds,)
        ed_action = np.take_along_axis(joint, np.broadcast_to(core.links.serving_idx, shape), axis=-1)
        sf, tp, bw = decode_joint_action(ed_action, cfg)
        return physics.slot_metrics(core.gains, core.links.serving_idx, core.associated, sf, tp, bw, cfg, core.tables)

    together = score(cand)
    for c in range(len(cand)):
        alone = score(cand[c])
        for key in physics.SLOT_METRICS:
            # (n_unassociated does not depend on the action: it is not broadcast over candidates)
            t = np.broadcast_to(together[key], (len(cand),) + np.shape(alone[key]))[c]
            np.testing.assert_allclose(t, alone[key], rtol=1e-12, atol=0, err_msg=key)


def test_optimal_beats_every_candidate_with_cross_gain():
    """With cross_gain the per-slot optimum is still the maximum: the EE_sys the env pays for
    optimal's action is >= that of greedy's and of random actions, slot by slot."""
    cfg = _cfg(interference="cross_gain", association="optimal")
    opt, greedy = make_baseline("optimal", cfg), make_baseline("greedy", cfg)
    rng = np.random.default_rng(2)
    core = BatchCore(cfg, 2)
    core.reset(21)
    for _ in range(2):
        a_opt, a_greedy = opt.act(core), greedy.act(core)
        tries = [a_greedy] + [random_actions(cfg, 2, rng) for _ in range(5)]
        ee = []
        for a in [a_opt] + tries:
            sf, tp, bw = core.allocations(a)
            m = physics.slot_metrics(core.gains, core.links.serving_idx, core.associated, sf, tp, bw, cfg, core.tables)
            ee.append(m["ee_sys"])
        assert all((ee[0] >= other * (1 - 1e-12)).all() for other in ee[1:])
        core.step(a_opt)


# ---------------------------------------------------------------- one training iteration per learner
# The scenario options change only the env's numbers, never the spaces a learner sees (the action
# mode, the learner's own axis below, does); every combination is stepped through the envs and the
# baselines above, so the learners train on the one furthest from the default path.
SCENARIO_OPTIONS = [{"interference": "cross_gain", "rate_model": "lora_phy", "association": "optimal"}]
# the smallest updates each learner allows on these 4-slot episodes
TINY = {
    "mappo": {
        "num_epochs": 1,
        "num_minibatches": 1,
        "batch_episodes": 2,
        "max_seq_len": 4,
        "gru_hidden": 8,
        "fc_hidden": 8,
        "critic_hidden": 8,
    },
    "ippo": {
        "num_epochs": 1,
        "num_minibatches": 1,
        "batch_episodes": 2,
        "max_seq_len": 4,
        "gru_hidden": 8,
        "fc_hidden": 8,
        "critic_hidden": 8,
    },
    # one update per episode, so that the first iteration's 2 episodes run the learner (0.25: none yet)
    "qmix": {
        "batch_size_episodes": 2,
        "buffer_size_episodes": 4,
        "learning_starts_episodes": 2,
        "gru_hidden": 8,
        "fc_hidden": 8,
        "updates_per_episode": 1.0,
    },
    "vdn": {
        "batch_size_episodes": 2,
        "buffer_size_episodes": 4,
        "learning_starts_episodes": 2,
        "gru_hidden": 8,
        "fc_hidden": 8,
        "updates_per_episode": 1.0,
    },
    "coma": {"batch_episodes": 2, "gru_hidden": 8, "actor_hidden": 8},
}
LEARNER_CASES = [
    (name, mode, options)
    for name in registry.available()
    for mode in registry.get(name).action_modes
    for options in SCENARIO_OPTIONS
]


def _finite_leaves(tree, path=""):
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield from _finite_leaves(v, f"{path}/{k}")
    elif isinstance(tree, (float, np.floating)) and not isinstance(tree, bool):
        yield path, float(tree)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name, action_mode, options", LEARNER_CASES, ids=[f"{n}-{m}-{_combo_id(o)}" for n, m, o in LEARNER_CASES]
)
def test_one_training_iteration_per_learner(ray_session, name, action_mode, options):
    """Every learner x every action mode it claims x every scenario option: one training
    iteration with finite learner metrics, then its greedy policy plays the scenario."""
    entry = registry.get(name)
    cfg = _cfg(action_mode=action_mode, **options)
    known = {f for f in entry.hparams_cls.__pydantic_fields__}
    hparams = entry.hparams({k: v for k, v in TINY.get(name, {}).items() if k in known})
    resources = registry.Resources(num_envs_per_env_runner=2)
    algo = entry.build(cfg, hparams, resources, 0).build_algo()
    try:
        result = algo.train()
        assert result["env_runners"]["num_env_steps_sampled_lifetime"] > 0
        assert result.get("learners"), "the iteration ran no learner update"
        bad = [(p, v) for p, v in _finite_leaves(result["learners"]) if not math.isfinite(v)]
        assert not bad, bad
        # the trained policy plays the same scenario (execution phase) to finite metrics
        summary = run_episodes(entry.greedy_policy(algo, cfg), cfg, episodes=1, seed=0).summary()
        assert all(math.isfinite(v) for k, v in summary.items() if k not in ("ci95", "episodes"))
    finally:
        algo.stop()
