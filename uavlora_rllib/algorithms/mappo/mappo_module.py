"""MAPPO / IPPO RLModule over the team view: GRU actors on local rows, critic for training only.

Spaces (team view, `uavlora_rllib.envs.team`): observation Box [U, obs_dim]; action
MultiDiscrete [U] (per_uav) or [U, 2 quota + 1] (per_device).

* `actor` (common `RecurrentAgentNet`, with a ReLU layer after the GRU and a near-zero last
  layer, or `PerEDActor` for per_device `actor_heads`: common/per_ed_actor.make_actor): decentralised; reads row u of the observation only (plus the agent id one-hot when
  shared). Its GRU state [U, gru_hidden] per scenario is RLlib's `STATE_IN/STATE_OUT`
  {HIDDEN: ...}; RLlib resets it to zeros at every episode start.
* `critic`: centralised V(s, u) on the GLOBAL state (train-batch column GLOBAL_STATE, filled by
  `mappo_learner.AddGlobalStateToBatch` from info["state"]): one trunk on s (input state_dim)
  with one output head per agent, for `critic="central"` (MAPPO); V(o_u, u) on the agent's own
  observation row (input obs_dim + U) for `critic="local"` (IPPO). Output [B, T, U]. It
  also holds the running value-normalisation statistics.

The module implements `InferenceOnlyAPI`: env runners build it with `inference_only=True`
and the critic (parameters and value-norm buffers) is deleted there, so env runners carry
and receive only the actor.

Env runner outputs (exploration): ACTIONS [B, 1, U(, L)] sampled here, ACTION_LOGP
[B, 1, U] (the per-agent log-probabilities; the loss clips each agent's ratio separately),
STATE_OUT. Inference: ACTIONS = argmax per agent (component).
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, ValueFunctionAPI
from ray.rllib.core.rl_module.rl_module import RLModule
from ray.rllib.core.rl_module.torch import TorchRLModule
from ray.rllib.utils.annotations import override
from torch import nn

from uavlora_rllib.algorithms.common.action_head import ActionHead
from uavlora_rllib.algorithms.common.actor_module import RecurrentActorForward
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.hparams import resolve_actor_heads
from uavlora_rllib.algorithms.common.per_ed_actor import make_actor
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process
from uavlora_rllib.algorithms.common.value_norm import ValueNorm


class Critic(nn.Module):
    """V(x, u) for every agent u, an MLP of two ReLU layers (docs/model.md#central-critic).

    * `shared=True` (MAPPO, x = the global state s, the same for every agent): per-agent heads
      on one trunk, V(s, u) = w_u . f(s) + b_u, the last layer having one output per agent. The
      trunk reads s once per slot, so the critic's cost does not grow with U but for that layer.
    * `shared=False` (IPPO, x = each agent's own observation row): the MLP on [x_u; one-hot(u)];
      the first layer is evaluated as W_x x_u + b + W_e[:, u] (the same parameters and function
      as on the concatenated input, without building it)."""

    def __init__(self, in_dim: int, hidden: int, n_agents: int, value_norm: bool, shared: bool = False):
        super().__init__()
        self.shared = shared
        self.in_dim = in_dim if shared else in_dim + n_agents  # + agent-id one-hot per agent
        self.n_agents = n_agents
        self.net = nn.Sequential(
            nn.Linear(self.in_dim, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, n_agents if shared else 1),  # shared: one head per agent
        )
        self.value_norm = ValueNorm() if value_norm else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [..., d] (shared) or [..., U, d] (per agent) -> values [..., U] (normalised space)."""
        if self.shared:
            return self.net(x).float()  # float32 under autocast too (common/precision.py)
        first = cast(nn.Linear, self.net[0])
        d = self.in_dim - self.n_agents
        z = nn.functional.linear(x, first.weight[:, :d], first.bias)
        z = z + first.weight[:, d:].t()  # [U, hidden]: the agent-id column of each agent
        return self.net[1:](z).squeeze(-1).float()


class MAPPOTorchRLModule(RecurrentActorForward, TorchRLModule, ValueFunctionAPI, InferenceOnlyAPI):
    """See module docstring. model_config (common/config.py): MAPPOHParams' fields (gru_hidden,
    fc_hidden, critic_hidden, share_actor, actor_agent_heads, value_norm, max_seq_len), critic
    ("central" | "local", resolved by the algorithm), state_dim, torch_threads."""

    @override(TorchRLModule)
    def setup(self):
        mc = self.model_config
        setup_torch_process(mc["torch_threads"])
        n_agents, obs_dim = self.observation_space.shape
        nvec = np.asarray(self.action_space.nvec)
        self.n_agents, self.obs_dim = int(n_agents), int(obs_dim)
        row = nvec.reshape(self.n_agents, -1)[0]
        self.per_device = nvec.ndim == 2
        self.head = ActionHead(row.tolist())
        fc_hidden = int(mc["fc_hidden"])
        self.actor = make_actor(  # actor_heads other than flat: per_device only (MAPPOHParams.check)
            self.obs_dim,
            self.n_agents,
            row.tolist(),
            heads=resolve_actor_heads(mc["actor_heads"], self.per_device),  # (null: by action mode)
            fc_hidden=fc_hidden,
            gru_hidden=int(mc["gru_hidden"]),
            share=bool(mc["share_actor"]),
            agent_heads=bool(mc["actor_agent_heads"]),
            out_hidden=fc_hidden,
            out_gain=0.01,  # near-uniform initial policy (standard for PPO actors)
        )
        self.critic_kind = mc["critic"]
        if not self.inference_only:  # TorchRLModule would delete it anyway (InferenceOnlyAPI)
            in_dim = int(mc["state_dim"]) if self.critic_kind == "central" else self.obs_dim
            self.critic = Critic(
                in_dim,
                int(mc["critic_hidden"]),
                self.n_agents,
                bool(mc["value_norm"]),
                shared=self.critic_kind == "central",
            )

    @override(InferenceOnlyAPI)
    def get_non_inference_attributes(self) -> list[str]:
        return ["critic"]

    @override(RLModule)
    def _forward_train(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        logits, state = self.actor_logits(batch)
        return {Columns.ACTION_DIST_INPUTS: logits, Columns.STATE_OUT: state}

    # ---------------------------------------------------------------- critic
    def critic_input(self, batch: dict[str, Any]) -> torch.Tensor:
        """The global state [..., S] (central; the same for every agent) or each agent's own
        observation row [..., U, d] (local)."""
        if self.critic_kind == "central":
            return batch[GLOBAL_STATE].float()
        return batch[Columns.OBS].float()

    @override(ValueFunctionAPI)
    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        """Per-agent values [B, T, U] in the critic's (normalised, if value_norm) space."""
        return self.critic(self.critic_input(batch))

    def denormalize(self, values: torch.Tensor) -> torch.Tensor:
        vn = self.critic.value_norm
        return values if vn is None else vn.denormalize(values)

    def normalize(self, values: torch.Tensor) -> torch.Tensor:
        vn = self.critic.value_norm
        return values if vn is None else vn.normalize(values)
