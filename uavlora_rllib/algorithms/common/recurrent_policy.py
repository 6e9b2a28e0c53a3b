"""Decentralised execution of a trained recurrent per-agent network, as an evaluation.Policy.

MAPPO's and COMA's GRU actors and QMIX/VDN's GRU Q-network share one calling convention,
net(obs [B, T, U, d], h [B, U, H]) -> (out [B, T, U, ...], h_T); this runs any of them one slot
at a time on a BatchCore's observations (CPU, no grad), carrying h across slots and resetting
it at each episode start. Only `pick` differs between algorithms: how the per-agent outputs
(logits or Q-values) of the slot become actions.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from uavlora_rllib.sim.core import BatchCore


def argmax_actions(out: torch.Tensor) -> torch.Tensor:
    """Greedy action per agent: [N, U, A] -> [N, U]."""
    return out.argmax(-1)


class RecurrentPolicy:
    def __init__(
        self,
        net: torch.nn.Module,
        pick: Callable[[torch.Tensor], torch.Tensor],
        initial_state: Callable[[int], torch.Tensor],
        name: str,
    ):
        self.name = name
        self.net = net.eval()
        self.pick = pick
        self.initial_state = initial_state
        self.h: torch.Tensor | None = None

    def reset(self, core: BatchCore) -> None:
        self.h = self.initial_state(core.n)

    def act(self, core: BatchCore) -> np.ndarray:
        if self.h is None or self.h.shape[0] != core.n:
            self.reset(core)
        # Clipped and float32 exactly as the team env hands observations to the env runners.
        obs = torch.as_tensor(np.clip(core.obs, -1.0, 1.0), dtype=torch.float32).unsqueeze(1)  # [N, 1, U, d]
        with torch.no_grad():
            out, self.h = self.net(obs, self.h)
            actions = self.pick(out[:, 0])
        return actions.numpy().astype(np.int64)
