"""COMA's learner: the critic's TD(lambda) loss, the counterfactual policy gradient, the
critic-only steps and the target critic's updates.

Batch (`episode_batch`, built by the algorithm from B complete episodes of length T): obs
[B, T+1, U, d], actions [B, T, U], rewards [B, T], global state [B, T+1, S] and the sampling
policy's log-probabilities [B, T, U]. The actor's GRU is unrolled over the whole episode from a
zero state (exactly what the env runner did while sampling), so no sequence length needs choosing.

One update on a batch (on-policy; `updates_per_iteration` > 1 reuses the batch, see below):
  critic loss  = mean_{b,t,u} (Q_u(s_t, a_t,-u)[a_t,u] - G^lambda_t,u)^2, G from the TARGET critic
                 (at gamma 0, G_t = r_t: the target critic is then not evaluated, `critic_targets`)
  actor loss   = -mean_{b,t,u} A_t,u log pi_u(a_t,u | tau_t,u) - entropy_coeff * mean entropy,
                 A_t,u = Q_u(s_t, a_t)[a_t,u] - sum_a' pi_u(a' | tau_t,u) Q_u(s_t, (a_t,-u, a'))
                 (`taken_value: return`: G^lambda_t in place of Q_u(s_t, a_t)[a_t,u], `sampled_advantage`)
Order within one update: first `critic_steps` (default 4) critic-only Adam steps on the batch
(`train_critic`, fixed TD(lambda) targets), so the critic goes first as in the paper; then one
learner update, the joint step: one backward pass of critic + actor loss (the actor's term sees
Q detached, the critic's term does not involve the actor), two Adam optimizers with their own
learning rates and their own grad-norm clipping, so the advantage comes from the critic after
its critic-only steps (critic_steps = 0: a purely joint step, the advantage from the critic
before this batch). Then the target critic moves: Polyak tau per update, or a hard copy every
K updates.
updates_per_iteration = K > 1: the algorithm runs K such updates on one batch; from the second on
the batch is off-policy, so the actor term becomes PPO's clipped surrogate
min(r A, clip(r, 1 -+ ratio_clip) A) with r = pi_u / pi_u,sampling per UAV and step (gradient
A grad log pi at r = 1, as COMA's); the critic's targets are recomputed each update, once: its
critic-only steps compute them and its joint step trains on the same (TD_TARGETS; with several
learners each trains on the first one's, which share its target critic), except where the joint
step draws its own critic rows (per_device, critic_branch_fraction < 1) or there are no critic-only
steps. Its actor forward is likewise the critic-only steps' (one learner: `keep_episode_logits`).
per_device (branching.py, docs/model.md#coma-per-device): every branch l of every UAV u is a row
of its own: the critic loss over all rows (u, l) (with critic_branch_fraction < 1 over a random
subset of them, drawn per update), A_t,u,l with the baseline over pi_u,l, the
actor loss -mean_{b,t,u} sum_l A_t,u,l log pi_u,l(a_t,u,l), the entropy of the product policy
(summed over a UAV's branches) and, when the batch is reused, one clipped ratio per branch.
Counters (`updates`: warm-up, hard-update period) restart at 0 after a checkpoint restore.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.policy.sample_batch import MultiAgentBatch
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.coma.branching import BRANCH_LOGP
from uavlora_rllib.algorithms.coma.coma_module import (
    ACTIONS,
    BOOTSTRAP,
    CRITIC_ROWS,
    LOGITS,
    OBS,
    Q_ROWS,
    Q_TARGET,
    Q_VALUES,
    REWARDS,
    TD_TARGETS,
    counterfactual_advantage,
    td_lambda_targets,
)
from uavlora_rllib.algorithms.common.action_head import taken
from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.target_learner import TargetNetworkLearner

ACTOR_OPT, CRITIC_OPT = "actor", "critic"
# [B, T, U] log pi_u(a_t,u) of the policy that sampled the batch (per_device: [B, T, U, L], per branch)
SAMPLED_LOGP = "coma_sampled_logp"


def lambda_returns(
    rewards: torch.Tensor, q_target_taken: torch.Tensor, bootstrap: torch.Tensor, gamma: float, lam: float
) -> torch.Tensor:
    """`td_lambda_targets` for every critic row: q_target_taken [B, T, ...] (per UAV, or per UAV
    and branch in per_device) with bootstrap [B, ...]; the trailing axes are flattened into the
    agent axis and restored."""
    out = td_lambda_targets(rewards, q_target_taken.flatten(2), bootstrap.flatten(1), gamma, lam)
    return out.view_as(q_target_taken)


def critic_targets(
    rewards: torch.Tensor, fwd: dict[str, Any], row_actions: torch.Tensor, gamma: float, lam: float
) -> torch.Tensor:
    """The critic's TD(lambda) targets [B, T, *rows] at the taken values `row_actions` [B, T, *rows],
    from the target critic's outputs in `fwd` (Q_TARGET, BOOTSTRAP). At gamma 0 every target is the
    step's reward, exactly what `lambda_returns` gives then, and the target critic is not evaluated
    (the module leaves Q_TARGET out): the per_device grids train at gamma 0."""
    if gamma == 0.0:
        return rewards[(...,) + (None,) * (row_actions.dim() - 2)].expand(row_actions.shape)
    return lambda_returns(rewards, taken(fwd[Q_TARGET], row_actions), fwd[BOOTSTRAP], gamma, lam)


def sampled_advantage(targets: torch.Tensor, baseline: torch.Tensor) -> torch.Tensor:
    """The advantage with the return in place of the critic's taken value (`taken_value: return`):
    G_t - b_u(s_t, a_t,-u) per UAV (per_device per branch), b the counterfactual baseline [B, T, *rows].
    G_t is the mean of the step's TD(lambda) targets over the critic rows trained (all estimate the same
    joint return; at gamma 0 each is r_t). b does not depend on the row's own action, so the gradient
    stays unbiased whatever the critic (Kuba et al., NeurIPS 2021); docs/model.md#coma-per-device."""
    ret = targets.flatten(2).mean(-1)  # [B, T]
    return ret[(...,) + (None,) * (baseline.dim() - 2)] - baseline


def episode_batch(episodes: list) -> dict[str, np.ndarray]:
    """B complete episodes of one length T -> the train batch's columns (see the module docstring)."""
    if not episodes:
        raise ValueError("COMA: no episodes to learn from")
    lengths = {len(ep) for ep in episodes}
    partial = [ep for ep in episodes if ep.t_started != 0 or not ep.is_done]
    if len(lengths) != 1 or partial:
        raise ValueError(
            f"COMA learns from whole episodes of one length; got lengths {sorted(lengths)} and "
            f"{len(partial)} partial chunk(s) (batch_episodes must be a multiple of the env runners' envs)"
        )
    obs = np.stack([np.asarray(ep.get_observations(), dtype=np.float32) for ep in episodes])
    actions = np.stack([np.asarray(ep.get_actions(), dtype=np.int64) for ep in episodes])
    rewards = np.stack([np.asarray(ep.get_rewards(), dtype=np.float32) for ep in episodes])
    # the sampling policy's per-UAV log-probabilities: the ratio's denominator when the
    # batch is reused (updates_per_iteration > 1)
    # (per_device, actions [B, T, U, L]: per branch, the per-branch ratio's denominator)
    logp_column = BRANCH_LOGP if actions.ndim == 4 else Columns.ACTION_LOGP
    logp = np.stack([np.asarray(ep.get_extra_model_outputs(logp_column), dtype=np.float32) for ep in episodes])
    state = np.stack(
        [np.stack([np.asarray(i[GLOBAL_STATE], dtype=np.float32) for i in ep.get_infos()]) for ep in episodes]
    )
    return {OBS: obs, ACTIONS: actions, REWARDS: rewards, GLOBAL_STATE: state, SAMPLED_LOGP: logp}


class COMATorchLearner(TargetNetworkLearner):
    """Losses of COMA; hyperparameters from the typed config.hparams (COMAHParams, coma.py)."""

    @override(TargetNetworkLearner)
    def build(self) -> None:
        super().build()
        self.updates = 0  # joint updates so far: the warm-up and the hard target period count them

    def train_critic(self, batch: MultiAgentBatch) -> dict[str, np.ndarray]:
        """`critic_steps` critic-only gradient steps on `batch` before its joint update, so that
        the actor's advantage comes from a critic that has already seen the batch (the paper
        trains the critic first). TD(lambda) targets are fixed: the target critic does not
        move within a batch. Each step goes through the Learner's compute_gradients /
        postprocess_gradients (grad clipping) / apply_gradients; the actor gets no gradient,
        so its optimizer leaves it as it is. Returns each module's targets [B, T, *rows] where
        they cover every critic row (all but per_device with critic_branch_fraction < 1): the
        joint step of the same update trains on them (TD_TARGETS)."""
        with self.precision():  # the trial's learner_precision, as the joint step's
            return self._train_critic(batch)

    def _train_critic(self, batch: MultiAgentBatch) -> dict[str, np.ndarray]:
        hp = self.config.hparams
        out = {}
        for module_id, columns in batch.policy_batches.items():
            module = self.module[module_id].unwrapped()
            cols = {k: torch.as_tensor(np.asarray(v)).to(self.device) for k, v in columns.items()}
            actions = cols[ACTIONS].long()
            rows = module.draw_critic_rows()  # this update's critic rows (None: all)
            row_actions = module.row_values(actions, rows)
            # the actor's logits (the bootstrap's policy), with gradient where the joint step reuses them:
            # with several learners it trains on a share of the batch, other observations than these
            keep = self.config.num_learners <= 1
            with torch.set_grad_enabled(keep):
                logits = module.episode_logits(cols[OBS])
            if keep:
                module.keep_episode_logits(cols[OBS], logits)
            # the target critic's side only (fixed for the batch): the critic itself is evaluated per step below
            fwd = module.target_terms({**cols, CRITIC_ROWS: rows}, logits.detach())
            targets = critic_targets(cols[REWARDS] * hp.reward_scale, fwd, row_actions, hp.gamma, hp.td_lambda)
            # copied once for the critic_steps evaluations (a slice of the T + 1 slots would be copied by each)
            obs, state = (cols[k][:, : actions.shape[1]].contiguous() for k in (OBS, GLOBAL_STATE))
            for _ in range(hp.critic_steps):
                q = module.critic_q(module.critic, state, obs, actions, rows)
                loss = ((taken(q, row_actions) - targets) ** 2).mean()
                grads = self.compute_gradients({module_id: loss})
                self.apply_gradients(self.postprocess_gradients({k: g for k, g in grads.items() if g is not None}))
            self.metrics.log_value((module_id, "critic_loss_before_joint_step"), loss.detach(), window=1)
            if rows is None:
                out[module_id] = targets.detach().contiguous().cpu().numpy()
        return out

    @override(TorchLearner)
    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        module = self.module[module_id]
        hp = self.config.hparams
        for name, net, lr in ((ACTOR_OPT, module.actor, hp.lr_actor), (CRITIC_OPT, module.critic, hp.lr_critic)):
            self.register_adam(module_id, list(net.parameters()), lr, name=name)

    @override(TorchLearner)
    def compute_loss_for_module(self, *, module_id, config, batch: dict[str, Any], fwd_out: dict[str, Any]):
        hp = self.config.hparams
        actions, rewards = batch[ACTIONS].long(), batch[REWARDS] * hp.reward_scale
        steps = actions.shape[1]
        module = self.module[module_id].unwrapped()
        # [B, T, U, A] (per_uav) or [B, T, U, L, W] (per_device: one row per branch of a UAV)
        q = fwd_out[Q_VALUES]
        # Critic: TD(lambda) targets from the target critic, on the rows it trains (all, or per_device
        # the update's random subset: Q_ROWS, Q_TARGET [B, T, K, W])
        row_actions = module.row_values(actions, fwd_out[CRITIC_ROWS])
        # [B, T, U], [B, T, U, L] or [B, T, K]
        if TD_TARGETS in fwd_out:  # the critic-only steps' own (train_critic, passed on by forward_train)
            targets = fwd_out[TD_TARGETS]
        else:
            targets = critic_targets(rewards, fwd_out, row_actions, hp.gamma, hp.td_lambda).detach()
        q_taken = taken(fwd_out[Q_ROWS], row_actions)
        critic_loss = ((q_taken - targets) ** 2).mean()
        # Actor: counterfactual advantage with the (detached) critic, per UAV (per branch).
        logits = fwd_out[LOGITS][:, :steps]  # [B, T, U, n_logits]
        pi, logp, entropy = module.policy_terms(logits, actions)
        adv, baseline, _ = counterfactual_advantage(q, pi, actions)
        if hp.taken_value == "return":
            adv = sampled_advantage(targets, baseline)
        if hp.normalize_advantages:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        entropy = entropy.mean()
        if hp.updates_per_iteration > 1:
            # the batch is reused: PPO's clipped surrogate per UAV around the sampling policy
            # (on the first update r = 1 and its gradient is COMA's A grad log pi)
            # (per_device: per branch, each branch's ratio clipped on its own)
            ratio = torch.exp(logp - batch[SAMPLED_LOGP])
            surrogate = torch.min(ratio * adv, ratio.clamp(1 - hp.ratio_clip, 1 + hp.ratio_clip) * adv)
            clip_fraction = ((ratio - 1).abs() > hp.ratio_clip).float().mean().detach()
        else:
            surrogate, clip_fraction = adv * logp, torch.zeros(())
        # per_device: the branches' terms summed per UAV (the product policy's gradient)
        actor_loss = -module.per_agent(surrogate).mean() - hp.entropy_coeff * entropy
        if self.updates < hp.critic_warmup_updates:
            actor_loss = actor_loss * 0.0  # critic only: the advantage is meaningless before it fits
        self.metrics.log_dict(
            {
                "critic_loss": critic_loss.detach(),
                "actor_loss": actor_loss.detach(),
                "entropy": entropy.detach(),
                "q_taken_mean": q_taken.detach().mean(),
                "td_target_mean": targets.mean(),
                "advantage_abs_mean": adv.detach().abs().mean(),
                "baseline_mean": baseline.mean(),
                "clip_fraction": clip_fraction,
            },
            key=module_id,
            window=1,
        )
        return critic_loss + actor_loss

    @override(TorchLearner)
    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        super().after_gradient_based_update(timesteps=timesteps)
        hp = self.config.hparams
        self.updates += 1
        hard_every = hp.target_hard_update_every
        if hard_every and self.updates % hard_every:
            tau = None  # a hard copy every K updates only
        else:
            tau = 1.0 if hard_every else hp.tau
        for module_id in self.module.keys():
            if tau is not None:
                self.update_target_networks(module_id, tau)
            self.metrics.log_value((module_id, "num_critic_updates"), self.updates, window=1)
