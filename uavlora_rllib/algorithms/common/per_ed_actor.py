"""The per_device actor with per-ED heads (MAPPO/IPPO `actor_heads`, docs/model.md#mappo-and-ippo-per-device).

The flat actor (`RecurrentAgentNet` with one output layer for all 2 quota + 1 branches) must carry
each ED's row through the GRU before its slot's logits can depend on it. Here each ED slot's logits
come from a head that also reads that ED's own observation row:

    o_u -> RecurrentAgentNet (Linear -> ReLU -> GRU -> Linear) -> ReLU -> f_u
    slot k:  logits_k  = head_k([f_u ; row_k(o_u) ; e_k])   n_sf SF logits, then n_tp TP logits
    BW:      logits_bw = head_bw(f_u)                        n_bw logits

`per_slot`: every slot has its own head (e_k left out: the head already knows its slot).
`shared`: one head for all slots, told apart by the row and the slot's one-hot e_k, so what it
learns about one ED's (x, y, d, G) serves every slot.

Output: the flat actor's layout [B, T, U, (n_sf + n_tp) quota + n_bw], so `ActionHead` (one
categorical per SF, TP and BW branch) and the losses are unchanged. The heads' last layers start
near zero, as the flat actor's (a near-uniform initial policy).
"""

from __future__ import annotations

import torch
from torch import nn

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.branch_heads import BranchHeads, slot_rows
from uavlora_rllib.sim.observation import OBS_EXTRA, OBS_ROW

ACTOR_HEADS = ("flat", "per_slot", "shared")  # flat: RecurrentAgentNet's one output layer


class PerEDActor(nn.Module):
    """obs [B, T, U, 4 quota + 3], h [B, U, H] -> logits [B, T, U, (n_sf + n_tp) quota + n_bw], h_T."""

    def __init__(
        self,
        obs_dim: int,
        n_agents: int,
        quota: int,
        n_sf: int,
        n_tp: int,
        n_bw: int,
        *,
        heads: str,
        fc_hidden: int,
        gru_hidden: int,
        share: bool,
        out_gain: float = 0.01,
    ):
        super().__init__()
        if heads not in ACTOR_HEADS[1:]:
            raise ValueError(f"heads: expected one of {ACTOR_HEADS[1:]}, got {heads!r}")
        if obs_dim != quota * OBS_ROW + OBS_EXTRA:
            raise ValueError(f"obs_dim: expected {quota * OBS_ROW + OBS_EXTRA} for quota {quota}, got {obs_dim}")
        self.quota, self.n_slot_logits, self.n_bw = quota, n_sf + n_tp, n_bw
        self.gru_hidden = gru_hidden
        self.shared = heads == "shared"
        self.torso = RecurrentAgentNet(
            obs_dim, n_agents, fc_hidden, fc_hidden=fc_hidden, gru_hidden=gru_hidden, share=share
        )
        groups = 1 if share else n_agents
        self.slot_heads = BranchHeads(
            groups,
            1 if self.shared else quota,
            fc_hidden,
            OBS_ROW,
            fc_hidden,
            n_sf + n_tp,
            slot_ids=quota if self.shared else 0,
        )
        self.bw_head = BranchHeads(groups, 1, fc_hidden, 0, fc_hidden, n_bw)
        with torch.no_grad():
            for head in (self.slot_heads, self.bw_head):
                head.w2.mul_(out_gain)
                head.b2.zero_()

    def initial_state(self, batch: int | None = None) -> torch.Tensor:
        return self.torso.initial_state(batch)

    def forward(self, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f, h_out = self.torso(obs, h)
        f = torch.relu(f)
        slot_logits = self.slot_heads(f, slot_rows(obs, self.quota), self.quota)  # [B, T, U, K, n_sf + n_tp]
        bw_logits = self.bw_head(f).squeeze(-2)  # [B, T, U, n_bw]
        # float32 under autocast too (common/precision.py)
        return torch.cat((slot_logits.flatten(-2), bw_logits), dim=-1).float(), h_out


def make_actor(
    obs_dim: int,
    n_agents: int,
    row: list[int],
    *,
    heads: str,
    fc_hidden: int,
    gru_hidden: int,
    share: bool,
    agent_heads: bool,
    **flat: float | int,
) -> RecurrentAgentNet | PerEDActor:
    """The actor an `actor_heads` value names, for one UAV's action branches `row` (per_device:
    [n_sf, n_tp] per ED slot, then n_bw; per_uav: [n_actions]): PerEDActor for per-ED heads, else
    RecurrentAgentNet with one output layer for all sum(row) logits (`flat`: its other keywords,
    such as out_hidden and out_gain)."""
    if heads == "flat":
        return RecurrentAgentNet(
            obs_dim,
            n_agents,
            sum(row),
            fc_hidden=fc_hidden,
            gru_hidden=gru_hidden,
            share=share,
            agent_heads=agent_heads,  # RecurrentAgentNet refuses it unshared
            **flat,  # type: ignore[arg-type]
        )
    quota = (len(row) - 1) // 2
    return PerEDActor(
        obs_dim,
        n_agents,
        quota,
        int(row[0]),
        int(row[1]),
        int(row[-1]),
        heads=heads,
        fc_hidden=fc_hidden,
        gru_hidden=gru_hidden,
        share=share,
    )
