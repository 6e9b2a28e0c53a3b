"""Per-agent action distributions over an actor's logits: one categorical per UAV (per_uav:
Discrete(90)) or a product of categoricals per UAV (per_device: nvec row [n_sf, n_tp] * quota +
[n_bw], docs/model.md#actions). Shared by MAPPO/IPPO and COMA.

Padded layout: the branches of one UAV sit in a [L, W] grid, W = max(row); entry (l, c) with
c >= n_l is padding (logit -inf, probability 0), so every branch of every UAV is one slice of
one tensor: one log-softmax, one multinomial draw and one argmax for all of them, however many
ED slots a UAV serves (COMA's per-branch baseline reads the same grid, coma/branching.py).
Log-probabilities and entropies are summed over a UAV's branches but kept per UAV ([..., U]).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn


def taken(values: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """values [..., n] at the taken index actions [...] -> [...] (per UAV or per branch)."""
    return torch.gather(values, -1, actions.long().unsqueeze(-1)).squeeze(-1)


class BranchLayout(nn.Module):
    """Where each branch's values live in a UAV's flat logits / one-hot vector of sum(row)
    entries, and the padded [L, W] grid the per-branch tensors use (see the module docstring).
    Holds only constant, non-persistent buffers (nothing in the state dict)."""

    starts: torch.Tensor
    index: torch.Tensor
    valid: torch.Tensor
    sizes: torch.Tensor

    def __init__(self, row: Sequence[int]):
        super().__init__()
        self.row = [int(n) for n in row]
        self.n_branches, self.width = len(self.row), max(self.row)
        self.padded = any(n != self.width for n in self.row)
        starts = np.concatenate([[0], np.cumsum(self.row)[:-1]])
        values = np.arange(self.width)
        valid = values[None, :] < np.asarray(self.row)[:, None]  # [L, W]
        index = starts[:, None] + np.minimum(values[None, :], np.asarray(self.row)[:, None] - 1)
        self.register_buffer("starts", torch.as_tensor(starts, dtype=torch.long), persistent=False)  # [L]
        self.register_buffer("index", torch.as_tensor(index, dtype=torch.long), persistent=False)  # [L, W]
        self.register_buffer("valid", torch.as_tensor(valid), persistent=False)  # [L, W] bool
        self.register_buffer("sizes", torch.as_tensor(self.row, dtype=torch.float32), persistent=False)  # [L]

    def grid(self, logits: torch.Tensor) -> torch.Tensor:
        """Logits [..., sum(row)] -> [..., L, W], padding -inf (a view when no branch is padded)."""
        if not self.padded:
            return logits.unflatten(-1, (self.n_branches, self.width))
        return logits[..., self.index].masked_fill(~self.valid, float("-inf"))

    def log_probs(self, logits: torch.Tensor) -> torch.Tensor:
        """Logits [..., sum(row)] -> per-branch log-probabilities [..., L, W] (log-softmax within
        each branch; padding -inf). With several branches it is computed on the [..., W, L] grid
        and handed back transposed (a view): a log-softmax over W values with the L branches
        contiguous vectorises across them (1.3x here at L = 25, W = 6)."""
        if self.n_branches == 1:
            return torch.log_softmax(logits.unsqueeze(-2), dim=-1)
        transposed = logits[..., self.index.t()]  # [..., W, L]
        if self.padded:
            transposed = transposed.masked_fill(~self.valid.t(), float("-inf"))
        return torch.log_softmax(transposed, dim=-2).transpose(-1, -2)

    def entropy(self, log_probs: torch.Tensor) -> torch.Tensor:
        """Per-branch entropies [..., L] of `log_probs` [..., L, W] (padding contributes 0)."""
        safe = log_probs.masked_fill(~self.valid, 0.0) if self.padded else log_probs
        return -(log_probs.exp() * safe).sum(-1)


class ActionHead(nn.Module):
    """Per-agent (multi-)categorical distributions over logits [..., U, sum(nvec)]: actions
    [..., U] (one branch) or [..., U, L]; no parameters, nothing in the state dict."""

    def __init__(self, nvec: Sequence[int]):
        super().__init__()
        self.nvec = [int(n) for n in nvec]
        self.multi = len(self.nvec) > 1
        self.n_logits = sum(self.nvec)
        self.layout = BranchLayout(self.nvec)

    def _as_actions(self, per_branch: torch.Tensor) -> torch.Tensor:
        return per_branch if self.multi else per_branch.squeeze(-1)

    def sample_branches(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Random actions ([..., U] or [..., U, L]) and each branch's logp [..., U, L]."""
        log_probs = self.layout.log_probs(logits)  # [..., U, L, W]
        width = log_probs.shape[-1]
        acts = torch.multinomial(log_probs.exp().reshape(-1, width), 1).reshape(log_probs.shape[:-1])
        return self._as_actions(acts), taken(log_probs, acts)

    def sample(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Random actions ([..., U] or [..., U, L]) and their per-agent logp [..., U]."""
        actions, branch_logp = self.sample_branches(logits)
        return actions, branch_logp.sum(-1)

    def greedy(self, logits: torch.Tensor) -> torch.Tensor:
        """The most likely action per agent (branch): the argmax of each branch's logits."""
        return self._as_actions(self.layout.grid(logits).argmax(dim=-1))

    def logp_and_entropy(self, logits: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-agent log-probability [..., U] of actions [..., U] or [..., U, L], and per-agent
        entropy [..., U] (both summed over an agent's branches), from one log-softmax."""
        log_probs = self.layout.log_probs(logits)
        per_branch = actions.long() if self.multi else actions.long().unsqueeze(-1)
        return taken(log_probs, per_branch).sum(-1), self.layout.entropy(log_probs).sum(-1)
