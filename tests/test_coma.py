"""COMA (issue 5): the counterfactual maths by hand, the critic's inputs, the module split
between learner and env runners, the result dict, batch reuse and config errors.
per_device mode: tests/test_coma_per_device.py; learning: tests/test_learning.py; checkpoints:
tests/test_algorithm_matrix.py. The Ray tests are marked slow (`make test-slow`).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from uavlora_rllib.algorithms.coma.coma import COMAHParams
from uavlora_rllib.algorithms.coma.coma_module import (
    COMATorchRLModule,
    counterfactual_advantage,
    critic_inputs,
    factor_onehot,
    td_lambda_targets,
)
from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.config import hparams_model_config
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)


# ------------------------------------------------------------------ maths by hand
def test_counterfactual_baseline_and_advantage_by_hand():
    # Joint Q(s, a0, a1) of 2 agents with 3 actions each (rows a0, columns a1).
    q_joint = np.array([[1.0, 2.0, 0.0], [4.0, -1.0, 3.0], [-2.0, 5.0, 1.0]])
    a0, a1 = 1, 2  # the joint action taken
    pi0 = np.array([0.2, 0.5, 0.3])
    pi1 = np.array([0.6, 0.1, 0.3])
    # The critic's row for agent u holds Q with a_-u fixed and u's own action varied.
    q_row0 = q_joint[:, a1]  # [0, 3, 1]
    q_row1 = q_joint[a0, :]  # [4, -1, 3]
    # Agent 0: baseline = 0.2*0 + 0.5*3 + 0.3*1 = 1.8; Q(s, a) = q_joint[1, 2] = 3; A = 3 - 1.8 = 1.2
    # Agent 1: baseline = 0.6*4 + 0.1*(-1) + 0.3*3 = 2.4 - 0.1 + 0.9 = 3.2; A = 3 - 3.2 = -0.2
    expected_baseline = np.array([1.8, 3.2])
    expected_adv = np.array([1.2, -0.2])

    q = torch.tensor(np.stack([q_row0, q_row1]), dtype=torch.float32, requires_grad=True)
    pi = torch.tensor(np.stack([pi0, pi1]), dtype=torch.float32, requires_grad=True)
    adv, baseline, q_taken = counterfactual_advantage(q, pi, torch.tensor([a0, a1]))
    np.testing.assert_allclose(baseline.numpy(), expected_baseline, atol=1e-6)
    np.testing.assert_allclose(adv.numpy(), expected_adv, atol=1e-6)
    np.testing.assert_allclose(q_taken.numpy(), [3.0, 3.0])
    assert not adv.requires_grad  # the actor's gradient must not flow into Q or the baseline's pi


def test_td_lambda_targets_by_hand():
    rewards = torch.tensor([[1.0, 2.0, 3.0]])  # [B=1, T=3]
    q_next = torch.tensor([[[9.9], [0.5], [0.7]]])  # [B, T, U=1]; entry 0 is never used
    bootstrap = torch.tensor([[1.0]])  # target value of the final state s_T (truncation)
    g, lam = 0.9, 0.5
    # G2 = 3 + 0.9*1.0 = 3.9
    # G1 = 2 + 0.9*((1-0.5)*0.7 + 0.5*3.9) = 2 + 0.9*2.3 = 4.07
    # G0 = 1 + 0.9*((1-0.5)*0.5 + 0.5*4.07) = 1 + 0.9*2.285 = 3.0565
    out = td_lambda_targets(rewards, q_next, bootstrap, g, lam)
    np.testing.assert_allclose(out[0, :, 0].numpy(), [3.0565, 4.07, 3.9], rtol=1e-6)
    # lambda = 1: discounted return plus the discounted bootstrap, no critic in between.
    out1 = td_lambda_targets(rewards, q_next, bootstrap, g, 1.0)
    np.testing.assert_allclose(out1[0, 0, 0].item(), 1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 1.0, rtol=1e-6)


# ------------------------------------------------------------------ module structure
def _module(inference_only: bool, n_agents=3, obs_dim=7, n_actions=4, state_dim=11, **overrides) -> COMATorchRLModule:
    config = {
        "state_dim": state_dim,
        "actor_hidden": 16,
        "gru_hidden": 8,
        "critic_hidden": [32, 32],
        "action_factors": [2, 2],
    }
    return COMATorchRLModule(
        observation_space=gym.spaces.Box(-1.0, 1.0, (n_agents, obs_dim), np.float32),
        action_space=gym.spaces.MultiDiscrete([n_actions] * n_agents),
        inference_only=inference_only,
        model_config=hparams_model_config(COMAHParams, **{**config, **overrides}),
    )


@pytest.mark.parametrize(
    "overrides",
    [{}, {"action_factors": [], "critic_use_obs": False}, {"critic_hidden": [32]}, {"critic_dueling": False}],
)
def test_critic_without_rows_is_the_mlp_on_its_concatenated_rows(overrides):
    """critic_q (the first layer as summed gathers, no input rows built) has the outputs and the
    gradients of the critic network applied to critic_inputs' rows."""
    torch.manual_seed(0)
    m = _module(False, **overrides)
    state, obs, actions = torch.randn(5, 2, 11), torch.rand(5, 2, 3, 7), torch.randint(0, 4, (5, 2, 3))
    factors = tuple(m.factors)
    rows = critic_inputs(state, obs if m.use_obs else None, actions, 4, factors)
    target = torch.randn(5, 2, 3, 4)
    grads = []
    for q in (m.critic_q(m.critic, state, obs, actions), m.critic(rows)):
        m.critic.zero_grad()
        ((q - target) ** 2).mean().backward()
        grads.append((q.detach(), {k: p.grad.clone() for k, p in m.critic.named_parameters()}))
    torch.testing.assert_close(grads[0][0], grads[1][0], atol=1e-5, rtol=1e-5)
    for k in grads[0][1]:
        torch.testing.assert_close(grads[0][1][k], grads[1][1][k], atol=1e-6, rtol=1e-5, msg=k)


@pytest.mark.parametrize("n_agents", [2, 3, 5])
def test_others_action_sum_is_the_summed_gather_with_its_gradient(n_agents):
    """_OthersActionSum (the critic's other-agent term) has embedding_bag's values and gradient over
    the [N U, U - 1] indices it replaces; float64 gradcheck of its hand-written backward."""
    from uavlora_rllib.algorithms.coma.coma_module import _OthersActionSum

    gen = torch.Generator().manual_seed(n_agents)
    n, n_actions, hid = 7, 4, 3
    table = torch.randn((n_agents - 1) * n_actions, hid, dtype=torch.float64, generator=gen, requires_grad=True)
    actions = torch.randint(0, n_actions, (n, n_agents), generator=gen)
    others = [[k for k in range(n_agents) if k != u] for u in range(n_agents)]
    index = torch.tensor([[p * n_actions + int(a[k]) for p, k in enumerate(row)] for a in actions for row in others])
    want = torch.nn.functional.embedding_bag(index, table, mode="sum")
    got = _OthersActionSum.apply(table, actions)
    torch.testing.assert_close(got, want)
    g = torch.randn(n * n_agents, hid, dtype=torch.float64, generator=gen)
    torch.testing.assert_close(torch.autograd.grad(got, table, g)[0], torch.autograd.grad(want, table, g)[0])
    assert torch.autograd.gradcheck(lambda t: _OthersActionSum.apply(t, actions), (table,))


def test_factor_onehot_matches_the_simulators_decoding():
    from uavlora_rllib.sim.actions import decode_joint_action

    cfg = ScenarioConfig()
    a = np.arange(cfg.n_joint_actions)
    sf, tp, bw = decode_joint_action(a, cfg)
    f = factor_onehot(torch.as_tensor(a), (cfg.n_sf, cfg.n_tp, cfg.n_bw)).numpy()
    np.testing.assert_array_equal(f[:, : cfg.n_sf].argmax(1), sf)
    np.testing.assert_array_equal(f[:, cfg.n_sf : cfg.n_sf + cfg.n_tp].argmax(1), tp)
    np.testing.assert_array_equal(f[:, cfg.n_sf + cfg.n_tp :].argmax(1), bw)
    assert (f.sum(1) == 3).all()


def test_critic_sees_state_and_others_actions_never_its_own():
    torch.manual_seed(0)
    m = _module(False)
    state = torch.randn(11)
    obs = torch.rand(3, 7)
    actions = torch.tensor([1, 3, 0])
    x = critic_inputs(state, obs, actions, 4, (2, 2))  # [U, in]
    assert x.shape == (3, 11 + 2 * (4 + 2 + 2) + 3 + 7)
    for u in range(3):
        np.testing.assert_array_equal(x[u, :11].numpy(), state.numpy())  # the global state
    q = m.critic_q(m.critic, state, obs, actions)  # [U, A]
    for u in range(3):
        changed = actions.clone()
        changed[u] = (changed[u] + 1) % 4  # u's own action only
        x2, q2 = critic_inputs(state, obs, changed, 4, (2, 2)), m.critic_q(m.critic, state, obs, changed)
        torch.testing.assert_close(x2[u], x[u])  # u's row ignores u's own action ...
        torch.testing.assert_close(q2[u], q[u])
        for k in range(3):
            if k != u:  # ... while every other agent's row sees it
                assert not torch.equal(x2[k], x[k])
                assert not torch.allclose(q2[k], q[k])


def test_actor_input_and_inference_only_module():
    learner_side, runner_side = _module(False), _module(True)
    assert learner_side.actor.nets[0].inp.in_features == 7 + 3  # obs_dim + U (one-hot id)
    assert not hasattr(runner_side, "critic") and not hasattr(runner_side, "target_critic")
    assert all(k.startswith("actor.") for k in runner_side.state_dict())
    assert any(k.startswith("critic.") for k in learner_side.state_dict())
    # The learner's inference-only weights are exactly what the env runner's module loads.
    runner_side.set_state(learner_side.get_state(inference_only=True))
    obs = torch.rand(5, 1, 3, 7)
    h = {"h": torch.zeros(5, 3, 8)}
    out_l = learner_side.forward_inference({"obs": obs, "state_in": h})
    out_r = runner_side.forward_inference({"obs": obs, "state_in": h})
    torch.testing.assert_close(out_l["actions"], out_r["actions"])
    torch.testing.assert_close(out_l["state_out"]["h"], out_r["state_out"]["h"])
    assert out_r["actions"].shape == (5, 1, 3)
    logits, _ = runner_side.actor(obs, h["h"])  # greedy = argmax of each UAV's logits
    torch.testing.assert_close(out_r["actions"], logits.argmax(-1))


# ------------------------------------------------------------------ config errors (no Ray)
def test_per_uav_actors_are_separate_networks():
    """share_actor=false: one batched actor per UAV (no id one-hot), the same output shapes."""
    m = _module(False, share_actor=False, actor_agent_heads=False)
    assert not m.actor.share and m.actor.in_dim == 7
    assert any(k.startswith("actor.nets.2.") for k in m.state_dict())
    logits = m.episode_logits(torch.rand(2, 4, 3, 7))
    assert logits.shape == (2, 4, 3, 4)


def test_bad_configs_raise_clear_config_errors():
    entry = registry.get("coma")
    assert entry.action_modes == ("per_uav", "per_device")
    with pytest.raises(ConfigError, match=r"algorithms\.coma\.lr_criticc: unknown field; allowed: .*lr_critic"):
        entry.hparams({"lr_criticc": 1e-3})
    with pytest.raises(ConfigError, match=r"algorithms\.coma\.td_lambda"):
        entry.hparams({"td_lambda": 1.5})
    with pytest.raises(ConfigError, match="batch_episodes"):
        resources = registry.Resources(num_envs_per_env_runner=4)
        entry.build(ScenarioConfig(), entry.hparams({"batch_episodes": 6}), resources, 0)
    with pytest.raises(ConfigError, match=r"algorithms\.coma\.actor_agent_heads: true needs share_actor: true"):
        entry.build(ScenarioConfig(), entry.hparams({"share_actor": False}), registry.Resources(), 0)
    hp = entry.hparams({"lr_critic": 5e-4, "critic_hidden": [64]})
    assert isinstance(hp, COMAHParams) and hp.lr_critic == 5e-4 and hp.critic_hidden == (64,)


# ------------------------------------------------------------------ training (Ray)
SMALL = {"n_eds": 4, "n_uavs": 2, "episode_len": 25}
LEARN_SEED = 0
LEARN_ITERS = 3  # x 16 episodes x 25 steps
LEARN_HPARAMS = {"lr_actor": 3e-4, "lr_critic": 1e-3, "critic_steps": 4}


@pytest.fixture(scope="module")
def trained(ray_session):
    entry = registry.get("coma")
    scenario = ScenarioConfig.from_dict(SMALL)
    resources = registry.Resources(num_envs_per_env_runner=16)
    algo = entry.build(scenario, entry.hparams(LEARN_HPARAMS), resources, LEARN_SEED).build_algo()
    try:
        results = [algo.train() for _ in range(LEARN_ITERS)]
        yield {"algo": algo, "entry": entry, "scenario": scenario, "results": results}
    finally:
        algo.stop()


def test_each_update_hands_its_critic_steps_targets_to_its_joint_step(ray_session, monkeypatch):
    """COMA.update_learners: the TD(lambda) targets that train_critic returns reach the joint step of
    the same update as its batch's TD_TARGETS column (so the target critic is evaluated once per update)."""
    from uavlora_rllib.algorithms.coma.coma_learner import COMATorchLearner
    from uavlora_rllib.algorithms.coma.coma_module import TD_TARGETS

    handed, seen = [], []
    train_critic, loss = COMATorchLearner.train_critic, COMATorchLearner.compute_loss_for_module

    def spy_train_critic(self, batch):
        handed.append(train_critic(self, batch))
        return handed[-1]

    def spy_loss(self, *, module_id, config, batch, fwd_out):
        seen.append(batch[TD_TARGETS].numpy().copy() if TD_TARGETS in batch else None)
        return loss(self, module_id=module_id, config=config, batch=batch, fwd_out=fwd_out)

    monkeypatch.setattr(COMATorchLearner, "train_critic", spy_train_critic)
    monkeypatch.setattr(COMATorchLearner, "compute_loss_for_module", spy_loss)
    entry = registry.get("coma")
    hparams = entry.hparams({"batch_episodes": 2, "updates_per_iteration": 2, "critic_steps": 1, "critic_hidden": [16]})
    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5)
    algo = entry.build(scenario, hparams, registry.Resources(num_envs_per_env_runner=2), 0).build_algo()
    try:
        algo.train()
    finally:
        algo.stop()
    assert len(handed) == len(seen) == 2
    for targets, got in zip(handed, seen):
        assert got is not None and got.shape == (2, 5, 2)
        np.testing.assert_array_equal(got, targets["default_policy"])
    assert not np.array_equal(seen[0], seen[1])  # each update's own targets (the target critic moved)


@pytest.mark.slow
def test_result_dict_and_runner_module(trained):
    first, last = trained["results"][0], trained["results"][-1]
    assert first["num_env_steps_sampled_lifetime"] == 16 * 25
    assert last["num_env_steps_sampled_lifetime"] == LEARN_ITERS * 16 * 25
    assert np.isfinite(last["env_runners"]["episode_return_mean"])
    stats = last["learners"]["default_policy"]
    for key in ("critic_loss", "actor_loss", "entropy"):
        assert np.isfinite(float(stats[key])), key
    runners = last["env_runners"]  # the paper's metrics of the sampled episodes (common/metrics.py)
    assert runners["ee_sys_mean"] > 0 and 0 <= runners["success_rate"] <= 1
    # The env runner holds the actor only.
    runner_module = trained["algo"].env_runner.module
    assert runner_module.inference_only
    assert not any(k.startswith(("critic", "target_critic")) for k in runner_module.state_dict())


@pytest.mark.slow
def test_updates_per_iteration_reuse_the_batch_with_a_clipped_ratio(trained):
    """updates_per_iteration = 3: three learner updates (each moving the target critic) on
    every sampled batch, the actor's term PPO's clipped surrogate around the sampling policy:
    on the first update the ratio is 1 (the env runner's log-probabilities match the learner's),
    so the clip fraction stays small, and the losses are finite."""
    entry = registry.get("coma")
    resources = registry.Resources(num_envs_per_env_runner=4)
    hparams = entry.hparams({"updates_per_iteration": 3, "batch_episodes": 4, "critic_steps": 1})
    algo = entry.build(trained["scenario"], hparams, resources, 0).build_algo()
    try:
        for i in (1, 2):
            result = algo.train()
            stats = result["learners"]["default_policy"]
            assert int(result["num_gradient_updates_lifetime"]) == 3 * i
            assert 0.0 <= float(stats["clip_fraction"]) < 0.5
            assert np.isfinite(float(stats["actor_loss"])) and np.isfinite(float(stats["critic_loss"]))
    finally:
        algo.stop()


def test_taken_value_return_per_uav_with_a_discount():
    """`taken_value: return` per_uav at gamma 0.99: the advantage is G^lambda_t (from the target critic)
    minus the counterfactual baseline; it differs from COMA's Q-based one and sends a gradient to the actor."""
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.algorithms.coma.coma_learner import SAMPLED_LOGP
    from uavlora_rllib.algorithms.coma.coma_module import ACTIONS, GLOBAL_STATE, OBS, REWARDS
    from uavlora_rllib.algorithms.common.config import module_dims
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5)
    entry = registry.get("coma")
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(scenario), team_action_space(scenario))}
    dims, gen = module_dims(scenario), torch.Generator().manual_seed(3)
    b, t, u = 2, scenario.episode_len, dims["n_agents"]
    batch = {
        OBS: torch.rand(b, t + 1, u, dims["obs_dim"], generator=gen),
        ACTIONS: torch.randint(0, 90, (b, t, u), generator=gen),
        REWARDS: torch.rand(b, t, generator=gen),
        GLOBAL_STATE: torch.randn(b, t + 1, dims["state_dim"], generator=gen),
        SAMPLED_LOGP: torch.zeros(b, t, u),
    }
    logged = {}
    for taken_value in ("critic", "return"):
        hparams = entry.hparams(
            {"actor_hidden": 16, "gru_hidden": 8, "critic_hidden": [32], "taken_value": taken_value}
        )
        learner = entry.build(scenario, hparams, registry.Resources(), 0).build_learner(env=None, spaces=spaces)
        module = learner.module[DEFAULT_MODULE_ID].unwrapped()
        torch.manual_seed(0)
        loss = learner.compute_loss_for_module(
            module_id=DEFAULT_MODULE_ID, config=None, batch=batch, fwd_out=module.forward_train(batch)
        )
        module.zero_grad()
        loss.backward()
        assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in module.actor.parameters())
        logged[taken_value] = float(learner.metrics.peek((DEFAULT_MODULE_ID, "advantage_abs_mean")))
    assert logged["critic"] != pytest.approx(logged["return"], rel=1e-3)
