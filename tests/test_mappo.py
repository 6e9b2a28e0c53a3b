"""MAPPO / IPPO: module contract (CTDE), GRU state, per-agent GAE, a few training iterations
(checkpoints: tests/test_algorithm_matrix.py; learning: tests/test_learning.py).

CI-sized: small scenarios (V = 4, U = 2, 20-slot episodes). Ray is started once for the
module (2 CPUs).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.action_head import ActionHead
from uavlora_rllib.algorithms.common.config import hparams_model_config
from uavlora_rllib.algorithms.common.policy import ModulePolicy
from uavlora_rllib.algorithms.mappo.mappo import MAPPOConfig, MAPPOHParams
from uavlora_rllib.algorithms.mappo.mappo_learner import per_agent_gae
from uavlora_rllib.algorithms.mappo.mappo_module import MAPPOTorchRLModule
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.envs.team import UavLoraTeamEnv, team_action_space, team_observation_space
from uavlora_rllib.experiment.evaluation import run_episodes
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.observation import obs_dim, state_dim
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

SMALL = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=20)
FAST = {"num_epochs": 2, "num_minibatches": 2, "batch_episodes": 4}  # smoke-test iterations
RES = registry.Resources(num_envs_per_env_runner=4)


def _module(cfg: ScenarioConfig, critic: str = "central", inference_only: bool = False, share_actor: bool = True):
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    spec = RLModuleSpec(
        module_class=MAPPOTorchRLModule,
        observation_space=team_observation_space(cfg),
        action_space=team_action_space(cfg),
        inference_only=inference_only,
        model_config=hparams_model_config(
            MAPPOHParams, critic=critic, state_dim=state_dim(cfg), share_actor=share_actor, max_seq_len=8
        ),
    )
    return spec.build()


def _build(name: str, cfg: ScenarioConfig, overrides: dict | None = None, seed: int = 0):
    entry = registry.get(name)
    return entry.build(cfg, entry.hparams(overrides or {}), RES, seed).build_algo()


# ---------------------------------------------------------------- hyperparameters / registry
def test_registered_with_both_action_modes():
    for name in ("mappo", "ippo"):
        entry = registry.get(name)
        assert entry.hparams_cls is MAPPOHParams
        assert set(entry.action_modes) == {"per_uav", "per_device"}
    h = registry.get("mappo").hparams(None)
    assert (h.lr, h.gamma, h.clip_param, h.num_epochs, h.gru_hidden, h.batch_episodes) == (1e-4, 0.99, 0.2, 15, 128, 16)
    assert (h.lambda_, h.entropy_coeff, h.grad_clip) == (0.0, 0.001, 10.0)


@pytest.mark.parametrize(
    "overrides, field",
    [({"lr": -1}, "algorithms.mappo.lr"), ({"no_such_knob": 1}, "unknown field"), ({"critic": "global"}, "critic")],
)
def test_bad_hparams_raise_config_error(overrides, field):
    with pytest.raises(ConfigError, match=field):
        registry.get("mappo").hparams(overrides)


def test_too_many_minibatches_is_a_config_error():
    entry = registry.get("ippo")
    with pytest.raises(ConfigError, match="algorithms.ippo.num_minibatches"):
        entry.build(SMALL, entry.hparams({"num_minibatches": 100}), RES, 0)


def test_build_sets_env_batch_and_seed():
    entry = registry.get("mappo")
    cfg = entry.build(SMALL, entry.hparams({"batch_episodes": 3, "num_minibatches": 2}), RES, 42)
    assert cfg.env is UavLoraTeamEnv
    assert cfg.env_config["uavlora_algorithm"] == "mappo"
    assert ScenarioConfig.from_dict(cfg.env_config["scenario"]) == SMALL
    assert cfg.train_batch_size_per_learner == 3 * SMALL.episode_len
    assert cfg.minibatch_size == 3 * SMALL.episode_len // 2
    assert cfg.seed == 42
    assert cfg.gym_env_vectorize_mode == "vector_entry_point" and cfg.num_envs_per_env_runner == 4
    assert cfg.hparams.batch_episodes == 3 and cfg.model_config["critic"] == "central"
    assert registry.get("ippo").build(SMALL, entry.hparams({}), RES, 0).model_config["critic"] == "local"


@pytest.mark.parametrize(
    "setting, name",
    [
        ({"use_kl_loss": True}, "use_kl_loss"),
        ({"entropy_coeff": [[0, 0.01], [1000, 0.0]]}, "entropy_coeff"),
        ({"vf_clip_param": 5.0}, "vf_clip_param"),
        ({"use_gae": False}, "use_gae"),
    ],
)
def test_ppo_features_the_learner_ignores_are_rejected(setting, name):
    """MAPPOConfig is a PPOConfig, but its learner is not PPO's: PPO-only settings must fail
    loudly instead of being accepted and silently ignored."""
    entry = registry.get("mappo")
    cfg = entry.build(SMALL, entry.hparams({}), RES, 0)
    cfg.validate()  # MAPPO's own settings are valid
    cfg.training(**setting)
    with pytest.raises(ConfigError, match=name):
        cfg.validate()
    assert isinstance(cfg, MAPPOConfig)


# ---------------------------------------------------------------- module: CTDE contract
def test_critic_reads_global_state_and_actor_only_local_rows():
    cfg = SMALL
    u, d, s_dim = cfg.n_uavs, obs_dim(cfg), state_dim(cfg)
    m = _module(cfg, "central")
    assert m.actor.in_dim == d + u
    assert m.actor.nets[0].inp.in_features == d + u
    assert m.critic.in_dim == s_dim and m.critic.net[0].in_features == s_dim  # the state once, no id
    assert m.critic.net[-1].out_features == u  # one value head per agent
    local = _module(cfg, "local")
    assert local.critic.net[0].in_features == d + u

    torch.manual_seed(0)
    b, t = 3, 5
    obs = torch.rand(b, t, u, d) * 2 - 1
    state = torch.rand(b, t, s_dim)
    batch = {"obs": obs, "state": state, "state_in": {"h": torch.zeros(b, u, m.actor.gru_hidden)}}
    v = m.compute_values(batch)
    assert v.shape == (b, t, u)
    # The central critic depends on the state, not on the observations.
    assert torch.allclose(m.compute_values({**batch, "obs": torch.zeros_like(obs)}), v)
    assert not torch.allclose(m.compute_values({**batch, "state": torch.zeros_like(state)}), v)
    # The actor ignores the state; agent 0's logits depend on its own row only.
    out = m.forward_train(batch)["action_dist_inputs"]
    assert out.shape == (b, t, u, cfg.n_joint_actions)
    assert torch.allclose(m.forward_train({**batch, "state": torch.zeros_like(state)})["action_dist_inputs"], out)
    obs2 = obs.clone()
    obs2[:, :, 1] = 0.0
    out2 = m.forward_train({**batch, "obs": obs2})["action_dist_inputs"]
    assert torch.allclose(out2[:, :, 0], out[:, :, 0]) and not torch.allclose(out2[:, :, 1], out[:, :, 1])


@pytest.mark.parametrize("critic", ["central", "local"])
def test_first_layers_equal_the_concatenated_one_hot_form(critic):
    """The actor and IPPO's local critic evaluate W [x; one-hot(u)] + b as W_x x + b + W_e[:, u]:
    the result must be the plain concatenated network's, values and gradients alike. MAPPO's
    central critic is per-agent heads on one trunk: agent u's value is head u of the MLP on s."""
    cfg = ScenarioConfig(n_eds=6, n_uavs=3, episode_len=20)
    u, d, s_dim = cfg.n_uavs, obs_dim(cfg), state_dim(cfg)
    m = _module(cfg, critic)
    torch.manual_seed(3)
    for p in m.parameters():
        p.data.normal_(0, 0.3)
    b, t = 2, 4
    obs = torch.rand(b, t, u, d) * 2 - 1
    state = torch.rand(b, t, s_dim)
    h = torch.rand(b, u, m.actor.gru_hidden)
    ids = torch.eye(u)

    logits, h_out = m.actor(obs, h)
    x = torch.cat([obs, ids.expand(b, t, u, u)], dim=-1)  # [B, T, U, d + U]
    net = m.actor.nets[0]
    z = torch.relu(net.inp(x.permute(0, 2, 1, 3).reshape(b * u, t, d + u)))  # the plain concatenated input
    y, ref_h = net.recurrent(z, h.reshape(b * u, -1))
    ref_logits = net.out(y).reshape(b, u, t, -1).permute(0, 2, 1, 3)
    assert torch.allclose(logits, ref_logits, atol=1e-5) and torch.allclose(h_out, ref_h.reshape(b, u, -1), atol=1e-5)

    batch = {"obs": obs, "state": state}
    if critic == "central":  # agent u's head on the trunk of s, one agent at a time
        trunk, head = m.critic.net[:-1], m.critic.net[-1]
        ref_v = torch.stack([nn.functional.linear(trunk(state), head.weight[i], head.bias[i]) for i in range(u)], -1)
    else:
        ref_v = m.critic.net(torch.cat([obs, ids.expand(b, t, u, u)], dim=-1)).squeeze(-1)
    v = m.compute_values(batch)
    assert v.shape == (b, t, u) and torch.allclose(v, ref_v, atol=1e-5)
    w = m.critic.net[0].weight
    (g,) = torch.autograd.grad(v.square().sum(), w)
    (g_ref,) = torch.autograd.grad(ref_v.square().sum(), w)
    assert torch.allclose(g, g_ref, atol=1e-4)


@pytest.mark.parametrize("nvec", [[90], [6, 5, 6, 5, 3]])
def test_action_head_logp_and_entropy_match_torch_categoricals(nvec):
    head = ActionHead(nvec)
    torch.manual_seed(4)
    logits = torch.randn(3, 4, 2, sum(nvec)) * 2  # [B, T, U, logits]
    actions, logp_sampled = head.sample(logits)
    logp, ent = head.logp_and_entropy(logits, actions)
    parts = torch.split(logits, nvec, dim=-1)
    acts = [actions] if len(nvec) == 1 else list(actions.unbind(-1))
    dists = [torch.distributions.Categorical(logits=p) for p in parts]
    assert torch.allclose(logp, sum(d.log_prob(a) for d, a in zip(dists, acts)), atol=1e-5)
    assert torch.allclose(ent, sum(d.entropy() for d in dists), atol=1e-5)
    assert torch.allclose(logp_sampled, logp, atol=1e-6) and logp.shape == (3, 4, 2)
    greedy = torch.stack([p.argmax(-1) for p in parts], -1)
    assert torch.equal(head.greedy(logits), greedy if len(nvec) > 1 else greedy[..., 0])


def test_action_head_samples_each_branch_from_its_own_softmax():
    """One multinomial draw over the padded [L, W] grid samples each branch from its own
    distribution: empirical frequencies within 0.015 of the softmax, padding never drawn."""
    nvec = [6, 5, 6, 5, 3]
    head = ActionHead(nvec)
    torch.manual_seed(5)
    logits = torch.randn(2, sum(nvec))  # [U, logits]
    actions, _ = head.sample(logits.expand(20_000, 2, -1))  # [N, U, L]
    for u in range(2):
        for branch, (n, part) in enumerate(zip(nvec, torch.split(logits[u], nvec))):
            freq = torch.bincount(actions[:, u, branch], minlength=n).float() / actions.shape[0]
            assert freq.shape == (n,)  # nothing drawn beyond the branch's n values
            torch.testing.assert_close(freq, torch.softmax(part, -1), rtol=0, atol=0.015)


def test_inference_only_module_has_no_critic():
    m = _module(SMALL, "central", inference_only=True)
    assert not hasattr(m, "critic")
    assert all(not k.startswith("critic") for k in m.state_dict())
    full = _module(SMALL, "central")
    assert any(k.startswith("critic") for k in full.state_dict())
    assert set(full.get_state(inference_only=True)) == set(m.state_dict())


def test_separate_actors_per_uav():
    m = _module(SMALL, share_actor=False)
    assert m.actor.stacked_inp_weight.shape[0] == SMALL.n_uavs and m.actor.in_dim == obs_dim(SMALL)
    assert {f"actor.nets.{i}.inp.weight" for i in range(SMALL.n_uavs)} <= set(m.state_dict())
    out = m.forward_train(
        {
            "obs": torch.zeros(2, 3, 2, obs_dim(SMALL)),
            "state": torch.zeros(2, 3, state_dim(SMALL)),
            "state_in": {"h": torch.zeros(2, 2, 128)},
        }
    )
    assert out["action_dist_inputs"].shape == (2, 3, 2, SMALL.n_joint_actions)


def test_shared_actor_with_per_uav_heads():
    """actor_agent_heads: a shared trunk plus each UAV's own output layer. The heads start at
    zero (the near-uniform initial policy stays), and once trained they let two UAVs with the
    same observation and history act differently; without a shared actor the switch is refused."""
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    spec = RLModuleSpec(
        module_class=MAPPOTorchRLModule,
        observation_space=team_observation_space(SMALL),
        action_space=team_action_space(SMALL),
        model_config=hparams_model_config(
            MAPPOHParams,
            critic="central",
            state_dim=state_dim(SMALL),
            share_actor=True,
            actor_agent_heads=True,
            max_seq_len=8,
        ),
    )
    m = spec.build()
    assert m.actor.agent_out is not None and float(m.actor.agent_out.detach().abs().sum()) == 0.0
    same = torch.rand(1, 1, 1, obs_dim(SMALL)).expand(1, 1, SMALL.n_uavs, -1)
    h0 = {"h": torch.zeros(1, SMALL.n_uavs, 128)}
    m.actor.nets[0].inp.weight.data[:, obs_dim(SMALL) :] = 0.0  # no agent-id input: only the heads differ
    logits = m.forward_train({"obs": same, "state_in": h0})["action_dist_inputs"]
    assert torch.allclose(logits[0, 0, 0], logits[0, 0, 1])
    with torch.no_grad():
        m.actor.agent_out.normal_(0, 1.0)
    logits = m.forward_train({"obs": same, "state_in": h0})["action_dist_inputs"]
    assert not torch.allclose(logits[0, 0, 0], logits[0, 0, 1])
    entry = registry.get("mappo")
    with pytest.raises(ConfigError, match=r"algorithms\.mappo\.actor_agent_heads: true needs share_actor: true"):
        entry.build(SMALL, entry.hparams({"actor_agent_heads": True, "share_actor": False}), RES, 0)


PER_DEVICE = ScenarioConfig(n_eds=6, n_uavs=2, episode_len=10, action_mode="per_device")


def _per_ed_module(heads: str):
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    spec = RLModuleSpec(
        module_class=MAPPOTorchRLModule,
        observation_space=team_observation_space(PER_DEVICE),
        action_space=team_action_space(PER_DEVICE),
        model_config=hparams_model_config(
            MAPPOHParams, critic="central", state_dim=state_dim(PER_DEVICE), actor_heads=heads, max_seq_len=8
        ),
    )
    return spec.build()


@pytest.mark.parametrize("heads", ["per_slot", "shared"])
def test_per_ed_heads_read_each_slots_own_row(heads):
    """actor_heads: the flat layout of logits, a near-uniform start, and slot k's head reading row k:
    with the trunk's input to the heads cut, a change to ED row j moves slot j's logits only."""
    from uavlora_rllib.algorithms.common.per_ed_actor import PerEDActor

    m = _per_ed_module(heads)
    assert isinstance(m.actor, PerEDActor)
    quota, u, d = PER_DEVICE.quota, PER_DEVICE.n_uavs, obs_dim(PER_DEVICE)
    n_slot = len(PER_DEVICE.sf_set) + len(PER_DEVICE.tp_dbm)
    torch.manual_seed(0)
    obs = torch.rand(2, 3, u, d) * 2 - 1
    batch = {"obs": obs, "state_in": {"h": torch.zeros(2, u, 128)}}
    logits = m.forward_train(batch)["action_dist_inputs"]
    assert logits.shape == (2, 3, u, m.head.n_logits) == (2, 3, u, n_slot * quota + len(PER_DEVICE.bw_khz))
    assert float(logits.detach().abs().max()) < 0.05  # near-uniform initial policy, as the flat actor's
    with torch.no_grad():
        m.actor.slot_heads.w1[:, :, : m.actor.slot_heads.in_x] = 0.0  # heads read their rows only
        m.actor.slot_heads.w2.normal_(0, 1.0)
    logits = m.forward_train(batch)["action_dist_inputs"]
    j = 1
    moved = obs.clone()
    moved[..., 4 * j : 4 * j + 4] = -obs[..., 4 * j : 4 * j + 4]
    changed = (m.forward_train({**batch, "obs": moved})["action_dist_inputs"] - logits).abs()
    per_slot = changed[..., : n_slot * quota].unflatten(-1, (quota, n_slot)).amax(dim=(0, 1, 2, 4))
    assert per_slot[j] > 1e-3 and torch.all(per_slot[torch.arange(quota) != j] == 0.0), per_slot
    # shared: two slots holding the same row differ only through their one-hot
    same = obs.clone()
    same[..., 4:8] = same[..., 0:4]
    out = m.forward_train({**batch, "obs": same})["action_dist_inputs"][..., : 2 * n_slot].unflatten(-1, (2, n_slot))
    assert not torch.allclose(out[..., 0, :], out[..., 1, :])
    if heads == "shared":
        with torch.no_grad():
            m.actor.slot_heads.w1[:, :, m.actor.slot_heads.in_x + 4 :] = 0.0  # cut the one-hot too
        out = m.forward_train({**batch, "obs": same})["action_dist_inputs"][..., : 2 * n_slot]
        assert torch.allclose(out[..., :n_slot], out[..., n_slot:])


@pytest.mark.parametrize(
    "overrides, scenario, message",
    [
        (
            {"actor_heads": "per_slot"},
            SMALL,
            r"algorithms\.mappo\.actor_heads: 'per_slot' needs action_mode per_device",
        ),
        (
            {"actor_heads": "shared", "share_actor": True, "actor_agent_heads": True},
            PER_DEVICE,
            r"algorithms\.mappo\.actor_agent_heads: true only with actor_heads 'flat'",
        ),
        ({"actor_heads": "per_ed"}, PER_DEVICE, "actor_heads"),
    ],
)
def test_per_ed_heads_refused_where_they_do_not_apply(overrides, scenario, message):
    entry = registry.get("mappo")
    with pytest.raises(ConfigError, match=message):
        entry.build(scenario, entry.hparams(overrides), RES, 0)


@pytest.mark.parametrize("name", ["mappo", "ippo"])
@pytest.mark.parametrize(
    "scenario, overrides, heads",
    [
        (PER_DEVICE, {}, "shared"),  # the default by action mode: per-ED heads in per_device
        (SMALL, {}, "flat"),  # and the flat actor in per_uav
        (PER_DEVICE, {"actor_heads": "flat"}, "flat"),  # a value set is kept
        (PER_DEVICE, {"actor_heads": "per_slot"}, "per_slot"),
    ],
)
def test_actor_heads_default_follows_the_action_mode(name, scenario, overrides, heads):
    """A null `actor_heads` resolves by action mode (common/hparams.py DEFAULT_ACTOR_HEADS) in the built
    config and in the module's actor: per-ED heads have slot heads, the flat actor has none."""
    entry = registry.get(name)
    config = entry.build(scenario, entry.hparams(overrides), RES, 0)
    assert config.model_config["actor_heads"] == heads
    module = config.get_default_rl_module_spec()
    module.observation_space, module.action_space = team_observation_space(scenario), team_action_space(scenario)
    module.model_config = config.model_config
    assert hasattr(module.build().actor, "slot_heads") == (heads != "flat")


def test_actor_heads_default_refuses_per_uav_heads_in_per_device():
    entry = registry.get("mappo")
    with pytest.raises(ConfigError, match=r"algorithms\.mappo\.actor_agent_heads: true needs actor_heads: flat"):
        entry.build(PER_DEVICE, entry.hparams({"share_actor": True, "actor_agent_heads": True}), RES, 0)


# ---------------------------------------------------------------- GRU state
def test_module_carries_gru_state():
    m = _module(SMALL)
    torch.manual_seed(1)
    for p in m.actor.parameters():  # a non-trivial actor (the last layer starts near zero)
        p.data.normal_(0, 0.5)
    u, d = SMALL.n_uavs, obs_dim(SMALL)
    o1, o2 = torch.rand(1, 1, u, d), torch.rand(1, 1, u, d)
    h0 = {"h": torch.as_tensor(m.get_initial_state()["h"])[None]}
    step1 = m.forward_train({"obs": o1, "state_in": h0})
    # Same observation o1 at step 2 after history [o1] vs after history [o2]: outputs differ.
    after_o1 = m.forward_train({"obs": o1, "state_in": step1["state_out"]})["action_dist_inputs"]
    after_o2 = m.forward_train({"obs": o1, "state_in": m.forward_train({"obs": o2, "state_in": h0})["state_out"]})
    assert not torch.allclose(after_o1, after_o2["action_dist_inputs"])
    assert not torch.allclose(after_o1, step1["action_dist_inputs"])
    # A 2-step sequence in one call equals the two single steps.
    seq = m.forward_train({"obs": torch.cat([o2, o1], dim=1), "state_in": h0})["action_dist_inputs"]
    assert torch.allclose(seq[:, 1], after_o2["action_dist_inputs"][:, 0], rtol=1e-4, atol=1e-4)


def test_policy_resets_gru_state_per_episode():
    m = _module(SMALL)
    torch.manual_seed(2)
    for p in m.actor.parameters():
        p.data.normal_(0, 0.5)
    policy = ModulePolicy(m, "mappo")
    core = BatchCore(SMALL, 3)
    core.reset(5)
    policy.reset(core)
    fresh = policy.act(core)
    h_fresh = policy.state["h"].clone()
    for _ in range(4):
        policy.act(core)
    assert not torch.allclose(policy.state["h"], h_fresh)  # state carried across slots
    logits_carried, _ = m.actor(torch.as_tensor(core.obs, dtype=torch.float32)[:, None], policy.state["h"])
    logits_fresh, _ = m.actor(torch.as_tensor(core.obs, dtype=torch.float32)[:, None], m.actor.initial_state(3))
    assert not torch.allclose(logits_carried, logits_fresh)
    policy.reset(core)  # after reset: the same as a fresh policy on the same observations
    assert np.array_equal(policy.act(core), fresh)
    assert fresh.shape == (3, SMALL.n_uavs) and fresh.dtype == np.int64


# ---------------------------------------------------------------- GAE
def _reference_gae(v, r, term, gamma, lam):
    """Plain per-agent GAE of ONE chunk; v has one more entry (bootstrap) than r."""
    adv = np.zeros((len(r), v.shape[1]))
    last = np.zeros(v.shape[1])
    for t in reversed(range(len(r))):
        nonterm = 0.0 if term[t] else 1.0
        delta = r[t] + gamma * nonterm * v[t + 1] - v[t]
        last = delta + gamma * lam * nonterm * last
        adv[t] = last
    return adv


def test_per_agent_gae_bootstraps_truncation_and_splits_chunks():
    rng = np.random.default_rng(0)
    l1, l2, u = 5, 3, 2
    v1, v2 = rng.normal(size=(l1 + 1, u)), rng.normal(size=(l2 + 1, u))
    r1, r2 = rng.normal(size=l1), rng.normal(size=l2)
    term2 = np.zeros(l2, dtype=bool)
    term2[-1] = True
    values = np.concatenate([v1, v2])
    rewards = np.concatenate([r1, [0.0], r2, [0.0]])
    terminated = np.concatenate([np.zeros(l1 + 1, bool), term2, [False]])
    real = np.concatenate([np.ones(l1, bool), [False], np.ones(l2, bool), [False]])
    adv = per_agent_gae(values, rewards, terminated, real, 0.9, 0.8)
    np.testing.assert_allclose(adv[:l1], _reference_gae(v1, r1, np.zeros(l1, bool), 0.9, 0.8))
    np.testing.assert_allclose(adv[l1 + 1 : l1 + 1 + l2], _reference_gae(v2, r2, term2, 0.9, 0.8))
    assert np.all(adv[~real] == 0.0)
    # Truncated (not terminal) end: the last real step bootstraps with V(final observation).
    np.testing.assert_allclose(adv[l1 - 1], r1[-1] + 0.9 * v1[-1] - v1[-2])
    # Terminated end: no bootstrap.
    np.testing.assert_allclose(adv[l1 + l2], r2[-1] - v2[-2])


def test_value_clip_centres_on_the_critics_own_output():
    """PerAgentGAE's VF_PREDS (the value clip's centre) is the critic's raw output before the update,
    so the first step's clipped and unclipped errors agree and the critic gets its full gradient,
    even when the batch moves the value normalisation by far more than the clip
    (docs/model.md#mappo-value-clip)."""
    from ray.rllib.core.columns import Columns
    from ray.rllib.evaluation.postprocessing import Postprocessing

    from uavlora_rllib.algorithms.common.columns import VF_PREDS
    from uavlora_rllib.algorithms.mappo.mappo_learner import PerAgentGAE

    torch.manual_seed(0)
    m = _module(SMALL, "central")
    b, t, u = 2, 6, SMALL.n_uavs
    seq_lens = torch.tensor([6, 4])  # each chunk ends with its phantom step; the second is padded
    loss_mask = torch.zeros(b, t, dtype=torch.bool)
    loss_mask[0, :5], loss_mask[1, :3] = True, True
    mb = {
        "state": torch.rand(b, t, state_dim(SMALL)),
        Columns.SEQ_LENS: seq_lens,
        Columns.REWARDS: torch.full((b, t), 50.0),  # targets ~50 normalised-std away from V ~ 0
        Columns.TERMINATEDS: torch.zeros(b, t, dtype=torch.bool),
        Columns.LOSS_MASK: loss_mask,
    }
    before = m.compute_values(mb).detach()
    PerAgentGAE(gamma=0.99, lambda_=0.95)(rl_module={"p": m}, batch={"p": mb}, episodes=[])
    assert m.critic.value_norm.debias > 0  # the statistics moved
    real = loss_mask.unsqueeze(-1).expand(b, t, u)
    torch.testing.assert_close(mb[VF_PREDS][real], before[real])
    values = m.compute_values(mb)
    targets = m.normalize(mb[Postprocessing.VALUE_TARGETS])
    clipped = mb[VF_PREDS] + torch.clamp(values - mb[VF_PREDS], -0.2, 0.2)
    loss = torch.max((values - targets) ** 2, (clipped - targets) ** 2)[real].mean()
    unclipped = ((values - targets) ** 2)[real].mean()
    w = m.critic.net[-1].weight
    grad, full = (torch.autograd.grad(x, w, retain_graph=True)[0] for x in (loss, unclipped))
    assert full.abs().sum() > 0
    torch.testing.assert_close(grad, full)


# ---------------------------------------------------------------- training (Ray)
@pytest.mark.slow
@pytest.mark.parametrize(
    "name, cfg, overrides",
    [("mappo", SMALL, {}), ("ippo", SMALL, {}), ("mappo", PER_DEVICE, {"actor_heads": "shared"})],
    ids=["mappo", "ippo", "mappo-per_ed_heads"],
)
def test_trains_a_few_iterations(ray_session, name, cfg, overrides):
    algo = _build(name, cfg, {**FAST, **overrides})
    try:
        for _ in range(2):
            res = algo.train()
        er = res["env_runners"]
        assert er["num_env_steps_sampled_lifetime"] == 2 * FAST["batch_episodes"] * cfg.episode_len
        assert er["ee_sys_mean"] > 0 and 0.0 <= er["success_rate"] <= 1.0
        lr = res["learners"]["default_policy"]
        assert np.isfinite(lr["policy_loss"]) and np.isfinite(lr["vf_loss"])
        module = algo.env_runner.module
        assert module.inference_only and not hasattr(module, "critic")  # env runners: actor only
        weights = algo.learner_group.get_weights(["default_policy"])["default_policy"]  # public API
        expected = state_dim(cfg) if name == "mappo" else obs_dim(cfg) + cfg.n_uavs  # local: + id
        assert weights["critic.net.0.weight"].shape[1] == expected
        assert weights["critic.value_norm.debias"] > 0  # value normalisation updated
        res = run_episodes(registry.get(name).greedy_policy(algo, cfg), cfg, episodes=2)
        assert res.mean("ee_sys_mean") > 0
    finally:
        algo.stop()
