"""QMIX and VDN: mixers, TD targets, matrix games, replay/GRU episode boundaries, learning, checkpoints."""

from __future__ import annotations

import itertools
import time

import gymnasium as gym
import numpy as np
import pytest
import torch
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, HIDDEN, TERMINATED
from uavlora_rllib.algorithms.common.config import hparams_model_config
from uavlora_rllib.algorithms.common.policy import trained_module
from uavlora_rllib.algorithms.qmix.qmix import QMIXConfig, QMIXHParams, VDNConfig
from uavlora_rllib.algorithms.qmix.qmix_learner import nstep_targets, td_targets
from uavlora_rllib.algorithms.qmix.qmix_module import (
    Q_ALL,
    Q_TAKEN,
    Q_TOT,
    TARGET_Q_TOT_NEXT,
    QMixer,
    QMixModule,
    VDNMixer,
    linear_epsilon,
)
from uavlora_rllib.algorithms.qmix.qmix_replay import EpisodeReplay
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

SMALL = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=20)
# A few iterations of a CI-sized run (learning itself: tests/test_learning.py): a larger lr, a
# shorter epsilon schedule and horizon and one agent network per UAV (docs/model.md#training-defaults).
CI_HPARAMS = {
    "share_agent_net": False,
    "lr": 1e-3,
    "gamma": 0.5,
    "t_max_env_steps": 20_000,
    "epsilon_anneal_fraction": 0.25,
    "updates_per_iteration": 2,
}
CI_ITERS = 12  # x 4 episodes: the replay (32 episodes) is full and 18 updates have run
CI_ENVS = 4


# ---------------------------------------------------------------------- config and registry
def test_hparams_defaults_follow_spec():
    h = QMIXHParams()
    assert (h.lr, h.gamma, h.gru_hidden, h.batch_size_episodes, h.buffer_size_episodes) == (1e-4, 0.99, 128, 16, 32)
    assert (h.tau, h.grad_clip, h.epsilon_start, h.epsilon_end, h.n_step, h.mixing_embed_dim) == (
        0.01,
        10.0,
        1.0,
        0.05,
        1,
        32,
    )
    assert h.epsilon_anneal_env_steps == 100_000  # 5% of T_max = 2M
    # the one default that differs, each measured (docs/model.md#training-defaults)
    assert (
        registry.get("qmix").hparams({}).updates_per_episode,
        registry.get("vdn").hparams({}).updates_per_episode,
    ) == (0.25, 1.0)
    assert VDNConfig().hparams == registry.get("vdn").hparams({}) and QMIXConfig().hparams == QMIXHParams()
    for name in ("qmix", "vdn"):
        entry = registry.get(name)
        assert entry.action_modes == ("per_uav", "per_device")  # per_device: tests/test_qmix_branching.py
        assert entry.hparams({"n_step": 3}).n_step == 3


def test_bad_config_errors_name_the_field():
    entry = registry.get("qmix")
    with pytest.raises(ConfigError, match=r"algorithms\.qmix\.learning_rate: unknown field; allowed: .*\blr\b"):
        entry.hparams({"learning_rate": 1e-3})
    with pytest.raises(ConfigError, match=r"algorithms\.vdn\.tau"):
        registry.get("vdn").hparams({"tau": 0.0})
    with pytest.raises(ConfigError, match=r"epsilon_end"):
        entry.hparams({"epsilon_end": 0.5, "epsilon_start": 0.1})
    with pytest.raises(ConfigError, match=r"algorithms\.qmix\.slot_head"):
        entry.hparams({"slot_head": "per_ed"})


@pytest.mark.parametrize(
    "per_episode, added, expected",
    [
        (0.25, [16, 16, 16], [4, 4, 4]),  # the default with the learning grids' / smoke's 16 envs
        (0.25, [2, 2, 2, 2], [0, 1, 0, 1]),  # fewer envs: the fraction carries over
        (1.0, [4, 0, 3], [4, 0, 3]),  # EPyMARL's ratio: one update per episode
        (1.5, [3, 3], [4, 5]),
    ],
)
def test_updates_per_episode_keeps_the_update_to_data_ratio(per_episode, added, expected):
    """The number of gradient updates follows the episodes added, whatever the envs per iteration."""
    from types import SimpleNamespace

    from uavlora_rllib.algorithms.qmix.qmix import QMIX

    algo = SimpleNamespace(
        config=SimpleNamespace(hparams=QMIXHParams(updates_per_episode=per_episode)), _update_credit=0.0
    )
    assert [QMIX._updates_due(algo, n) for n in added] == expected
    assert sum(expected) == int(per_episode * sum(added))


# ---------------------------------------------------------------------- mixers and targets
def test_qmix_mixer_is_monotonic_and_vdn_sums_exactly():
    torch.manual_seed(0)
    u, s_dim = 4, 23
    mixer = QMixer(u, s_dim, embed_dim=32, hypernet_embed=64)
    q = (torch.randn(64, 5, u) * 10).requires_grad_(True)
    state = torch.randn(64, 5, s_dim) * 3
    mixer(q, state).sum().backward()
    assert (q.grad >= 0).all()
    assert (q.grad > 0).float().mean() > 0.99  # ELU' > 0 and |w| > 0: strictly increasing almost surely
    q2 = torch.randn(7, 3, u, dtype=torch.float64)
    assert torch.equal(VDNMixer()(q2, torch.zeros(7, 3, 1)), q2.sum(-1))


def _qmix_by_layers(mixer: QMixer, q: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """Rashid et al.'s mixer written with each hypernetwork called on its own: the reference for the
    mixer's one fused product over the state."""
    u, e = mixer.n_agents, mixer.embed_dim
    w1 = mixer.hyper_w1(state).abs().reshape(-1, u, e)
    hidden = torch.nn.functional.elu(torch.bmm(q.reshape(-1, 1, u), w1) + mixer.hyper_b1(state).reshape(-1, 1, e))
    y = torch.bmm(hidden, mixer.hyper_w2(state).abs().reshape(-1, e, 1)).reshape(q.shape[:-1])
    return y if mixer.v is None else y + mixer.v(state).squeeze(-1)


@pytest.mark.parametrize("state_bias", [True, False])
@pytest.mark.parametrize("first", [0, 1])
def test_mixers_on_a_longer_state_sequence_equal_the_mixer_on_its_slice(state_bias, first):
    """The modules pass the whole state sequence [B, T+1, S] and `first` (0 online, 1 target); the mixer must
    equal the hypernetworks called one by one on state[:, first:first + T], value and every gradient."""
    torch.manual_seed(0)
    u, s_dim, b, t = 3, 11, 4, 6
    state = torch.randn(b, t + 1, s_dim)
    for mixer in (
        QMixer(u, s_dim, embed_dim=8, hypernet_embed=16, state_bias=state_bias),
        VDNMixer(s_dim, embed_dim=8, state_bias=state_bias),
    ):
        q = torch.randn(b, t, u, requires_grad=True)
        out = mixer(q, state, first=first)
        grads = torch.autograd.grad(out.square().sum(), [q, *mixer.parameters()])
        sliced = state[:, first : first + t]
        if isinstance(mixer, QMixer):
            ref = _qmix_by_layers(mixer, q, sliced)
        else:  # VDN(-S): the sum, plus V(s) called on its own
            ref = q.sum(-1) if mixer.v is None else q.sum(-1) + mixer.v(sliced).squeeze(-1)
        ref_grads = torch.autograd.grad(ref.square().sum(), [q, *mixer.parameters()])
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5)
        for g, rg in zip(grads, ref_grads, strict=True):
            torch.testing.assert_close(g, rg, rtol=1e-5, atol=1e-5)
        with pytest.raises(ValueError, match="first"):
            mixer(q, state, first=2)
        with pytest.raises(ValueError, match=r"expected \[B, T"):  # no [N, U] / [N, S] call without a time axis
            mixer(q[:, 0], state[:, 0])


def test_state_bias_adds_a_state_value_that_leaves_every_uav_gradient_at_one():
    torch.manual_seed(0)
    u, s_dim = 3, 5
    mixer = VDNMixer(s_dim, embed_dim=8, state_bias=True)  # VDN-S
    q = torch.randn(4, 6, u, requires_grad=True)
    state = torch.randn(4, 6, s_dim)
    out = mixer(q, state)
    out.sum().backward()
    assert torch.equal(q.grad, torch.ones_like(q))  # dQ_tot/dQ_u = 1: still VDN's credit assignment
    v = out.detach() - q.detach().sum(-1)
    torch.testing.assert_close(v, mixer.v(state).squeeze(-1).detach())
    assert v.std() > 0  # a function of the state, not a constant
    # QMIX without V(s): Q_tot loses exactly the V(s) term
    torch.manual_seed(1)
    with_v = QMixer(u, s_dim, embed_dim=8, hypernet_embed=8)
    no_v = QMixer(u, s_dim, embed_dim=8, hypernet_embed=8, state_bias=False)
    no_v.load_state_dict({k: p for k, p in with_v.state_dict().items() if not k.startswith("v.")})
    torch.testing.assert_close(with_v(q.detach(), state) - no_v(q.detach(), state), with_v.v(state).squeeze(-1))
    # the modules take it from the config (default on for both mixers); execution never reads it
    for kind in ("vdn", "qmix"):
        assert _module(n_agents=u, state_dim=s_dim, mixer=kind).mixer.v is not None
        assert _module(n_agents=u, state_dim=s_dim, mixer=kind, state_bias=False).mixer.v is None
    assert QMIXHParams().state_bias is True


def _brute_nstep(r, nxt, term, gamma, n):
    b, t = r.shape
    y = np.zeros((b, t))
    for i in range(b):
        for s in range(t):
            m = min(n, t - s)
            y[i, s] = sum(gamma**k * r[i, s + k] for k in range(m))
            if not (term[i] and s + m == t):
                y[i, s] += gamma**m * nxt[i, s + m - 1]
    return y


@pytest.mark.parametrize("n", [1, 3, 25])
def test_nstep_targets_bootstrap_through_truncation(n):
    rng = np.random.default_rng(n)
    r, nxt = rng.normal(size=(3, 20)), rng.normal(size=(3, 20))
    term = np.array([False, True, False])
    y = nstep_targets(torch.as_tensor(r), torch.as_tensor(nxt), torch.as_tensor(term), 0.9, n).numpy()
    np.testing.assert_allclose(y, _brute_nstep(r, nxt, term, 0.9, n), rtol=1e-10, atol=1e-10)
    # Truncated episode (row 0): the last transition bootstraps from the final state.
    assert y[0, -1] == pytest.approx(r[0, -1] + 0.9 * nxt[0, -1])
    assert y[1, -1] == pytest.approx(r[1, -1])  # terminated: no bootstrap


@pytest.mark.parametrize("n", [1, 3])
def test_gamma_zero_targets_are_the_rewards_without_the_target_networks(n):
    """At gamma 0 every n-step target is r_t, whatever the bootstrap: td_targets returns the rewards, and the
    module leaves TARGET_Q_TOT_NEXT out without running the target agent network or mixer (the per_device
    benchmark trains at gamma 0, so this skips a third of each update's forward passes)."""
    rng = np.random.default_rng(n)
    r, nxt = torch.as_tensor(rng.normal(size=(3, 20))), torch.as_tensor(rng.normal(size=(3, 20)) * 100)
    term = torch.tensor([False, True, False])
    torch.testing.assert_close(td_targets(r, {}, term, 0.0, n), nstep_targets(r, nxt, term, 0.0, n))
    torch.testing.assert_close(
        td_targets(r, {TARGET_Q_TOT_NEXT: nxt}, term, 0.9, n), nstep_targets(r, nxt, term, 0.9, n)
    )
    batch = {
        Columns.OBS: torch.randn(2, 5, 2, 3),
        Columns.ACTIONS: torch.randint(0, 5, (2, 4, 2)),
        GLOBAL_STATE: torch.randn(2, 5, 4),
    }
    for gamma in (0.0, 0.5):
        mod = _module(gamma=gamma)
        mod.make_target_networks()
        calls: list[int] = []
        mod._target_agent.register_forward_hook(lambda *_, calls=calls: calls.append(1))
        out = mod.forward_train(batch)
        assert (TARGET_Q_TOT_NEXT in out, len(calls)) == ((False, 0) if gamma == 0.0 else (True, 1))


def test_epsilon_schedule_and_exploration():
    assert linear_epsilon(0, 1.0, 0.05, 1000) == 1.0
    assert linear_epsilon(500, 1.0, 0.05, 1000) == pytest.approx(0.525)
    assert linear_epsilon(10**9, 1.0, 0.05, 1000) == pytest.approx(0.05)
    torch.manual_seed(0)
    mod = _module(n_actions=90, epsilon_anneal_env_steps=1000, epsilon_end=0.0)
    batch = {Columns.OBS: torch.randn(500, 1, 2, 3), Columns.STATE_IN: {HIDDEN: torch.zeros(500, 2, 8)}}
    greedy = mod.forward_inference(batch)[Columns.ACTIONS]
    assert greedy.shape == (500, 1, 2)
    early = mod.forward_exploration(batch, t=0)[Columns.ACTIONS]
    late = mod.forward_exploration(batch, t=1000)[Columns.ACTIONS]
    assert torch.equal(late, greedy)  # epsilon_end = 0: greedy
    assert (early != greedy).float().mean() > 0.9  # epsilon = 1: uniform over 90 actions
    # Without a training clock (sampled execution after training): epsilon_end.
    assert torch.equal(mod.forward_exploration(batch)[Columns.ACTIONS], greedy)
    half = _module(n_actions=90, epsilon_anneal_env_steps=1000, epsilon_end=0.5)
    b = half.forward_inference(batch)[Columns.ACTIONS]
    off = (half.forward_exploration(batch)[Columns.ACTIONS] != b).float().mean()
    assert 0.4 < off < 0.6  # epsilon 0.5, a random action equals the greedy one 1/90 of the time


# ---------------------------------------------------------------------- GRU unroll boundaries
def _module(n_agents=2, obs_dim=3, n_actions=5, state_dim=4, mixer="qmix", **extra) -> QMixModule:
    mc = hparams_model_config(
        QMIXHParams,
        **{
            "n_agents": n_agents,
            "obs_dim": obs_dim,
            "n_actions": n_actions,
            "state_dim": state_dim,
            "gru_hidden": 8,
            "fc_hidden": 8,
            "mixer": mixer,
            "epsilon_anneal_env_steps": QMIXHParams().epsilon_anneal_env_steps,
            **extra,
        },
    )
    obs_space = gym.spaces.Box(-1, 1, (n_agents, obs_dim), np.float32)
    return QMixModule(
        observation_space=obs_space, action_space=gym.spaces.MultiDiscrete([n_actions] * n_agents), model_config=mc
    )


@pytest.mark.parametrize("share", [True, False])
def test_unroll_starts_each_episode_from_zero_state(share):
    torch.manual_seed(1)
    mod = _module(share_agent_net=share)
    obs = torch.randn(3, 6, 2, 3)
    q = mod.compute_q_values({Columns.OBS: obs})[Q_ALL]
    for b in range(3):  # step by step, one episode at a time, from h = 0
        h = torch.zeros(1, 2, 8)
        for t in range(6):
            out = mod._step({Columns.OBS: obs[b : b + 1, t : t + 1], Columns.STATE_IN: {HIDDEN: h}})
            q_t, h = out
            torch.testing.assert_close(q_t[0], q[b, t], rtol=1e-5, atol=1e-6)
    other = obs.clone()
    other[1] += 5.0  # another episode in the batch must not change episode 0's or 2's Qs
    q_other = mod.compute_q_values({Columns.OBS: other})[Q_ALL]
    torch.testing.assert_close(q_other[[0, 2]], q[[0, 2]])
    assert not torch.allclose(q_other[1], q[1])


def test_replay_stores_and_samples_whole_episodes():
    rep = EpisodeReplay(capacity=3, episode_len=4, n_agents=2, obs_dim=1, state_dim=2, seed=0)
    for k in range(5):  # ring buffer: keeps the last 3
        obs = np.full((5, 2, 1), k, np.float32)
        state = np.stack([np.full(5, k), np.arange(5) / 4], axis=-1).astype(np.float32)
        rep.add(obs, np.zeros((4, 2)), np.full(4, k), state)
    assert len(rep) == 3 and rep.added == 5
    s = rep.sample(3)
    assert sorted(s[Columns.OBS][:, 0, 0, 0].tolist()) == [2, 3, 4]
    assert (s[Columns.OBS] == s[Columns.OBS][:, :1]).all()  # every row is one episode, never spliced
    with pytest.raises(ValueError, match="whole episodes of 4 steps"):
        rep.add(np.zeros((4, 2, 1)), np.zeros((3, 2)), np.zeros(3), np.zeros((4, 2)))


# ---------------------------------------------------------------------- learner on matrix games
MATRIX_DIMS = {"n_agents": 2, "obs_dim": 1, "state_dim": 1, "n_actions": 3}  # a 2-agent, 3-action game


def _matrix_config(cls, **hparams):
    """The algorithm's config through its one entry point (`uavlora`), with the game's sizes."""
    obs_space, act_space = gym.spaces.Box(-1, 1, (2, 1), np.float32), gym.spaces.MultiDiscrete([3, 3])
    cfg = (
        cls()
        .environment(observation_space=obs_space, action_space=act_space)
        .uavlora(cls.hparams_cls(**hparams), SMALL)
    )
    cfg.rl_module(model_config={**cfg.model_config, **MATRIX_DIMS})
    return cfg, {DEFAULT_MODULE_ID: (obs_space, act_space)}


def _matrix_learner(cls, lr=2e-2, seed=0):
    torch.manual_seed(seed)
    cfg, spaces = _matrix_config(cls, lr=lr, gamma=0.0, tau=1.0, gru_hidden=16, fc_hidden=16)
    return cfg.build_learner(spaces=spaces)


def _matrix_batch(payoff, reps=2):
    """One-step episodes covering every joint action equally often (uniform exploration data)."""
    joint = np.array(list(itertools.product(range(3), range(3))) * reps)
    b = len(joint)
    data = {
        Columns.OBS: np.zeros((b, 2, 2, 1), np.float32),
        Columns.ACTIONS: joint[:, None, :].astype(np.int64),
        Columns.REWARDS: payoff[joint[:, 0], joint[:, 1]][:, None].astype(np.float32),
        GLOBAL_STATE: np.zeros((b, 2, 1), np.float32),
        TERMINATED: np.ones(b, bool),
    }
    return MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch(data)}, env_steps=b)


def _fit(cls, payoff, updates):
    learner = _matrix_learner(cls)
    batch = _matrix_batch(payoff)
    for _ in range(updates):
        learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
    mod = learner.module[DEFAULT_MODULE_ID]
    one = {k: torch.as_tensor(v) for k, v in _matrix_batch(payoff, reps=1).policy_batches[DEFAULT_MODULE_ID].items()}
    with torch.no_grad():
        out = mod.forward_train(one)
    q_tot = out[Q_TOT].numpy().reshape(3, 3)
    greedy = tuple(out[Q_ALL][0, 0].argmax(-1).tolist())  # decentralised: each agent's own argmax
    return q_tot, greedy


def _additive_fit(payoff):
    """Least-squares fit q1(i) + q2(j) of a payoff under uniform data: what VDN converges to."""
    m = payoff.mean()
    return payoff.mean(1)[:, None] + payoff.mean(0)[None, :] - m


@pytest.mark.slow
def test_matrix_games_qmix_vs_vdn():
    # Monotonic but non-additive game: R = (i + j)^2, optimum (2, 2). QMIX represents it;
    # VDN cannot (its error is the additive fit's residual) but still ranks (2, 2) first.
    mono = np.add.outer(np.arange(3.0), np.arange(3.0)) ** 2
    q_mono, g_mono = _fit(QMIXConfig, mono, 300)
    assert ((q_mono - mono) ** 2).mean() < 0.1 and np.abs(q_mono - mono).max() < 0.6 and g_mono == (2, 2)
    v_mono, gv_mono = _fit(VDNConfig, mono, 200)
    np.testing.assert_allclose(v_mono, _additive_fit(mono), atol=0.15)
    assert ((v_mono - mono) ** 2).mean() > 1.5 and gv_mono == (2, 2)  # LS residual: 1.78
    # Non-monotonic game (Rashid et al. 2020, WQMIX): optimum (0, 0) = 8, miscoordination -12.
    # Per-agent greedy choices differ from the team optimum: VDN's Q_tot is the additive fit
    # (row means -5.33 vs -4), so both agents avoid action 0 and settle on a payoff-0 joint
    # action; QMIX's monotonic mixer cannot represent the game either and also misses (0, 0),
    # but its decentralised argmax is the argmax of its own Q_tot (IGM).
    nonmono = np.array([[8, -12, -12], [-12, 0, 0], [-12, 0, 0]], float)
    v_non, gv_non = _fit(VDNConfig, nonmono, 200)
    np.testing.assert_allclose(v_non, _additive_fit(nonmono), atol=0.15)
    assert gv_non[0] != 0 and gv_non[1] != 0 and nonmono[gv_non] == 0
    q_non, g_non = _fit(QMIXConfig, nonmono, 300)
    assert g_non != (0, 0) and nonmono[g_non] == 0
    assert q_non[g_non] == pytest.approx(q_non.max(), abs=1e-5)


@pytest.mark.slow
def test_optimistic_td_weighting_finds_the_coordinated_optimum():
    """negative_td_weight < 1 (hysteretic Q-learning; OW-QMIX's weighting): on the non-monotonic game above,
    where plain VDN and QMIX miss (0, 0), down-weighting the over-estimates makes each agent's utility follow
    the better outcomes of its action, so both greedy choices meet at the optimum."""
    nonmono = np.array([[8, -12, -12], [-12, 0, 0], [-12, 0, 0]], float)
    for cls, updates in ((VDNConfig, 200), (QMIXConfig, 300)):
        torch.manual_seed(0)
        cfg, spaces = _matrix_config(
            cls, lr=2e-2, gamma=0.0, tau=1.0, gru_hidden=16, fc_hidden=16, negative_td_weight=0.1
        )
        learner = cfg.build_learner(spaces=spaces)
        batch = _matrix_batch(nonmono)
        for _ in range(updates):
            learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
        one = {
            k: torch.as_tensor(v) for k, v in _matrix_batch(nonmono, reps=1).policy_batches[DEFAULT_MODULE_ID].items()
        }
        with torch.no_grad():
            out = learner.module[DEFAULT_MODULE_ID].forward_train(one)
        assert tuple(out[Q_ALL][0, 0].argmax(-1).tolist()) == (0, 0), cls.__name__


def test_negative_td_weight_scales_only_over_estimates():
    """The loss: mean of w (Q_tot - y)^2 with w = negative_td_weight where Q_tot > y, else 1 (gamma 0: y = r)."""
    torch.manual_seed(0)
    cfg, spaces = _matrix_config(QMIXConfig, gamma=0.0, gru_hidden=8, fc_hidden=8, negative_td_weight=0.25)
    learner = cfg.build_learner(spaces=spaces)
    q_tot = torch.tensor([[1.0], [3.0], [2.0]])
    rewards = torch.tensor([[2.0], [1.0], [2.0]])
    batch = {Columns.REWARDS: rewards, TERMINATED: torch.ones(3, dtype=torch.bool)}
    fwd = {Q_TOT: q_tot, TARGET_Q_TOT_NEXT: torch.zeros(3, 1), Q_TAKEN: torch.zeros(3, 1, 2)}
    loss = learner.compute_loss_for_module(module_id=DEFAULT_MODULE_ID, config=cfg, batch=batch, fwd_out=fwd)
    assert float(loss) == pytest.approx((1.0 + 0.25 * 4.0 + 0.0) / 3)


@pytest.mark.slow
def test_target_networks_move_by_tau_per_update():
    torch.manual_seed(0)
    cfg, spaces = _matrix_config(QMIXConfig, lr=1e-2, tau=0.01, gru_hidden=8, fc_hidden=8)
    learner = cfg.build_learner(spaces=spaces)
    mod = learner.module[DEFAULT_MODULE_ID]
    pairs = mod.get_target_network_pairs()
    batch = _matrix_batch(np.arange(9.0).reshape(3, 3))
    for _ in range(3):
        before = [{k: v.clone() for k, v in tgt.state_dict().items()} for _, tgt in pairs]
        online_before = [{k: v.clone() for k, v in net.state_dict().items()} for net, _ in pairs]
        learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
        moved = False
        for (net, tgt), old, on_old in zip(pairs, before, online_before):
            for k, v in tgt.state_dict().items():
                online = net.state_dict()[k]
                torch.testing.assert_close(v, 0.99 * old[k] + 0.01 * online, rtol=0, atol=1e-6)
                moved |= not torch.equal(online, on_old[k])
        assert moved  # the online nets did take a gradient step
    for _, tgt in pairs:
        assert all(not p.requires_grad for p in tgt.parameters())


@pytest.mark.parametrize("lr_end", [None, 1e-3])
def test_lr_end_decays_the_step_linearly_over_t_max(lr_end):
    # lr_end: Adam's step falls linearly from lr at env step 0 to lr_end at t_max_env_steps, then holds;
    # unset: the paper's constant lr
    cfg, spaces = _matrix_config(QMIXConfig, lr=1e-2, lr_end=lr_end, t_max_env_steps=1000, gru_hidden=8, fc_hidden=8)
    learner = cfg.build_learner(spaces=spaces)
    batch = _matrix_batch(np.arange(9.0).reshape(3, 3))
    for step, decayed in ((0, 1e-2), (250, 7.75e-3), (1000, 1e-3), (5000, 1e-3)):
        learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": step})
        lr = learner.get_optimizer(DEFAULT_MODULE_ID).param_groups[0]["lr"]
        assert lr == pytest.approx(1e-2 if lr_end is None else decayed, rel=1e-6)


# ---------------------------------------------------------------------- RLlib end to end
def _train(name: str, seed: int, iters: int):
    entry = registry.get(name)
    hp = entry.hparams(CI_HPARAMS)
    algo = entry.build(SMALL, hp, registry.Resources(num_envs_per_env_runner=CI_ENVS), seed).build_algo()
    result = None
    try:
        for _ in range(iters):
            result = algo.train()
    except BaseException:  # the shared Ray outlives the test: stop the algorithm's actors
        algo.stop()
        raise
    return algo, result


@pytest.fixture(scope="module")
def trained(ray_session):
    out = {}
    for name in ("qmix",):
        t0 = time.perf_counter()
        algo, result = _train(name, seed=0, iters=CI_ITERS)
        out[name] = (algo, result, time.perf_counter() - t0)
    yield out
    for algo, _, _ in out.values():
        algo.stop()


@pytest.mark.slow
def test_result_metrics(trained):
    algo, result, _ = trained["qmix"]
    learner = result["learners"][DEFAULT_MODULE_ID]
    for key in ("td_loss", "q_taken_mean", "q_tot_mean", "target_mean"):
        assert np.isfinite(learner[key])
    assert learner["num_soft_target_updates"] == result["num_gradient_updates_lifetime"]
    assert result["num_gradient_updates_lifetime"] == 2 * (CI_ITERS - 3)  # learning starts at 16 episodes
    assert 0.05 <= result["epsilon"] < 1.0
    # the env runners explore with the schedule the result reports (same env-step clock)
    steps = result["num_env_steps_sampled_lifetime"]
    assert algo.get_module().epsilon(steps) == pytest.approx(result["epsilon"])
    assert algo.get_module().epsilon(0) == 1.0
    assert np.isfinite(result["env_runners"]["episode_return_mean"])
    runners = result["env_runners"]  # the paper's metrics of the sampled episodes (common/metrics.py)
    assert runners["ee_sys_mean"] > 0 and 0 <= runners["success_rate"] <= 1
    assert result["replay_episodes"] == 32 and result["episodes_dropped_lifetime"] == 0


@pytest.mark.slow
def test_replay_sequences_start_at_episode_starts(trained):
    algo, _, _ = trained["qmix"]
    s = algo.replay.sample(16)
    t_feature = s[GLOBAL_STATE][..., -1]  # the global state's last feature is t / T
    np.testing.assert_allclose(t_feature, np.broadcast_to(np.arange(21) / 20, t_feature.shape), atol=1e-6)
    assert s[Columns.OBS].shape == (16, 21, 2, algo.config.model_config["obs_dim"])


@pytest.mark.slow
def test_env_runner_gru_state_is_zero_at_episode_start(trained):
    """Greedy actions sampled by RLlib's env runner (state carried by its connectors across
    two sample() calls, i.e. across an autoreset) equal the argmax of a from-zero unroll."""
    algo, _, _ = trained["qmix"]
    runner = algo.env_runner
    mod = trained_module(algo)  # the learner's weights (public APIs)
    episodes = runner.sample(explore=False) + runner.sample(explore=False)
    assert len(episodes) == 2 * CI_ENVS
    for ep in episodes:
        obs = torch.as_tensor(np.asarray(ep.get_observations()))[None]
        with torch.no_grad():
            q = mod.compute_q_values({Columns.OBS: obs})[Q_ALL][0, :-1]
        np.testing.assert_array_equal(q.argmax(-1).numpy(), np.asarray(ep.get_actions()))


@pytest.mark.slow
def test_env_runners_hold_only_the_agent_network(trained):
    algo, _, _ = trained["qmix"]
    runner_mod = algo.get_module()
    assert runner_mod.inference_only
    assert not hasattr(runner_mod, "mixer") and not hasattr(runner_mod, "_target_agent")
    learner_weights = algo.learner_group.get_weights([DEFAULT_MODULE_ID])[DEFAULT_MODULE_ID]
    assert any(k.startswith("mixer.") for k in learner_weights)  # the learner does hold the mixer
    for k, v in runner_mod.agent.state_dict().items():  # weights were synced after the last update
        torch.testing.assert_close(v, torch.as_tensor(learner_weights["agent." + k]))


@pytest.mark.slow
def test_checkpoint_round_trip(trained, tmp_path):
    from ray.rllib.algorithms.algorithm import Algorithm

    from uavlora_rllib.sim.core import BatchCore

    algo, _, _ = trained["qmix"]
    algo.save_to_path(str(tmp_path))
    restored = Algorithm.from_checkpoint(str(tmp_path))
    try:
        assert registry.entry_for_algorithm(restored).name == "qmix"
        assert restored.iteration == algo.iteration
        pols = [registry.get("qmix").greedy_policy(a, SMALL) for a in (algo, restored)]
        cores = [BatchCore(SMALL, 4) for _ in pols]
        for pol, core in zip(pols, cores):
            core.reset(123)
            pol.reset(core)
        for _ in range(SMALL.episode_len):
            acts = [pol.act(core) for pol, core in zip(pols, cores)]
            np.testing.assert_array_equal(acts[0], acts[1])
            for core in cores:
                core.step(acts[0])
        # keeps training; the replay refills (not part of the checkpoint), counters carry on
        before = trained["qmix"][1]["num_gradient_updates_lifetime"]
        after = restored.train()
        assert after["num_gradient_updates_lifetime"] == before  # replay < learning_starts: no update yet
        assert (
            after["num_env_steps_sampled_lifetime"]
            == trained["qmix"][1]["num_env_steps_sampled_lifetime"] + CI_ENVS * 20
        )
    finally:
        restored.stop()


def test_agent_net_shapes_without_sharing():
    net = RecurrentAgentNet(5, 3, 7, fc_hidden=6, gru_hidden=4, share=False)
    q, h = net(torch.randn(2, 9, 3, 5), torch.zeros(2, 3, 4))
    assert q.shape == (2, 9, 3, 7) and h.shape == (2, 3, 4)
    assert net.stacked_inp_weight.shape[0] == 3  # one stacked network per UAV


def test_reward_norm_fits_standardised_rewards_with_the_same_argmax():
    """reward_norm: the TD targets are the rewards standardised by a running mean/std that the module keeps
    as buffers (so a checkpoint keeps them). Rewards scaled and shifted (r -> 100 r + 250) then train the
    same networks, so every argmax is the same, and the stats follow the map."""
    runs = {}
    for scale, shift in ((1.0, 0.0), (100.0, 250.0)):
        torch.manual_seed(0)
        cfg, spaces = _matrix_config(QMIXConfig, lr=1e-2, gru_hidden=8, fc_hidden=8, reward_norm=True)
        learner = cfg.build_learner(spaces=spaces)
        mod = learner.module[DEFAULT_MODULE_ID]
        batch = _matrix_batch(np.arange(9.0).reshape(3, 3) * scale + shift)
        for _ in range(3):
            learner.update(batch=batch, timesteps={"num_env_steps_sampled_lifetime": 0})
        assert {"reward_norm.mean", "reward_norm.mean_sq", "reward_norm.debias"} <= set(mod.state_dict())
        runs[scale] = (
            [float(x) for x in mod.reward_norm.stats()],
            {k: v.clone() for k, v in mod.agent.state_dict().items()},
        )
    (m1, s1), agent1 = runs[1.0]
    (m100, s100), agent100 = runs[100.0]
    assert m100 == pytest.approx(100.0 * m1 + 250.0, rel=1e-5) and s100 == pytest.approx(100.0 * s1, rel=1e-5)
    for k, v in agent1.items():
        torch.testing.assert_close(agent100[k], v, rtol=1e-4, atol=1e-5)
    # off: the rewards enter as they are, and there is no normaliser
    cfg, spaces = _matrix_config(QMIXConfig, gru_hidden=8, fc_hidden=8)
    assert cfg.build_learner(spaces=spaces).module[DEFAULT_MODULE_ID].reward_norm is None
