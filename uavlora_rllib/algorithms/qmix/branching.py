"""Action branching for QMIX/VDN in per_device mode: the factored agent network and its branch math.

In per_device mode a UAV's action is a vector of length 2 Lambda + 1 (sim/actions.py): an (SF, TP)
pair for each of its Lambda ED slots (rows of its local observation), then one BW. Enumerating
the joint per-UAV space ((n_sf n_tp)^Lambda n_bw actions) is out of reach, so the agent network
follows Branching Dueling Q-Networks (Tavakoli et al., AAAI 2018, "Action Branching
Architectures for Deep Reinforcement Learning"): a shared torso, then one utility head per
action branch (docs/model.md#qmix-and-vdn-per-device):

    o_u -> RecurrentAgentNet (the per_uav trunk: Linear -> ReLU -> GRU -> Linear) -> ReLU -> f_u
    slot k:  Q_k(o_u, .) = head_k([f_u ; row_k(o_u)])  over the n_sf n_tp (SF, TP) pairs
             (`slot_utility: additive`: the head gives n_sf + n_tp values and Q_k(sf, tp) = Q_k^SF(sf) + Q_k^TP(tp))
    BW:      Q_bw(o_u, .) = head_bw(f_u)                over the n_bw bandwidths

Each head is Linear -> ReLU -> Linear (BDQ's per-branch hidden layer). With `dueling` (BDQ's
dueling form) the heads give advantages A_d and a state-value head V_u(f_u) the level shared by
all branches of the UAV: Q_d(o_u, a) = V_u + A_d(a) - mean_a' A_d(a'); the argmax of a branch is
the argmax of its advantage. `slot_head: per_slot`
gives every slot its own head parameters; `shared` uses one head for all slots, told apart by
the slot's own observation row (its ED's x, y, d, G), which every slot head reads. Without a
shared network (`share_agent_net: false`) every UAV also has its own heads.

A UAV's utility, the input of the mixer, is the mean of its chosen branch utilities over the
ACTIVE branches: the slots that hold a served ED (the first `count` rows of its observation,
count = round(Lambda x the served-count feature); the zero "virtual ED" rows do not count) and
the BW branch:

    Q_u = (sum_{k < count_u} Q_k(a_k) + Q_bw(a_bw)) / (count_u + 1)

Greedy action: the argmax of every branch on its own. The TD target's per-UAV term is the same
mean, with each branch's argmax taken by the online network and evaluated by the target network
(double Q per branch). Exploration: each branch is replaced by a uniform random choice with
probability epsilon, independently of the others.
"""

from __future__ import annotations

import torch
from torch import nn

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.branch_heads import BranchHeads, slot_rows
from uavlora_rllib.sim.observation import OBS_EXTRA, OBS_ROW

SLOT_HEADS = ("per_slot", "shared")
SLOT_UTILITIES = ("joint", "additive")


def action_dims(nvec_row) -> tuple[int, int, int, int]:
    """(quota, n_sf, n_tp, n_bw) of one UAV's per_device action row [n_sf, n_tp] * quota + [n_bw]."""
    row = [int(n) for n in nvec_row]
    if len(row) < 3 or len(row) % 2 != 1:
        raise ValueError(f"per_device action row: expected [n_sf, n_tp] * quota + [n_bw], got {row}")
    quota = (len(row) - 1) // 2
    if row[:-1] != row[:2] * quota:
        raise ValueError(f"per_device action row: expected [n_sf, n_tp] * quota + [n_bw], got {row}")
    return quota, row[0], row[1], row[-1]


def active_slots(obs: torch.Tensor, quota: int) -> torch.Tensor:
    """Which slots hold a served ED: obs [..., 4 quota + 3] -> bool [..., quota]. Served EDs fill
    the first `count` rows (sim/observation.py); count / quota is the first extra feature."""
    count = torch.round(obs[..., quota * OBS_ROW] * quota)
    return torch.arange(quota, device=obs.device) < count.unsqueeze(-1)


def branch_indices(actions: torch.Tensor, n_tp: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Env actions [..., 2 quota + 1] -> (slot pair index sf n_tp + tp [..., quota], bw index [...])."""
    actions = actions.long()
    return actions[..., 0:-1:2] * n_tp + actions[..., 1:-1:2], actions[..., -1]


def env_actions(slot_idx: torch.Tensor, bw_idx: torch.Tensor, n_tp: int) -> torch.Tensor:
    """(slot pair index [..., quota], bw index [...]) -> env actions [..., 2 quota + 1]."""
    pairs = torch.stack((slot_idx // n_tp, slot_idx % n_tp), dim=-1).flatten(-2)
    return torch.cat((pairs, bw_idx.unsqueeze(-1)), dim=-1)


def aggregate(slot_values: torch.Tensor, bw_value: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """A UAV's utility: the mean of its active branch values, slot_values [..., quota] (masked by
    active [..., quota]) and bw_value [...] (always active) -> [...]."""
    total = torch.where(active, slot_values, torch.zeros_like(slot_values)).sum(-1) + bw_value
    return total / (active.sum(-1).to(total.dtype) + 1.0)


def greedy(slot_q: torch.Tensor, bw_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-branch argmax: slot_q [..., quota, P], bw_q [..., n_bw] -> ([..., quota], [...])."""
    return slot_q.argmax(-1), bw_q.argmax(-1)


def taken(slot_q: torch.Tensor, bw_q: torch.Tensor, slot_idx: torch.Tensor, bw_idx: torch.Tensor):
    """The branch utilities of the chosen indices: ([..., quota], [...])."""
    return slot_q.gather(-1, slot_idx.unsqueeze(-1)).squeeze(-1), bw_q.gather(-1, bw_idx.unsqueeze(-1)).squeeze(-1)


def explore(slot_idx: torch.Tensor, bw_idx: torch.Tensor, n_pairs: int, n_bw: int, epsilon: float):
    """Epsilon-greedy per branch: each slot and the BW branch, independently, uniform with
    probability epsilon (a uniform pair index is a uniform SF and a uniform TP)."""

    def one(idx: torch.Tensor, n: int) -> torch.Tensor:
        rand = torch.randint(0, n, idx.shape, device=idx.device)
        return torch.where(torch.rand(idx.shape, device=idx.device) < epsilon, rand, idx)

    return one(slot_idx, n_pairs), one(bw_idx, n_bw)


class BranchingAgentNet(nn.Module):
    """The per_device agent network (module docstring): obs [B, T, U, d], h [B, U, H] ->
    slot utilities [B, T, U, quota, n_sf n_tp], BW utilities [B, T, U, n_bw], h_T [B, U, H]."""

    def __init__(
        self,
        obs_dim: int,
        n_agents: int,
        quota: int,
        n_pairs: int,
        n_bw: int,
        *,
        n_tp: int | None = None,
        slot_utility: str = "joint",
        fc_hidden: int,
        gru_hidden: int,
        head_hidden: int,
        share: bool,
        slot_head: str,
        dueling: bool,
    ):
        super().__init__()
        if slot_head not in SLOT_HEADS:
            raise ValueError(f"slot_head: expected one of {SLOT_HEADS}, got {slot_head!r}")
        if slot_utility not in SLOT_UTILITIES:
            raise ValueError(f"slot_utility: expected one of {SLOT_UTILITIES}, got {slot_utility!r}")
        if slot_utility == "additive" and (n_tp is None or n_pairs % n_tp):
            raise ValueError(f"slot_utility additive: n_tp must divide n_pairs ({n_pairs}), got {n_tp}")
        if obs_dim != quota * OBS_ROW + OBS_EXTRA:
            raise ValueError(f"obs_dim: expected {quota * OBS_ROW + OBS_EXTRA} for quota {quota}, got {obs_dim}")
        self.quota, self.n_pairs, self.n_bw = quota, n_pairs, n_bw
        self.n_agents, self.gru_hidden = n_agents, gru_hidden
        self.torso = RecurrentAgentNet(
            obs_dim, n_agents, fc_hidden, fc_hidden=fc_hidden, gru_hidden=gru_hidden, share=share
        )
        groups = 1 if share else n_agents
        # additive: SF values then TP values, combined into the pair utilities in forward
        self.n_tp = n_tp if slot_utility == "additive" else None
        n_slot_out = n_pairs if self.n_tp is None else n_pairs // self.n_tp + self.n_tp
        self.slot_heads = BranchHeads(
            groups, quota if slot_head == "per_slot" else 1, fc_hidden, OBS_ROW, head_hidden, n_slot_out
        )
        self.bw_head = BranchHeads(groups, 1, fc_hidden, 0, head_hidden, n_bw)
        self.value_head = BranchHeads(groups, 1, fc_hidden, 0, head_hidden, 1) if dueling else None

    def forward(self, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f, h_out = self.torso(obs, h)
        f = torch.relu(f)
        slot_q = self.slot_heads(f, slot_rows(obs, self.quota), self.quota)
        if self.n_tp is not None:  # Q(sf, tp) = Q^SF(sf) + Q^TP(tp), pair index sf n_tp + tp
            q_sf, q_tp = slot_q[..., : -self.n_tp], slot_q[..., -self.n_tp :]
            slot_q = (q_sf.unsqueeze(-1) + q_tp.unsqueeze(-2)).flatten(-2)
        bw_q = self.bw_head(f).squeeze(-2)
        if self.value_head is not None:  # dueling: Q_d(a) = V_u + A_d(a) - mean_a' A_d(a')
            v = self.value_head(f)  # [B, T, U, 1, 1]
            slot_q = v + slot_q - slot_q.mean(-1, keepdim=True)
            bw_q = v.squeeze(-2) + bw_q - bw_q.mean(-1, keepdim=True)
        return slot_q.float(), bw_q.float(), h_out  # float32 under autocast too (common/precision.py)
