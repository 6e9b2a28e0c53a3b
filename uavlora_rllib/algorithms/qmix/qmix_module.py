"""The QMIX/VDN RLModule: recurrent per-UAV Q-network, mixer, and their target copies.

Shapes (one team = one row of the batch; U UAVs, d = obs_dim, A = actions per UAV, S = state_dim):
  obs     [B, T, U, d]   each UAV's LOCAL observation (row u of the team view)
  state   [B, T, S]      global state (mixer only, never read by the agent network)
  h       [B, U, H]      GRU hidden state, H = gru_hidden
  q       [B, T, U, A]   per-UAV Q-values

Agent network: the common `RecurrentAgentNet` (one per UAV by default; shared with share_agent_net=True):
  [o_u ; one-hot(u)] -> Linear(fc_hidden) -> ReLU -> GRU(gru_hidden) -> Linear(A)
The one-hot id is only appended when the network is shared. This module acts in per_uav mode;
per_device mode (an action vector per UAV) is `BranchingQMixModule` (branching_module.py), the
same mixers over a factored agent network.

Mixers (Rashid et al. 2018/2020):
  vdn:  Q_tot = sum_u Q_u + V(s)
  qmix: Q_tot = |W2(s)|^T ELU(|W1(s)|^T q + b1(s)) + V(s); W1, W2 from 2-layer hypernetworks
        (hypernet_embed_dim), b1 from one linear layer. Absolute weights make dQ_tot/dQ_u >= 0
        (monotonic).
  V(s), a 2-layer MLP (mixing_embed_dim), is there with state_bias (default); VDN with it is the
  "VDN-S" of Rashid et al.'s ablation. It takes the state's value, which the UAVs' local Q-values
  cannot split among themselves; execution (argmax of each Q_u) never reads it.

On env runners the module is built inference-only: the mixer and every target network are
dropped (InferenceOnlyAPI), so decentralised execution only ever holds the agent network.
Env runners call it one step at a time with the GRU state carried by RLlib's connectors
(Columns.STATE_IN/STATE_OUT, zero at every episode start: `get_initial_state`).
"""

from __future__ import annotations

from typing import Any, cast

import torch
import torch.nn.functional as F
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, QNetAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.rl_module import RLModule
from ray.rllib.core.rl_module.torch import TorchRLModule
from ray.rllib.utils.annotations import override
from torch import nn

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, HIDDEN
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process
from uavlora_rllib.algorithms.common.value_norm import ValueNorm

Q_ALL = "q_all"  # [B, T+1, U, A] online Qs over the whole sequence
Q_TAKEN = "q_taken"  # [B, T, U] online Q of the action taken
Q_TOT = "q_tot"  # [B, T] mixed online Q of the joint action taken
TARGET_Q_TOT_NEXT = "target_q_tot_next"  # [B, T] target Q_tot at s_{t+1} (double-Q action)


def linear_epsilon(t: int | float, start: float, end: float, anneal_steps: int | float) -> float:
    """Epsilon after t env steps: linear from start to end over anneal_steps, then end."""
    if anneal_steps <= 0:
        return float(end)
    frac = min(max(float(t) / float(anneal_steps), 0.0), 1.0)
    return float(start + frac * (end - start))


def _state_value(state_dim: int, embed_dim: int) -> nn.Sequential:
    """V(s): the state-dependent bias of both mixers."""
    return nn.Sequential(nn.Linear(state_dim, embed_dim), nn.ReLU(), nn.Linear(embed_dim, 1))


class VDNMixer(nn.Module):
    """Sum of the UAVs' Q-values, plus V(s) with state_bias (VDN-S); without it the state is unused."""

    def __init__(self, state_dim: int = 0, embed_dim: int = 32, state_bias: bool = False):
        super().__init__()
        self.v = _state_value(state_dim, embed_dim) if state_bias else None

    @override(nn.Module)
    def forward(self, q: torch.Tensor, state: torch.Tensor, first: int = 0) -> torch.Tensor:
        """q [B, T, U], state [B, T', S] -> Q_tot [B, T] on the states first .. first + T - 1 (_state_rows)."""
        if q.dim() != 3:
            raise ValueError(f"q: expected [B, T, U], got {tuple(q.shape)}")
        total = q.sum(dim=-1)
        if self.v is None:
            _state_rows(state, first, q.shape[1])  # unread, but the same rows must exist
            return total
        return total + _state_rows(self.v(state), first, q.shape[1]).squeeze(-1).float()  # (common/precision.py)


def _state_rows(per_state: torch.Tensor, first: int, n_t: int) -> torch.Tensor:
    """Rows first .. first + n_t - 1 of a per-state output [B, T', k]. The mixers run their state layers on the
    whole sequence and slice the narrow output: slicing the wide state [B, T', S] first would copy it (the
    online mixer reads s_0 .. s_{T-1}, the target mixer s_1 .. s_T; docs/model.md#qmix-mixer-cost). So every
    state row must be finite, the unused ones too (an inf there would give 0 x inf in the weight gradients)."""
    if per_state.dim() != 3:
        raise ValueError(f"state: expected [B, T', S], got {tuple(per_state.shape)}")
    if first < 0 or first + n_t > per_state.shape[1]:
        raise ValueError(
            f"first: states {first} .. {first + n_t - 1} asked of a sequence of {per_state.shape[1]} states"
        )
    return per_state[:, first : first + n_t]


class QMixer(nn.Module):
    """Monotonic mixing network with hypernetworks on the global state."""

    def __init__(
        self, n_agents: int, state_dim: int, embed_dim: int = 32, hypernet_embed: int = 64, state_bias: bool = True
    ):
        super().__init__()
        self.n_agents, self.embed_dim = n_agents, embed_dim
        self.hyper_w1 = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, n_agents * embed_dim)
        )
        self.hyper_b1 = nn.Linear(state_dim, embed_dim)
        self.hyper_w2 = nn.Sequential(
            nn.Linear(state_dim, hypernet_embed), nn.ReLU(), nn.Linear(hypernet_embed, embed_dim)
        )
        self.v = _state_value(state_dim, embed_dim) if state_bias else None

    def _state_layers(self) -> list[nn.Linear]:
        """The layers that read the state: the first of hyper_w1, hyper_b1, hyper_w2 and V(s)."""
        first = [self.hyper_w1[0], self.hyper_b1, self.hyper_w2[0]] + ([self.v[0]] if self.v is not None else [])
        return cast(list[nn.Linear], first)

    @override(nn.Module)
    def forward(self, q: torch.Tensor, state: torch.Tensor, first: int = 0) -> torch.Tensor:
        """q [B, T, U], state [B, T', S] -> Q_tot [B, T] on the states first .. first + T - 1 (_state_rows).
        The four layers that read the state run as ONE product with their weights side by side, so the wide
        state is read once per pass, not four times (docs/model.md#qmix-mixer-cost)."""
        if q.dim() != 3 or state.dim() != 3:
            raise ValueError(f"q, state: expected [B, T, U] and [B, T', S], got {tuple(q.shape)}, {tuple(state.shape)}")
        lead = q.shape[:-1]
        layers = self._state_layers()
        weight = torch.cat([layer.weight for layer in layers])
        bias = torch.cat([layer.bias for layer in layers])
        terms = _state_rows(F.linear(state, weight, bias), first, q.shape[1]).reshape(-1, weight.shape[0])
        parts = terms.split([layer.out_features for layer in layers], dim=-1)
        qf = q.reshape(-1, 1, self.n_agents)
        w1 = self.hyper_w1[2](torch.relu(parts[0])).abs().view(-1, self.n_agents, self.embed_dim)
        hidden = F.elu(torch.bmm(qf, w1) + parts[1].unsqueeze(1))
        w2 = self.hyper_w2[2](torch.relu(parts[2])).abs().view(-1, self.embed_dim, 1)
        y = torch.bmm(hidden, w2).view(-1)
        if self.v is not None:
            y = y + self.v[2](torch.relu(parts[3])).view(-1)
        return y.view(lead).float()  # float32 under autocast too (common/precision.py)


def make_mixer(
    kind: str, n_agents: int, state_dim: int, embed_dim: int, hypernet_embed: int, state_bias: bool = True
) -> nn.Module:
    if kind == "vdn":
        return VDNMixer(state_dim, embed_dim, state_bias=state_bias)
    if kind == "qmix":
        return QMixer(n_agents, state_dim, embed_dim, hypernet_embed, state_bias=state_bias)
    raise ValueError(f"mixer: expected 'qmix' or 'vdn', got {kind!r}")


class QMixModule(TorchRLModule, QNetAPI, TargetNetworkAPI, InferenceOnlyAPI):
    """model_config: QMIXHParams' fields plus n_agents, obs_dim, n_actions, state_dim, mixer,
    epsilon_anneal_env_steps, torch_threads (common/config.py)."""

    @override(TorchRLModule)
    def setup(self) -> None:
        mc = self.model_config
        setup_torch_process(mc["torch_threads"])
        self.n_agents = int(mc["n_agents"])
        self.n_actions = int(mc["n_actions"])
        self.gru_hidden = int(mc["gru_hidden"])
        self.double_q = bool(mc["double_q"])
        # 0: every TD target is the reward, so the target networks are not evaluated (target_terms)
        self.gamma = float(mc["gamma"])
        self.agent = self._make_agent()
        # The mixer is built here and removed again on inference-only (env runner) copies.
        self.mixer = make_mixer(
            str(mc["mixer"]),
            self.n_agents,
            int(mc["state_dim"]),
            int(mc["mixing_embed_dim"]),
            int(mc["hypernet_embed_dim"]),
            state_bias=bool(mc["state_bias"]),
        )
        # The running reward standardiser of the TD targets (`reward_norm`), read by the learner only (a
        # checkpoint from before the option gets its default, off: HParamsConfig._model_config_auto_includes)
        self.reward_norm = ValueNorm() if bool(mc["reward_norm"]) else None
        self._eps = (float(mc["epsilon_start"]), float(mc["epsilon_end"]), float(mc["epsilon_anneal_env_steps"]))

    def _make_agent(self) -> nn.Module:
        """The agent network (built before the mixer): one Q-value per joint per_uav action."""
        mc = self.model_config
        return RecurrentAgentNet(
            int(mc["obs_dim"]),
            self.n_agents,
            self.n_actions,
            fc_hidden=int(mc["fc_hidden"]),
            gru_hidden=self.gru_hidden,
            share=bool(mc["share_agent_net"]),
        )

    # ------------------------------------------------------------------ recurrent state
    @override(RLModule)
    def get_initial_state(self) -> dict[str, Any]:
        return {HIDDEN: torch.zeros(self.n_agents, self.gru_hidden)}

    def epsilon(self, t: int | float | None) -> float:
        """Exploration epsilon after t env steps; t None (no training clock, e.g. sampled
        execution after training): the end of the schedule, epsilon_end."""
        return self._eps[1] if t is None else linear_epsilon(t, *self._eps)

    # ------------------------------------------------------------------ acting (env runners)
    def _step(self, batch: dict[str, Any]) -> tuple[Any, torch.Tensor]:
        """Greedy-ready Qs of one step: obs [B, 1, U, d] (or [B, U, d]) -> q [B, U, A], h [B, U, H]."""
        obs = batch[Columns.OBS].float()
        if obs.dim() == 3:
            obs = obs.unsqueeze(1)
        h0 = batch[Columns.STATE_IN][HIDDEN]
        q, h = self.agent(obs, h0)
        return q[:, -1], h

    @override(RLModule)
    def _forward_inference(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        with torch.no_grad():
            q, h = self._step(batch)
            return {Columns.ACTIONS: q.argmax(-1).unsqueeze(1), Columns.STATE_OUT: {HIDDEN: h}}

    @override(RLModule)
    def _forward_exploration(self, batch: dict[str, Any], t: int | None = None, **kwargs) -> dict[str, Any]:
        """Epsilon-greedy per UAV. RLlib's env runners pass t (env steps sampled so far);
        without it (sampled execution of a trained policy) epsilon is epsilon_end."""
        with torch.no_grad():
            q, h = self._step(batch)
            greedy = q.argmax(-1)
            eps = self.epsilon(t)
            rand = torch.randint(0, self.n_actions, greedy.shape, device=greedy.device)
            explore = torch.rand(greedy.shape, device=greedy.device) < eps  # each UAV on its own
            actions = torch.where(explore, rand, greedy)
            return {Columns.ACTIONS: actions.unsqueeze(1), Columns.STATE_OUT: {HIDDEN: h}}

    # ------------------------------------------------------------------ learning
    def _zero_h(self, obs: torch.Tensor) -> torch.Tensor:
        return obs.new_zeros(obs.shape[0], self.n_agents, self.gru_hidden)

    @override(QNetAPI)
    def compute_q_values(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Online per-UAV Qs over whole sequences, GRU started at zero: obs [B, T, U, d]."""
        obs = batch[Columns.OBS].float()
        q, _ = self.agent(obs, self._zero_h(obs))
        return {Q_ALL: q}

    @override(RLModule)
    def _forward_train(self, batch: dict[str, Any], **kwargs) -> dict[str, Any]:
        """Batch of whole episodes: obs [B, T+1, U, d], actions [B, T, U], state [B, T+1, S]."""
        q_all = self.compute_q_values(batch)[Q_ALL]
        actions = batch[Columns.ACTIONS].long()
        n_t = actions.shape[1]
        q_taken = q_all[:, :n_t].gather(-1, actions.unsqueeze(-1)).squeeze(-1)
        state = batch[GLOBAL_STATE].float()
        q_tot = self.mixer(q_taken, state)
        return {Q_ALL: q_all, Q_TAKEN: q_taken, Q_TOT: q_tot, **self.target_terms({**batch, Q_ALL: q_all.detach()})}

    def target_terms(self, batch: dict[str, Any]) -> dict[str, Any]:
        """forward_target's TARGET_Q_TOT_NEXT without gradient, or {} at gamma 0: every TD target is then
        the reward (qmix_learner.td_targets) and the target agent network and mixer are never read."""
        if self.gamma == 0.0:
            return {}
        with torch.no_grad():
            return {TARGET_Q_TOT_NEXT: self.forward_target(batch)[TARGET_Q_TOT_NEXT]}

    # ------------------------------------------------------------------ target networks
    @override(TargetNetworkAPI)
    def make_target_networks(self) -> None:
        self._target_agent = make_target_network(self.agent)
        self._target_mixer = make_target_network(self.mixer)

    @override(TargetNetworkAPI)
    def get_target_network_pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        return [(self.agent, self._target_agent), (self.mixer, self._target_mixer)]

    @override(TargetNetworkAPI)
    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Target Q_tot at s_{t+1}, t = 0..T-1. Double Q: the ONLINE agent net picks the
        argmax at t+1 (batch[Q_ALL] if given), the target agent net evaluates it, and the
        target mixer mixes on s_{t+1}. The last transition bootstraps from the final
        observation/state (truncation is not termination)."""
        obs = batch[Columns.OBS].float()
        state = batch[GLOBAL_STATE].float()
        tq_all, _ = self._target_agent(obs, self._zero_h(obs))
        nxt = tq_all[:, 1:]
        if self.double_q:
            online = batch.get(Q_ALL)
            if online is None:
                online = self.compute_q_values(batch)[Q_ALL]
            a_star = online[:, 1:].argmax(-1, keepdim=True)
            tq_next = nxt.gather(-1, a_star).squeeze(-1)
        else:
            tq_next = nxt.max(-1).values
        return {TARGET_Q_TOT_NEXT: self._target_mixer(tq_next, state, first=1)}

    # ------------------------------------------------------------------ inference-only
    @override(InferenceOnlyAPI)
    def get_non_inference_attributes(self) -> list[str]:
        return ["mixer", "_target_agent", "_target_mixer"]
