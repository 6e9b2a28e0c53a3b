"""The forward passes of a decentralised recurrent actor, shared by the MAPPO/IPPO and COMA modules.

A module that mixes in `RecurrentActorForward` (before TorchRLModule) holds `self.actor`, a
`RecurrentAgentNet` over the team observation [B, T, U, d] with GRU state [B, U, H] under
HIDDEN, `self.head`, the `ActionHead` of its action space, and `self.n_agents`. Env runners
and the registry's policy then act through it: greedy (argmax per agent and component) in
forward_inference, sampled with each agent's log-probability in forward_exploration.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.rl_module import RLModule
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common.action_head import ActionHead
from uavlora_rllib.algorithms.common.columns import HIDDEN


class RecurrentActorForward:
    """Mixin: acting with the module's recurrent actor (see the module docstring)."""

    # set by the module's setup()
    n_agents: int
    actor: Any  # a RecurrentAgentNet
    head: ActionHead

    @override(RLModule)
    def get_initial_state(self) -> dict[str, Any]:
        return {HIDDEN: torch.zeros(self.n_agents, self.actor.gru_hidden)}

    def actor_logits(self, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Logits [B, T, U, n_logits] and the GRU state after them. Env runners pass obs
        [B, 1, U, d] (RLlib adds the time axis for stateful modules); a direct call may leave
        the time axis out ([B, U, d])."""
        obs = batch[Columns.OBS]
        if obs.dim() == 3:
            obs = obs.unsqueeze(1)
        logits, h = self.actor(obs.float(), batch[Columns.STATE_IN][HIDDEN].float())
        return logits, {HIDDEN: h}

    # Acting builds no autograd graph: RLlib's env runners call these with gradients enabled, and a
    # graph per step would also send the GRU through its saving autograd Function (common/gru_sequence.py).
    @override(RLModule)
    @torch.no_grad()
    def _forward_inference(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        logits, state = self.actor_logits(batch)
        return {Columns.ACTIONS: self.head.greedy(logits), Columns.STATE_OUT: state}

    @override(RLModule)
    @torch.no_grad()
    def _forward_exploration(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        logits, state = self.actor_logits(batch)
        actions, logp = self.head.sample(logits)
        return {Columns.ACTIONS: actions, Columns.ACTION_LOGP: logp, Columns.STATE_OUT: state}

    @override(RLModule)
    def _forward(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        return self._forward_inference(batch, **kwargs)
