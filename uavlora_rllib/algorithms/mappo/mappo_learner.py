"""MAPPO / IPPO learner: the learner-connector pieces and the per-agent clipped PPO loss.

Learner pipeline (RLlib's defaults plus three pieces of this module's learner):

    AddOneTsToEpisodesAndTruncate        (RLlib: one phantom step per episode chunk whose
                                          observation/info is the chunk's FINAL one, for
                                          bootstrapping; loss mask False there)
    AddGlobalStateToBatch                (here, central critic only: info["state"] -> "state")
    ... RLlib defaults: observations, other columns, zero-padding to max_seq_len, GRU
        STATE_IN at each sequence start (from the rollout's stored STATE_OUT), batching,
        tensors ...
    PerAgentGAE                          (here: V [B, T, U], per-agent GAE on the shared
                                          reward, value targets, value-norm update)

Truncation (the end of every episode, T slots) is not terminal: the last real step of a
chunk bootstraps with V of the phantom step, i.e. V(final state) / V(final observation);
GAE does not run across chunk boundaries. A terminated step (never in this env) would not
bootstrap.

Loss (per agent u, per real step t; masked means over (t, u)):
    ratio_u = exp(logp_u - logp_old_u)                          (each agent's own ratio)
    L_pi  = -mean(min(ratio_u A_u, clip(ratio_u, 1-eps, 1+eps) A_u))
    L_v   = mean(max((V - V^tgt)^2, (V_old + clip(V - V_old, -c, c) - V^tgt)^2)) / 2
            (V and V_old the critic's raw outputs now and before this batch's update; the targets normalised
             with the statistics updated on this batch when value_norm; the clipped term only
             with value_clip)
    L     = L_pi + vf_coeff L_v - entropy_coeff mean(H(pi_u))
Gradient-norm clipping: RLlib's `grad_clip` (global norm).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.connectors.learner import AddOneTsToEpisodesAndTruncate
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.learner import ENTROPY_KEY, POLICY_LOSS_KEY, VF_LOSS_KEY
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.core.rl_module.apis import ValueFunctionAPI
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.annotations import override

from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, VF_PREDS
from uavlora_rllib.algorithms.common.learner import UavLoraLearner


class AddGlobalStateToBatch(ConnectorV2):
    """Train-batch column "state": info["state"] of every observation of every episode chunk
    (including the phantom bootstrap step), so it is zero-padded like the observations."""

    @override(ConnectorV2)
    def __call__(self, *, rl_module, batch: dict[str, Any], episodes: list[Any], **kwargs) -> Any:
        if GLOBAL_STATE in batch:
            return batch
        for ep in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            infos = ep.get_infos(slice(0, len(ep)))
            states = np.stack([np.asarray(i[GLOBAL_STATE], dtype=np.float32) for i in infos])
            self.add_n_batch_items(batch, GLOBAL_STATE, items_to_add=states, num_items=len(ep), single_agent_episode=ep)
        return batch


def per_agent_gae(
    values: np.ndarray, rewards: np.ndarray, terminated: np.ndarray, real: np.ndarray, gamma: float, lambda_: float
) -> np.ndarray:
    """GAE advantages [N, U] over a flat sequence of concatenated episode chunks.

    values [N, U] (denormalised); rewards, terminated, real [N]. Every chunk ends with one
    phantom step (real=False) whose value bootstraps the chunk's last real step; phantom
    steps get advantage 0 and cut the recursion between chunks.
    """
    n = len(rewards)
    ends = np.flatnonzero(~real)  # phantom index of each chunk
    starts = np.concatenate([[0], ends[:-1] + 1])
    lens = ends - starts + 1  # with the phantom
    e, lmax, u = len(ends), int(lens.max()) if len(ends) else 0, values.shape[1]
    # Chunk-major padded layout [E, Lmax]; padding behaves like phantoms (value 0, cut).
    idx = starts[:, None] + np.arange(lmax)[None, :]
    valid = np.arange(lmax)[None, :] < lens[:, None]
    idx = np.where(valid, idx, n - 1)
    v = np.where(valid[..., None], values[idx], 0.0)
    r = np.where(valid, rewards[idx], 0.0)
    live = valid & real[idx]
    cont = np.where(live, 1.0 - terminated[idx].astype(np.float64), 0.0)
    adv = np.zeros((e, lmax, u))
    last = np.zeros((e, u))
    for t in range(lmax - 1, -1, -1):
        nxt = v[:, t + 1] if t + 1 < lmax else np.zeros((e, u))
        delta = r[:, t, None] + gamma * cont[:, t, None] * nxt - v[:, t]
        last = np.where(live[:, t, None], delta + gamma * lambda_ * cont[:, t, None] * last, 0.0)
        adv[:, t] = last
    out = np.zeros_like(values, dtype=np.float64)
    out[idx[valid]] = adv[valid]
    return out


class PerAgentGAE(ConnectorV2):
    """Last learner-connector piece: advantages and value targets [B, T, U] per agent."""

    def __init__(self, input_observation_space=None, input_action_space=None, *, gamma: float, lambda_: float):
        super().__init__(input_observation_space, input_action_space)
        self.gamma, self.lambda_ = gamma, lambda_

    @override(ConnectorV2)
    def __call__(self, *, rl_module, batch: dict[str, Any], episodes: list[Any], **kwargs) -> Any:
        for mid, mb in batch.items():
            module = rl_module[mid]
            if not isinstance(module, ValueFunctionAPI):
                continue
            with torch.no_grad():
                v_norm = module.compute_values(mb)  # [B, T, U]
                v = module.denormalize(v_norm)
            device = v.device
            seq_lens = mb[Columns.SEQ_LENS].cpu().numpy()
            b, t = v.shape[:2]
            valid = np.arange(t)[None, :] < seq_lens[:, None]  # [B, T] real or phantom, not padding
            flat_v = v.cpu().numpy()[valid]
            flat_v_norm = v_norm.cpu().numpy()[valid]
            rewards = mb[Columns.REWARDS].cpu().numpy()[valid]
            terminated = mb[Columns.TERMINATEDS].cpu().numpy()[valid].astype(bool)
            real = mb[Columns.LOSS_MASK].cpu().numpy()[valid].astype(bool)
            adv = per_agent_gae(flat_v, rewards, terminated, real, self.gamma, self.lambda_)
            targets = adv + flat_v
            a_real = adv[real]
            adv = (adv - a_real.mean()) / max(1e-4, float(a_real.std()))
            adv[~real] = 0.0
            vn = getattr(getattr(module, "critic", None), "value_norm", None)
            if vn is not None:
                vn.update(torch.as_tensor(targets[real], device=device))

            def pad(x: np.ndarray) -> torch.Tensor:
                out = np.zeros((b, t) + x.shape[1:], dtype=np.float32)  # noqa: B023 (called in this iteration)
                out[valid] = x  # noqa: B023
                return torch.as_tensor(out, device=device)  # noqa: B023

            mb[Postprocessing.ADVANTAGES] = pad(adv)
            mb[Postprocessing.VALUE_TARGETS] = pad(targets)
            # the critic's output before this batch's update, the centre of the value clip: equal to the
            # loss's `values` until the first step moves the critic (docs/model.md#mappo-value-clip)
            mb[VF_PREDS] = pad(flat_v_norm)
        return batch


class MAPPOTorchLearner(UavLoraLearner):
    """Per-agent clipped PPO with a (central or local) critic. Settings: the typed
    `config.hparams` (MAPPOHParams: value_clip) and the PPOConfig fields MAPPOConfig sets from
    it (clip_param, vf_loss_coeff, entropy_coeff, gamma, lambda_, grad_clip, lr); the critic
    kind from the module's model_config."""

    @override(TorchLearner)
    def build(self) -> None:
        super().build()
        # Extends the learner's connector pipeline in place, the way RLlib's own PPOLearner
        # adds its GAE piece (config.learner_connector could only prepend).
        if self._learner_connector is not None and self.config.add_default_connectors_to_learner_pipeline:
            if self.config.model_config["critic"] == "central":
                self._learner_connector.prepend(AddGlobalStateToBatch())
            self._learner_connector.prepend(AddOneTsToEpisodesAndTruncate())
            self._learner_connector.append(PerAgentGAE(gamma=self.config.gamma, lambda_=self.config.lambda_))

    @classmethod
    @override(TorchLearner)
    def rl_module_required_apis(cls) -> list[type]:
        return [ValueFunctionAPI]

    @override(TorchLearner)
    def configure_optimizers_for_module(self, module_id, config=None) -> None:
        self.register_adam(module_id, self.get_parameters(self.module[module_id]), config.lr)

    @override(TorchLearner)
    def compute_loss_for_module(self, *, module_id, config, batch: dict[str, Any], fwd_out: dict[str, Any]):
        module = self.module[module_id].unwrapped()
        mask = batch[Columns.LOSS_MASK].float().unsqueeze(-1)  # [B, T, 1]
        n_valid = mask.sum() * module.n_agents

        def mmean(x: torch.Tensor) -> torch.Tensor:  # masked mean over (B, T, U)
            return (x * mask).sum() / n_valid.clamp(min=1.0)

        logits = fwd_out[Columns.ACTION_DIST_INPUTS]
        logp, entropy = module.head.logp_and_entropy(logits, batch[Columns.ACTIONS])  # [B, T, U] each
        ratio = torch.exp(logp - batch[Columns.ACTION_LOGP])
        adv = batch[Postprocessing.ADVANTAGES]
        eps = config.clip_param
        surrogate = torch.min(ratio * adv, torch.clamp(ratio, 1 - eps, 1 + eps) * adv)

        values = module.compute_values(batch)
        targets = module.normalize(batch[Postprocessing.VALUE_TARGETS])
        vf_loss = (values - targets) ** 2
        value_clip = config.hparams.value_clip
        if value_clip:
            old = batch[VF_PREDS]
            clipped = old + torch.clamp(values - old, -value_clip, value_clip)
            vf_loss = torch.max(vf_loss, (clipped - targets) ** 2)
        vf_loss = 0.5 * vf_loss

        policy_loss = -mmean(surrogate)
        mean_vf = mmean(vf_loss)
        mean_entropy = mmean(entropy)
        total = policy_loss + config.vf_loss_coeff * mean_vf - config.entropy_coeff * mean_entropy
        with torch.no_grad():
            clip_frac = mmean(((ratio - 1.0).abs() > eps).float())
            approx_kl = mmean((ratio - 1.0) - torch.log(ratio))
        self.metrics.log_dict(
            {
                POLICY_LOSS_KEY: policy_loss,
                VF_LOSS_KEY: mean_vf,
                ENTROPY_KEY: mean_entropy,
                "clip_fraction": clip_frac,
                "approx_kl": approx_kl,
            },
            key=module_id,
            window=1,
        )
        return total


__all__ = ["AddGlobalStateToBatch", "PerAgentGAE", "MAPPOTorchLearner", "per_agent_gae", "DEFAULT_MODULE_ID"]
