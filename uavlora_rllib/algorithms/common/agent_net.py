"""The one recurrent agent network of every algorithm, and the per-agent action heads.

`RecurrentAgentNet` maps each UAV's LOCAL observation row, with a GRU carrying the UAV's
history, to one output vector per UAV: action logits (MAPPO/IPPO actors, COMA's actor) or
Q-values (QMIX/VDN agent networks):

    o_u [(+ one-hot of u)] -> Linear -> ReLU -> GRU -> [Linear -> ReLU] -> Linear -> out_u
                                                         (out_hidden)        (+ W_u h, agent_heads)

Shapes: observations [B, T, U, obs_dim], GRU state [B, U, gru_hidden], output [B, T, U, n_out].

* `share=True`: one network for all UAVs, the agent id appended as a one-hot; all UAVs run
  in ONE GRU call with the agent axis folded into the batch ([B, T, U, d] -> [B*U, T, d]).
  The first layer never builds the concatenated input: W [o; e_u] + b = W_o o + b + W_e[:, u],
  the same parameters, function and gradients without a [B, T, U, d + U] copy.
* `share=False`: one network per UAV (no id input), run one after the other.
* `agent_heads=True` (shared only): each UAV also adds its own linear map of the GRU output
  to the shared output, a cheap way to let identical UAVs act differently (COMA uses it).

`ActionHead` turns logits into per-agent distributions: one categorical per UAV (per_uav:
Discrete(90)) or a product of categoricals per UAV (per_device: [n_sf, n_tp] * quota + [n_bw]).
Log-probabilities and entropies are summed over a UAV's components but kept per UAV ([..., U]).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, cast

import numpy as np
import torch
from torch import nn


class _AgentStack(nn.Module):
    """One agent's layers: Linear+ReLU -> GRU -> [Linear+ReLU] -> Linear."""

    inp: nn.Linear
    gru: nn.GRU
    out: nn.Sequential

    def __init__(self, in_dim: int, fc_hidden: int, gru_hidden: int, n_out: int, out_hidden: int | None):
        super().__init__()
        self.inp = nn.Linear(in_dim, fc_hidden)
        self.gru = nn.GRU(fc_hidden, gru_hidden, batch_first=True)
        layers: list[nn.Module] = []
        width = gru_hidden
        if out_hidden:
            layers += [nn.Linear(gru_hidden, out_hidden), nn.ReLU()]
            width = out_hidden
        layers.append(nn.Linear(width, n_out))
        self.out = nn.Sequential(*layers)

    def recurrent(self, z: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """After the first layer: z [N, T, fc_hidden] (post-ReLU), h [N, H] -> GRU output [N, T, H], h_T [N, H]."""
        y, h_out = self.gru(z, h.unsqueeze(0).contiguous())
        return y, h_out.squeeze(0)


class RecurrentAgentNet(nn.Module):
    """Decentralised recurrent network for U agents (see the module docstring)."""

    agent_out: nn.Parameter | None

    def __init__(
        self,
        obs_dim: int,
        n_agents: int,
        n_out: int,
        *,
        fc_hidden: int = 128,
        gru_hidden: int = 128,
        share: bool = True,
        out_hidden: int | None = None,
        agent_heads: bool = False,
        out_gain: float | None = None,
    ):
        super().__init__()
        if agent_heads and not share:
            raise ValueError("agent_heads: only with share=True (separate networks already have their own heads)")
        self.obs_dim, self.n_agents, self.n_out = obs_dim, n_agents, n_out
        self.gru_hidden, self.share = gru_hidden, share
        self.in_dim = obs_dim + (n_agents if share else 0)
        self.nets = nn.ModuleList(
            _AgentStack(self.in_dim, fc_hidden, gru_hidden, n_out, out_hidden) for _ in range(1 if share else n_agents)
        )
        if out_gain is not None:  # e.g. 0.01 for a PPO actor: a near-uniform initial policy
            for net in self.stacks:
                last = cast(nn.Linear, net.out[-1])
                nn.init.orthogonal_(last.weight, gain=out_gain)
                nn.init.zeros_(last.bias)
        self.agent_out = None
        if agent_heads:
            width = out_hidden or gru_hidden
            bound = 1.0 / np.sqrt(width)  # nn.Linear's default range for this fan-in
            self.agent_out = nn.Parameter(torch.empty(n_agents, width, n_out).uniform_(-bound, bound))
            if out_gain is not None:  # the heads start at zero: the near-uniform policy of out_gain stays
                nn.init.zeros_(self.agent_out)

    @property
    def stacks(self) -> list[_AgentStack]:
        """The agents' layer stacks (one when shared), typed."""
        return cast(list[_AgentStack], list(self.nets))

    def initial_state(self, batch: int | None = None) -> torch.Tensor:
        """Zero GRU state: [U, H], or [batch, U, H]."""
        shape = (self.n_agents, self.gru_hidden) if batch is None else (batch, self.n_agents, self.gru_hidden)
        return torch.zeros(shape)

    def forward(self, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """obs [B, T, U, obs_dim], h [B, U, H] -> out [B, T, U, n_out], h_T [B, U, H].
        The GRU starts from h at t = 0 of every row: rows never share a hidden state."""
        b, t, u, d = obs.shape
        if u != self.n_agents or d != self.obs_dim:
            raise ValueError(f"obs: expected [B, T, {self.n_agents}, {self.obs_dim}], got {tuple(obs.shape)}")
        if not self.share:
            outs, hs = [], []
            for i, net in enumerate(self.stacks):
                y, h_i = net.recurrent(torch.relu(net.inp(obs[:, :, i])), h[:, i])
                outs.append(net.out(y))
                hs.append(h_i)
            return torch.stack(outs, dim=2), torch.stack(hs, dim=1)
        net = cast(_AgentStack, self.nets[0])
        first = net.inp
        z = nn.functional.linear(obs, first.weight[:, :d], first.bias)  # [B, T, U, fc]
        z = torch.relu(z + first.weight[:, d:].t())  # + the agent-id column of each agent
        z = z.permute(0, 2, 1, 3).reshape(b * u, t, z.shape[-1])
        y, h_out = net.recurrent(z, h.reshape(b * u, self.gru_hidden))
        if self.agent_out is None:
            out = net.out(y)
        else:  # the shared last layer's input feeds each agent's own linear map too
            feat = net.out[:-1](y).reshape(b, u, t, -1)
            own = torch.einsum("buth,uho->buto", feat, self.agent_out).reshape(b * u, t, -1)
            out = net.out[-1](feat.reshape(b * u, t, -1)) + own
        out = out.reshape(b, u, t, self.n_out).permute(0, 2, 1, 3)
        return out, h_out.reshape(b, u, self.gru_hidden)


class ActionHead:
    """Per-agent (multi-)categorical distributions over logits [..., U, sum(nvec)]."""

    def __init__(self, nvec: Sequence[int]):
        self.nvec = [int(n) for n in nvec]
        self.multi = len(self.nvec) > 1
        self.n_logits = sum(self.nvec)

    def _split(self, logits: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.split(logits, self.nvec, dim=-1))

    def sample(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Random actions ([..., U] or [..., U, L]) and their per-agent logp [..., U]."""
        acts: list[torch.Tensor] = []
        logp: Any = 0.0  # a tensor from the first component on
        for part in self._split(logits):
            lp = torch.log_softmax(part, dim=-1)
            a = torch.multinomial(lp.exp().reshape(-1, part.shape[-1]), 1).reshape(part.shape[:-1])
            acts.append(a)
            logp = logp + lp.gather(-1, a.unsqueeze(-1)).squeeze(-1)
        return (torch.stack(acts, dim=-1) if self.multi else acts[0]), logp

    def greedy(self, logits: torch.Tensor) -> torch.Tensor:
        """The most likely action per agent (component): argmax of each logit group."""
        acts = [part.argmax(dim=-1) for part in self._split(logits)]
        return torch.stack(acts, dim=-1) if self.multi else acts[0]

    def logp_and_entropy(self, logits: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-agent log-probability [..., U] of actions [..., U] or [..., U, L], and per-agent
        entropy [..., U] (both summed over an agent's components), from one log-softmax."""
        actions = actions.long()
        logp: Any = 0.0  # tensors from the first component on
        ent: Any = 0.0
        for k, part in enumerate(self._split(logits)):
            lp = torch.log_softmax(part, dim=-1)
            a = actions[..., k] if self.multi else actions
            logp = logp + lp.gather(-1, a.unsqueeze(-1)).squeeze(-1)
            ent = ent - (lp.exp() * lp).sum(-1)
        return logp, ent
