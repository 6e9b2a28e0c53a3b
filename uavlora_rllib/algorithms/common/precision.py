"""The learner's number format (`Resources.learner_precision`, docs/model.md#learner-precision).

`bfloat16` lowers the internal precision of the float32 matrix products of every training update
(the learner connectors' value passes, the forward passes, the losses and their backward): each
product rounds its inputs to bfloat16 (~3 significant digits) and accumulates in float32, which
CPUs with AMX or AVX512-BF16 multiply several times faster than float32 (torch's oneDNN backend;
on a CPU without them torch computes the product in float32). Every tensor stays float32: the
parameters and the optimiser's state, the activations, the GRU's gates and carried state, and every
network's output, so no cast is added and log-probabilities, PPO ratios and TD errors are computed
at full precision. On an NVIDIA GPU torch offers no bfloat16 mode for float32 products, and the
learner uses its TF32 mode instead (10 explicit mantissa bits). The setting is process-wide, so it
holds only while an update runs: acting stays float32.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

# torch's float32 product settings per device type, and each one's reduced precision
_REDUCED = {
    "cpu": (torch.backends.mkldnn.matmul, "bf16"),  # type: ignore[attr-defined]  # set at torch's import
    "cuda": (torch.backends.cuda.matmul, "tf32"),
}


@contextlib.contextmanager
def matmul_precision(precision: str, device: torch.device) -> Iterator[None]:
    """Within it, float32 products on `device` run in `precision`'s internal format: reduced for
    'bfloat16' (module docstring), unchanged for 'float32'. The previous setting comes back on exit."""
    if precision != "bfloat16" or device.type not in _REDUCED:
        yield
        return
    backend, reduced = _REDUCED[device.type]
    before = backend.fp32_precision
    backend.fp32_precision = reduced
    try:
        yield
    finally:
        backend.fp32_precision = before
