"""The decentralised recurrent actor shared by the policy-gradient algorithms (MAPPO, IPPO).

`GRUActor` maps each agent's LOCAL observation row to logits of that agent's action, with a
GRU carrying the agent's history:

    o_u [(+ one-hot of u)] -> Linear -> ReLU -> GRU(hidden) -> Linear -> ReLU -> Linear -> logits_u

Shapes: observations [B, T, U, obs_dim], GRU state [B, U, hidden], logits [B, T, U, n_logits].
With `share_actor=True` (default) one network serves every UAV and the agent id is appended
as a one-hot (input obs_dim + U); all agents run in ONE GRU call by folding the agent axis
into the batch ([B, T, U, d] -> [B*U, T, d]). The first layer never builds the concatenated
input: W [o; e_u] + b = W_o o + b + W_e[:, u], so the one-hot part is a per-agent bias (same
parameters, same function and gradients, no [B, T, U, d + U] copy on the learner's hot path). With `share_actor=False` each UAV has its own
network (input obs_dim, no id), run one after the other.

`ActionHead` turns the logits into per-agent distributions: one categorical per agent
(per_uav: Discrete(90)) or a product of categoricals per agent (per_device:
MultiDiscrete([n_sf, n_tp] * quota + [n_bw])). Log-probabilities and entropies are summed
over an agent's components but kept separate per agent ([..., U]), which is what MAPPO's
per-agent ratio clipping needs. Nothing here reads the global state.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import nn


class _ActorNet(nn.Module):
    def __init__(self, in_dim: int, fc_hidden: int, gru_hidden: int, n_logits: int):
        super().__init__()
        self.pre = nn.Sequential(nn.Linear(in_dim, fc_hidden), nn.ReLU())
        self.gru = nn.GRU(fc_hidden, gru_hidden, batch_first=True)
        self.post = nn.Sequential(nn.Linear(gru_hidden, fc_hidden), nn.ReLU(), nn.Linear(fc_hidden, n_logits))
        # Small last layer: near-uniform initial policy (standard for PPO actors).
        nn.init.orthogonal_(self.post[-1].weight, gain=0.01)
        nn.init.zeros_(self.post[-1].bias)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x [N, T, in_dim], h [N, hidden] -> logits [N, T, n_logits], h_out [N, hidden]."""
        return self.recurrent(self.pre(x), h)

    def recurrent(self, z: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The part after the first layer: z [N, T, fc_hidden] (post-ReLU), h [N, hidden]."""
        out, h_out = self.gru(z, h.unsqueeze(0).contiguous())
        return self.post(out), h_out.squeeze(0)


class GRUActor(nn.Module):
    """Recurrent decentralised actor for U agents (see module docstring)."""

    def __init__(
        self,
        obs_dim: int,
        n_agents: int,
        n_logits: int,
        gru_hidden: int = 128,
        fc_hidden: int = 128,
        share_actor: bool = True,
    ):
        super().__init__()
        self.obs_dim, self.n_agents, self.n_logits = obs_dim, n_agents, n_logits
        self.gru_hidden, self.share_actor = gru_hidden, share_actor
        if share_actor:
            self.in_dim = obs_dim + n_agents
            self.net = _ActorNet(self.in_dim, fc_hidden, gru_hidden, n_logits)
        else:
            self.in_dim = obs_dim
            self.nets = nn.ModuleList(_ActorNet(obs_dim, fc_hidden, gru_hidden, n_logits) for _ in range(n_agents))

    def initial_state(self, batch: int | None = None) -> torch.Tensor:
        shape = (self.n_agents, self.gru_hidden) if batch is None else (batch, self.n_agents, self.gru_hidden)
        return torch.zeros(shape)

    def forward(self, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """obs [B, T, U, obs_dim], h [B, U, hidden] -> logits [B, T, U, n_logits], h_out [B, U, hidden]."""
        b, t, u, d = obs.shape
        if u != self.n_agents or d != self.obs_dim:
            raise ValueError(f"obs: expected [B, T, {self.n_agents}, {self.obs_dim}], got {tuple(obs.shape)}")
        if self.share_actor:
            first = self.net.pre[0]
            z = nn.functional.linear(obs, first.weight[:, :d], first.bias)  # [B, T, U, fc]
            z = torch.relu(z + first.weight[:, d:].t())  # + the agent-id column of each agent
            z = z.permute(0, 2, 1, 3).reshape(b * u, t, z.shape[-1])
            logits, h_out = self.net.recurrent(z, h.reshape(b * u, self.gru_hidden))
            logits = logits.reshape(b, u, t, self.n_logits).permute(0, 2, 1, 3)
            return logits, h_out.reshape(b, u, self.gru_hidden)
        outs, hs = [], []
        for i, net in enumerate(self.nets):
            lo, hi = net(obs[:, :, i], h[:, i])
            outs.append(lo)
            hs.append(hi)
        return torch.stack(outs, dim=2), torch.stack(hs, dim=1)


class ActionHead:
    """Per-agent (multi-)categorical distributions over logits [..., U, sum(nvec)]."""

    def __init__(self, nvec: Sequence[int]):
        self.nvec = [int(n) for n in nvec]
        self.multi = len(self.nvec) > 1
        self.n_logits = sum(self.nvec)

    def _split(self, logits: torch.Tensor) -> list[torch.Tensor]:
        return list(torch.split(logits, self.nvec, dim=-1))

    @staticmethod
    def _log_softmax(x: torch.Tensor) -> torch.Tensor:
        return torch.log_softmax(x, dim=-1)

    def sample(self, logits: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Random actions ([..., U] or [..., U, L]) and their per-agent logp [..., U]."""
        acts, logp = [], 0.0
        for part in self._split(logits):
            lp = self._log_softmax(part)
            a = torch.multinomial(lp.exp().reshape(-1, part.shape[-1]), 1).reshape(part.shape[:-1])
            acts.append(a)
            logp = logp + lp.gather(-1, a.unsqueeze(-1)).squeeze(-1)
        return (torch.stack(acts, dim=-1) if self.multi else acts[0]), logp

    def greedy(self, logits: torch.Tensor) -> torch.Tensor:
        acts = [part.argmax(dim=-1) for part in self._split(logits)]
        return torch.stack(acts, dim=-1) if self.multi else acts[0]

    def logp_and_entropy(self, logits: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-agent log-probability [..., U] of actions [..., U] or [..., U, L], and per-agent
        entropy [..., U] (both summed over an agent's components), from one log-softmax."""
        actions = actions.long()
        logp, ent = 0.0, 0.0
        for k, part in enumerate(self._split(logits)):
            lp = self._log_softmax(part)
            a = actions[..., k] if self.multi else actions
            logp = logp + lp.gather(-1, a.unsqueeze(-1)).squeeze(-1)
            ent = ent - (lp.exp() * lp).sum(-1)
        return logp, ent
