"""The learner's number format (`Resources.learner_precision`, docs/model.md#learner-precision).

`bfloat16` runs every training update (the learner connectors' value passes, the forward passes,
the losses and their backward) under `torch.autocast`: matrix products take bfloat16 inputs, which
CPUs with AVX512-BF16 or AMX, and GPUs, multiply several times faster than float32. Everything
else stays float32: the parameters and the optimiser's state, the GRU's gates and carried state
(gru_sequence.py's `gru_steps`), and every network's output, cast back before a loss reads it, so that
log-probabilities, PPO ratios and TD errors are not rounded to bfloat16's ~3 significant digits.
Acting on the env runners is untouched (float32).
"""

from __future__ import annotations

import torch


def autocast_for(precision: str, device: torch.device) -> torch.autocast:
    """The autocast context of `precision` on `device`: bfloat16 products, or disabled (float32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16")
