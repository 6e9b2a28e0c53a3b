"""QMIX/VDN in per_device mode: the branching agent network, its branch math, the replay of
action vectors, double Q per branch, and one short build through the registry."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, HIDDEN, TERMINATED
from uavlora_rllib.algorithms.common.config import hparams_model_config
from uavlora_rllib.algorithms.qmix import branching
from uavlora_rllib.algorithms.qmix.branching_module import Q_BW, Q_SLOTS, BranchingQMixModule
from uavlora_rllib.algorithms.qmix.qmix import QMIXHParams
from uavlora_rllib.algorithms.qmix.qmix_module import Q_TAKEN, Q_TOT, TARGET_Q_TOT_NEXT, QMixModule
from uavlora_rllib.algorithms.qmix.qmix_replay import EpisodeReplay
from uavlora_rllib.envs.team import team_action_space, team_observation_space
from uavlora_rllib.sim.observation import OBS_ROW
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

U, K, N_SF, N_TP, N_BW = 2, 3, 6, 5, 3  # the paper's sets; quota 3
P = N_SF * N_TP
OBS_DIM = 4 * K + 3
L = 2 * K + 1
STATE_DIM = 4


def _module(mixer="vdn", **extra) -> BranchingQMixModule:
    mc = hparams_model_config(
        QMIXHParams,
        **{
            "n_agents": U,
            "obs_dim": OBS_DIM,
            "n_actions": N_SF * N_TP * N_BW,
            "state_dim": STATE_DIM,
            "gru_hidden": 8,
            "fc_hidden": 8,
            "head_hidden": 6,
            "mixer": mixer,
            "action_mode": "per_device",
            "epsilon_anneal_env_steps": QMIXHParams().epsilon_anneal_env_steps,
            **extra,
        },
    )
    nvec = np.tile(np.array([N_SF, N_TP] * K + [N_BW]), (U, 1))
    obs_space = gym.spaces.Box(-1, 1, (U, OBS_DIM), np.float32)
    mod = BranchingQMixModule(observation_space=obs_space, action_space=gym.spaces.MultiDiscrete(nvec), model_config=mc)
    mod.make_target_networks()  # as the learner does after its build
    return mod


def _obs(b: int, t: int, counts: np.ndarray | None = None, seed: int = 0) -> torch.Tensor:
    """Observations [b, t, U, d] with counts [b, t, U] served EDs (random rows, zero rows after)."""
    rng = np.random.default_rng(seed)
    if counts is None:
        counts = rng.integers(0, K + 1, size=(b, t, U))
    obs = np.zeros((b, t, U, OBS_DIM), np.float32)
    rows = rng.uniform(-1, 1, size=(b, t, U, K, OBS_ROW)).astype(np.float32)
    rows[np.arange(K) >= counts[..., None]] = 0.0
    obs[..., : K * OBS_ROW] = rows.reshape(b, t, U, -1)
    obs[..., K * OBS_ROW] = counts / K
    obs[..., K * OBS_ROW + 1 :] = rng.uniform(-1, 1, size=(b, t, U, 2))
    return torch.as_tensor(obs)


def _batch(b=3, t=5, seed=0) -> dict:
    rng = np.random.default_rng(seed)
    nvec = np.array([N_SF, N_TP] * K + [N_BW])
    return {
        Columns.OBS: _obs(b, t + 1, seed=seed),
        Columns.ACTIONS: torch.as_tensor(rng.integers(0, nvec, size=(b, t, U, L))),
        Columns.REWARDS: torch.as_tensor(rng.normal(size=(b, t)).astype(np.float32)),
        GLOBAL_STATE: torch.as_tensor(rng.normal(size=(b, t + 1, STATE_DIM)).astype(np.float32)),
        TERMINATED: torch.zeros(b, dtype=torch.bool),
    }


# ---------------------------------------------------------------------- network and branch math
@pytest.mark.parametrize("slot_head", ["per_slot", "shared"])
@pytest.mark.parametrize("share", [True, False])
def test_shapes_and_head_parameters(slot_head, share):
    torch.manual_seed(0)
    mod = _module(slot_head=slot_head, share_agent_net=share)
    q = mod.compute_q_values({Columns.OBS: _obs(4, 7)})
    assert q[Q_SLOTS].shape == (4, 7, U, K, P) and q[Q_BW].shape == (4, 7, U, N_BW)
    heads = mod.agent.slot_heads
    assert heads.w1.shape == (1 if share else U, K if slot_head == "per_slot" else 1, 8 + OBS_ROW, 6)
    assert heads.w2.shape[-1] == P and mod.agent.bw_head.w2.shape[-1] == N_BW
    assert (mod.quota, mod.n_pairs, mod.n_bw) == (K, P, N_BW)


@pytest.mark.parametrize("dueling", [True, False])
def test_additive_slot_utility_is_sf_value_plus_tp_value(dueling):
    """slot_utility additive: the slot head gives n_sf + n_tp values and each pair's utility is Q(sf) + Q(tp)
    (around V_u when dueling), so the greedy pair is the SF argmax with the TP argmax."""
    torch.manual_seed(3)
    mod = _module(slot_utility="additive", dueling=dueling)
    assert mod.agent.slot_heads.w2.shape[-1] == N_SF + N_TP
    q = mod.compute_q_values({Columns.OBS: _obs(2, 3)})[Q_SLOTS].unflatten(-1, (N_SF, N_TP))  # [.., sf, tp]
    assert q.shape == (2, 3, U, K, N_SF, N_TP)
    # additive: every 2x2 minor of the pair table has zero interaction, q[a,c] + q[b,d] = q[a,d] + q[b,c]
    torch.testing.assert_close(q[..., 1:, 1:] + q[..., :1, :1], q[..., 1:, :1] + q[..., :1, 1:], rtol=0, atol=1e-5)
    best = q.flatten(-2).argmax(-1)
    torch.testing.assert_close(best // N_TP, q.amax(-1).argmax(-1))
    torch.testing.assert_close(best % N_TP, q.amax(-2).argmax(-1))
    assert _module().agent.slot_heads.w2.shape[-1] == P  # joint, the default: one value per pair


@pytest.mark.parametrize("dueling", [True, False])
def test_dueling_branches_share_the_uav_state_value(dueling):
    torch.manual_seed(7)
    mod = _module(dueling=dueling)
    q = mod.compute_q_values({Columns.OBS: _obs(3, 4)})
    assert (mod.agent.value_head is not None) == dueling
    means = torch.cat((q[Q_SLOTS].mean(-1), q[Q_BW].mean(-1, keepdim=True)), dim=-1)  # [B, T, U, K + 1]
    same = torch.allclose(means, means[..., :1].expand_as(means), atol=1e-5)
    assert same == dueling  # dueling: every branch's mean utility is V_u


def test_action_encoding_round_trips():
    rng = np.random.default_rng(0)
    actions = torch.as_tensor(rng.integers(0, [N_SF, N_TP] * K + [N_BW], size=(10, U, L)))
    slot_idx, bw_idx = branching.branch_indices(actions, N_TP)
    assert slot_idx.shape == (10, U, K) and (slot_idx < P).all()
    assert torch.equal(branching.env_actions(slot_idx, bw_idx, N_TP), actions)
    assert branching.action_dims([6, 5, 6, 5, 3]) == (2, 6, 5, 3)
    with pytest.raises(ValueError, match="per_device action row"):
        branching.action_dims([6, 5, 5, 6, 3])


def test_greedy_is_the_argmax_of_every_branch():
    torch.manual_seed(1)
    mod = _module()
    obs = _obs(64, 1)
    batch = {Columns.OBS: obs, Columns.STATE_IN: {HIDDEN: torch.zeros(64, U, 8)}}
    actions = mod.forward_inference(batch)[Columns.ACTIONS]
    assert actions.shape == (64, 1, U, L)
    (slot_q, bw_q), _ = mod._step(batch)
    sf, tp, bw = actions[:, 0, :, 0:-1:2], actions[:, 0, :, 1:-1:2], actions[:, 0, :, -1]
    assert torch.equal(sf * N_TP + tp, slot_q.argmax(-1)) and torch.equal(bw, bw_q.argmax(-1))
    # each branch on its own: the chosen utility is the maximum of its branch
    chosen = slot_q.gather(-1, (sf * N_TP + tp).unsqueeze(-1)).squeeze(-1)
    assert torch.equal(chosen, slot_q.max(-1).values)
    space = gym.spaces.MultiDiscrete(np.tile(np.array([N_SF, N_TP] * K + [N_BW]), (U, 1)))
    assert all(space.contains(a.numpy()) for a in actions[:, 0])


def test_active_slots_follow_the_served_count():
    counts = np.array([[[0, 3], [1, 2]]])  # [1, 2, U]
    active = branching.active_slots(_obs(1, 2, counts), K)
    assert active.tolist() == [[[[False] * 3, [True] * 3], [[True, False, False], [True, True, False]]]]
    # the real observation marks them the same way: rows beyond the count are the zero rows
    from uavlora_rllib.sim.core import BatchCore

    cfg = ScenarioConfig(n_eds=5, n_uavs=3, action_mode="per_device", episode_len=4)
    core = BatchCore(cfg, 8)
    core.reset(3)
    obs = torch.as_tensor(np.clip(core.obs, -1, 1), dtype=torch.float32)
    act = branching.active_slots(obs, cfg.quota)
    rows = branching.slot_rows(obs, cfg.quota)
    assert torch.equal(act, (rows != 0).any(-1)) and act.sum() == int(
        core.obs[..., cfg.quota * 4].sum() * cfg.quota + 0.5
    )


def test_aggregation_ignores_empty_slots():
    slot_v = torch.tensor([[1.0, 2.0, 100.0], [5.0, -7.0, 3.0], [9.0, 9.0, 9.0]])
    bw_v = torch.tensor([4.0, 1.0, 2.0])
    active = torch.tensor([[True, True, False], [True, True, True], [False, False, False]])
    torch.testing.assert_close(branching.aggregate(slot_v, bw_v, active), torch.tensor([7.0 / 3, 2.0 / 4, 2.0]))
    # through the module: utilities of empty slots never reach Q_u, Q_tot or the target
    torch.manual_seed(2)
    mod = _module()
    batch = _batch()
    out = mod.forward_train(batch)
    other = dict(batch)
    act = branching.active_slots(batch[Columns.OBS][:, :-1], K)
    other_actions = batch[Columns.ACTIONS].clone()
    flip = torch.stack((~act, ~act), dim=-1).flatten(-2)  # the SF and TP entries of empty slots
    other_actions[..., :-1] = torch.where(
        flip, (other_actions[..., :-1] + 1) % torch.tensor([N_SF, N_TP] * K), other_actions[..., :-1]
    )
    other[Columns.ACTIONS] = other_actions
    assert not torch.equal(other_actions, batch[Columns.ACTIONS])
    torch.testing.assert_close(mod.forward_train(other)[Q_TAKEN], out[Q_TAKEN])


def test_epsilon_is_per_branch():
    torch.manual_seed(3)
    n = 20_000
    slot_idx, bw_idx = torch.zeros(n, U, K, dtype=torch.long), torch.zeros(n, U, dtype=torch.long)
    eps = 0.3
    s, b = branching.explore(slot_idx, bw_idx, P, N_BW, eps)
    # a branch differs from greedy when it explored and drew another value
    assert abs((s != 0).float().mean().item() - eps * (1 - 1 / P)) < 0.01
    assert abs((b != 0).float().mean().item() - eps * (1 - 1 / N_BW)) < 0.01
    # independently: both slots 0 and 1 of a UAV changed about (eps (1 - 1/P))^2 of the time, not eps
    both = ((s[..., 0] != 0) & (s[..., 1] != 0)).float().mean().item()
    assert abs(both - (eps * (1 - 1 / P)) ** 2) < 0.01
    # a random branch is uniform over SF and over TP
    s1, _ = branching.explore(slot_idx, bw_idx, P, N_BW, 1.0)
    for part, n_part in ((s1 // N_TP, N_SF), (s1 % N_TP, N_TP)):
        share = torch.bincount(part.reshape(-1), minlength=n_part).float() / part.numel()
        assert (share - 1 / n_part).abs().max() < 0.01
    # the module: epsilon 1 at t = 0 of the schedule, epsilon_end = 0 after it: greedy
    mod = _module(epsilon_end=0.0)
    batch = {Columns.OBS: _obs(200, 1), Columns.STATE_IN: {HIDDEN: torch.zeros(200, U, 8)}}
    greedy = mod.forward_inference(batch)[Columns.ACTIONS]
    assert torch.equal(mod.forward_exploration(batch, t=10**9)[Columns.ACTIONS], greedy)
    early = mod.forward_exploration(batch, t=0)[Columns.ACTIONS]
    assert (early[..., :-1] != greedy[..., :-1]).float().mean() > 0.75  # uniform SF (5/6) and TP (4/5)


# ---------------------------------------------------------------------- replay and learning
def test_replay_stores_and_returns_action_vectors():
    rep = EpisodeReplay(capacity=4, episode_len=3, n_agents=U, obs_dim=OBS_DIM, state_dim=2, seed=0, action_len=L)
    assert rep.actions.shape == (4, 3, U, L)
    rng = np.random.default_rng(0)
    stored = []
    for k in range(4):
        actions = rng.integers(0, 5, size=(3, U, L))
        stored.append(actions)
        rep.add(np.full((4, U, OBS_DIM), k, np.float32), actions, np.zeros(3), np.zeros((4, 2)))
    s = rep.sample(4)
    assert s[Columns.ACTIONS].shape == (4, 3, U, L) and s[Columns.ACTIONS].dtype == np.int64
    for row, ep in zip(s[Columns.ACTIONS], s[Columns.OBS][:, 0, 0, 0].astype(int)):
        np.testing.assert_array_equal(row, stored[ep])
    with pytest.raises(ValueError, match="whole episodes of 3 steps"):
        rep.add(np.zeros((4, U, OBS_DIM)), np.zeros((3, U)), np.zeros(3), np.zeros((4, 2)))  # per_uav actions
    assert EpisodeReplay(2, 3, U, OBS_DIM, 2).actions.shape == (2, 3, U)  # per_uav: one index per UAV


def test_gamma_zero_leaves_the_target_networks_unread():
    """At gamma 0 (the per_device benchmark) the TD target is the reward: no target agent network pass,
    no TARGET_Q_TOT_NEXT; the online outputs are those of any other gamma."""
    batch = _batch(b=2, t=4, seed=6)
    outs = {}
    for gamma in (0.0, 0.9):
        torch.manual_seed(7)
        mod = _module(mixer="qmix", gamma=gamma)
        calls: list[int] = []
        mod._target_agent.register_forward_hook(lambda *_, calls=calls: calls.append(1))
        outs[gamma] = mod.forward_train(batch)
        assert (TARGET_Q_TOT_NEXT in outs[gamma], len(calls)) == ((False, 0) if gamma == 0.0 else (True, 1))
    torch.testing.assert_close(outs[0.0][Q_TOT], outs[0.9][Q_TOT])


@pytest.mark.parametrize("double_q", [True, False])
def test_target_is_double_q_per_branch(double_q):
    """TARGET_Q_TOT_NEXT against a hand computation (VDN without V(s): the sum of the UAVs' means)."""
    torch.manual_seed(4)
    mod = _module(mixer="vdn", state_bias=False, double_q=double_q)
    with torch.no_grad():  # a target network that differs from the online one
        for p in mod._target_agent.parameters():
            p.add_(torch.randn_like(p) * 0.5)
    batch = _batch(b=2, t=4, seed=5)
    with torch.no_grad():
        online = mod.compute_q_values(batch)
        t_slot, t_bw, _ = mod._target_agent(batch[Columns.OBS], torch.zeros(2, U, 8))
        got = mod.forward_train(batch)[TARGET_Q_TOT_NEXT].numpy()
    on_s, on_b = online[Q_SLOTS].numpy(), online[Q_BW].numpy()
    t_slot, t_bw = t_slot.numpy(), t_bw.numpy()
    counts = np.rint(batch[Columns.OBS][..., K * OBS_ROW].numpy() * K).astype(int)
    want = np.zeros((2, 4))
    for b in range(2):
        for t in range(4):
            for u in range(U):
                vals = []
                for k in range(counts[b, t + 1, u]):
                    a = on_s[b, t + 1, u, k].argmax() if double_q else t_slot[b, t + 1, u, k].argmax()
                    vals.append(t_slot[b, t + 1, u, k, a])
                a_bw = on_b[b, t + 1, u].argmax() if double_q else t_bw[b, t + 1, u].argmax()
                vals.append(t_bw[b, t + 1, u, a_bw])
                want[b, t] += np.mean(vals)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("slot_head", ["per_slot", "shared"])
@pytest.mark.parametrize("mixer", ["qmix", "vdn"])
def test_gradient_reaches_every_head(slot_head, mixer):
    torch.manual_seed(5)
    mod = _module(mixer=mixer, slot_head=slot_head, share_agent_net=False)
    batch = _batch(b=4, t=6, seed=6)
    batch[Columns.OBS][:, :, :, K * OBS_ROW] = 1.0  # every slot active, rows random
    out = mod.forward_train(batch)
    (out[Q_TOT] ** 2).mean().backward()
    for name, p in mod.agent.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    heads = mod.agent.slot_heads
    # every UAV's every slot head (per_slot) received a gradient, and the BW heads
    per_head = heads.w2.grad.abs().sum(dim=(-2, -1))  # [U, K or 1]
    assert (per_head > 0).all(), per_head
    assert (mod.agent.bw_head.w2.grad.abs().sum(dim=(-2, -1)) > 0).all()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in mod.agent.torso.parameters())


def test_registry_builds_the_branching_module_only_in_per_device_mode():
    small = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=20)
    for name in ("qmix", "vdn"):
        entry = registry.get(name)
        assert set(entry.action_modes) == {"per_uav", "per_device"}
        for mode, cls in (("per_uav", QMixModule), ("per_device", BranchingQMixModule)):
            cfg = entry.build(small.replace(action_mode=mode), entry.hparams({}), registry.Resources(), 0)
            assert cfg.get_default_rl_module_spec().module_class is cls
            assert cfg.model_config["action_mode"] == mode
    h = QMIXHParams()
    assert (h.slot_head, h.head_hidden) == ("per_slot", 64)
    with pytest.raises(Exception, match="slot_head"):
        registry.get("qmix").hparams({"slot_head": "per_ed"})


def test_module_fits_the_team_spaces():
    cfg = ScenarioConfig(n_eds=12, n_uavs=3, episode_len=20, action_mode="per_device")
    mc = hparams_model_config(
        QMIXHParams,
        **{
            "n_agents": 3,
            "obs_dim": team_observation_space(cfg).shape[1],
            "n_actions": cfg.n_joint_actions,
            "state_dim": 5,
            "mixer": "qmix",
            "action_mode": "per_device",
            "epsilon_anneal_env_steps": 100,
        },
    )
    mod = BranchingQMixModule(
        observation_space=team_observation_space(cfg), action_space=team_action_space(cfg), model_config=mc
    )
    assert mod.quota == cfg.quota and mod.n_pairs == cfg.n_sf * cfg.n_tp and mod.n_bw == cfg.n_bw


# ---------------------------------------------------------------------- through RLlib
@pytest.mark.slow
@pytest.mark.parametrize("name", ["qmix", "vdn"])
def test_per_device_build_trains_and_acts(ray_session, name):
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.sim.core import BatchCore

    cfg = ScenarioConfig(n_eds=6, n_uavs=2, episode_len=10, action_mode="per_device")
    entry = registry.get(name)
    hp = entry.hparams(
        {
            "learning_starts_episodes": 2,
            "batch_size_episodes": 2,
            "buffer_size_episodes": 8,
            "updates_per_iteration": 2,
            "gru_hidden": 16,
            "fc_hidden": 16,
            "head_hidden": 8,
        }
    )
    algo = entry.build(cfg, hp, registry.Resources(num_envs_per_env_runner=2), 0).build_algo()
    try:
        results = [algo.train() for _ in range(2)]
        assert results[-1]["num_gradient_updates_lifetime"] == 4
        assert np.isfinite(results[-1]["learners"][DEFAULT_MODULE_ID]["td_loss"])
        assert algo.replay.actions.shape[-1] == 2 * cfg.quota + 1 and len(algo.replay) == 4
        for explore in (False, True):
            policy = entry.policy(algo, cfg, explore=explore)
            core = BatchCore(cfg, 3)
            core.reset(1)
            policy.reset(core)
            a = policy.act(core)
            assert a.shape == (3, 2, 2 * cfg.quota + 1)
            core.step(a)
    finally:
        algo.stop()
