"""The learner's number format (`Resources.learner_precision`, docs/model.md#learner-precision).

`bfloat16` gives every matrix product of a training update (the learner connectors' value passes,
the forward passes, the losses and their backward) bfloat16 inputs (~3 significant digits) and a
float32 sum, by one of two routes, chosen per device:

* **oneDNN's bfloat16 products**, on a CPU whose oneDNN multiplies float32 products in bfloat16 when
  allowed to (Intel's AMX, from Sapphire Rapids on; possibly ARM chips with BF16; probed once per
  process): torch's float32 product precision for the CPU is lowered while the update runs. Each
  product oneDNN computes rounds its inputs inside the product and returns float32 (torch sends
  some small products, such as those with an inner dimension of 16 or less, to its float32
  library); every tensor stays float32, so nothing is cast.
* **torch.autocast(bfloat16)** everywhere else (CPUs with AVX512-BF16 but no AMX, such as AMD
  Zen 4, where oneDNN ignores that permission; GPUs): products take bfloat16 copies of their inputs
  and give bfloat16 outputs. The parameters and the optimiser's state, the GRU's gates and carried
  state (gru_sequence.py's `gru_steps`) and every network's output stay float32, cast back before a
  loss reads it, so that log-probabilities, PPO ratios and TD errors are not rounded to bfloat16.
  A CPU with neither emulates bfloat16, slower than float32.

Either route holds only while an update runs (the float32 product precision is process-wide and
given back after it), so acting stays float32.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import torch

_ONEDNN = torch.backends.mkldnn.matmul  # type: ignore[attr-defined]  # torch's CPU product settings, set at import


def autocast_for(precision: str, device: torch.device) -> torch.autocast:
    """The autocast context of `precision` on `device`: bfloat16 products, or disabled (float32)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bfloat16")


@contextlib.contextmanager
def onednn_bfloat16() -> Iterator[None]:
    """Within it, oneDNN may compute the CPU's float32 products in bfloat16; the previous setting
    comes back on exit."""
    before = _ONEDNN.fp32_precision
    _ONEDNN.fp32_precision = "bf16"
    try:
        yield
    finally:
        _ONEDNN.fp32_precision = before


@functools.cache
def onednn_rounds_in_bfloat16() -> bool:
    """Does this CPU's oneDNN compute float32 products in bfloat16 when allowed to? (1 + 2^-10) x 1
    loses its 2^-10 there. 64 x 64: torch sends some small products to its float32 library."""
    x = torch.full((64, 64), 1.0 + 2.0**-10)
    # a float32 product whatever region the first caller is in (autocast's bfloat16 output would round too)
    with onednn_bfloat16(), torch.autocast("cpu", enabled=False), torch.no_grad():
        y = x @ torch.eye(64)
    return y.dtype == torch.float32 and not torch.equal(y, x)


def bfloat16_route(device: torch.device) -> str:
    """'onednn' or 'autocast': how `bfloat16` runs on `device` (module docstring)."""
    return "onednn" if device.type == "cpu" and onednn_rounds_in_bfloat16() else "autocast"


def precision_context(precision: str, device: torch.device) -> contextlib.AbstractContextManager[None]:
    """The context an update runs in: `precision`'s route on `device`, or nothing for float32."""
    if precision != "bfloat16":
        return contextlib.nullcontext()
    return onednn_bfloat16() if bfloat16_route(device) == "onednn" else autocast_for(precision, device)


def precision_name(precision: str, device: torch.device) -> str:
    """What an update runs in, as a run records it: 'float32', 'bfloat16/onednn' or 'bfloat16/autocast'
    (`precision` and, for bfloat16, its route on `device`): the routes differ in speed and in the last
    digits, and which one a trial took depends on the machine it ran on."""
    return precision if precision != "bfloat16" else f"bfloat16/{bfloat16_route(device)}"
