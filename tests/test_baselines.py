"""Baselines: ordering of their EE, optimality of `optimal`, ADR's rule, the factory's errors."""

from __future__ import annotations

import numpy as np
import pytest

from uavlora_rllib.baselines.policies import (
    BASELINES,
    AdrPolicy,
    adr_update,
    make_baseline,
)
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment.evaluation import run_episodes
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import decode_joint_action, encode_joint_action
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

PAPER = ScenarioConfig()


def slot_ee(core: BatchCore, actions: np.ndarray, key: str = "ee_sys") -> np.ndarray:
    """Objective of `actions` in the core's current slot, without stepping it."""
    sf, tp, bw = core.allocations(actions)
    m = physics.slot_metrics(core.gains, core.links.serving_idx, core.associated, sf, tp, bw, core.cfg, core.tables)
    return m[key]


def test_names_and_factory_errors():
    assert BASELINES == ("random", "fixed", "adr", "best_fixed", "greedy", "optimal")
    for name in BASELINES:
        assert make_baseline(name, PAPER).name == name
    with pytest.raises(ConfigError, match=r"unknown baseline 'nope'.*random.*fixed.*adr.*best_fixed.*greedy.*optimal"):
        make_baseline("nope", PAPER)
    with pytest.raises(ConfigError, match="objective"):
        make_baseline("greedy", PAPER, objective="bits")
    per_device = PAPER.replace(action_mode="per_device")
    assert make_baseline("greedy", per_device).name == "greedy"  # per_device references: tests/test_references.py
    with pytest.raises(ConfigError, match=r"^scenario\.n_eds: baseline 'optimal' in per_device mode"):
        make_baseline("optimal", per_device)


def test_optimal_refuses_too_many_uavs():
    with pytest.raises(ConfigError, match=r"n_uavs.*90\^4.*limit"):
        make_baseline("optimal", ScenarioConfig(n_eds=10, n_uavs=4))


def test_mean_ee_ordering_short_episodes():
    cfg = PAPER.replace(episode_len=10)
    ee = {
        name: run_episodes(make_baseline(name, cfg, seed=3), cfg, episodes=3, seed=5).mean("ee_sys_mean")
        for name in ("random", "greedy", "optimal")
    }
    assert ee["optimal"] >= ee["greedy"] - 1e-9
    assert ee["greedy"] > ee["random"]


def test_ordering_per_slot_on_default_scenario():
    """The default (T = 150) scenario over its first slots: optimal is the per-slot max."""
    core = BatchCore(PAPER, n_envs=2)
    core.reset(11)
    policies = {name: make_baseline(name, PAPER, seed=1) for name in ("random", "fixed", "adr", "greedy", "optimal")}
    for p in policies.values():
        p.reset(core)
    totals = {name: 0.0 for name in policies}
    for _ in range(4):
        ee = {name: slot_ee(core, p.act(core)) for name, p in policies.items()}
        for name in policies:
            assert np.all(ee["optimal"] >= ee[name] - 1e-9), name
            totals[name] += float(ee[name].sum())
        core.step(policies["random"].act(core))
    assert totals["greedy"] > totals["random"]
    assert totals["greedy"] > totals["fixed"]


@pytest.mark.parametrize("objective", ["ee", "reward"])
def test_optimal_beats_random_joint_actions(objective):
    key = "ee_sys" if objective == "ee" else "reward"
    core = BatchCore(PAPER, n_envs=3)
    core.reset(7)
    best = slot_ee(core, make_baseline("optimal", PAPER, objective=objective).act(core), key)
    rng = np.random.default_rng(0)
    for _ in range(300):
        other = slot_ee(core, rng.integers(0, 90, (3, 2)), key)
        assert np.all(best >= other)
    # and every single-UAV deviation from the optimum (a local check of the whole neighbourhood)
    opt = make_baseline("optimal", PAPER, objective=objective).act(core)
    for u in range(2):
        for a in range(90):
            dev = opt.copy()
            dev[:, u] = a
            assert np.all(best >= slot_ee(core, dev, key))


def test_greedy_is_exact_with_one_uav():
    cfg = ScenarioConfig(n_eds=8, n_uavs=1)
    core = BatchCore(cfg, n_envs=4)
    core.reset(3)
    greedy, optimal = make_baseline("greedy", cfg), make_baseline("optimal", cfg)
    for _ in range(3):
        g, o = greedy.act(core), optimal.act(core)
        np.testing.assert_array_equal(slot_ee(core, g), slot_ee(core, o))
        everything = [slot_ee(core, np.full((4, 1), a)) for a in range(90)]
        np.testing.assert_array_equal(slot_ee(core, o), np.max(everything, axis=0))
        core.step(g)


def test_fixed_decodes_to_sf7_14dbm_500khz():
    core = BatchCore(PAPER, n_envs=2)
    core.reset(0)
    a = make_baseline("fixed", PAPER).act(core)
    assert a.shape == (2, 2)
    sf, tp, bw = decode_joint_action(a, PAPER)
    assert np.all(np.asarray(PAPER.sf_set)[sf] == 7)
    assert np.all(np.asarray(PAPER.tp_dbm)[tp] == 14.0)
    assert np.all(np.asarray(PAPER.bw_khz)[bw] == 500)
    cfg = PAPER.replace(action_mode="per_device")
    core = BatchCore(cfg, n_envs=2)
    core.reset(0)
    sf, tp, bw = core.allocations(make_baseline("fixed", cfg).act(core))
    assert np.all(sf == 0) and np.all(tp == cfg.n_tp - 1) and np.all(bw == cfg.n_bw - 1)


def test_random_is_seeded_and_in_range():
    core = BatchCore(PAPER, n_envs=5)
    core.reset(0)
    a1 = make_baseline("random", PAPER, seed=9).act(core)
    a2 = make_baseline("random", PAPER, seed=9).act(core)
    a3 = make_baseline("random", PAPER, seed=10).act(core)
    np.testing.assert_array_equal(a1, a2)
    assert not np.array_equal(a1, a3)
    assert a1.min() >= 0 and a1.max() < 90


def test_adr_rule_unit():
    # margin 7 dB -> 2 steps: SF12 -> SF10, TP unchanged
    sf, tp = adr_update(np.array([5]), np.array([4]), np.array([7.0]), n_tp=5)
    assert (sf[0], tp[0]) == (3, 4)
    # margin 30 dB -> 10 steps: SF down to SF7 (5 steps), then TP down 4 steps to min (2 dBm)
    sf, tp = adr_update(np.array([5]), np.array([4]), np.array([30.0]), n_tp=5)
    assert (sf[0], tp[0]) == (0, 0)
    # negative margin -5 dB -> floor(-5/3) = -2: TP up two steps, SF unchanged
    sf, tp = adr_update(np.array([0]), np.array([1]), np.array([-5.0]), n_tp=5)
    assert (sf[0], tp[0]) == (0, 3)
    # TP up is capped at the max; SF never rises
    sf, tp = adr_update(np.array([2]), np.array([3]), np.array([-20.0]), n_tp=5)
    assert (sf[0], tp[0]) == (2, 4)


def _one_ed_core(distance_m: float, cfg: ScenarioConfig) -> BatchCore:
    core = BatchCore(cfg, n_envs=1)
    core.reset(0)
    core.ed_xy[0, 0] = core.uav_xy[0] + np.array([distance_m, 0.0])
    core.observe()
    return core


def test_adr_policy_lowers_sf_when_margin_large_and_raises_tp_when_negative():
    cfg = ScenarioConfig(n_eds=1, n_uavs=1)
    core = _one_ed_core(0.0, cfg)  # right under the UAV: a huge margin
    adr = AdrPolicy(cfg)
    adr.reset(core)
    sf, tp, bw = decode_joint_action(adr.act(core), cfg)
    assert sf[0, 0] == 0 and tp[0, 0] < cfg.n_tp - 1  # SF12 -> SF7, then TP down
    assert np.asarray(cfg.bw_khz)[bw[0, 0]] == 125
    for _ in range(5):
        sf, tp, _ = decode_joint_action(adr.act(core), cfg)
    assert (sf[0, 0], tp[0, 0]) == (0, 0)
    # A noisy receiver (noise +40 dB above the link budget): margin negative -> TP rises.
    noisy = cfg.replace(noise_dbm=-40.0)
    core = _one_ed_core(500.0, noisy)
    adr = AdrPolicy(noisy)
    adr.reset(core)
    adr._sf[:] = 0
    adr._tp[:] = 0
    sf, tp, _ = decode_joint_action(adr.act(core), noisy)
    assert sf[0, 0] == 0 and tp[0, 0] > 0


def test_adr_per_uav_uses_worst_margin_and_per_device_runs():
    cfg = ScenarioConfig(n_eds=2, n_uavs=1)
    core = BatchCore(cfg, n_envs=1)
    core.reset(0)
    core.ed_xy[0, 0] = core.uav_xy[0]  # strong ED
    core.ed_xy[0, 1] = core.uav_xy[0] + np.array([450.0, 0.0])  # weak ED
    core.observe()
    adr = AdrPolicy(cfg)
    adr.reset(core)
    adr.act(core)
    # expected: the rule applied to the weak ED's margin
    g = core.gains[0, 0, 1]
    snr_db = physics.lin_to_db(physics.snr(core.tables.tp_w[-1], g, core.tables.noise_w))
    m = snr_db - core.tables.threshold_db[-1, 0] - 10.0
    sf, tp = adr_update(np.array([5]), np.array([4]), np.array([m]), 5)
    assert (adr._sf[0, 0], adr._tp[0, 0]) == (sf[0], tp[0])
    dev = cfg.replace(action_mode="per_device")
    r = run_episodes(make_baseline("adr", dev), dev.replace(episode_len=5), episodes=2)
    assert np.isfinite(r.mean("ee_sys_mean"))


def test_greedy_reward_objective_and_encode_roundtrip():
    cfg = PAPER.replace(episode_len=5)
    r_reward = run_episodes(make_baseline("greedy", cfg, objective="reward"), cfg, episodes=2).mean("reward_mean")
    r_random = run_episodes(make_baseline("random", cfg), cfg, episodes=2).mean("reward_mean")
    assert r_reward > r_random
    a = encode_joint_action(*decode_joint_action(np.arange(90), PAPER), PAPER)
    np.testing.assert_array_equal(a, np.arange(90))
