"""Per-branch output heads of a factored agent network: one small MLP per action branch.

Shared by QMIX/VDN's branching agent network (its branch utilities, qmix/branching.py) and the
MAPPO/IPPO per-ED actor (its branch logits, common/per_ed_actor.py); docs/model.md#qmix-and-vdn-per-device.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from uavlora_rllib.sim.observation import OBS_ROW


def slot_rows(obs: torch.Tensor, quota: int) -> torch.Tensor:
    """The ED rows of local observations: obs [..., 4 quota + 3] -> [..., quota, 4]."""
    return obs[..., : quota * OBS_ROW].reshape(*obs.shape[:-1], quota, OBS_ROW)


class BranchHeads(nn.Module):
    """`branches` heads Linear(in_x + in_r + slot_ids, hidden) -> ReLU -> Linear(hidden, n_out),
    for each of `groups` agents (1: shared by all agents; 1 branch: shared by all branches). The
    first layer's input is split into a per-agent part x [B, T, U, in_x] (the same for every
    branch), an optional per-branch part r [B, T, U, K, in_r] and, with `slot_ids` = K (one head
    for all K branches), the one-hot of the branch, never built (its columns are a per-branch
    bias of the first layer: the same function). A head shared by the branches reads x's product
    once per agent; one head per branch reads x once per branch (its own weights).

    All agents and branches run as batched products on one hidden tensor [U K, B T, hidden], the
    rows' product added in the same call and the ReLU then in place (a per-ED head's hidden layer
    is K times the GRU's: passes over memory, not products, are what it costs;
    docs/model.md#mappo-and-ippo-per-device). The last layer's bias is added after its product,
    so under learner_precision bfloat16's autocast route the output is float32 (common/precision.py)."""

    def __init__(self, groups: int, branches: int, in_x: int, in_r: int, hidden: int, n_out: int, slot_ids: int = 0):
        super().__init__()
        if slot_ids and branches != 1:
            raise ValueError("slot_ids: only a head shared by the branches reads the branch's one-hot")
        self.in_x, self.in_r, self.slot_ids = in_x, in_r, slot_ids
        fan_in = in_x + in_r + slot_ids
        self.w1 = nn.Parameter(torch.empty(groups, branches, fan_in, hidden))
        self.b1 = nn.Parameter(torch.empty(groups, branches, hidden))
        self.w2 = nn.Parameter(torch.empty(groups, branches, hidden, n_out))
        self.b2 = nn.Parameter(torch.empty(groups, branches, n_out))
        for w, b, fan in ((self.w1, self.b1, fan_in), (self.w2, self.b2, hidden)):
            bound = 1.0 / math.sqrt(fan)  # nn.Linear's default range
            nn.init.uniform_(w, -bound, bound)
            nn.init.uniform_(b, -bound, bound)

    def forward(self, x: torch.Tensor, r: torch.Tensor | None = None, k: int = 1) -> torch.Tensor:
        """x [B, T, U, in_x], r [B, T, U, k, in_r] or None -> [B, T, U, k, n_out]."""
        b, t, u, in_x = x.shape
        n, n_out, hid = b * t, self.w2.shape[-1], self.w2.shape[-2]
        per_branch = self.w1.shape[1] > 1  # one head per branch
        if per_branch and k != self.w1.shape[1]:
            raise ValueError(f"k: {k} branches asked of heads with branches={self.w1.shape[1]}")
        if self.slot_ids and k != self.slot_ids:
            raise ValueError(f"k: {k} branches asked of heads with slot_ids={self.slot_ids}")
        if r is not None and r.shape[-2:] != (k, self.in_r):
            raise ValueError(f"r: expected [..., {k}, {self.in_r}], got {tuple(r.shape)}")
        w1, b1, w2, b2 = (p.expand(u, -1, *p.shape[2:]) for p in (self.w1, self.b1, self.w2, self.b2))
        xa = x.permute(2, 0, 1, 3).reshape(u, n, in_x)  # agent-major rows (a view of a stacked torso's output)
        if per_branch:  # [U K, N, H]: agent u's branch-k head on every row
            pre = torch.baddbmm(
                b1.reshape(u * k, 1, hid),
                xa.unsqueeze(1).expand(u, k, n, in_x).reshape(u * k, n, in_x),
                w1[:, :, :in_x].reshape(u * k, in_x, hid),
            )
        else:  # the x part once per agent, then broadcast over the branches
            a = torch.baddbmm(b1, xa, w1[:, 0, :in_x]).unsqueeze(1)  # [U, 1, N, H]
            if self.slot_ids:
                slot_bias = w1[:, 0, in_x + self.in_r :].unsqueeze(2).to(a.dtype)  # branch k's one-hot column
                a = a + slot_bias  # [U, K, N, H]
            pre = a.expand(u, k, n, hid).reshape(u * k, n, hid)
        if r is None:
            h = torch.relu(pre)
        else:  # + the branch's own rows; a fresh product, so its ReLU runs in place
            rows = r.permute(2, 3, 0, 1, 4).reshape(u * k, n, self.in_r)
            w_r = w1[:, :, in_x : in_x + self.in_r].expand(u, k, -1, -1).reshape(u * k, self.in_r, hid)
            h = torch.baddbmm(pre, rows, w_r).relu_()
        if per_branch:
            out = torch.bmm(h, w2.reshape(u * k, hid, n_out)) + b2.reshape(u * k, 1, n_out)
        else:
            out = torch.bmm(h.view(u, k * n, hid), w2[:, 0]) + b2
        return out.view(u, k, b, t, n_out).permute(2, 3, 0, 1, 4)
