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
    """`branches` heads Linear(in_dim, hidden) -> ReLU -> Linear(hidden, n_out), for each of
    `groups` agents (1: shared by all agents; 1 branch: shared by all branches). The first
    layer's input is split into a per-agent part x [B, T, U, in_x] (same for every branch) and
    an optional per-branch part r [B, T, U, K, in_r], so x is never copied K times."""

    def __init__(self, groups: int, branches: int, in_x: int, in_r: int, hidden: int, n_out: int):
        super().__init__()
        self.in_x = in_x
        self.w1 = nn.Parameter(torch.empty(groups, branches, in_x + in_r, hidden))
        self.b1 = nn.Parameter(torch.empty(groups, branches, hidden))
        self.w2 = nn.Parameter(torch.empty(groups, branches, hidden, n_out))
        self.b2 = nn.Parameter(torch.empty(groups, branches, n_out))
        for w, b, fan_in in ((self.w1, self.b1, in_x + in_r), (self.w2, self.b2, hidden)):
            bound = 1.0 / math.sqrt(fan_in)  # nn.Linear's default range
            nn.init.uniform_(w, -bound, bound)
            nn.init.uniform_(b, -bound, bound)

    def forward(self, x: torch.Tensor, r: torch.Tensor | None = None, k: int = 1) -> torch.Tensor:
        """x [B, T, U, in_x], r [B, T, U, k, in_r] or None -> [B, T, U, k, n_out]."""
        u = x.shape[2]
        w1, b1, w2, b2 = (p.expand(u, -1, *p.shape[2:]) for p in (self.w1, self.b1, self.w2, self.b2))
        h = torch.einsum("btui,ukih->btukh", x, w1[:, :, : self.in_x]) + b1  # [B, T, U, 1 or k, H]
        if r is not None:
            h = h + torch.einsum("btuki,ukih->btukh", r, w1[:, :, self.in_x :].expand(u, k, -1, -1))
        h = torch.relu(h).expand(*h.shape[:3], k, h.shape[-1])
        return torch.einsum("btukh,ukho->btuko", h, w2.expand(u, k, -1, -1)) + b2
