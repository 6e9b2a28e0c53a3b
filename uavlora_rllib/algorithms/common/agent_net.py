"""The one recurrent agent network of every algorithm.

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
* `share=False`: one network per UAV (no id input), all U run in ONE batched call: each
  parameter is stacked over the agents ([U, ...]) and every layer is a batched matrix product
  (`torch.baddbmm`), the GRU a loop over time of batched products with nn.GRU's gate maths
  (docs/model.md#batched-agent-networks). The same function, initial values and gradients as U
  separate networks; state_dict keys stay per agent (`nets.{u}.inp.weight`, ...), so
  checkpoints and target-network copies keep the layout of U separate networks.
* `agent_heads=True` (shared only): each UAV also adds its own linear map of the GRU output
  to the shared output, a cheap way to let identical UAVs act differently (COMA uses it).

Its logits become per-agent distributions in common/action_head.py.
"""

from __future__ import annotations

from typing import cast

import numpy as np
import torch
from torch import nn

from uavlora_rllib.algorithms.common.gru_sequence import gru_sequence, gru_steps


class _AgentStack(nn.Module):
    """One agent's layers: Linear+ReLU -> GRU -> [Linear+ReLU] -> Linear."""

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


def _stacked_name(name: str) -> str:
    """The attribute of a stacked parameter: 'gru.weight_ih_l0' -> 'stacked_gru_weight_ih_l0'."""
    return "stacked_" + name.replace(".", "_")


def _split_stacked_state(module: RecurrentAgentNet, state: dict, prefix: str, _meta) -> None:
    """state_dict post-hook: each stacked [U, ...] tensor leaves as U per-agent entries
    `nets.{u}.<name>`, the keys U separate networks have (checkpoints keep their layout)."""
    full = {name: state.pop(prefix + _stacked_name(name)) for name in module.stacked_names}
    for u in range(module.n_agents):  # agent-major, the order of U separate networks
        for name in module.stacked_names:
            state[f"{prefix}nets.{u}.{name}"] = full[name][u]


def _stack_agent_state(module: RecurrentAgentNet, state: dict, prefix: str, *_args) -> None:
    """load_state_dict pre-hook: the per-agent entries `nets.{u}.<name>` become the stacked
    tensor again (a state without them, e.g. a partial one, is left alone)."""
    for name in module.stacked_names:
        keys = [f"{prefix}nets.{u}.{name}" for u in range(module.n_agents)]
        if all(k in state for k in keys):
            state[prefix + _stacked_name(name)] = torch.stack([torch.as_tensor(state.pop(k)) for k in keys])


class RecurrentAgentNet(nn.Module):
    """Decentralised recurrent network for U agents (see the module docstring)."""

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
        stacks = [
            _AgentStack(self.in_dim, fc_hidden, gru_hidden, n_out, out_hidden) for _ in range(1 if share else n_agents)
        ]
        if out_gain is not None:  # e.g. 0.01 for a PPO actor: a near-uniform initial policy
            for net in stacks:
                last = cast(nn.Linear, net.out[-1])
                nn.init.orthogonal_(last.weight, gain=out_gain)
                nn.init.zeros_(last.bias)
        nets = nn.ModuleList(stacks)
        self.stacked_names: tuple[str, ...] = ()
        if share:
            self.nets = nets
        else:  # U separate networks, initialised one by one as above, then stacked [U, ...]
            self.stacked_names = tuple(name for name, _ in nets[0].named_parameters())
            for name in self.stacked_names:
                full = torch.stack([net.get_parameter(name).detach() for net in nets])
                self.register_parameter(_stacked_name(name), nn.Parameter(full))
            self.n_out_layers = sum(isinstance(m, nn.Linear) for m in stacks[0].out)
            self.register_state_dict_post_hook(_split_stacked_state)
            self.register_load_state_dict_pre_hook(_stack_agent_state)
        self.agent_out = None
        if agent_heads:
            width = out_hidden or gru_hidden
            bound = 1.0 / np.sqrt(width)  # nn.Linear's default range for this fan-in
            self.agent_out = nn.Parameter(torch.empty(n_agents, width, n_out).uniform_(-bound, bound))
            if out_gain is not None:  # the heads start at zero: the near-uniform policy of out_gain stays
                nn.init.zeros_(self.agent_out)

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
            return self._forward_stacked(obs, h)
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
        return out.float(), h_out.reshape(b, u, self.gru_hidden)  # float32 under autocast too (common/precision.py)

    def _stacked(self, name: str) -> torch.Tensor:
        """The stacked [U, ...] parameter of the per-agent parameter `name` (share=False)."""
        return cast(torch.Tensor, getattr(self, _stacked_name(name)))

    def _linear(self, x: torch.Tensor, name: str) -> torch.Tensor:
        """Agent u's nn.Linear `name` on x[u]: x [U, N, in] -> [U, N, out], one batched product."""
        w, b = self._stacked(name + ".weight"), self._stacked(name + ".bias")
        return torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2))

    def _forward_stacked(self, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """share=False: all U networks at once on the agent-major layout [U, B*T, .]."""
        b, t, u, d = obs.shape
        x = obs.permute(2, 0, 1, 3).reshape(u, b * t, d)
        z = torch.relu(self._linear(x, "inp"))
        y, h_out = self._gru(z.reshape(u, b, t, -1), h.transpose(0, 1))
        y = y.reshape(u, b * t, self.gru_hidden)
        for k in range(self.n_out_layers):  # out.0 [-> ReLU -> out.2]: Linear at every other index
            y = self._linear(y, f"out.{2 * k}")
            if k < self.n_out_layers - 1:
                y = torch.relu(y)
        out = y.reshape(u, b, t, self.n_out).permute(1, 2, 0, 3).float()  # float32 under autocast too
        return out, h_out.transpose(0, 1).contiguous()

    def _gru(self, z: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """U GRUs at once: z [U, B, T, fc], h [U, B, H] -> outputs [U, B, T, H], h_T [U, B, H].
        nn.GRU's equations (common/gru_sequence.py); the input projection of all T steps is one
        batched product, as nn.GRU does on the CPU."""
        u, b, t, f = z.shape
        w_ih, w_hh, b_ih, b_hh = (
            self._stacked(f"gru.{k}_l0") for k in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")
        )
        # .to(h.dtype): under bf16 autocast (learner_precision) the products run in bf16 but the gates and
        # the carried state stay float32, so rounding does not compound over T (a no-op otherwise)
        gi = torch.baddbmm(b_ih.unsqueeze(1), z.reshape(u, b * t, f), w_ih.transpose(1, 2))
        gi = gi.to(h.dtype).view(u, b, t, -1)
        recurrence = gru_steps if torch.is_autocast_enabled(z.device.type) else gru_sequence
        hs = recurrence(gi, h, w_hh, b_hh)
        return hs, hs[:, :, -1]
