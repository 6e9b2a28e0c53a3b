"""The simulator core and its two environment views: API conformance (PettingZoo, RLlib),
determinism and batch/single equivalence bit for bit, spaces, infos, truncation, rendering,
the action mappings, and invariants over random scenarios (hypothesis)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import make_cfg, random_actions, reference_greedy, run_core
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test, parallel_seed_test
from ray.rllib.utils.pre_checks.env import check_multiagent_environments

from uavlora_rllib.envs.multi_agent import UavLoraMultiAgentEnv, UavLoraParallelEnv, state_space
from uavlora_rllib.sim import physics
from uavlora_rllib.sim.actions import ActionError, decode_joint_action, encode_joint_action
from uavlora_rllib.sim.association import UNASSOCIATED
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.links import AllPairLinks, NearestLinks
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig

MODES = ["per_uav", "per_device"]
AGENTS = ["uav_0", "uav_1"]


def dict_actions(env, rng: np.random.Generator) -> dict:
    arr = random_actions(env.scenario, 1, rng)[0]
    return {a: arr[i] if arr.ndim == 2 else int(arr[i]) for i, a in enumerate(env.possible_agents)}


# ------------------------------------------------------------------ API conformance
@pytest.mark.parametrize("mode", MODES)
def test_pettingzoo_parallel_api(mode):
    env = UavLoraParallelEnv({"action_mode": mode, "episode_len": 40})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=100)
    pz = [str(w.message) for w in caught if "pettingzoo" in (w.filename or "")]
    assert not pz, pz  # the API test only warns about real protocol slips


@pytest.mark.parametrize("mode", MODES)
def test_pettingzoo_parallel_seed(mode):
    parallel_seed_test(lambda: UavLoraParallelEnv({"action_mode": mode, "episode_len": 60}), num_cycles=100)


@pytest.mark.parametrize("mode", MODES)
def test_rllib_multiagent_env_check(mode):
    env = UavLoraMultiAgentEnv({"scenario": {"action_mode": mode}})
    # the checker silently skips envs that did not call MultiAgentEnv.__init__: make sure it runs
    assert hasattr(env, "_agent_ids") and hasattr(env, "observation_space") and hasattr(env, "action_space")
    check_multiagent_environments(env)
    assert env.get_observation_space("uav_1") == env.observation_spaces["uav_1"]


# ------------------------------------------------------------------ determinism, equivalence
@pytest.mark.parametrize(
    "fields",
    [
        {},
        {"action_mode": "per_device"},
        {"association": "optimal", "interference": "cross_gain", "rate_model": "lora_phy", "n_eds": 15, "n_uavs": 3},
        {"n_eds": 30, "max_eds_per_uav": 4, "comm_range_m": 300.0},
    ],
)
def test_batch_equals_single_runs_bit_for_bit(fields):
    """BatchCore(N) seeded s == N runs of BatchCore(1) seeded s, s+1, ..., over a full episode
    (150 steps: crosses several refills of the noise buffers)."""
    cfg = make_cfg(**fields)
    n, seed, rng = 4, 17, np.random.default_rng(0)
    actions = [random_actions(cfg, n, rng) for _ in range(cfg.episode_len)]
    batch = run_core(cfg, n, seed, actions)
    assert batch["truncated"][-1].all() and not batch["truncated"][-2].any()
    for i in range(n):
        single = run_core(cfg, 1, seed + i, [a[i : i + 1] for a in actions])
        assert single.keys() == batch.keys()
        for key in batch:
            for t, (b, s) in enumerate(zip(batch[key], single[key])):
                assert np.array_equal(b[i], s[0]), f"{key} differs at step {t}, scenario {i}"
    # a list of seeds is the same as the int form
    listed = run_core(cfg, n, [seed + i for i in range(n)], actions[:10])
    for key in listed:
        assert all(np.array_equal(x, y) for x, y in zip(listed[key], batch[key][:11])), key


def test_same_seed_same_trajectory_and_different_seed_differs():
    cfg = make_cfg(n_eds=20)
    rng = np.random.default_rng(1)
    actions = [random_actions(cfg, 2, rng) for _ in range(50)]
    a, b, c = run_core(cfg, 2, 42, actions), run_core(cfg, 2, 42, actions), run_core(cfg, 2, 43, actions)
    for key in a:
        assert all(np.array_equal(x, y) for x, y in zip(a[key], b[key])), key
    assert not np.array_equal(a["ed_xy"][0], c["ed_xy"][0])
    # scenario 1 of seed 42 is scenario 0 of seed 43
    assert np.array_equal(a["ed_xy"][-1][1], c["ed_xy"][-1][0])
    # and a re-reset of the same core replays the episode
    core = BatchCore(cfg, 2)
    core.reset(42)
    for act in actions:
        core.step(act)
    assert np.array_equal(core.reset(42), a["obs"][0])


@pytest.mark.parametrize("mode", MODES)
def test_both_envs_give_the_same_trajectory(mode):
    cfg = make_cfg(action_mode=mode, n_eds=12, episode_len=30)
    pz, rl = UavLoraParallelEnv(cfg), UavLoraMultiAgentEnv({"scenario": cfg.to_dict()})
    obs_p, _ = pz.reset(seed=5)
    obs_r, info_r = rl.reset(seed=5)
    core = BatchCore(cfg, 1)
    core_obs = core.reset(5)
    rng = np.random.default_rng(3)
    for t in range(cfg.episode_len):
        for i, agent in enumerate(AGENTS):
            assert pz.observation_space(agent).contains(obs_p[agent])
            assert np.array_equal(obs_p[agent], obs_r[agent])
            assert np.array_equal(obs_p[agent], np.clip(core_obs[0, i], -1, 1).astype(np.float32))
        assert np.array_equal(pz.state(), rl.global_state())
        acts = dict_actions(pz, rng)
        obs_p, rew_p, term_p, trunc_p, info_p = pz.step(acts)
        obs_r, rew_r, term_r, trunc_r, info_r = rl.step(acts)
        res = core.step(np.array([[acts[a] for a in AGENTS]]))
        core_obs = res.obs
        assert rew_p == {a: rew_r[a] for a in AGENTS}
        assert rew_p["uav_0"] == float(res.reward[0])
        for agent in AGENTS:
            metrics_r = {k: v for k, v in info_r[agent].items() if k != "state"}
            assert info_p[agent] == metrics_r
            assert np.array_equal(info_r[agent]["state"], pz.state())
            assert trunc_p[agent] == trunc_r[agent] == (t == cfg.episode_len - 1)
            assert term_p[agent] is False and term_r[agent] is False
    assert pz.agents == []


# ------------------------------------------------------------------ spaces, infos, truncation, render
@pytest.mark.parametrize(
    "fields",
    [
        {},
        {"action_mode": "per_device"},
        {"n_eds": 1, "n_uavs": 4},  # V < U
        {"max_eds_per_uav": 1, "n_eds": 8},  # quota 1
        {"comm_range_m": 1.0},  # (almost) no ED in range
        {"association": "optimal", "n_eds": 40, "n_uavs": 3},
    ],
)
def test_observations_states_and_infos_every_step(fields):
    cfg = make_cfg(episode_len=25, **fields)
    env = UavLoraMultiAgentEnv(cfg)
    obs, infos = env.reset(seed=8)
    space_s = state_space(cfg)
    assert space_s.shape == (state_dim(cfg),) == (env.core.state_dim,)
    assert env.observation_spaces["uav_0"].shape == (obs_dim(cfg),)
    rng = np.random.default_rng(2)
    for t in range(cfg.episode_len + 1):
        assert set(obs) == set(env.possible_agents)
        for agent, o in obs.items():
            assert env.observation_spaces[agent].contains(o), (t, agent, o)
        for info in infos.values():
            assert info["state"].shape == space_s.shape and space_s.contains(info["state"])
            if t > 0:
                assert set(physics.SLOT_METRICS) <= set(info)
                assert all(np.isfinite(info[k]) for k in physics.SLOT_METRICS)
        # the raw core observation is already in [-1, 1]: the env's clip must not hide a scaling bug
        assert np.abs(env.core.obs).max() <= 1.0 + 1e-9
        assert env.core.state().shape == (1, env.core.state_dim)
        if t == cfg.episode_len:
            break
        obs, rew, terms, truncs, infos = env.step(dict_actions(env, rng))
        assert all(np.isfinite(r) for r in rew.values())


def test_episode_truncates_at_episode_len_never_terminates():
    cfg = make_cfg(episode_len=5)
    pz = UavLoraParallelEnv(cfg)
    rl = UavLoraMultiAgentEnv(cfg)
    pz.reset(seed=0)
    rl.reset(seed=0)
    acts = {a: 0 for a in AGENTS}
    for t in range(1, 6):
        _, _, term_p, trunc_p, _ = pz.step(acts)
        _, _, term_r, trunc_r, _ = rl.step(acts)
        assert not any(term_p.values()) and not any(term_r.values())
        assert term_r["__all__"] is False
        assert all(v == (t == 5) for v in trunc_p.values())
        assert all(v == (t == 5) for v in trunc_r.values()) and "__all__" in trunc_r
    assert pz.agents == []
    with pytest.raises(RuntimeError, match="reset"):
        pz.step(acts)
    pz.reset(seed=1)
    assert pz.agents == AGENTS
    core = BatchCore(cfg, 3)
    core.reset(0)
    flags = [core.step(np.zeros((3, 2), dtype=np.int64)).truncated.copy() for _ in range(5)]
    assert [f.tolist() for f in flags] == [[False] * 3] * 4 + [[True] * 3]


def _check_image(img):
    assert isinstance(img, np.ndarray) and img.dtype == np.uint8
    assert img.ndim == 3 and img.shape[2] == 3 and img.shape[0] >= 100 and img.shape[1] >= 100
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10  # not blank: several colours drawn
    assert (img < 200).any(axis=-1).mean() > 0.01  # and some ink, not just a white canvas


def test_render_rgb_array():
    env = UavLoraParallelEnv({"n_eds": 20}, render_mode="rgb_array")
    env.reset(seed=0)
    _check_image(env.render())
    env.step({a: 7 for a in AGENTS})
    first = env.render()
    _check_image(first)
    assert UavLoraParallelEnv({}).render() is None  # no render_mode: nothing to draw
    with pytest.raises(ValueError, match="render_mode"):  # "human" prints lines: tests/test_env_conventions.py
        UavLoraParallelEnv({}, render_mode="ansi")
    rl = UavLoraMultiAgentEnv({"scenario": {"n_eds": 20}})
    rl.reset(seed=0)
    rl.step({a: 7 for a in AGENTS})
    _check_image(rl.render())


# ------------------------------------------------------------------ action mappings
def test_per_uav_action_encoding():
    cfg = ScenarioConfig()
    # index = (sf_index * 5 + tp_index) * 3 + bw_index
    assert [tuple(int(x) for x in decode_joint_action(a, cfg)) for a in (0, 1, 3, 15, 89)] == [
        (0, 0, 0), (0, 0, 1), (0, 1, 0), (1, 0, 0), (5, 4, 2)
    ]  # fmt: skip
    all_a = np.arange(90)
    sf, tp, bw = decode_joint_action(all_a, cfg)
    np.testing.assert_array_equal(encode_joint_action(sf, tp, bw, cfg), all_a)
    assert sf.max() == 5 and tp.max() == 4 and bw.max() == 2


def test_per_uav_action_applies_to_every_ed_the_uav_serves():
    cfg = make_cfg(n_eds=20)
    core = BatchCore(cfg, 2)
    core.reset(4)
    actions = np.array([[89, 16], [0, 44]])
    sf, tp, bw = core.allocations(actions)
    for i in range(2):
        for v in range(20):
            u = core.serving[i, v]
            if u == UNASSOCIATED:
                continue
            a = actions[i, u]
            assert (sf[i, v], tp[i, v], bw[i, v]) == (a // 15, (a // 3) % 5, a % 3)


def test_per_device_slot_k_is_the_kth_served_ed_by_gain():
    cfg = make_cfg(action_mode="per_device", n_eds=14, n_uavs=2)
    q = cfg.quota  # ceil(1.5 * 14 / 2) = 11
    assert q == 11
    core = BatchCore(cfg, 2)
    core.reset(31)
    rng = np.random.default_rng(5)
    actions = random_actions(cfg, 2, rng)
    gains, serving, associated = core.gains.copy(), core.serving.copy(), core.associated.copy()
    obs = core.obs.copy()
    expected = np.full((2, 14, 3), -1)
    for i in range(2):
        for u in range(2):
            served = [v for v in range(14) if serving[i, v] == u]
            ranked = sorted(served, key=lambda v: -gains[i, u, v])  # best gain first
            assert obs[i, u, 4 * q] == pytest.approx(len(served) / q)  # count feature
            for k, v in enumerate(ranked):
                expected[i, v] = actions[i, u, 2 * k], actions[i, u, 2 * k + 1], actions[i, u, -1]
                # row k of UAV u's observation is that ED: its scaled position
                np.testing.assert_allclose(obs[i, u, 4 * k : 4 * k + 2], 2 * core.ed_xy[i, v] / 1000 - 1)
            assert not obs[i, u, 4 * len(served) : 4 * q].any()  # padding rows are zeros
    got = np.stack(core.allocations(actions), axis=-1)
    assoc = associated[..., None]
    np.testing.assert_array_equal(np.where(assoc, got, -1), expected)
    # and the step scores exactly those allocations
    srv = np.where(associated, serving, 0)
    sf, tp, bw = (np.where(associated, expected[..., j], 0) for j in range(3))
    want = physics.slot_metrics(gains, srv, associated, sf, tp, bw, cfg, core.tables)
    res = core.step(actions)
    for key in physics.SLOT_METRICS:
        np.testing.assert_allclose(res.metrics[key], want[key], rtol=1e-12, err_msg=key)
    # padding slots are ignored: changing them changes nothing
    core2 = BatchCore(cfg, 2)
    core2.reset(31)
    padded = actions.copy()
    for i in range(2):
        for u in range(2):
            n_served = int((serving[i] == u).sum())
            padded[i, u, 2 * n_served : 2 * q] = 0
    res2 = core2.step(padded)
    for key in physics.SLOT_METRICS:
        assert np.array_equal(res2.metrics[key], res.metrics[key]), key


# ------------------------------------------------------------------ invariants over random scenarios
@st.composite
def scenarios(draw):
    n_uavs = draw(st.integers(1, 5))
    fields = {
        "n_eds": draw(st.integers(1, 12)),
        "n_uavs": n_uavs,
        "area_m": draw(st.sampled_from([100.0, 1000.0, 3000.0])),
        "comm_range_m": draw(st.sampled_from([0.5, 50.0, 600.0, 5000.0])),
        "max_eds_per_uav": draw(st.one_of(st.none(), st.integers(1, 4))),
        "association": draw(st.sampled_from(["greedy", "optimal"])),
        "interference": draw(st.sampled_from(["paper", "cross_gain"])),
        "rate_model": draw(st.sampled_from(["shannon", "lora_phy"])),
        "action_mode": draw(st.sampled_from(MODES)),
        "mobility": {"sigma": draw(st.sampled_from([0.0, 0.5, 30.0])), "v_max_mps": draw(st.sampled_from([1.0, 50.0]))},
    }
    return make_cfg(**fields), draw(st.integers(0, 2**31)), draw(st.integers(1, 3))


def check_slot(core: BatchCore) -> None:
    cfg = core.cfg
    assert np.isfinite(core.obs).all() and np.abs(core.obs).max() <= 1.0 + 1e-9
    state = core.state()
    assert state.shape == (core.n, core.state_dim) and np.isfinite(state).all()
    assert state.min() >= -3.0 and state.max() <= 1.0
    serving = core.serving
    assert ((serving >= UNASSOCIATED) & (serving < cfg.n_uavs)).all()  # at most one UAV each
    for i in range(core.n):
        counts = np.bincount(serving[i][serving[i] >= 0], minlength=cfg.n_uavs)
        assert (counts <= cfg.quota).all()
        np.testing.assert_allclose(core.obs[i, :, 4 * cfg.quota], counts / cfg.quota)
        for v in np.flatnonzero(serving[i] >= 0):
            assert core.d_h[i, serving[i, v], v] <= cfg.comm_range_m
        if cfg.association == "greedy":
            assert serving[i].tolist() == reference_greedy(core.gains[i], core.d_h[i], cfg.comm_range_m, cfg.quota)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenarios())
def test_invariants_over_random_scenarios(case):
    cfg, seed, n = case
    core = BatchCore(cfg, n)
    core.reset(seed)
    rng = np.random.default_rng(seed)
    check_slot(core)
    for _ in range(6):
        res = core.step(random_actions(cfg, n, rng))
        assert set(res.metrics) == set(physics.SLOT_METRICS)
        for key, value in res.metrics.items():
            assert value.shape == (n,) and np.isfinite(value).all(), key
        assert np.isfinite(res.reward).all()
        assert ((res.metrics["success_rate"] >= 0) & (res.metrics["success_rate"] <= 1)).all()
        assert ((res.metrics["beta"] >= -10) & (res.metrics["beta"] <= 1)).all()
        assert (res.metrics["ee_sys"] >= 0).all()
        check_slot(core)


@pytest.mark.parametrize("mode", MODES)
def test_ed_right_under_a_uav_is_finite(mode):
    # memory 1, sigma 0 and zero velocity: the EDs stay exactly where they are put
    cfg = make_cfg(action_mode=mode, n_eds=4, mobility={"memory": 1.0, "sigma": 0.0})
    core = BatchCore(cfg, 1)
    core.reset(0)
    core.ed_xy[0] = [core.uav_xy[0], core.uav_xy[1], core.uav_xy[0], [10.0, 10.0]]
    core.ed_vel[...] = 0.0
    rng = np.random.default_rng(0)
    core.step(random_actions(cfg, 1, rng))  # the next slot has d_h = 0 exactly
    assert core.d_h[0, 0, 0] == 0.0 and core.d_h[0, 1, 1] == 0.0
    check_slot(core)
    assert core.obs[0, 0, 3] == pytest.approx(1.0)  # the best possible link maps to gain feature 1
    res = core.step(random_actions(cfg, 1, rng))
    assert all(np.isfinite(v).all() for v in res.metrics.values())


@pytest.mark.parametrize("n_eds", [8, 30])
def test_partial_reset_replays_single_runs(n_eds):
    """reset(seed, mask) restarts only the masked scenarios; each scenario still equals its own
    single run (the batch's noise cursors then differ between scenarios)."""
    cfg = make_cfg(n_eds=n_eds)
    rng = np.random.default_rng(11)
    first = [random_actions(cfg, 3, rng) for _ in range(45)]
    core = BatchCore(cfg, 3)
    core.reset(0)  # scenarios seeded 0, 1, 2
    for a in first[:13]:
        core.step(a)
    core.reset([None, 100, None], mask=np.array([False, True, False]))
    assert core.t.tolist() == [13, 0, 13]
    for a in first[13:]:
        core.step(a)
    single0 = run_core(cfg, 1, 0, [a[0:1] for a in first])
    single1 = run_core(cfg, 1, 100, [a[1:2] for a in first[13:]])
    single2 = run_core(cfg, 1, 2, [a[2:3] for a in first])
    assert np.array_equal(core.ed_xy[0], single0["ed_xy"][-1][0])
    assert np.array_equal(core.ed_xy[1], single1["ed_xy"][-1][0])
    assert np.array_equal(core.ed_xy[2], single2["ed_xy"][-1][0])
    assert np.array_equal(core.obs[1], single1["obs"][-1][0])
    with pytest.raises(ValueError, match="first reset"):
        BatchCore(cfg, 2).reset(0, mask=np.array([True, False]))


def test_unseeded_resets_differ():
    core = BatchCore(make_cfg(), 2)
    a = core.reset().copy()
    b = core.reset().copy()
    assert not np.array_equal(a, b)
    assert not np.array_equal(a[0], a[1])


def test_state_layout_by_hand():
    """s = [ED positions 2V | gain features UV | association one-hot V(U+1) | previous SF, TP, BW
    one-hots V n_sf, V n_tp, V n_bw | t / T] (core.py docstring, README)."""
    cfg = make_cfg(n_eds=5, n_uavs=2, comm_range_m=400.0)
    v, u = 5, 2
    core = BatchCore(cfg, 1)
    core.reset(12)
    s0 = core.state()[0]
    assert s0.shape == (2 * v + u * v + v * (u + 1) + v * (6 + 5 + 3) + 1,) == (core.state_dim,)
    np.testing.assert_allclose(s0[: 2 * v], (2 * core.ed_xy[0] / 1000 - 1).reshape(-1))
    assert not s0[2 * v + u * v + v * (u + 1) : -1].any()  # no previous action yet
    assert s0[-1] == 0.0
    core.step(np.array([[encode_joint_action(5, 1, 2, cfg), encode_joint_action(0, 4, 0, cfg)]]))
    played = core.prev_alloc[0]  # the slot just played: (sf, tp, bw) or -1 per ED
    s1 = core.state()[0]
    off = 2 * v + u * v
    assoc = s1[off : off + v * (u + 1)].reshape(v, u + 1)
    col = np.where(core.serving[0] >= 0, core.serving[0], u)  # last column = unassociated
    np.testing.assert_array_equal(assoc, np.eye(u + 1)[col])
    off += v * (u + 1)
    blocks = []
    for size in (6, 5, 3):
        blocks.append(s1[off : off + v * size].reshape(v, size))
        off += v * size
    for ed in range(v):
        if played[ed, 0] < 0:
            assert not any(b[ed].any() for b in blocks)  # silent ED: zeros
        else:
            for b, idx in zip(blocks, played[ed]):
                np.testing.assert_array_equal(b[ed], np.eye(b.shape[1])[idx])
    assert set(map(tuple, played[played[:, 0] >= 0].tolist())) <= {(5, 1, 2), (0, 4, 0)}
    assert s1[-1] == pytest.approx(1 / 150)


def test_gain_feature_is_minus_one_at_r_comm():
    cfg = make_cfg(n_eds=2, comm_range_m=400.0, mobility={"memory": 1.0, "sigma": 0.0})
    core = BatchCore(cfg, 1)
    core.reset(0)
    core.ed_xy[0] = [[250.0, 900.0], [750.0, 500.0]]  # 400 m from UAV0 (640 m from UAV1); under UAV1
    core.ed_vel[...] = 0.0
    core.step(np.zeros((1, 2), dtype=np.int64))
    assert core.serving[0].tolist() == [0, 1]
    np.testing.assert_allclose(core.obs[0, 0, :4], [-0.5, 0.8, 1.0, -1.0], atol=1e-9)  # x, y, d/R, G
    np.testing.assert_allclose(core.obs[0, 1, :4], [0.5, 0.0, 0.0, 1.0], atol=1e-9)


@pytest.mark.parametrize("mode", MODES)
def test_spaces_follow_reduced_sets(mode):
    cfg = make_cfg(action_mode=mode, sf_set=[9, 12], bw_khz=[125], tp_dbm=[5.0, 14.0], n_eds=6, n_uavs=3)
    env = UavLoraParallelEnv(cfg)
    space = env.action_space("uav_2")
    if mode == "per_uav":
        assert space.n == 2 * 2 * 1 == cfg.n_joint_actions
    else:
        assert space.nvec.tolist() == [2, 2] * cfg.quota + [1]
    obs, _ = env.reset(seed=3)
    for _ in range(5):
        obs, *_ = env.step({a: space.sample() for a in env.agents})
        assert all(env.observation_space(a).contains(o) for a, o in obs.items())
    zero = np.zeros(2 * cfg.quota + 1, dtype=np.int64)
    if mode == "per_uav":
        bad, high, ok = 4, 4, 0  # 2 SFs x 2 TPs x 1 BW joint actions
    else:
        bad, high, ok = np.r_[2, zero[1:]], 2, zero  # slot 0's SF index, 2 SFs
    with pytest.raises(ActionError, match=rf"action of uav_0 .*is outside \[0, {high}\)"):
        env.step({"uav_0": bad, "uav_1": ok, "uav_2": ok})


# ------------------------------------------------------------------ fast paths = the general ones
CORE_VARIANTS = [
    {},
    {"n_eds": 30, "max_eds_per_uav": 4, "comm_range_m": 300.0},  # quotas bind, some EDs out of range
    {"n_eds": 40, "n_uavs": 3, "action_mode": "per_device"},
    {"n_eds": 100, "n_uavs": 8},  # long rows: the quicksort path of the slot ranking
]


@pytest.mark.parametrize("fields", CORE_VARIANTS)
def test_nearest_path_equals_the_all_pairs_path(fields):
    """The default path (channel at the nearest UAV only) against the path that computes every
    pair's channel and runs greedy_association on it: the same trajectory, bit for bit."""
    cfg = make_cfg(**fields)
    fast, full = BatchCore(cfg, 3), BatchCore(cfg, 3, link_stage=AllPairLinks)
    assert isinstance(fast.link_stage, NearestLinks)
    rng = np.random.default_rng(4)
    assert np.array_equal(fast.reset(8), full.reset(8))
    for _ in range(40):
        a = random_actions(cfg, 3, rng)
        rf, rp = fast.step(a), full.step(a)
        assert np.array_equal(rf.obs, rp.obs)
        assert np.array_equal(fast.serving, full.serving) and np.array_equal(fast.slot_of_ed, full.slot_of_ed)
        assert np.array_equal(fast.state(), full.state())
        for key in physics.SLOT_METRICS:
            assert np.array_equal(rf.metrics[key], rp.metrics[key]), key


@pytest.mark.parametrize(
    "fields",
    CORE_VARIANTS
    + [{"association": "optimal", "interference": "cross_gain", "n_eds": 12}, {"eta_los_db": 30.0, "eta_nlos_db": 0.0}],
)
def test_lookahead_equals_plain_stepping(fields):
    """BatchCore(cfg, 1, lookahead=K) precomputes K slots at once: same numbers as stepping one
    slot at a time, across block boundaries, episode ends and re-resets."""
    cfg = make_cfg(episode_len=23, **fields)
    rng = np.random.default_rng(6)
    plain, ahead = BatchCore(cfg, 1), BatchCore(cfg, 1, lookahead=5)
    for seed in (3, 3, 11):
        assert np.array_equal(plain.reset(seed), ahead.reset(seed))
        for _ in range(int(rng.integers(1, 30))):
            a = random_actions(cfg, 1, rng)
            rp, ra = plain.step(a), ahead.step(a)
            assert np.array_equal(rp.obs, ra.obs) and np.array_equal(rp.truncated, ra.truncated)
            for key in physics.SLOT_METRICS:
                assert np.array_equal(rp.metrics[key], ra.metrics[key]), key
            for attr in ("ed_xy", "ed_vel", "ed_mean_vel", "serving", "slot_of_ed", "t", "prev_alloc", "gains", "d_h"):
                assert np.array_equal(getattr(plain, attr), getattr(ahead, attr)), attr
            assert np.array_equal(plain.state(), ahead.state())
    with pytest.raises(ValueError, match="lookahead"):
        BatchCore(cfg, 2, lookahead=4)


@pytest.mark.parametrize("action_mode", ["per_uav", "per_device"])
def test_step_scores_the_gains_the_core_exposes(action_mode):
    """slot_metrics on core.gains (every pair, computed on demand) gives the step's metrics:
    bit for bit in per_device mode; in per_uav mode the step uses slot_metrics_shared (the
    same equations with each UAV's factors taken out of its sums), equal up to rounding, and
    bit for bit to slot_metrics_shared on the gains the core exposes."""
    cfg = make_cfg(n_eds=20, comm_range_m=300.0, action_mode=action_mode)  # (some EDs out of range)
    core = BatchCore(cfg, 4)
    core.reset(2)
    rng = np.random.default_rng(0)
    silent = 0
    for _ in range(10):
        a = random_actions(cfg, 4, rng)
        sf, tp, bw = core.allocations(a)
        want = physics.slot_metrics(core.gains, core.links.serving_idx, core.associated, sf, tp, bw, cfg, core.tables)
        if action_mode == "per_uav":
            g = physics.at_serving(core.gains, core.links.serving_idx)
            g_db = physics.at_serving(core.gain_db, core.links.serving_idx)
            flat = core.links.serving_idx + np.arange(4)[:, None] * cfg.n_uavs
            counts = physics.group_count(np.where(core.associated, core.links.serving_idx, cfg.n_uavs), cfg.n_uavs + 1)
            alloc = physics.shared_allocation(*decode_joint_action(a, cfg), core.tables)
            shared = physics.slot_metrics_shared(
                g, g_db, flat, core.associated, counts[:, :-1], alloc, cfg, core.tables
            )
        silent += int((~core.associated).sum())
        res = core.step(a)
        for key in physics.SLOT_METRICS:
            if action_mode == "per_device":
                assert np.array_equal(res.metrics[key], want[key]), key
            else:
                assert np.array_equal(res.metrics[key], shared[key]), key
                np.testing.assert_allclose(res.metrics[key], want[key], rtol=1e-12, atol=1e-12, err_msg=key)
    assert silent > 0  # the masks of unassociated EDs were exercised


@pytest.mark.parametrize("n_eds,n_uavs", [(100, 8), (10, 2), (40, 64)])
def test_slot_is_the_rank_by_gain_ties_by_ed_id(n_eds, n_uavs):
    """slot_of_ed and the counts against their definition, with tied gains (EDs at the same
    place) to exercise the sorts' tie handling."""
    cfg = make_cfg(n_eds=n_eds, n_uavs=n_uavs)
    core = BatchCore(cfg, 5)
    core.reset(3)
    xy = core.ed_xy  # a view: writing moves the EDs
    xy[1, 1::2] = xy[1, 0::2]  # scenario 1: pairs of EDs at the same place
    xy[2] = xy[2, 0]  # scenario 2: all at one place
    core.observe()
    g, serving = core.g_serving, core.serving
    for i in range(core.n):
        for v in range(n_eds):
            u = serving[i, v]
            if u < 0:
                assert core.slot_of_ed[i, v] == -1
                continue
            ahead = [w for w in range(n_eds) if serving[i, w] == u and (g[i, w], -w) > (g[i, v], -v)]
            assert core.slot_of_ed[i, v] == len(ahead)
        np.testing.assert_array_equal(core.links.counts[i], np.bincount(serving[i][serving[i] >= 0], minlength=n_uavs))
