"""TD learner of QMIX/VDN: n-step double-Q targets through the (target) mixer, soft target updates.

Loss (per update, over B whole episodes of T steps):
  y_t = sum_{k<m} gamma^k r_{t+k} + gamma^m (1 - d) Q_tot^target(s_{t+m}, argmax_a Q^online(o_{t+m}))
  with m = min(n_step, T - t); d = 1 only when the episode TERMINATED at t+m = T. A truncation
  (this project's only episode end) bootstraps from the final observation/state. With `reward_norm`
  r is the reward standardised by its running mean and std (updated with each batch first).
  L = mean_{b,t} w_t (Q_tot(s_t, a_t) - y_t)^2, w_t = 1 where y_t >= Q_tot, else `negative_td_weight`
  (1 by default: plain QMIX/VDN; below 1 the optimistic weighting of hysteretic Q-learning and OW-QMIX)
After every gradient update: target <- (1 - tau) target + tau online (agent network and mixer).
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.core.rl_module.apis import QNetAPI
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common.columns import TERMINATED
from uavlora_rllib.algorithms.common.target_learner import TargetNetworkLearner
from uavlora_rllib.algorithms.qmix.qmix_module import Q_TAKEN, Q_TOT, TARGET_Q_TOT_NEXT

TD_LOSS = "td_loss"
NUM_TARGET_UPDATES = "num_soft_target_updates"


def nstep_targets(
    rewards: torch.Tensor, next_values: torch.Tensor, terminated: torch.Tensor, gamma: float, n_step: int
) -> torch.Tensor:
    """rewards [B, T], next_values[:, j] = target Q_tot at s_{j+1} [B, T], terminated [B] -> y [B, T]."""
    b, t = rewards.shape
    n = max(int(n_step), 1)
    padded = torch.cat([rewards, rewards.new_zeros(b, n)], dim=1)
    ret = torch.zeros_like(rewards)
    for k in range(n):  # rewards past T are the zero padding
        ret = ret + (gamma**k) * padded[:, k : k + t]
    steps = torch.arange(t, device=rewards.device)
    last = torch.clamp(steps + n, max=t) - 1  # index into next_values of the bootstrap state
    m = (last + 1 - steps).to(rewards.dtype)
    boot = next_values.gather(1, last.expand(b, t))
    done = terminated.to(torch.bool).view(b, 1) & (last == t - 1).view(1, t)
    return ret + torch.pow(torch.full_like(m, gamma), m).view(1, t) * boot * (~done).to(rewards.dtype)


def td_targets(
    rewards: torch.Tensor, fwd_out: dict[str, Any], terminated: torch.Tensor, gamma: float, n_step: int
) -> torch.Tensor:
    """The TD targets y [B, T]: n-step ones from the module's TARGET_Q_TOT_NEXT, or at gamma 0 the rewards
    themselves (the module leaves the target networks unevaluated then: QMixModule.target_terms)."""
    if gamma == 0.0:
        return rewards
    return nstep_targets(rewards, fwd_out[TARGET_Q_TOT_NEXT].detach(), terminated, gamma, n_step)


class QMIXTorchLearner(TargetNetworkLearner):
    """TD loss above; hyperparameters from the typed config.hparams (QMIXHParams)."""

    @override(TorchLearner)
    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        params = [p for p in self.module[module_id].parameters() if p.requires_grad]  # agent net + mixer
        self.register_adam(module_id, params, config.lr)

    @override(TorchLearner)
    def compute_loss_for_module(self, *, module_id, config, batch: dict[str, Any], fwd_out: dict[str, Any]):
        rewards = batch[Columns.REWARDS].float()
        norm = self.module[module_id].unwrapped().reward_norm
        if norm is not None:  # `reward_norm`: targets in standardised reward units
            norm.update(rewards)
            rewards = norm.normalize(rewards)
        q_tot = fwd_out[Q_TOT]
        y = td_targets(rewards, fwd_out, batch[TERMINATED], config.gamma, config.hparams.n_step)
        td = q_tot - y
        # optimistic weighting: an over-estimate (target below Q_tot) counts negative_td_weight (1: plain TD)
        loss = (torch.where(td > 0, config.hparams.negative_td_weight, 1.0) * td**2).mean()
        self.metrics.log_dict(
            {
                TD_LOSS: loss.detach(),
                "td_error_abs_mean": td.detach().abs().mean(),
                "q_taken_mean": fwd_out[Q_TAKEN].detach().mean(),
                "q_tot_mean": q_tot.detach().mean(),
                "target_mean": y.mean(),
            },
            key=module_id,
            window=1,
        )
        return loss

    @override(TorchLearner)
    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        super().after_gradient_based_update(timesteps=timesteps)
        for module_id in self.module.keys():
            self.update_target_networks(module_id, self.config.get_config_for_module(module_id).hparams.tau)
            self.metrics.log_value((module_id, NUM_TARGET_UPDATES), 1, reduce="lifetime_sum")

    @classmethod
    @override(TargetNetworkLearner)
    def rl_module_required_apis(cls) -> list[type]:
        return [QNetAPI, *super().rl_module_required_apis()]
