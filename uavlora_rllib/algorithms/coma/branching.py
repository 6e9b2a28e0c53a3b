"""COMA's per_device form: a factored ("branching") policy and its per-branch counterfactual critic.

In per_device mode (docs/model.md#actions) UAV u's action is a vector of L = 2 quota + 1 branches,
nvec row [n_sf, n_tp] * quota + [n_bw]: an SF and a TP for each served-ED slot, then one BW.
The actor is a product of one categorical per branch (the common `ActionHead`, exactly as MAPPO's
per_device head; sampling, greedy and the env runners' log-probabilities go through it). The
critic marginalises one branch at a time (docs/model.md#coma-per-device; Foerster et al., AAAI
2018, with the action branching of Tavakoli et al., AAAI 2018):

  Q_{u,l}(s, a)[c] = Q(s, a with branch l of u set to c),  c = 0 .. n_l - 1,
  A_{u,l}         = Q_{u,l}(s, a)[a_{u,l}] - sum_c pi_{u,l}(c) Q_{u,l}(s, a)[c],

all other branches of u and all other UAVs' actions held at the taken ones. The policy gradient
sums A_{u,l} grad log pi_{u,l}(a_{u,l}) over the branches.

Padded layout (common/action_head.BranchLayout): the values of the branches of one UAV sit in a
[L, W] grid, W = max(row); entry (l, c) with c >= n_l is padding (probability 0, Q 0), so every
branch of every UAV is one slice of one tensor and the baseline of all of them is one
`counterfactual_advantage` call.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from uavlora_rllib.algorithms.common.action_head import BranchLayout

# Env-runner output and train-batch column: log pi_{u,l}(a_{u,l}) of the sampling policy per
# branch, [B, T, U, L]; the denominator of the per-branch ratio when a batch is reused.
BRANCH_LOGP = "coma_branch_logp"


class BranchQCritic(nn.Module):
    """Q_{u,l}(s, a)[c] for every branch l of every UAV u in one call: [..., U, L, W].

    The function is an MLP on the concatenated input row of (u, l)
        x_{u,l} = [s, one-hot of every UAV's every branch with branch l of u left out (all zeros),
                   one-hot of (u, l), o_u (if `obs_dim`)]
    with one output layer per branch l (W values, + 1 state value when `dueling`), shared by
    the UAVs (u is in the input). The first layer is never applied to the concatenated rows:
    W x + b = W_s s + b + sum_{k,m} W[:, a_{k,m}] - W[:, a_{u,l}] + W[:, (u, l)] + W_o o_u,
    the same parameters and function, the joint action's sum computed once per step and the
    U L rows then differing by one column each. No Python loop over UAVs or branches."""

    layout: BranchLayout
    offsets: torch.Tensor
    columns: torch.Tensor
    table_rows: torch.Tensor
    row_agent: torch.Tensor
    row_branch: torch.Tensor

    def __init__(
        self,
        layout: BranchLayout,
        n_agents: int,
        state_dim: int,
        obs_dim: int,
        hidden: Sequence[int],
        dueling: bool,
    ):
        super().__init__()
        if not hidden:
            raise ValueError("BranchQCritic needs at least one hidden layer (critic_hidden)")
        self.layout, self.n_agents = layout, int(n_agents)
        self.state_dim, self.obs_dim, self.dueling = int(state_dim), int(obs_dim), bool(dueling)
        per_agent = sum(layout.row)
        self.n_onehot = self.n_agents * per_agent
        self.n_ids = self.n_agents * layout.n_branches
        self.in_dim = self.state_dim + self.n_onehot + self.n_ids + self.obs_dim
        self.first = nn.Linear(self.in_dim, int(hidden[0]))
        layers: list[nn.Module] = [nn.ReLU()]
        width = int(hidden[0])
        for w in hidden[1:]:
            layers += [nn.Linear(width, int(w)), nn.ReLU()]
            width = int(w)
        self.body = nn.Sequential(*layers)
        n_out = layout.width + (1 if self.dueling else 0)
        bound = 1.0 / np.sqrt(width)  # nn.Linear's default range for this fan-in
        self.out_weight = nn.Parameter(torch.empty(layout.n_branches, width, n_out).uniform_(-bound, bound))
        self.out_bias = nn.Parameter(torch.empty(layout.n_branches, n_out).uniform_(-bound, bound))
        # one-hot column of (UAV k, branch m) value 0 within the action block: k * sum(row) + start_m
        offsets = torch.arange(self.n_agents)[:, None] * per_agent + layout.starts[None, :]
        self.register_buffer("offsets", offsets, persistent=False)  # [U, L]
        # one-hot column of (UAV k, branch m, value c) for every padded c (clamped to the branch): [U, L, W]
        columns = torch.arange(self.n_agents)[:, None, None] * per_agent + layout.index[None]
        self.register_buffer("columns", columns, persistent=False)
        # row of (u, l, c) in the flattened [U L W, H] table of `forward`: (u L + l) W + c
        table_rows = torch.arange(self.n_ids).reshape(self.n_agents, layout.n_branches) * layout.width
        self.register_buffer("table_rows", table_rows, persistent=False)  # [U, L]
        # UAV and branch of each flat row u L + l
        self.register_buffer("row_agent", torch.arange(self.n_ids) // layout.n_branches, persistent=False)
        self.register_buffer("row_branch", torch.arange(self.n_ids) % layout.n_branches, persistent=False)

    def inputs(self, state: torch.Tensor, obs: torch.Tensor | None, actions: torch.Tensor) -> torch.Tensor:
        """The concatenated rows x_{u,l} [..., U, L, in_dim] (what `forward` computes without
        building them; for tests and for reading what the critic sees)."""
        lead = actions.shape[:-2]
        u_n, l_n = self.n_agents, self.layout.n_branches
        onehot = torch.zeros(*lead, self.n_onehot, device=actions.device)
        onehot.scatter_(-1, (actions.long() + self.offsets).flatten(-2), 1.0)
        rows = onehot[..., None, None, :].expand(*lead, u_n, l_n, self.n_onehot).clone()
        own = (actions.long() + self.offsets).unsqueeze(-1)  # [..., U, L, 1]
        rows.scatter_(-1, own, 0.0)  # branch l of u left out of its own row
        ids = (
            torch.eye(self.n_ids, device=actions.device)
            .reshape(u_n, l_n, self.n_ids)
            .expand(*lead, u_n, l_n, self.n_ids)
        )
        parts = [state[..., None, None, :].expand(*lead, u_n, l_n, self.state_dim), rows, ids]
        if self.obs_dim:
            assert obs is not None  # (obs_dim > 0)
            parts.append(obs[..., :, None, :].expand(*lead, u_n, l_n, self.obs_dim))
        return torch.cat(parts, dim=-1)

    def forward(
        self, state: torch.Tensor, obs: torch.Tensor | None, actions: torch.Tensor, rows: torch.Tensor | None = None
    ) -> torch.Tensor:
        """state [..., S], obs [..., U, obs_dim] (None without obs_dim), actions [..., U, L] ->
        Q [..., U, L, W] (padding entries 0); with `rows` (flat indices u L + l, [K]) only those
        rows, [..., K, W] (what a critic step on a subset of the rows needs, `COMAHParams.critic_branch_fraction`).

        The first layer as in the class docstring, in one gather: the joint term (state and the
        whole joint action, a [..., H] per step) plus table[u, l, a_{u,l}], where
        table[u, l, c] = W[:, (u, l)] - W[:, (u, l, c)] is what row (u, l) differs by when a_{u,l} = c.
        The rows lead the layout ([U, L, ..., H], or [K, ..., H]) so that the per-branch output
        layers are one batched matrix product (each row's branch picks its layer) and the hidden
        layers run in place on one [rows, H] buffer."""
        w, s_dim, n_act = self.first.weight, self.state_dim, self.n_onehot
        u_n, l_n, hid = self.n_agents, self.layout.n_branches, w.shape[0]
        lead = actions.shape[:-2]
        actions = actions.long()
        w_act = w[:, s_dim : s_dim + n_act].t()  # [n_onehot, H]: one column per (UAV, branch, value)
        w_ids = w[:, s_dim + n_act : s_dim + n_act + self.n_ids].t().reshape(u_n, l_n, 1, hid)
        table = (w_ids - w_act[self.columns]).reshape(-1, hid)  # [U L W, H]
        onehot = torch.zeros(*lead, n_act, device=actions.device, dtype=w.dtype)
        onehot.scatter_(-1, (actions + self.offsets).flatten(-2), 1.0)
        joint = nn.functional.linear(state, w[:, :s_dim], self.first.bias) + onehot @ w_act  # [..., H]
        index = self.table_rows + actions  # [..., U, L]: row (u, l)'s table entry
        if rows is None:  # all rows, as [U, L, ..., H]: u's own term broadcasts over its branches
            branch = self.row_branch
            z = nn.functional.embedding(index.movedim(-2, 0).movedim(-1, 1), table)
        else:
            branch = self.row_branch[rows]
            z = nn.functional.embedding(index.flatten(-2)[..., rows].movedim(-1, 0), table)  # [K, ..., H]
        z += joint
        if self.obs_dim:
            assert obs is not None  # (obs_dim > 0)
            own = nn.functional.linear(obs, w[:, s_dim + n_act + self.n_ids :]).movedim(-2, 0)  # [U, ..., H]
            z += own.unsqueeze(1) if rows is None else own[self.row_agent[rows]]
        h = z.relu_().view(-1, hid)  # the body's first module (its ReLU), in place
        for layer in list(self.body)[1:]:
            h = layer(h) if isinstance(layer, nn.Linear) else h.relu_()
        k = branch.shape[0]
        y = torch.baddbmm(self.out_bias[branch, None, :], h.view(k, -1, h.shape[-1]), self.out_weight[branch])
        y = y.view(k, *lead, -1).movedim(0, -2)  # [..., K, n_out]
        valid = self.layout.valid[branch]  # [K, W]
        if self.dueling:
            value, diff = y[..., :1], y[..., 1:].masked_fill(~valid, 0.0)
            mean = diff.sum(-1, keepdim=True) / self.layout.sizes[branch, None]
            y = value + diff - mean
        y = y.masked_fill(~valid, 0.0)
        return y if rows is not None else y.view(*lead, u_n, l_n, -1)
