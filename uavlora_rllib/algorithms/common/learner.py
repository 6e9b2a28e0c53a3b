"""The package's TorchLearner, the base of every built-in learner (docs/model.md#the-learner).

* Each update runs in the trial's number format, `resources.learner_precision`
  (common/precision.py, docs/model.md#learner-precision); under its autocast route every optimiser
  step drops autocast's bfloat16 copies of the weights, so that the update's next forward reads the
  stepped ones.
* `register_adam` builds every network's Adam one way: torch's fused implementation (on the CPU
  torch otherwise loops over the parameters, several small operations each). A checkpoint
  restores an optimiser's param groups with their flags, so `set_state` makes them fused again.
* `apply_gradients` decides whether the gradients are finite with one 2-norm over all of them
  (torch's foreach norm); RLlib's own method tests each parameter twice, four element-wise
  passes each. It takes its own path only where RLlib's method would end the same way: every
  gradient present and finite, every other parameter without a gradient, no gradient scaler or
  torch lr scheduler. Anything else runs RLlib's method (NaN/inf zeroed, with its warnings).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import torch
from ray.rllib.core.learner.learner import DEFAULT_OPTIMIZER, Learner
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.utils.annotations import override
from ray.rllib.utils.typing import LearningRateOrSchedule, ParamDict, StateDict

from uavlora_rllib.algorithms.common.precision import precision_context, precision_name


def surely_finite(tensors: Sequence[torch.Tensor]) -> bool:
    """True only if no element of `tensors` is NaN or +-inf: their 2-norm is finite (NaN and inf
    propagate into it). False also where finite elements square beyond float range: a caller
    then tests element by element. The 2-norm: torch's foreach kernel, much faster than the max-norm's."""
    tensors = [t for t in tensors if t.numel()]
    return not tensors or bool(torch.isfinite(torch.nn.utils.get_total_norm(tensors)))


class UavLoraLearner(TorchLearner):
    """See the module docstring."""

    @override(Learner)
    def update(self, *args: Any, **kwargs: Any) -> Any:
        with self.precision():
            return super().update(*args, **kwargs)

    def precision(self) -> contextlib.AbstractContextManager[None]:
        """The trial's `learner_precision` as a context (common/precision.py's route for the learner's
        device): every forward and backward of an update runs in it (update; a learner's own extra
        steps, such as COMA's critic-only ones, too)."""
        return precision_context(self.config.model_config["learner_precision"], torch.device(self.device))

    def precision_name(self) -> str:
        """The format and route `precision` runs in on this learner's device (common/precision.py's
        `precision_name`), for the trial's MLflow run."""
        return precision_name(self.config.model_config["learner_precision"], torch.device(self.device))

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

    @override(Learner)
    def set_state(self, state: StateDict) -> None:
        super().set_state(state)
        adams = (o for o in self._optimizers() if isinstance(o, torch.optim.Adam) and o.defaults.get("fused"))
        for opt in adams:  # register_adam's; a checkpoint written before Adam was fused restores its loop
            for group in opt.param_groups:
                group["fused"], group["foreach"] = True, None
                for p in group["params"]:  # the fused step reads `step` as float32 on the parameter's device
                    if "step" in opt.state.get(p, {}):
                        opt.state[p]["step"] = torch.as_tensor(
                            opt.state[p]["step"], dtype=torch.float32, device=p.device
                        )

    def _optimizers(self) -> list[torch.optim.Optimizer]:
        """Every registered optimiser, in RLlib's order (the one its apply_gradients steps them in)."""
        return [opt for mid in self._module_optimizers for _name, opt in self.get_optimizers_for_module(mid)]

    @override(TorchLearner)
    def apply_gradients(self, gradients_dict: ParamDict) -> None:
        self._step_optimizers(gradients_dict)
        # autocast keeps one bfloat16 copy of each weight until its outermost region ends, and one
        # update steps several times inside it (RLlib's loop over minibatches and epochs, COMA's
        # critic-only steps): drop the copies, or the next forward would read the weights before this step
        if torch.is_autocast_enabled(torch.device(self.device).type):
            torch.clear_autocast_cache()

    def _step_optimizers(self, gradients_dict: ParamDict) -> None:
        grads = list(gradients_dict.values())
        # RLlib's method steps every optimiser unchanged when each gradient it is given is finite and
        # each parameter it is not given has no gradient (its per-optimiser test reads those too); a
        # gradient scaler or torch lr scheduler (RLlib's experimental settings) steps inside it.
        same_end = (
            self._grad_scalers is None
            and self._lr_scheduler_classes is None
            and bool(grads)
            and all(g is not None for g in grads)
            and all(p.grad is None for pid, p in self._params.items() if pid not in gradients_dict)
            and surely_finite(grads)  # False: RLlib's method tests each gradient
        )
        if not same_end:
            super().apply_gradients(gradients_dict)
            return
        for pid, grad in gradients_dict.items():  # what RLlib's method does then (the same private fields)
            self._params[pid].grad = grad
        for optim in self._optimizers():
            optim.step()
