"""COMA's learner: whole-episode batches, the critic's TD(lambda) loss, the counterfactual
policy gradient, and the target critic's updates.

Batch: the default learner connectors (time-chunking to max_seq_len, zero padding) are
replaced by `COMAEpisodeBatch`, which stacks B complete episodes of length T into
[B, T(+1), ...] tensors. The actor's GRU is unrolled over the whole episode from a zero state
(exactly what the env runner did while sampling), so no sequence length needs choosing.

One update per sampled batch (on-policy; `updates_per_iteration` > 1 reuses the batch, see below):
  critic loss  = mean_{b,t,u} (Q_u(s_t, a_t,-u)[a_t,u] - G^lambda_t,u)^2, G from the TARGET critic
  actor loss   = -mean_{b,t,u} A_t,u log pi_u(a_t,u | tau_t,u) - entropy_coeff * mean entropy,
                 A_t,u = Q_u(s_t, a_t)[a_t,u] - sum_a' pi_u(a' | tau_t,u) Q_u(s_t, (a_t,-u, a'))
Order within one update: first `critic_steps` (default 4) critic-only Adam steps on the batch
(fixed TD(lambda) targets), so the critic goes first as in the paper; then one joint step:
one backward pass of critic + actor loss (the actor's term sees Q detached, the critic's term
does not involve the actor), two Adam optimizers with their own learning rates and their own
grad-norm clipping, so the advantage comes from the critic after its critic-only steps
(critic_steps = 0: a purely joint step, the advantage from the critic before this batch).
Then the target critic moves: Polyak tau per update, or a hard copy every K updates.
updates_per_iteration = K > 1: the algorithm runs K such updates on one batch; from the second on
the batch is off-policy, so the actor term becomes PPO's clipped surrogate
min(r A, clip(r, 1 -+ ratio_clip) A) with r = pi_u / pi_u,sampling per UAV and step (gradient
A grad log pi at r = 1, as COMA's); the critic's targets are recomputed each update.
Counters (`_updates`: warm-up, hard-update period) restart at 0 after a checkpoint restore.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.utils.annotations import override
from ray.rllib.utils.torch_utils import update_target_network

from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE

from uavlora_rllib.algorithms.coma.coma_module import (
    ACTIONS,
    BOOTSTRAP,
    LOGITS,
    OBS,
    Q_TARGET,
    Q_VALUES,
    REWARDS,
    counterfactual_advantage,
    td_lambda_targets,
)

ACTOR_OPT, CRITIC_OPT = "actor", "critic"
SAMPLED_LOGP = "coma_sampled_logp"  # [B, T, U] log pi_u(a_t,u) of the policy that sampled the batch


class COMAEpisodeBatch(ConnectorV2):
    """Learner connector: B complete episodes -> {module: {obs, actions, rewards, global_state}}."""

    @override(ConnectorV2)
    def __call__(self, *, rl_module, batch, episodes, explore=None, shared_data=None, metrics=None, **kwargs):
        if not episodes:
            raise ValueError("COMA: the learner got no episodes")
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
        logp = np.stack(
            [np.asarray(ep.get_extra_model_outputs(Columns.ACTION_LOGP), dtype=np.float32) for ep in episodes]
        )
        state = np.stack(
            [np.stack([np.asarray(i[GLOBAL_STATE], dtype=np.float32) for i in ep.get_infos()]) for ep in episodes]
        )
        # on the learner's device (a GPU learner): RLlib's default connectors, which would move
        # them, are replaced by this one
        device = next(rl_module[DEFAULT_MODULE_ID].parameters()).device
        cols = {OBS: obs, ACTIONS: actions, REWARDS: rewards, GLOBAL_STATE: state, SAMPLED_LOGP: logp}
        return {DEFAULT_MODULE_ID: {k: torch.from_numpy(v).to(device) for k, v in cols.items()}}


class COMATorchLearner(TorchLearner):
    """Losses of COMA; hyperparameters from the typed config.hparams (COMAHParams, coma.py)."""

    @override(TorchLearner)
    def build(self) -> None:
        super().build()
        self._updates = 0

    def _critic_only_steps(self, module_id, cols: dict[str, Any], steps: int) -> None:
        """`steps` critic-only gradient steps on this batch before the joint step, so that the
        actor's advantage comes from a critic that has already seen the batch (the paper
        trains the critic first). TD(lambda) targets are fixed: the target critic does not
        move within a batch."""
        hp = self.config.hparams
        module = self.module[module_id].unwrapped()
        optim = self.get_optimizer(module_id, CRITIC_OPT)
        params = [p for group in optim.param_groups for p in group["params"]]
        with torch.no_grad():
            fwd = module.forward_train(cols)
            actions = cols[ACTIONS].long()
            q_target_taken = torch.gather(fwd[Q_TARGET], -1, actions.unsqueeze(-1)).squeeze(-1)
            targets = td_lambda_targets(
                cols[REWARDS] * hp.reward_scale, q_target_taken, fwd[BOOTSTRAP], hp.gamma, hp.td_lambda
            )
        obs, state = cols[OBS][:, : actions.shape[1]], cols[GLOBAL_STATE][:, : actions.shape[1]]
        for _ in range(steps):
            q = module.critic_q(module.critic, state, obs, actions)
            loss = ((torch.gather(q, -1, actions.unsqueeze(-1)).squeeze(-1) - targets) ** 2).mean()
            optim.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, hp.grad_clip)
            optim.step()
        self.metrics.log_value((module_id, "critic_loss_before_joint_step"), loss.detach(), window=1)

    @override(TorchLearner)
    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        module = self.module[module_id]
        hp = self.config.hparams
        actor_params = list(module.actor.parameters())
        critic_params = list(module.critic.parameters())
        self.register_optimizer(
            module_id=module_id,
            optimizer_name=ACTOR_OPT,
            optimizer=torch.optim.Adam(actor_params),
            params=actor_params,
            lr_or_lr_schedule=hp.lr_actor,
        )
        self.register_optimizer(
            module_id=module_id,
            optimizer_name=CRITIC_OPT,
            optimizer=torch.optim.Adam(critic_params),
            params=critic_params,
            lr_or_lr_schedule=hp.lr_critic,
        )

    @override(TorchLearner)
    def compute_loss_for_module(self, *, module_id, config, batch: dict[str, Any], fwd_out: dict[str, Any]):
        hp = self.config.hparams
        if hp.critic_steps:
            # the critic goes first: its critic-only steps on this batch, then the joint step's
            # forward pass again, so that the advantage comes from the critic after them. The
            # forward pass RLlib made before this hook (critic before the steps) is discarded,
            # and so are its random draws (the bootstrap's sampled actions): the draws restart
            # from where they stood before the update, so the random stream is the same as
            # with the critic steps run before any forward pass.
            torch.set_rng_state(self._rng_before_update)
            self._critic_only_steps(module_id, batch, hp.critic_steps)
            fwd_out = self.module[module_id].forward_train(batch)
        actions, rewards = batch[ACTIONS].long(), batch[REWARDS] * hp.reward_scale
        steps = actions.shape[1]
        q, q_target = fwd_out[Q_VALUES], fwd_out[Q_TARGET]  # [B, T, U, A]
        # Critic: TD(lambda) targets from the target critic.
        q_target_taken = torch.gather(q_target, -1, actions.unsqueeze(-1)).squeeze(-1)  # [B, T, U]
        targets = td_lambda_targets(
            rewards, q_target_taken, fwd_out[BOOTSTRAP], hp.gamma, hp.td_lambda
        ).detach()
        q_taken = torch.gather(q, -1, actions.unsqueeze(-1)).squeeze(-1)
        critic_loss = ((q_taken - targets) ** 2).mean()
        # Actor: counterfactual advantage with the (detached) critic.
        logits = fwd_out[LOGITS][:, :steps]  # [B, T, U, A]
        logp_all = torch.log_softmax(logits, dim=-1)
        pi = logp_all.exp()
        adv, baseline, _ = counterfactual_advantage(q, pi, actions)
        if hp.normalize_advantages:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        logp = torch.gather(logp_all, -1, actions.unsqueeze(-1)).squeeze(-1)
        entropy = -(pi * logp_all).sum(-1).mean()
        if hp.updates_per_iteration > 1:
            # the batch is reused: PPO's clipped surrogate per UAV around the sampling policy
            # (on the first update r = 1 and its gradient is COMA's A grad log pi)
            ratio = torch.exp(logp - batch[SAMPLED_LOGP])
            surrogate = torch.min(ratio * adv, ratio.clamp(1 - hp.ratio_clip, 1 + hp.ratio_clip) * adv)
            clip_fraction = ((ratio - 1).abs() > hp.ratio_clip).float().mean().detach()
        else:
            surrogate, clip_fraction = adv * logp, torch.zeros(())
        actor_loss = -surrogate.mean() - hp.entropy_coeff * entropy
        if self._updates < hp.critic_warmup_updates:
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
    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        super().before_gradient_based_update(timesteps=timesteps)
        self._rng_before_update = torch.get_rng_state()  # see compute_loss_for_module

    @override(TorchLearner)
    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        super().after_gradient_based_update(timesteps=timesteps)
        hp = self.config.hparams
        self._updates += 1
        hard_every = hp.target_hard_update_every
        for module_id in self.module.keys():
            module = self.module[module_id].unwrapped()
            if hard_every:
                if self._updates % hard_every == 0:
                    update_target_network(main_net=module.critic, target_net=module.target_critic, tau=1.0)
            else:
                update_target_network(main_net=module.critic, target_net=module.target_critic, tau=hp.tau)
            self.metrics.log_value((module_id, "num_critic_updates"), self._updates, window=1)
