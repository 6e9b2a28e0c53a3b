"""The QMIX/VDN RLModule of per_device mode: QMixModule's mixers over the branching agent network.

Everything but the agent network is QMixModule's (mixer, V(s), targets, epsilon schedule,
inference-only copies); branching.py holds the network and the branch math. Shapes (U UAVs,
K = quota slots, P = n_sf n_tp (SF, TP) pairs, L = 2 K + 1):
  obs      [B, T, U, d]      each UAV's LOCAL observation
  actions  [B, T, U, L]      env actions (sf_0, tp_0, ..., sf_{K-1}, tp_{K-1}, bw) per UAV
  slot_q   [B, T, U, K, P]   slot branch utilities
  bw_q     [B, T, U, n_bw]   BW branch utilities
  q_u      [B, T, U]         per-UAV utility fed to the mixer: the mean over active branches
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis import QNetAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.rl_module import RLModule
from ray.rllib.utils.annotations import override
from torch import nn

from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, HIDDEN
from uavlora_rllib.algorithms.qmix import branching
from uavlora_rllib.algorithms.qmix.qmix_module import Q_TAKEN, Q_TOT, TARGET_Q_TOT_NEXT, QMixModule

Q_SLOTS = "q_slots"  # [B, T+1, U, K, P] online slot utilities over the whole sequence
Q_BW = "q_bw"  # [B, T+1, U, n_bw] online BW utilities


class BranchingQMixModule(QMixModule):
    """model_config: QMixModule's; the branch sizes come from the per_device action space
    (MultiDiscrete [U, 2 quota + 1])."""

    @override(QMixModule)
    def _make_agent(self) -> nn.Module:
        mc = self.model_config
        nvec = np.asarray(self.action_space.nvec)
        if nvec.ndim != 2 or nvec.shape[0] != self.n_agents:
            raise ValueError(
                f"action space: expected per_device MultiDiscrete [U={self.n_agents}, 2 quota + 1], got {nvec.shape}"
            )
        self.quota, n_sf, self.n_tp, self.n_bw = branching.action_dims(nvec[0])
        self.n_pairs = n_sf * self.n_tp
        return branching.BranchingAgentNet(
            int(mc["obs_dim"]),
            self.n_agents,
            self.quota,
            self.n_pairs,
            self.n_bw,
            fc_hidden=int(mc["fc_hidden"]),
            gru_hidden=self.gru_hidden,
            head_hidden=int(mc["head_hidden"]),
            share=bool(mc["share_agent_net"]),
            slot_head=str(mc["slot_head"]),
            n_tp=self.n_tp,
            slot_utility=str(mc.get("slot_utility", "joint")),  # a checkpoint from before the field: joint
            dueling=bool(mc["dueling"]),
        )

    # ------------------------------------------------------------------ acting (env runners)
    def _step(self, batch: dict[str, Any]) -> tuple[tuple[torch.Tensor, torch.Tensor], torch.Tensor]:
        """Branch utilities of one step: obs [B, 1, U, d] (or [B, U, d]) ->
        ((slot_q [B, U, K, P], bw_q [B, U, n_bw]), h [B, U, H])."""
        obs = batch[Columns.OBS].float()
        if obs.dim() == 3:
            obs = obs.unsqueeze(1)
        slot_q, bw_q, h = self.agent(obs, batch[Columns.STATE_IN][HIDDEN])
        return (slot_q[:, -1], bw_q[:, -1]), h

    @override(RLModule)
    def _forward_inference(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        with torch.no_grad():
            (slot_q, bw_q), h = self._step(batch)
            actions = branching.env_actions(*branching.greedy(slot_q, bw_q), self.n_tp)
            return {Columns.ACTIONS: actions.unsqueeze(1), Columns.STATE_OUT: {HIDDEN: h}}

    @override(RLModule)
    def _forward_exploration(self, batch: dict[str, Any], t: int | None = None, **kwargs) -> dict[str, Any]:
        """Epsilon-greedy per branch (every slot and the BW of every UAV on its own); t as in QMixModule."""
        with torch.no_grad():
            (slot_q, bw_q), h = self._step(batch)
            slot_idx, bw_idx = branching.greedy(slot_q, bw_q)
            slot_idx, bw_idx = branching.explore(slot_idx, bw_idx, self.n_pairs, self.n_bw, self.epsilon(t))
            actions = branching.env_actions(slot_idx, bw_idx, self.n_tp)
            return {Columns.ACTIONS: actions.unsqueeze(1), Columns.STATE_OUT: {HIDDEN: h}}

    # ------------------------------------------------------------------ learning
    @override(QNetAPI)
    def compute_q_values(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Online branch utilities over whole sequences, GRU started at zero: obs [B, T, U, d]."""
        obs = batch[Columns.OBS].float()
        slot_q, bw_q, _ = self.agent(obs, self._zero_h(obs))
        return {Q_SLOTS: slot_q, Q_BW: bw_q}

    @override(RLModule)
    def _forward_train(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """Batch of whole episodes: obs [B, T+1, U, d], actions [B, T, U, L], state [B, T+1, S]."""
        obs = batch[Columns.OBS].float()
        q = self.compute_q_values(batch)
        n_t = batch[Columns.ACTIONS].shape[1]
        slot_idx, bw_idx = branching.branch_indices(batch[Columns.ACTIONS], self.n_tp)
        slot_v, bw_v = branching.taken(q[Q_SLOTS][:, :n_t], q[Q_BW][:, :n_t], slot_idx, bw_idx)
        q_taken = branching.aggregate(slot_v, bw_v, branching.active_slots(obs[:, :n_t], self.quota))
        q_tot = self.mixer(q_taken, batch[GLOBAL_STATE].float())
        online = {Q_SLOTS: q[Q_SLOTS].detach(), Q_BW: q[Q_BW].detach()}
        return {**q, Q_TAKEN: q_taken, Q_TOT: q_tot, **self.target_terms({**batch, **online})}

    # ------------------------------------------------------------------ target networks
    @override(TargetNetworkAPI)
    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Target Q_tot at s_{t+1}, t = 0..T-1. Double Q per branch: the ONLINE network picks
        each branch's argmax at t+1 (batch[Q_SLOTS], batch[Q_BW] if given), the target network
        evaluates it; the branches are averaged over the slots active at t+1 and mixed by the
        target mixer on s_{t+1}. Without double_q: each branch's target maximum."""
        obs = batch[Columns.OBS].float()
        state = batch[GLOBAL_STATE].float()
        t_slot, t_bw, _ = self._target_agent(obs, self._zero_h(obs))
        t_slot, t_bw = t_slot[:, 1:], t_bw[:, 1:]
        if self.double_q:
            online = batch if Q_SLOTS in batch else self.compute_q_values(batch)
            slot_idx, bw_idx = branching.greedy(online[Q_SLOTS][:, 1:], online[Q_BW][:, 1:])
            slot_v, bw_v = branching.taken(t_slot, t_bw, slot_idx, bw_idx)
        else:
            slot_v, bw_v = t_slot.max(-1).values, t_bw.max(-1).values
        q_next = branching.aggregate(slot_v, bw_v, branching.active_slots(obs[:, 1:], self.quota))
        return {TARGET_Q_TOT_NEXT: self._target_mixer(q_next, state, first=1)}
