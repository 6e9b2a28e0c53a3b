"""COMA's networks (Foerster et al., AAAI 2018) as one RLlib RLModule, and its pure maths.

Layout of the team view (uavlora_rllib/envs/team.py): observation [U, obs_dim] (row u is UAV
u's LOCAL observation), action MultiDiscrete([A] * U) with A = 90 (per_uav), shared reward,
global state under info["state"]. This docstring describes per_uav; per_device (action
[U, L], L = 2 quota + 1 branches) has the same actor with one logit group per branch and the
per-branch critic of branching.py (`setup_per_device`).

* Actor (the common `RecurrentAgentNet`, decentralised, shared by all UAVs unless `share_actor`
  is false (one batched network per UAV); its forward passes
  are the common `RecurrentActorForward`): row u of the observation, concatenated with the
  one-hot id of u, -> Linear + ReLU (actor_hidden) -> GRU (gru_hidden) -> Linear -> A logits;
  with `actor_agent_heads` each UAV adds its own linear output layer to the shared one's
  logits (everything before the output layer stays shared), so that identical UAVs can pick
  different SFs (same-SF EDs interfere). The GRU state is [U, gru_hidden] per scenario; it is
  the only thing env runners carry between steps. An actor never sees the global state or
  another UAV's row.
* Critic (centralised, learner only): Q_u(s, a_-u, .) -> A values, one per action of UAV u.
  Input per (scenario, step, u): global state s, the one-hot actions of the OTHER U - 1
  UAVs in id order (u's own action is never an input), the one-hot id of u and, if
  `critic_use_obs`, u's own observation row. A target copy of the critic (RLlib's
  `TargetNetworkAPI`: made by the learner, moved by Polyak or hard updates, see
  coma_learner.py) gives the TD(lambda) targets.

`InferenceOnlyAPI`: env runners build the module with inference_only=True and hold the actor
alone (no critic, no target critic; RLlib also drops them from the weights it syncs).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.rl_module import RLModule
from ray.rllib.core.rl_module.torch import TorchRLModule
from ray.rllib.utils.annotations import override
from torch import nn
from torch.autograd.function import once_differentiable

from uavlora_rllib.algorithms.coma.branching import BRANCH_LOGP, BranchQCritic
from uavlora_rllib.algorithms.common.action_head import ActionHead, BranchLayout, taken
from uavlora_rllib.algorithms.common.actor_module import RecurrentActorForward
from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.per_ed_actor import make_actor
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process

# Batch columns of the learner's episode batch (coma_learner.episode_batch): obs
# [B, T + 1, U, obs_dim], actions [B, T, U] int64, rewards [B, T], GLOBAL_STATE [B, T + 1, S].
OBS = Columns.OBS
ACTIONS = Columns.ACTIONS
REWARDS = Columns.REWARDS
# Outputs of forward_train (per_device: A -> [L, W], one row per branch, and [B, U] -> [B, U, L]).
LOGITS = "coma_logits"  # [B, T + 1, U, A] actor logits (the last step only for bootstrapping)
Q_VALUES = "coma_q"  # [B, T, U, A] critic: Q_u(s_t, a_t,-u, .)
Q_TARGET = "coma_q_target"  # [B, T, U, A] target critic, same inputs
BOOTSTRAP = "coma_bootstrap"  # [B, U] target-critic value of the final state, expectation under pi_u
# The critic rows whose TD loss a step trains (per_device with critic_branch_fraction < 1): their flat
# indices u L + l [K], and the critic's Q on them with gradient [B, T, K, W]. Q_TARGET and BOOTSTRAP are
# then on these rows only ([B, T, K, W], [B, K]), Q_VALUES on all rows without gradient (the advantage).
CRITIC_ROWS = "coma_critic_rows"
Q_ROWS = "coma_q_rows"
# Batch column [B, T, *rows]: the TD(lambda) targets of every critic row that the update's critic-only
# steps trained on (coma_learner.train_critic), handed to its joint step (COMA.update_learners): the target
# critic does not move between them, so it is evaluated once per update. forward_train passes it on to
# the loss where its critic trains every row; otherwise (per_device critic_branch_fraction < 1, or no
# critic-only steps) it evaluates the target critic itself.
TD_TARGETS = "coma_td_targets"


# ------------------------------------------------------------------ pure maths (tested by hand)
def other_actions_onehot(actions: torch.Tensor, n_actions: int) -> torch.Tensor:
    """[..., U] int actions -> [..., U, (U - 1) A]: row u holds the one-hot actions of every
    agent except u, in id order. Agent u's own action appears nowhere in row u."""
    n_agents = actions.shape[-1]
    onehot = nn.functional.one_hot(actions.long(), n_actions).to(torch.float32)  # [..., U, A]
    rows = []
    for u in range(n_agents):
        others = [k for k in range(n_agents) if k != u]
        rows.append(onehot[..., others, :].flatten(-2))  # [..., (U - 1) A]
    return torch.stack(rows, dim=-2)


def factor_onehot(actions: torch.Tensor, factors: tuple[int, ...]) -> torch.Tensor:
    """[..., U] joint indices -> [..., U, sum(factors)]: one-hot of each factor of the index
    (mixed radix, last factor fastest; for per_uav (n_sf, n_tp, n_bw) this is the SF, TP and
    BW of actions.decode_joint_action)."""
    parts, rest = [], actions.long()
    for size in reversed(factors):
        parts.append(nn.functional.one_hot(rest % size, size).to(torch.float32))
        rest = rest // size
    return torch.cat(parts[::-1], dim=-1)


def critic_inputs(
    state: torch.Tensor,
    obs: torch.Tensor | None,
    actions: torch.Tensor,
    n_actions: int,
    factors: tuple[int, ...] = (),
) -> torch.Tensor:
    """The critic's input rows [..., U, in_dim] = [s, one-hot a_-u, (factors of a_-u), one-hot id u, (o_u)].

    state [..., S], obs [..., U, obs_dim] or None (critic_use_obs=False), actions [..., U];
    `factors` (e.g. (n_sf, n_tp, n_bw)) adds the one-hot SF/TP/BW of every OTHER agent."""
    n_agents = actions.shape[-1]
    lead = actions.shape[:-1]
    parts = [state.unsqueeze(-2).expand(*lead, n_agents, state.shape[-1]), other_actions_onehot(actions, n_actions)]
    if factors:
        fac = factor_onehot(actions, factors)  # [..., U, F]
        rows = [fac[..., [k for k in range(n_agents) if k != u], :].flatten(-2) for u in range(n_agents)]
        parts.append(torch.stack(rows, dim=-2))
    parts.append(torch.eye(n_agents, dtype=torch.float32, device=actions.device).expand(*lead, n_agents, n_agents))
    if obs is not None:
        parts.append(obs)
    return torch.cat(parts, dim=-1)


class _OthersActionSum(torch.autograd.Function):
    """Row n U + u of [N U, H]: sum over the other agents k != u of table[p(k, u) A + a_k], p(k, u) = k's
    place among u's others (k, or k - 1 past u); table [(U - 1) A, H], actions [N, U] int64.

    The same function and gradient as embedding_bag(mode="sum") over the [N U, U - 1] indices, whose
    path with gradient sorts and scatters all N U (U - 1) of them: here the forward is embedding_bag's
    gradient-free path, and the backward sums each agent's gradient rows once. Agent k sits at place k
    in the rows u > k and at place k - 1 in the rows u < k, so table row k A + a_k receives sum_{u > k} g_u, and row
    (k - 1) A + a_k receives sum_{u < k} g_u: two running sums over the agents and two index_adds of
    N (U - 1) rows, instead of a sort and a scatter of N U (U - 1) rows."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        n_agents = actions.shape[1]
        n_other = n_agents - 1
        n_actions = table.shape[0] // n_other
        eye = torch.eye(n_agents, dtype=torch.bool, device=actions.device)
        others = torch.arange(n_agents, device=actions.device).expand(n_agents, n_agents)[~eye].view(n_agents, n_other)
        place = torch.arange(n_other, device=actions.device) * n_actions
        index = actions[:, others] + place  # [N, U, U - 1]: entry j of row u is table row j A + a_k
        ctx.save_for_backward(actions, place)
        ctx.n_rows = table.shape[0]
        # detached: embedding_bag keeps what its own backward would need while its weight requires grad
        return nn.functional.embedding_bag(index.view(-1, n_other), table.detach(), mode="sum")  # [N U, H]

    @staticmethod
    @once_differentiable  # (the backward writes into buffers: no second derivative)
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        actions, place = ctx.saved_tensors
        (n, n_agents), hid = actions.shape, grad.shape[-1]
        grad = grad.reshape(n, n_agents, hid)
        after = grad.new_empty(n, n_agents - 1, hid)  # [:, k]: sum_{u > k} g_u, agents k = 0 .. U - 2
        before = grad.new_empty(n, n_agents - 1, hid)  # [:, k - 1]: sum_{u < k} g_u, agents k = 1 .. U - 1
        after[:, -1] = grad[:, -1]
        for k in range(n_agents - 3, -1, -1):
            torch.add(after[:, k + 1], grad[:, k + 1], out=after[:, k])
        before[:, 0] = grad[:, 0]
        for k in range(1, n_agents - 1):
            torch.add(before[:, k - 1], grad[:, k], out=before[:, k])
        out = grad.new_zeros(ctx.n_rows, hid)
        out.index_add_(0, (actions[:, :-1] + place).reshape(-1), after.view(-1, hid))
        out.index_add_(0, (actions[:, 1:] + place).reshape(-1), before.view(-1, hid))
        return out, None


def first_layer_of_rows(
    first: nn.Linear,
    state: torch.Tensor,
    obs: torch.Tensor | None,
    actions: torch.Tensor,
    n_actions: int,
    factor_map: torch.Tensor | None,
) -> torch.Tensor:
    """first(critic_inputs(state, obs, actions, ...)) [..., U, H] without building the rows.

    Row u's first layer is W_s s + b + sum_{k != u} T_p(k, u)[a_k] + W_id[:, u] + W_o o_u, where
    p(k, u) is k's position among u's others (k, or k - 1 past u) and T_p[a] = W_a,p[:, a] (+ the
    columns of a's SF/TP/BW, `factor_map` [A, F]) is what an other agent at position p adds when it
    plays a: one summed gather per row (`_OthersActionSum`) instead of a product with its one-hot
    (U - 1) (A + F) columns. Same parameters, same function (docs/model.md#training-defaults)."""
    lead, n_agents = actions.shape[:-1], actions.shape[-1]
    w, s_dim, hid = first.weight, state.shape[-1], first.weight.shape[0]
    n_other, n_fac = n_agents - 1, (factor_map.shape[1] if factor_map is not None else 0)
    col = s_dim
    w_act = w[:, col : col + n_other * n_actions].reshape(hid, n_other, n_actions).permute(1, 2, 0)  # [U-1, A, H]
    col += n_other * n_actions
    if factor_map is not None:
        w_fac = w[:, col : col + n_other * n_fac].reshape(hid, n_other, n_fac)
        w_act = w_act + torch.einsum("hpf,af->pah", w_fac, factor_map)
        col += n_other * n_fac
    w_ids, col = w[:, col : col + n_agents].t(), col + n_agents  # [U, H]
    flat = actions.long().reshape(-1, n_agents)
    # contiguous: the sum of the permuted slice and the einsum keeps the slice's column-major layout,
    # and gathering its rows would read memory with a stride of (U - 1) A floats
    z = _OthersActionSum.apply(w_act.reshape(-1, hid).contiguous(), flat)  # [N U, H], a fresh tensor
    if obs is not None:  # in place on that tensor, not on a view of it (autograd would copy it back)
        z += nn.functional.linear(obs.reshape(-1, obs.shape[-1]), w[:, col:])
    z = z.view(flat.shape[0], n_agents, hid) + nn.functional.linear(
        state.reshape(-1, s_dim), w[:, :s_dim], first.bias
    ).unsqueeze(-2)
    z += w_ids
    return z.view(*lead, n_agents, hid)


def critic_input_dim(
    state_dim: int, obs_dim: int, n_agents: int, n_actions: int, use_obs: bool, factors: tuple[int, ...] = ()
) -> int:
    per_other = n_actions + sum(factors)
    return state_dim + (n_agents - 1) * per_other + n_agents + (obs_dim if use_obs else 0)


def counterfactual_advantage(
    q: torch.Tensor, pi: torch.Tensor, actions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """COMA's counterfactual baseline and advantage (Foerster et al., Eq. 4).

    q [..., A]: Q_u(s, (a_-u, a')) for every a' of agent u; pi [..., A]: pi_u(a' | tau_u);
    actions [...]: the action a_u taken. Returns (advantage, baseline, q_taken) with
    baseline = sum_a' pi(a') Q(s, (a_-u, a')) and advantage = Q(s, a)[a_u] - baseline.
    No gradient flows through pi or q (the actor's loss multiplies this with log pi)."""
    q, pi = q.detach(), pi.detach()
    q_taken = torch.gather(q, -1, actions.long().unsqueeze(-1)).squeeze(-1)
    baseline = (pi * q).sum(-1)
    return q_taken - baseline, baseline, q_taken


def td_lambda_targets(
    rewards: torch.Tensor, q_taken_next: torch.Tensor, bootstrap: torch.Tensor, gamma: float, lam: float
) -> torch.Tensor:
    """TD(lambda) returns for a truncated (never terminated) episode, per agent.

    rewards [B, T]; q_taken_next [B, T, U]: target-critic Q of the taken joint action at steps
    0..T-1 (entry t is used as the one-step bootstrap of step t - 1); bootstrap [B, U]: the
    value of the final state s_T (truncation: bootstrap through it, never zero). Recursion
      G_{T-1} = r_{T-1} + gamma V(s_T)
      G_t     = r_t + gamma ((1 - lam) Q_tgt(s_{t+1}, a_{t+1}) + lam G_{t+1}).
    Returns [B, T, U]."""
    steps = rewards.shape[1]
    out = torch.empty_like(q_taken_next)
    g = rewards[:, steps - 1, None] + gamma * bootstrap
    out[:, steps - 1] = g
    for t in range(steps - 2, -1, -1):
        g = rewards[:, t, None] + gamma * ((1.0 - lam) * q_taken_next[:, t + 1] + lam * g)
        out[:, t] = g
    return out


# ------------------------------------------------------------------ networks
def mlp(in_dim: int, hidden: tuple[int, ...] | list[int], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class QHead(nn.Module):
    """Critic MLP with A outputs (one per action of agent u).

    `dueling`: Q = V + (D - mean_a D), V and D from one trunk. Every sample trains V, so an
    action that is rarely taken starts at the state's value rather than at the network's
    initial output (about 0): with large positive returns a plain head makes every untried
    action look bad and the policy collapses onto whatever it happened to sample first.
    `factors` (n_sf, n_tp, n_bw): D[a] = free[a] + sum_f g_f[factor_f(a)], the g_f shared by
    all actions with the same SF (TP, BW). A sample of one action then also teaches the
    values of the actions that share its SF, which is what the critic needs to learn the
    interference between UAVs on the same SF (a plain 90-way head sees each action ~1/90 of
    the time and learned that interaction far too slowly on the small scenario)."""

    factor_map: torch.Tensor
    trunk: nn.Sequential | nn.Identity

    def __init__(self, in_dim: int, hidden: tuple[int, ...], n_actions: int, dueling: bool, factors=()):
        super().__init__()
        self.dueling = dueling
        self.trunk = mlp(in_dim, hidden[:-1], hidden[-1]) if hidden else nn.Identity()
        width = hidden[-1] if hidden else in_dim
        self.act = nn.ReLU() if hidden else nn.Identity()
        self.out = nn.Linear(width, n_actions + (1 if dueling else 0))
        self.factor_out = nn.Linear(width, sum(factors)) if factors else None
        if factors:
            self.register_buffer("factor_map", factor_onehot(torch.arange(n_actions), tuple(factors)))  # [A, F]

    @override(nn.Module)
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        first = self.first
        return self.after_first(first(x) if first is not None else x)

    @property
    def first(self) -> nn.Linear | None:
        """The first linear layer (on the concatenated input rows); None without hidden layers."""
        if not isinstance(self.trunk, nn.Sequential):
            return None
        layer = self.trunk[0]
        assert isinstance(layer, nn.Linear)
        return layer

    def after_first(self, z: torch.Tensor) -> torch.Tensor:
        """Q values from the first layer's output z (or from the input row, without hidden layers)."""
        h = self.act(self.trunk[1:](z) if isinstance(self.trunk, nn.Sequential) else z)
        y = self.out(h)
        value, diff = (y[..., :1], y[..., 1:]) if self.dueling else (None, y)
        if self.factor_out is not None:
            diff = diff + self.factor_out(h) @ self.factor_map.T
        if value is None:
            return diff
        return value + diff - diff.mean(-1, keepdim=True)


class COMATorchRLModule(RecurrentActorForward, TorchRLModule, TargetNetworkAPI, InferenceOnlyAPI):
    """Actor on env runners; actor + critic + target critic on the learner.

    model_config (common/config.py): COMAHParams' fields (actor_hidden, gru_hidden,
    actor_agent_heads, critic_hidden, critic_use_obs, critic_dueling), state_dim,
    action_factors (per_uav only), torch_threads. The action space picks the mode: nvec [U]
    per_uav, [U, L] per_device."""

    # (observations, logits, actor parameter versions) kept by keep_episode_logits for the next forward_train
    _kept_logits: tuple[torch.Tensor, torch.Tensor, tuple[int, ...]] | None = None

    @property
    def layout(self) -> BranchLayout:
        """The padded [L, W] branch grid of the actor's action head (per_device)."""
        return self.head.layout

    @override(TorchRLModule)
    def setup(self) -> None:
        mc = self.model_config
        setup_torch_process(mc["torch_threads"])
        self.n_agents, self.obs_dim = self.observation_space.shape
        self.gamma = float(mc["gamma"])  # 0: the critic's target is the reward, the target critic unread
        nvec = np.asarray(self.action_space.nvec)
        self.per_device = nvec.ndim == 2
        if self.per_device:
            self.setup_per_device(nvec)
            return
        if nvec.ndim != 1 or not (nvec == nvec[0]).all():
            raise ValueError(f"COMA needs MultiDiscrete([A] * U) actions (per_uav), got nvec {nvec.tolist()}")
        self.n_actions = int(nvec[0])
        self.state_dim = int(mc["state_dim"])
        self.use_obs = bool(mc["critic_use_obs"])
        self.factors = tuple(int(f) for f in mc["action_factors"])
        if self.factors and int(np.prod(self.factors)) != self.n_actions:
            raise ValueError(f"action_factors {self.factors} do not multiply to {self.n_actions} actions")
        self.actor = RecurrentAgentNet(
            self.obs_dim,
            self.n_agents,
            self.n_actions,
            fc_hidden=int(mc["actor_hidden"]),
            gru_hidden=int(mc["gru_hidden"]),
            share=bool(mc["share_actor"]),
            agent_heads=bool(mc["actor_agent_heads"]),
        )
        self.head = ActionHead([self.n_actions])
        if not self.inference_only:
            in_dim = critic_input_dim(
                self.state_dim, self.obs_dim, self.n_agents, self.n_actions, self.use_obs, self.factors
            )
            self.critic: nn.Module = QHead(
                in_dim, tuple(mc["critic_hidden"]), self.n_actions, bool(mc["critic_dueling"]), self.factors
            )

    def setup_per_device(self, nvec: np.ndarray) -> None:
        """per_device: the actor's logits are one group per branch (ActionHead over the nvec row,
        as MAPPO's per_device head) and the critic is branching.BranchQCritic."""
        mc = self.model_config
        if nvec.shape[0] != self.n_agents or not (nvec == nvec[0]).all():
            raise ValueError(
                f"COMA per_device needs the same nvec row for all {self.n_agents} UAVs, got {nvec.tolist()}"
            )
        self.state_dim = int(mc["state_dim"])
        self.use_obs = bool(mc["critic_use_obs"])
        self.branch_fraction = float(mc["critic_branch_fraction"])
        self.head = ActionHead(nvec[0].tolist())
        self.actor = make_actor(
            self.obs_dim,
            self.n_agents,
            nvec[0].tolist(),
            heads=str(mc["actor_heads"]),
            fc_hidden=int(mc["actor_hidden"]),
            gru_hidden=int(mc["gru_hidden"]),
            share=bool(mc["share_actor"]),
            agent_heads=bool(mc["actor_agent_heads"]),
        )
        if not self.inference_only:
            self.critic = BranchQCritic(
                self.layout,
                self.n_agents,
                self.state_dim,
                self.obs_dim if self.use_obs else 0,
                tuple(mc["critic_hidden"]),
                bool(mc["critic_dueling"]),
            )

    @override(InferenceOnlyAPI)
    def get_non_inference_attributes(self) -> list[str]:
        return ["critic", "target_critic"]

    # -- target critic (made by the learner, RLlib's TargetNetworkAPI)
    @override(TargetNetworkAPI)
    def make_target_networks(self) -> None:
        self.target_critic = make_target_network(self.critic)

    @override(TargetNetworkAPI)
    def get_target_network_pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        return [(self.critic, self.target_critic)]

    @override(TargetNetworkAPI)
    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Target-critic Qs of the taken joint actions [B, T, U, A] and the value of the final
        state [B, U]. Truncation at T: the bootstrap is the target critic on s_T, where the
        other UAVs play actions sampled from their policies at o_T and UAV u is averaged over
        its own policy: V_u(s_T) = sum_a' pi_u(a' | tau_T) Q_tgt(s_T, (a_T,-u, a')). batch:
        the train batch plus the actor's LOGITS [B, T+1, U, A].
        per_device: the same per branch, Q [B, T, U, L, W] and the bootstrap [B, U, L], every
        branch of every UAV sampled at o_T and branch l of u averaged over pi_{u,l}."""
        obs, actions, state = batch[OBS], batch[ACTIONS].long(), batch[GLOBAL_STATE]
        steps, rows = actions.shape[1], batch.get(CRITIC_ROWS)
        q_target = self.critic_q(self.target_critic, state[:, :steps], obs[:, :steps], actions, rows)
        if self.per_device:
            logits_last = batch[LOGITS][:, steps]  # [B, U, sum(row)]
            a_last, _ = self.head.sample(logits_last)  # [B, U, L]
            pi_last = self.row_values(self.layout.log_probs(logits_last).exp(), rows, 2)  # [B, U, L, W] or [B, K, W]
            q_last = self.critic_q(self.target_critic, state[:, steps], obs[:, steps], a_last, rows)
            return {Q_TARGET: q_target, BOOTSTRAP: (pi_last * q_last).sum(-1)}
        pi_last = torch.softmax(batch[LOGITS][:, steps], dim=-1)  # [B, U, A]
        a_last = torch.distributions.Categorical(probs=pi_last).sample()  # [B, U]
        q_last = self.critic_q(self.target_critic, state[:, steps], obs[:, steps], a_last)
        return {Q_TARGET: q_target, BOOTSTRAP: (pi_last * q_last).sum(-1)}

    # -- learner
    def critic_q(
        self,
        net: nn.Module,
        state: torch.Tensor,
        obs: torch.Tensor,
        actions: torch.Tensor,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Q [..., U, A] (per_uav) or [..., U, L, W] (per_device) of the critic `net` (or its target);
        per_device with `rows` (flat u L + l, [K]): those rows only, [..., K, W]."""
        q = self._critic_q(net, state, obs, actions, rows)
        return q.float()  # float32 under autocast too (common/precision.py)

    def _critic_q(
        self, net: nn.Module, state: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor, rows: torch.Tensor | None
    ) -> torch.Tensor:
        if self.per_device:
            return net(state, obs if self.use_obs else None, actions, rows)
        assert rows is None, "per_uav critics evaluate every UAV's row"
        obs_in = obs if self.use_obs else None
        assert isinstance(net, QHead)
        if net.first is None or self.n_agents == 1:
            return net(critic_inputs(state, obs_in, actions, self.n_actions, self.factors))
        factor_map = net.factor_map if self.factors else None
        return net.after_first(first_layer_of_rows(net.first, state, obs_in, actions, self.n_actions, factor_map))

    def target_terms(self, batch: dict[str, Any], logits: torch.Tensor | None = None) -> dict[str, Any]:
        """forward_target's outputs without gradient (the actor's episode logits computed here unless
        given), or {} at gamma 0: every TD target is then the reward (coma_learner.critic_targets)
        and the target critic is never read."""
        if self.gamma == 0.0:
            return {}
        with torch.no_grad():
            logits = self.episode_logits(batch[OBS]) if logits is None else logits
            return self.forward_target({**batch, LOGITS: logits})

    def draw_critic_rows(self) -> torch.Tensor | None:
        """The (UAV, branch) rows, flat u L + l sorted, [K], whose TD loss the next update trains:
        round(critic_branch_fraction U L) of them drawn without replacement (at least one); None
        (every row) at fraction 1 or per_uav. Every row is the same Q(s, a) at its taken value,
        so a random subset is an unbiased minibatch of the critic's loss over the rows."""
        if not self.per_device or self.branch_fraction >= 1.0:
            return None
        n_rows = self.n_agents * self.layout.n_branches
        k = max(1, round(self.branch_fraction * n_rows))
        return torch.randperm(n_rows)[:k].sort().values.to(self.layout.valid.device)

    def row_values(self, x: torch.Tensor, rows: torch.Tensor | None, trailing: int = 1) -> torch.Tensor:
        """x [..., U, L, *tail] (tail of `trailing` - 1 axes) at the critic rows: [..., K, *tail];
        x itself when rows is None."""
        if rows is None:
            return x
        return x.flatten(-1 - trailing, -trailing)[(..., rows) + (slice(None),) * (trailing - 1)]

    def policy_terms(
        self, logits: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The actor's side of the loss: (pi, logp, entropy) of logits [B, T, U, n_logits] at the
        taken actions. per_uav: pi [B, T, U, A], logp [B, T, U]; per_device: per branch,
        pi [B, T, U, L, W] (padding 0), logp [B, T, U, L]. entropy [B, T, U] per UAV (per_device:
        summed over its branches, the entropy of the product policy). Both from the action head's
        branch grid (per_uav: one branch)."""
        log_probs = self.layout.log_probs(logits)  # [B, T, U, L, W]
        branch_actions = actions if self.per_device else actions.unsqueeze(-1)
        pi, logp = log_probs.exp(), taken(log_probs, branch_actions)
        entropy = self.layout.entropy(log_probs).sum(-1)
        return (pi, logp, entropy) if self.per_device else (pi.squeeze(-2), logp.squeeze(-1), entropy)

    def per_agent(self, x: torch.Tensor) -> torch.Tensor:
        """Per-branch terms [..., U, L] summed to per-UAV terms [..., U] (per_device); per_uav
        terms are per UAV already."""
        return x.sum(-1) if self.per_device else x

    @override(RLModule)
    @torch.no_grad()  # acting builds no graph (common/actor_module.py)
    def _forward_exploration(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """Sampled actions (the common actor forward); per_device also hands the env runner each
        branch's log-probability (BRANCH_LOGP), the per-branch ratio's denominator."""
        if not self.per_device:
            return super()._forward_exploration(batch, **kwargs)
        logits, state = self.actor_logits(batch)
        actions, branch_logp = self.head.sample_branches(logits)
        return {
            Columns.ACTIONS: actions,
            Columns.ACTION_LOGP: branch_logp.sum(-1),
            BRANCH_LOGP: branch_logp,
            Columns.STATE_OUT: state,
        }

    def episode_logits(self, obs: torch.Tensor) -> torch.Tensor:
        """Actor logits [B, T+1, U, n_logits] over whole episodes obs [B, T+1, U, d], the GRU
        unrolled from a zero state as the env runners did while sampling."""
        return self.actor(obs, self.actor.initial_state(obs.shape[0]).to(obs.device))[0]

    def keep_episode_logits(self, obs: torch.Tensor, logits: torch.Tensor) -> None:
        """Keep episode_logits(obs) `logits`, with their autograd graph, for the next forward_train on the
        same observations: the critic-only steps of an update need the actor's logits for their
        bootstrap, and its joint step (the actor has not moved in between) reuses them instead of
        unrolling the GRU again. Taken once; a forward_train on other observations, without
        gradient or after an in-place change of the actor's parameters (their version counters: a
        change through `.data` is not seen) computes its own. Both calls must run under the same
        autocast setting: the learner runs each under the trial's precision."""
        self._kept_logits = (obs, logits, self._actor_versions())

    def _actor_versions(self) -> tuple[int, ...]:
        """The version counters of the actor's parameters (torch bumps one on every in-place change)."""
        return tuple(p._version for p in self.actor.parameters())

    def _take_kept_logits(self, obs: torch.Tensor) -> torch.Tensor | None:
        kept, self._kept_logits = self._kept_logits, None
        if kept is None or not torch.is_grad_enabled():
            return None
        kept_obs, logits, versions = kept
        if kept_obs.shape != obs.shape or versions != self._actor_versions() or not torch.equal(kept_obs, obs):
            return None
        return logits

    @override(RLModule)
    def _forward_train(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """Whole episodes: obs [B, T+1, U, d], actions [B, T, U], global_state [B, T+1, S]."""
        obs, actions, state = batch[OBS], batch[ACTIONS].long(), batch[GLOBAL_STATE]
        steps = actions.shape[1]
        logits = self._take_kept_logits(obs)  # this update's critic-only steps computed them (keep_episode_logits)
        if logits is None:
            logits = self.episode_logits(obs)
        state, obs_t = state[:, :steps], obs[:, :steps]
        rows = self.draw_critic_rows()
        if rows is None:  # every row: one pass serves the critic's loss and (detached) the advantage
            q = q_rows = self.critic_q(self.critic, state, obs_t, actions)
        else:
            with torch.no_grad():
                q = self.critic_q(self.critic, state, obs_t, actions)
            q_rows = self.critic_q(self.critic, state, obs_t, actions, rows)
        if rows is None and TD_TARGETS in batch:  # the critic steps' targets cover every row: the loss reads them
            target = {TD_TARGETS: batch[TD_TARGETS]}
        else:
            target = self.target_terms({**batch, CRITIC_ROWS: rows}, logits)
        return {LOGITS: logits, Q_VALUES: q, Q_ROWS: q_rows, CRITIC_ROWS: rows, **target}
