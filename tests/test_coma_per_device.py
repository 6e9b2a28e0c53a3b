"""COMA in per_device mode (issue 23 item 3): a factored policy with a per-branch counterfactual
baseline (algorithms/coma/branching.py, docs/model.md#coma-per-device).

The fast tests check the maths by hand and by loops on tiny modules, and one learner update
without Ray; the registry build that samples and trains is marked slow.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns

from uavlora_rllib.algorithms.coma.branching import BRANCH_LOGP
from uavlora_rllib.algorithms.coma.coma import COMAHParams
from uavlora_rllib.algorithms.coma.coma_learner import (
    SAMPLED_LOGP,
    critic_targets,
    lambda_returns,
    sampled_advantage,
)
from uavlora_rllib.algorithms.coma.coma_module import (
    ACTIONS,
    BOOTSTRAP,
    CRITIC_ROWS,
    LOGITS,
    OBS,
    Q_ROWS,
    Q_TARGET,
    Q_VALUES,
    REWARDS,
    TD_TARGETS,
    COMATorchRLModule,
    counterfactual_advantage,
)
from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.action_head import BranchLayout, taken
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.config import hparams_model_config
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

U, OBS_DIM, STATE_DIM = 3, 7, 11
ROW = [3, 2, 3, 2, 2]  # [n_sf, n_tp] * 2 slots + [n_bw], small sizes
L, W = len(ROW), max(ROW)


def _module(inference_only: bool = False, **overrides) -> COMATorchRLModule:
    torch.manual_seed(0)
    config = {
        "state_dim": STATE_DIM,
        "actor_hidden": 16,
        "gru_hidden": 8,
        "critic_hidden": [32, 32],
        "action_factors": [],
    }
    module = COMATorchRLModule(
        observation_space=gym.spaces.Box(-1.0, 1.0, (U, OBS_DIM), np.float32),
        action_space=gym.spaces.MultiDiscrete(np.tile(ROW, (U, 1))),
        inference_only=inference_only,
        model_config=hparams_model_config(COMAHParams, **{**config, **overrides}),
    )
    if not inference_only:
        module.make_target_networks()
    return module


def _actions(*lead: int, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return torch.stack([torch.randint(0, n, lead + (U,), generator=gen) for n in ROW], dim=-1)  # [..., U, L]


def _batch(b: int = 2, t: int = 4, seed: int = 1) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return {
        OBS: torch.rand(b, t + 1, U, OBS_DIM, generator=gen) * 2 - 1,
        GLOBAL_STATE: torch.randn(b, t + 1, STATE_DIM, generator=gen),
        ACTIONS: _actions(b, t, seed=seed),
        REWARDS: torch.rand(b, t, generator=gen),
    }


# ------------------------------------------------------------------ maths by hand
def test_per_branch_baseline_by_hand():
    """One UAV, two branches of sizes 2 and 3, a joint Q table: each branch's baseline averages
    Q over its own values with the other branch held at the taken value."""
    q_joint = torch.tensor([[1.0, 4.0, -2.0], [3.0, 0.0, 6.0]])  # Q(a_0, a_1)
    a = (1, 2)  # taken: Q = 6
    pi0, pi1 = torch.tensor([0.25, 0.75]), torch.tensor([0.5, 0.2, 0.3])
    layout = BranchLayout([2, 3])
    # per-branch rows in the padded [L, W] grid (padding: Q 0, pi 0)
    q = torch.tensor([[q_joint[0, 2], q_joint[1, 2], 0.0], q_joint[1].tolist()])  # [[-2, 6, 0], [3, 0, 6]]
    pi = torch.stack([torch.cat([pi0, torch.zeros(1)]), pi1])
    adv, baseline, q_taken = counterfactual_advantage(q, pi, torch.tensor(a))
    # branch 0: 0.25 (-2) + 0.75 (6) = 4.0, A = 6 - 4 = 2;  branch 1: 0.5 3 + 0.2 0 + 0.3 6 = 3.3, A = 2.7
    torch.testing.assert_close(baseline, torch.tensor([4.0, 3.3]))
    torch.testing.assert_close(adv, torch.tensor([2.0, 2.7]))
    torch.testing.assert_close(q_taken, torch.tensor([6.0, 6.0]))
    assert layout.valid.tolist() == [[True, True, False], [True, True, True]]


def test_branch_log_probs_are_the_action_heads():
    """The padded per-branch distributions are ActionHead's: summed over a UAV's branches, the
    taken log-probabilities and the entropies equal ActionHead.logp_and_entropy."""
    m = _module()
    logits = torch.randn(5, U, m.head.n_logits)
    actions = _actions(5)
    lp = m.layout.log_probs(logits)  # [5, U, L, W]
    assert lp.shape == (5, U, L, W)
    torch.testing.assert_close(lp.exp().sum(-1), torch.ones(5, U, L))
    assert (lp.exp()[..., ~m.layout.valid] == 0).all()
    logp, ent = m.head.logp_and_entropy(logits, actions)
    torch.testing.assert_close(taken(lp, actions).sum(-1), logp)
    torch.testing.assert_close(m.layout.entropy(lp).sum(-1), ent)
    assert torch.isfinite(m.layout.entropy(lp)).all()


# ------------------------------------------------------------------ the critic
def test_branch_critic_is_an_mlp_on_its_concatenated_rows():
    """forward (first layer as sums of columns) equals the MLP on the concatenated rows
    [s, one-hot of all branches with (u, l) left out, one-hot (u, l), o_u]; row (u, l) never sees
    a_{u,l} and sees every other branch of every UAV."""
    m = _module()
    c = m.critic
    state, obs, actions = torch.randn(4, STATE_DIM), torch.rand(4, U, OBS_DIM), _actions(4)
    x = c.inputs(state, obs, actions)  # [4, U, L, in]
    assert x.shape == (4, U, L, STATE_DIM + U * sum(ROW) + U * L + OBS_DIM) == (4, U, L, c.in_dim)
    # each row: the other U L - 1 branches one-hot, plus the one-hot of (u, l)
    block = x[..., STATE_DIM : STATE_DIM + U * sum(ROW)]
    assert (block.sum(-1) == U * L - 1).all()
    h = c.body(c.first(x))
    y = torch.einsum("...lh,lhn->...ln", h, c.out_weight) + c.out_bias
    value, diff = y[..., :1], y[..., 1:]
    diff_valid = diff.masked_fill(~m.layout.valid, 0.0)
    want = (value + diff - diff_valid.sum(-1, keepdim=True) / m.layout.sizes[:, None]).masked_fill(~m.layout.valid, 0.0)
    q = c(state, obs, actions)
    assert q.shape == (4, U, L, W)
    torch.testing.assert_close(q, want, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(q.masked_fill(~m.layout.valid, 0).mean(-1).mean(), q.mean(-1).mean())  # padding is 0
    for u in range(U):
        for branch in range(L):
            changed = actions.clone()
            changed[:, u, branch] = (changed[:, u, branch] + 1) % ROW[branch]
            q2 = c(state, obs, changed)
            torch.testing.assert_close(q2[:, u, branch], q[:, u, branch])  # its own branch: not an input
            other = (u + 1) % U
            assert not torch.allclose(q2[:, other], q[:, other])  # every other UAV's rows see it
            if L > 1:
                sibling = (branch + 1) % L
                assert not torch.allclose(q2[:, u, sibling], q[:, u, sibling])  # and u's other branches


@pytest.mark.parametrize("hidden", [[32], [32, 16]])
def test_branch_critic_gradients_are_the_concatenated_mlps(hidden):
    """The in-place, branch-major forward has the gradients of the plain MLP on the concatenated
    rows, for every parameter."""
    m = _module(critic_hidden=hidden)
    c = m.critic
    state, obs, actions = torch.randn(3, 4, STATE_DIM), torch.rand(3, 4, U, OBS_DIM), _actions(3, 4)
    target = torch.randn(3, 4, U, L, W)
    h = c.body(c.first(c.inputs(state, obs, actions)))
    y = torch.einsum("...lh,lhn->...ln", h, c.out_weight) + c.out_bias
    value, diff = y[..., :1], y[..., 1:].masked_fill(~m.layout.valid, 0.0)
    concatenated = (value + diff - diff.sum(-1, keepdim=True) / m.layout.sizes[:, None]).masked_fill(
        ~m.layout.valid, 0.0
    )
    grads = []
    for q in (c(state, obs, actions), concatenated):
        c.zero_grad()
        ((q - target) ** 2).mean().backward()
        grads.append({k: p.grad.clone() for k, p in c.named_parameters()})
    for k in grads[0]:
        torch.testing.assert_close(grads[0][k], grads[1][k], atol=1e-6, rtol=1e-5, msg=k)


def test_critic_on_a_subset_of_rows_is_those_rows_of_the_whole_critic():
    """critic(..., rows) gives the rows u L + l of the full [U, L, W] output, and a loss on them
    the gradient of the same loss taken on the full output's rows, for every parameter."""
    m = _module(critic_hidden=[32, 16])
    c = m.critic
    state, obs, actions = torch.randn(3, 4, STATE_DIM), torch.rand(3, 4, U, OBS_DIM), _actions(3, 4)
    rows = torch.tensor([0, 3, L + 1, 2 * L + L - 1])  # (0, 0), (0, 3), (1, 1), (2, L - 1)
    target = torch.randn(3, 4, len(rows), W)
    grads = []
    for q in (c(state, obs, actions, rows), m.row_values(c(state, obs, actions), rows, 2)):
        assert q.shape == (3, 4, len(rows), W)
        c.zero_grad()
        ((q - target) ** 2).mean().backward()
        grads.append({k: p.grad.clone() for k, p in c.named_parameters()})
    torch.testing.assert_close(
        c(state, obs, actions, rows), c(state, obs, actions)[:, :, [0, 0, 1, 2], [0, 3, 1, L - 1]]
    )
    for k in grads[0]:
        torch.testing.assert_close(grads[0][k], grads[1][k], atol=1e-6, rtol=1e-5, msg=k)
    assert grads[0]["out_weight"][2].abs().sum() == 0  # branch 2 is in none of the rows: no gradient


def test_critic_branch_fraction_trains_a_random_subset_and_advises_from_all():
    """critic_branch_fraction < 1: each draw is round(f U L) distinct sorted rows, different draws
    differ; forward_train's Q_ROWS and targets are those rows of the full critic's, and Q_VALUES
    (the advantage's) is every row without gradient. At 1 nothing is drawn and Q_ROWS is Q_VALUES."""
    m = _module(critic_branch_fraction=0.25)
    draws = [m.draw_critic_rows() for _ in range(20)]
    k = round(0.25 * U * L)
    for rows in draws:
        assert rows.shape == (k,) and (rows.diff() > 0).all() and 0 <= rows.min() and rows.max() < U * L
    assert len({tuple(r.tolist()) for r in draws}) > 1
    batch = _batch()
    torch.manual_seed(5)
    out = m.forward_train(batch)
    rows = out[CRITIC_ROWS]
    assert out[Q_ROWS].shape == out[Q_TARGET].shape == (2, 4, k, W) and out[BOOTSTRAP].shape == (2, k)
    assert out[Q_ROWS].requires_grad and not out[Q_VALUES].requires_grad
    assert out[Q_VALUES].shape == (2, 4, U, L, W)
    torch.testing.assert_close(out[Q_ROWS], m.row_values(out[Q_VALUES], rows, 2))
    full = _module()  # the same seed, so the same parameters; every row
    assert full.draw_critic_rows() is None
    torch.manual_seed(5)
    out_full = full.forward_train(batch)
    assert out_full[CRITIC_ROWS] is None and out_full[Q_ROWS] is out_full[Q_VALUES]
    torch.testing.assert_close(out[Q_VALUES], out_full[Q_VALUES].detach())
    torch.testing.assert_close(out[Q_TARGET], m.row_values(out_full[Q_TARGET], rows, 2))
    assert _module(critic_branch_fraction=1e-6).draw_critic_rows().shape == (1,)  # at least one row


@pytest.mark.parametrize("fraction", [1.0, 0.4])
def test_at_gamma_zero_the_targets_are_the_rewards_without_the_target_critic(fraction):
    """gamma 0: forward_train leaves the target critic out, and critic_targets gives what TD(lambda)
    from the target critic gives at gamma 0 (the rewards), on every row or the drawn ones."""
    batch = _batch()
    m = _module(gamma=0.0, critic_branch_fraction=fraction)
    out = m.forward_train(batch)
    assert Q_TARGET not in out and BOOTSTRAP not in out
    row_actions = m.row_values(batch[ACTIONS], out[CRITIC_ROWS])
    with_target = _module(gamma=0.5, critic_branch_fraction=fraction).forward_target(
        {**batch, LOGITS: m.episode_logits(batch[OBS]), CRITIC_ROWS: out[CRITIC_ROWS]}
    )
    want = lambda_returns(batch[REWARDS], taken(with_target[Q_TARGET], row_actions), with_target[BOOTSTRAP], 0.0, 0.8)
    got = critic_targets(batch[REWARDS], out, row_actions, 0.0, 0.8)
    assert got.shape == row_actions.shape
    torch.testing.assert_close(got, want)
    torch.testing.assert_close(
        got[:, :, 0], batch[REWARDS] if fraction < 1 else batch[REWARDS][..., None].expand(2, 4, L)
    )


def test_counterfactual_baseline_equals_a_loop_over_branch_values():
    """The learner's one-call baseline equals, for every UAV u and branch l, the loop
    sum_c pi_{u,l}(c) Q_{u,l}(s, a with branch l of u set to c); A = Q(s, a) - baseline; and
    the advantages have zero mean under the policy of each branch."""
    m = _module()
    batch = _batch(b=1, t=2)
    with torch.no_grad():
        fwd = m.forward_train(batch)
        steps = 2
        pi, logp, _ = m.policy_terms(fwd[LOGITS][:, :steps], batch[ACTIONS])
        adv, baseline, q_taken = counterfactual_advantage(fwd[Q_VALUES], pi, batch[ACTIONS])
        state, obs = batch[GLOBAL_STATE][:, :steps], batch[OBS][:, :steps]
        for u in range(U):
            for branch in range(L):
                loop_baseline = torch.zeros(1, steps)
                adv_under_pi = torch.zeros(1, steps)
                for value in range(ROW[branch]):
                    changed = batch[ACTIONS].clone()
                    changed[..., u, branch] = value
                    q_value = m.critic_q(m.critic, state, obs, changed)
                    loop_baseline += pi[..., u, branch, value] * q_value[..., u, branch, value]
                    # the advantage had the policy taken `value` here, the rest as taken
                    a_value, _, _ = counterfactual_advantage(q_value, pi, changed)
                    adv_under_pi += pi[..., u, branch, value] * a_value[..., u, branch]
                torch.testing.assert_close(baseline[..., u, branch], loop_baseline, atol=1e-5, rtol=1e-5)
                q_joint = m.critic_q(m.critic, state, obs, batch[ACTIONS])[..., u, branch, :]
                torch.testing.assert_close(
                    adv[..., u, branch],
                    taken(q_joint, batch[ACTIONS][..., u, branch]) - loop_baseline,
                    atol=1e-5,
                    rtol=1e-5,
                )
                torch.testing.assert_close(adv_under_pi, torch.zeros_like(adv_under_pi), atol=1e-5, rtol=0)
    assert adv.shape == baseline.shape == q_taken.shape == logp.shape == (1, steps, U, L)


# ------------------------------------------------------------------ module
def test_shapes_of_the_forward_passes():
    m = _module()
    b, t = 2, 4
    out = m.forward_train(_batch(b, t))
    assert out[LOGITS].shape == (b, t + 1, U, sum(ROW))
    assert out[Q_VALUES].shape == out[Q_TARGET].shape == (b, t, U, L, W)
    assert out[BOOTSTRAP].shape == (b, U, L)
    h = {"h": torch.zeros(b, U, 8)}
    obs = torch.rand(b, 1, U, OBS_DIM)
    explore = m.forward_exploration({Columns.OBS: obs, Columns.STATE_IN: h})
    assert explore[Columns.ACTIONS].shape == explore[BRANCH_LOGP].shape == (b, 1, U, L)
    assert explore[Columns.ACTION_LOGP].shape == (b, 1, U)
    torch.testing.assert_close(explore[BRANCH_LOGP].sum(-1), explore[Columns.ACTION_LOGP])
    assert (explore[Columns.ACTIONS] < torch.tensor(ROW)).all() and (explore[Columns.ACTIONS] >= 0).all()


def test_greedy_is_the_per_branch_argmax_and_runners_hold_the_actor_only():
    learner_side, runner_side = _module(), _module(inference_only=True)
    assert not hasattr(runner_side, "critic") and not hasattr(runner_side, "target_critic")
    assert all(k.startswith("actor.") for k in runner_side.state_dict())
    runner_side.set_state(learner_side.get_state(inference_only=True))
    obs, h = torch.rand(5, 1, U, OBS_DIM), {"h": torch.zeros(5, U, 8)}
    greedy = runner_side.forward_inference({Columns.OBS: obs, Columns.STATE_IN: h})[Columns.ACTIONS]
    torch.testing.assert_close(
        greedy, learner_side.forward_inference({Columns.OBS: obs, Columns.STATE_IN: h})[Columns.ACTIONS]
    )
    logits, _ = runner_side.actor(obs, h["h"])
    want = torch.stack([part.argmax(-1) for part in torch.split(logits, ROW, dim=-1)], dim=-1)
    torch.testing.assert_close(greedy, want)
    torch.testing.assert_close(greedy, runner_side.layout.log_probs(logits).argmax(-1))


# ------------------------------------------------------------------ one learner update, no Ray
@pytest.fixture(scope="module")
def learner():
    """COMA's learner for a tiny per_device scenario, built from the registry's config (no Ray)."""
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5, action_mode="per_device")
    entry = registry.get("coma")
    hparams = entry.hparams({"actor_hidden": 16, "gru_hidden": 8, "critic_hidden": [32], "updates_per_iteration": 2})
    config = entry.build(scenario, hparams, registry.Resources(num_envs_per_env_runner=2), 0)
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(scenario), team_action_space(scenario))}
    return config.build_learner(env=None, spaces=spaces), scenario


def _learner_batch(module, scenario, b: int = 2) -> dict[str, torch.Tensor]:
    """Whole episodes as coma_learner.episode_batch lays them out, actions sampled by the module."""
    from uavlora_rllib.algorithms.common.config import module_dims

    t, dims = scenario.episode_len, module_dims(scenario)
    gen = torch.Generator().manual_seed(3)
    obs = torch.rand(b, t + 1, dims["n_agents"], dims["obs_dim"], generator=gen)
    with torch.no_grad():
        logits, _ = module.actor(obs, module.actor.initial_state(b))
        actions, _ = module.head.sample(logits[:, :t])
        branch_logp = taken(module.layout.log_probs(logits[:, :t]), actions)
    return {
        OBS: obs,
        ACTIONS: actions,
        REWARDS: torch.rand(b, t, generator=gen),
        GLOBAL_STATE: torch.randn(b, t + 1, dims["state_dim"], generator=gen),
        SAMPLED_LOGP: branch_logp,
    }


def test_gradients_reach_every_branch_head(learner):
    """The learner's loss (critic TD(lambda) + per-branch counterfactual policy gradient) sends a
    gradient into every actor parameter, every branch's logits (every UAV's own output layer
    included) and every branch's critic output layer; the sampled ratio is 1."""
    learner, scenario = learner
    module = learner.module[DEFAULT_MODULE_ID].unwrapped()
    batch = _learner_batch(module, scenario)
    fwd = module.forward_train(batch)
    loss = learner.compute_loss_for_module(module_id=DEFAULT_MODULE_ID, config=None, batch=batch, fwd_out=fwd)
    module.zero_grad()
    loss.backward()
    for name, p in list(module.actor.named_parameters()) + list(module.critic.named_parameters()):
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    out_bias = module.actor.nets[0].out[-1].bias.grad  # [sum(row)]: every branch's logit group
    for part in torch.split(out_bias, module.head.nvec):
        assert part.abs().sum() > 0
    per_uav_heads = module.actor.agent_out.grad  # [U, H, sum(row)]
    for u in range(per_uav_heads.shape[0]):
        for part in torch.split(per_uav_heads[u], module.head.nvec, dim=-1):
            assert part.abs().sum() > 0
    for branch in range(module.layout.n_branches):
        assert module.critic.out_weight.grad[branch].abs().sum() > 0
    assert not any(p.grad is not None and p.grad.abs().sum() > 0 for p in module.target_critic.parameters())
    stats = learner.metrics.peek((DEFAULT_MODULE_ID, "clip_fraction"))
    assert float(stats) == 0.0  # the batch's sampled per-branch log-probabilities are the module's


def test_per_ed_heads_get_the_gradient_of_every_branch():
    """actor_heads (common/per_ed_actor.make_actor, as MAPPO's): COMA's per_device actor becomes
    PerEDActor; the learner's loss reaches every slot head, the BW head and the torso, and each
    branch's logit group."""
    from ray.rllib.core import DEFAULT_MODULE_ID as MID

    from uavlora_rllib.algorithms.common.per_ed_actor import PerEDActor
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5, action_mode="per_device")
    entry = registry.get("coma")
    overrides = {"actor_hidden": 16, "gru_hidden": 8, "critic_hidden": [32], "actor_heads": "shared"}
    hparams = entry.hparams({**overrides, "actor_agent_heads": False})
    config = entry.build(scenario, hparams, registry.Resources(num_envs_per_env_runner=2), 0)
    spaces = {MID: (team_observation_space(scenario), team_action_space(scenario))}
    learner = config.build_learner(env=None, spaces=spaces)
    module = learner.module[MID].unwrapped()
    assert isinstance(module.actor, PerEDActor)
    batch = _learner_batch(module, scenario)
    fwd = module.forward_train(batch)
    assert fwd[LOGITS].shape[-1] == module.head.n_logits
    loss = learner.compute_loss_for_module(module_id=MID, config=None, batch=batch, fwd_out=fwd)
    module.zero_grad()
    loss.backward()
    for name, p in module.actor.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    logits = fwd[LOGITS]
    grads = torch.autograd.grad(
        learner.compute_loss_for_module(module_id=MID, config=None, batch=batch, fwd_out=fwd), logits
    )[0]
    for part in torch.split(grads.abs().sum(dim=(0, 1, 2)), module.head.nvec):
        assert part.sum() > 0
    with pytest.raises(ConfigError, match=r"algorithms\.coma\.actor_agent_heads: true only with actor_heads 'flat'"):
        entry.build(scenario, entry.hparams(overrides), registry.Resources(), 0)  # COMA's default is true
    per_uav = ScenarioConfig(n_eds=4, n_uavs=2)
    with pytest.raises(ConfigError, match=r"algorithms\.coma\.actor_heads: 'shared' needs action_mode per_device"):
        entry.build(per_uav, hparams, registry.Resources(), 0)


@pytest.mark.parametrize("fraction", [1.0, 0.3])
def test_critic_steps_lower_the_td_error(learner, fraction):
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    learner, scenario = learner
    module = learner.module[DEFAULT_MODULE_ID].unwrapped()
    module.branch_fraction = fraction  # (the module's copy of critic_branch_fraction)
    batch = _learner_batch(module, scenario)
    multi = MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch({k: v.numpy() for k, v in batch.items()})}, env_steps=10)
    hp, steps = learner.config.hparams, scenario.episode_len

    def td_error() -> float:
        """Over every row, whatever rows the steps train, against the TD(lambda) targets of the
        target critic (which critic-only steps leave as it is; its bootstrap sample seeded)."""
        torch.manual_seed(0)
        with torch.no_grad():
            fwd = module.forward_target({**batch, LOGITS: module.episode_logits(batch[OBS])})
            targets = lambda_returns(
                batch[REWARDS] * hp.reward_scale,
                taken(fwd[Q_TARGET], batch[ACTIONS]),
                fwd[BOOTSTRAP],
                hp.gamma,
                hp.td_lambda,
            )
            q = module.critic_q(module.critic, batch[GLOBAL_STATE][:, :steps], batch[OBS][:, :steps], batch[ACTIONS])
            return float(((taken(q, batch[ACTIONS]) - targets) ** 2).mean())

    before = td_error()
    module.branch_fraction = fraction
    for _ in range(6):
        learner.train_critic(multi)
    module.branch_fraction = 1.0
    assert td_error() < before


@pytest.mark.parametrize("fraction", [1.0, 0.3])
def test_the_joint_step_trains_on_the_critic_steps_targets(learner, fraction):
    """train_critic returns the TD(lambda) targets its steps trained on where they cover every critic
    row: those of the target critic with the same bootstrap draw. Given them (TD_TARGETS, as
    COMA.update_learners hands them over), the joint step leaves the target critic unevaluated and its
    critic loss is against them. On a subset of rows (fraction < 1) nothing is handed over."""
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    learner, scenario = learner
    module = learner.module[DEFAULT_MODULE_ID].unwrapped()
    module.branch_fraction = fraction
    try:
        batch = _learner_batch(module, scenario)
        multi = MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch({k: v.numpy() for k, v in batch.items()})}, 10)
        hp = learner.config.hparams
        torch.manual_seed(5)
        handed = learner.train_critic(multi)
        if fraction < 1.0:
            assert handed == {}
            return
        torch.manual_seed(5)  # the same bootstrap draw (fraction 1 draws no rows)
        want = critic_targets(
            batch[REWARDS] * hp.reward_scale, module.target_terms(batch), batch[ACTIONS], hp.gamma, hp.td_lambda
        )
        targets = torch.as_tensor(handed[DEFAULT_MODULE_ID])
        torch.testing.assert_close(targets, want)
        given = {**batch, TD_TARGETS: targets + 1.0}  # shifted: the loss must read these, not its own
        fwd = module.forward_train(given)
        assert Q_TARGET not in fwd and BOOTSTRAP not in fwd and fwd[TD_TARGETS] is given[TD_TARGETS]
        learner.compute_loss_for_module(module_id=DEFAULT_MODULE_ID, config=None, batch=given, fwd_out=fwd)
        want_loss = ((taken(fwd[Q_ROWS], batch[ACTIONS]) - given[TD_TARGETS]) ** 2).mean()
        assert float(learner.metrics.peek((DEFAULT_MODULE_ID, "critic_loss"))) == pytest.approx(
            float(want_loss.detach())
        )
    finally:
        module.branch_fraction = 1.0
        module._kept_logits = None  # (the learner is the module's fixture)


def test_the_joint_step_reuses_the_critic_steps_actor_forward(learner):
    """train_critic's actor logits (with their graph) are the next forward_train's on the same
    observations: the same values and actor gradients as a forward of its own. Taken once; other
    observations or an actor changed in between get a forward of their own."""
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    learner, scenario = learner
    module = learner.module[DEFAULT_MODULE_ID].unwrapped()
    batch = _learner_batch(module, scenario)
    multi = MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch({k: v.numpy() for k, v in batch.items()})}, 10)
    actor = list(module.actor.parameters())

    def joint_step(fwd_batch):
        torch.manual_seed(2)  # the joint step's bootstrap draw
        fwd = module.forward_train(fwd_batch)
        loss = learner.compute_loss_for_module(module_id=DEFAULT_MODULE_ID, config=None, batch=fwd_batch, fwd_out=fwd)
        return fwd[LOGITS], torch.autograd.grad(loss, actor)

    learner.train_critic(multi)
    kept = module._kept_logits[1]
    logits, grads = joint_step(batch)
    assert logits is kept and kept.requires_grad
    own, own_grads = joint_step(batch)  # taken once: this forward is its own
    assert own is not kept
    torch.testing.assert_close(own, kept)
    for got, want in zip(grads, own_grads):
        torch.testing.assert_close(got, want)
    learner.train_critic(multi)
    kept = module._kept_logits[1]
    assert module.forward_train({**batch, OBS: batch[OBS] + 1.0})[LOGITS] is not kept
    learner.train_critic(multi)
    kept = module._kept_logits[1]
    with torch.no_grad():
        actor[0].add_(0.0)  # an in-place change of the actor (a version bump)
    assert module.forward_train(batch)[LOGITS] is not kept


def test_sampled_advantage_by_hand():
    """G_t - b per row, G_t the mean of the step's targets over the rows trained (each is r_t at gamma 0)."""
    baseline = torch.tensor([[[[1.0, 2.0], [3.0, 4.0]]]])  # [B=1, T=1, U=2, L=2]
    targets = torch.full((1, 1, 2, 2), 5.0)
    assert torch.equal(sampled_advantage(targets, baseline), 5.0 - baseline)
    subset = torch.tensor([[[4.0, 6.0, 8.0]]])  # [B, T, K=3]: a row subset, per_device at fraction < 1
    assert torch.equal(sampled_advantage(subset, baseline), 6.0 - baseline)
    per_uav = torch.tensor([[[7.0, 9.0]]])  # [B, T, U]
    assert torch.equal(sampled_advantage(per_uav, baseline[..., 0]), 8.0 - baseline[..., 0])


@pytest.mark.parametrize("fraction", [1.0, 0.4])
def test_taken_value_return_puts_the_reward_in_place_of_the_critics_q(fraction):
    """`taken_value: return` at gamma 0: the actor's advantage is r_t - the counterfactual baseline of
    the same critic, on every row whatever rows the critic trains; `critic` (COMA's) uses Q's taken value."""
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5, action_mode="per_device")
    entry = registry.get("coma")
    small = {
        "actor_hidden": 16,
        "gru_hidden": 8,
        "critic_hidden": [32],
        "gamma": 0.0,
        "critic_branch_fraction": fraction,
    }
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(scenario), team_action_space(scenario))}
    advantages = {}
    for taken_value in ("critic", "return"):
        config = entry.build(scenario, entry.hparams({**small, "taken_value": taken_value}), registry.Resources(), 0)
        learner = config.build_learner(env=None, spaces=spaces)
        module = learner.module[DEFAULT_MODULE_ID].unwrapped()
        batch = _learner_batch(module, scenario)
        torch.manual_seed(0)
        fwd = module.forward_train(batch)
        learner.compute_loss_for_module(module_id=DEFAULT_MODULE_ID, config=None, batch=batch, fwd_out=fwd)
        pi, _, _ = module.policy_terms(fwd[LOGITS][:, : scenario.episode_len], batch[ACTIONS])
        adv, baseline, _ = counterfactual_advantage(fwd[Q_VALUES], pi, batch[ACTIONS])
        expected = adv if taken_value == "critic" else batch[REWARDS][..., None, None] - baseline
        logged = float(learner.metrics.peek((DEFAULT_MODULE_ID, "advantage_abs_mean")))
        assert logged == pytest.approx(float(expected.abs().mean()), rel=1e-5)
        advantages[taken_value] = logged
    assert advantages["critic"] != pytest.approx(advantages["return"], rel=1e-3)


# ------------------------------------------------------------------ registry and config
def test_registry_offers_per_device_and_checks_the_critic():
    entry = registry.get("coma")
    assert entry.action_modes == ("per_uav", "per_device")
    per_device = ScenarioConfig(n_eds=4, n_uavs=2, action_mode="per_device")
    with pytest.raises(
        ConfigError, match=r"algorithms\.coma\.critic_hidden: per_device needs at least one critic layer"
    ):
        entry.build(per_device, entry.hparams({"critic_hidden": []}), registry.Resources(), 0)
    config = entry.build(per_device, entry.hparams({}), registry.Resources(), 0)
    assert config.model_config["action_factors"] == []  # the per_uav factoring has no role here


@pytest.mark.slow
def test_per_device_trains_through_the_registry(ray_session):
    """Two iterations of the registry's per_device COMA (Ray, one env runner in-process): the
    paper's metrics, finite losses, 2 updates per batch reusing it with per-branch ratios, and
    greedy / sampled actions inside the per_device action space."""
    from uavlora_rllib.envs.team import team_action_space
    from uavlora_rllib.sim.core import BatchCore

    scenario = ScenarioConfig(n_eds=6, n_uavs=2, episode_len=8, action_mode="per_device")
    entry = registry.get("coma")
    hparams = entry.hparams({"batch_episodes": 4, "updates_per_iteration": 2, "critic_steps": 1})
    algo = entry.build(scenario, hparams, registry.Resources(num_envs_per_env_runner=4), 0).build_algo()
    try:
        for i in (1, 2):
            result = algo.train()
            assert int(result["num_gradient_updates_lifetime"]) == 2 * i
            stats = result["learners"][DEFAULT_MODULE_ID]
            for key in ("critic_loss", "actor_loss", "entropy", "advantage_abs_mean"):
                assert np.isfinite(float(stats[key])), key
            assert 0.0 <= float(stats["clip_fraction"]) < 0.5
        assert result["env_runners"]["ee_sys_mean"] > 0
        space = team_action_space(scenario)
        for explore in (False, True):
            policy = entry.policy(algo, scenario, explore=explore, seed=1)
            core = BatchCore(scenario, 3)
            core.reset(7)
            policy.reset(core)
            for _ in range(3):
                a = policy.act(core)
                assert a.shape == (3,) + space.shape and (a >= 0).all() and (a < space.nvec).all()
                core.step(a)
    finally:
        algo.stop()
