"""The learner's number format (`Resources.learner_precision`, docs/model.md#learner-precision).

`bfloat16` runs every training update (the learner connectors' value passes, the forward passes,
the losses and their backward) under `torch.autocast`: matrix products take bfloat16 inputs, which
CPUs with AVX512-BF16 or AMX, and GPUs, multiply several times faster than float32. Everything
else stays float32: the parameters and the optimiser's state, the GRU's gates and carried state
(agent_net.py), and every network's output, cast back before a loss reads it, so that
log-probabilities, PPO ratios and TD errors are not rounded to bfloat16's ~3 significant digits.
Acting on the env runners is untouched (float32).
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.learner.learner import Learner
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.utils.annotations import override


def autocast_for(precision: str, device: torch.device) -> torch.autocast:
    """The autocast context of `precision` on `device`: bfloat16 products, or disabled (float32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


class PrecisionLearner(TorchLearner):
    """A TorchLearner whose updates run in the trial's `learner_precision` (model_config)."""

    @override(Learner)
    def update(self, *args: Any, **kwargs: Any) -> Any:
        with autocast_for(self.config.model_config["learner_precision"], torch.device(self.device)):
            return super().update(*args, **kwargs)
