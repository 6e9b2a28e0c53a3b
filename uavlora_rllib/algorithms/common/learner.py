"""The package's TorchLearner, the base of every built-in learner (docs/model.md#the-learner).

* Each update runs in the trial's number format, `resources.learner_precision`
  (common/precision.py, docs/model.md#learner-precision).
* `register_adam` builds every network's Adam one way: torch's fused step, one kernel per
  parameter for all of Adam's arithmetic (on the CPU torch otherwise loops over the parameters).
* `apply_gradients` decides whether every gradient is finite with ONE fused max-norm over all of
  them; RLlib's own method tests each parameter twice, four element-wise passes each. Only
  when that norm is not finite does RLlib's method run, so NaN/inf gradients are handled as in
  RLlib (set to zero, with its warnings).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from ray.rllib.core.learner.learner import DEFAULT_OPTIMIZER, Learner
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.utils.annotations import override
from ray.rllib.utils.typing import LearningRateOrSchedule, ParamDict

from uavlora_rllib.algorithms.common.precision import autocast_for


def all_finite(tensors: Sequence[torch.Tensor]) -> bool:
    """True iff no element of `tensors` is NaN or +-inf: their max-norm is finite (it never
    overflows, and NaN propagates through it)."""
    return bool(torch.isfinite(torch.nn.utils.get_total_norm(tensors, norm_type=math.inf)))


class UavLoraLearner(TorchLearner):
    """See the module docstring."""

    @override(Learner)
    def update(self, *args: Any, **kwargs: Any) -> Any:
        with autocast_for(self.config.model_config["learner_precision"], torch.device(self.device)):
            return super().update(*args, **kwargs)

    def register_adam(
        self,
        module_id: str,
        params: Sequence[torch.nn.Parameter],
        lr: LearningRateOrSchedule,
        name: str = DEFAULT_OPTIMIZER,
    ) -> None:
        """Register Adam (torch's defaults, fused step) over `params`; `lr` a rate or RLlib's schedule of one."""
        params = list(params)
        self.register_optimizer(
            module_id=module_id,
            optimizer_name=name,
            optimizer=torch.optim.Adam(params, fused=True),
            params=params,
            lr_or_lr_schedule=lr,
        )

    @override(TorchLearner)
    def apply_gradients(self, gradients_dict: ParamDict) -> None:
        grads = [g for g in gradients_dict.values() if g is not None]
        # A gradient scaler or a torch lr scheduler (RLlib experimental settings) steps inside
        # RLlib's method: those learners keep it whole.
        plain = self._grad_scalers is None and self._lr_scheduler_classes is None
        if not (plain and grads and all_finite(grads)):
            super().apply_gradients(gradients_dict)
            return
        # What RLlib's method does once every gradient is finite (the same private fields).
        for pid, grad in gradients_dict.items():
            self._params[pid].grad = grad
        for module_id in self._module_optimizers:
            for _name, optim in self.get_optimizers_for_module(module_id):
                optim.step()
