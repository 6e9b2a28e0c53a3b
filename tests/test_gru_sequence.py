"""The two implementations of the GRU recurrence (common/gru_sequence.py) are one function.

`gru_sequence` (one autograd node, backward written out) against `gru_steps` (the step loop that
autograd differentiates): outputs and the gradients of all four inputs agree, also on the views
`RecurrentAgentNet` passes; its backward passes gradcheck in float64, never runs under autocast,
and reads no memory it did not write; and `RecurrentAgentNet` runs it except under autocast
(docs/model.md#batched-agent-networks).
"""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

import uavlora_rllib.algorithms.common.gru_sequence as gru_sequence_module
from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.gru_sequence import gru_sequence, gru_steps


def _inputs(u: int, b: int, t: int, h: int, dtype: torch.dtype, seed: int = 0) -> list[torch.Tensor]:
    """gi [U, B, T, 3H], h0, w_hh, b_hh at nn.GRU's scale (weights ~ U(-1/sqrt(H), 1/sqrt(H))), all leaves."""
    gen = torch.Generator().manual_seed(seed)
    bound = h**-0.5
    shapes = [(u, b, t, 3 * h), (u, b, h), (u, 3 * h, h), (u, 3 * h)]
    scales = [1.0, 1.0, bound, bound]
    return [((torch.rand(s, generator=gen, dtype=dtype) * 2 - 1) * c).requires_grad_() for s, c in zip(shapes, scales)]


def _as_called(gi: torch.Tensor, h0: torch.Tensor, w_hh: torch.Tensor, b_hh: torch.Tensor) -> list[torch.Tensor]:
    """The inputs in the form `RecurrentAgentNet._gru` passes them: gi a view of a product's rows,
    h0 a transposed view of the [B, U, H] state."""
    u, b, t, g3 = gi.shape
    rows = torch.baddbmm(
        torch.zeros(u, 1, g3, dtype=gi.dtype), gi.reshape(u, b * t, g3), torch.eye(g3, dtype=gi.dtype).expand(u, g3, g3)
    )
    return [rows.view(u, b, t, g3), h0.transpose(0, 1).contiguous().transpose(0, 1), w_hh, b_hh]


def _outputs_and_gradients(fn, ins: list[torch.Tensor], weight: torch.Tensor, *, views: bool = False):
    """fn's output, and the gradients of all four leaves for a loss that weighs every step's state
    differently plus the last state on its own (a recurrent carry)."""
    for x in ins:
        x.grad = None
    out = fn(*(_as_called(*ins) if views else ins))
    ((out * weight).sum() + out[:, :, -1].square().sum()).backward()
    return out.detach(), [x.grad.clone() for x in ins]


@pytest.mark.parametrize("views", [False, True])
@pytest.mark.parametrize("t", [1, 2, 3, 9])
def test_sequence_matches_steps_outputs_and_gradients(t, views):
    ins = _inputs(3, 4, t, 8, torch.float32)
    weight = torch.randn(3, 4, t, 8, generator=torch.Generator().manual_seed(1))
    out, grads = _outputs_and_gradients(gru_sequence, ins, weight, views=views)
    out_ref, grads_ref = _outputs_and_gradients(gru_steps, ins, weight)
    torch.testing.assert_close(out, out_ref, atol=1e-6, rtol=1e-5)
    for name, g, ref in zip(("gi", "h0", "w_hh", "b_hh"), grads, grads_ref):
        torch.testing.assert_close(g, ref, atol=1e-5, rtol=1e-5, msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("t", [1, 2, 4])
def test_sequence_backward_passes_gradcheck(t):
    assert torch.autograd.gradcheck(gru_sequence, tuple(_inputs(2, 3, t, 4, torch.float64)))


@pytest.mark.parametrize("mode", [torch.no_grad, torch.inference_mode])
@pytest.mark.parametrize("t", [1, 5])
def test_sequence_without_gradient_matches_steps(mode, t):
    ins = _inputs(2, 3, t, 4, torch.float32)
    with mode():
        out, ref = gru_sequence(*ins), gru_steps(*ins)
    assert not out.requires_grad
    torch.testing.assert_close(out, ref, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("t", [1, 3, 12])
def test_forward_without_backward_reuses_step_buffers_and_gives_the_same_digits(t, monkeypatch):
    """Without a backward (acting, QMIX's target network) gru_sequence writes each step's gates into one
    reused buffer instead of keeping all T; the states must be the saving forward's (the same operations in
    the same order; vectorised and strided elementwise kernels may differ in the last bit), and inputs that
    do not require a gradient take that path under grad mode too."""
    ins = _inputs(3, 4, t, 8, torch.float32)
    saved = gru_sequence(*ins)
    assert saved.grad_fn is not None

    def refuse(*_):
        raise AssertionError("the saving forward ran where no backward will")

    monkeypatch.setattr(gru_sequence_module._GRUSequence, "apply", refuse)
    with torch.no_grad():
        torch.testing.assert_close(gru_sequence(*ins), saved.detach(), atol=1e-6, rtol=1e-6)
    plain = [x.detach() for x in ins]
    out = gru_sequence(*plain)
    assert out.grad_fn is None
    torch.testing.assert_close(out, saved.detach(), atol=1e-6, rtol=1e-6)


def test_backward_under_autocast_stays_float32():
    """A backward that runs inside an autocast region (the learner's precision context) computes
    the float32 gradients: no product of the written-out backward is cast to bfloat16."""
    ins = _inputs(2, 3, 6, 16, torch.float32)
    weight = torch.randn(2, 3, 6, 16, generator=torch.Generator().manual_seed(1))
    _, grads = _outputs_and_gradients(gru_sequence, ins, weight)
    for x in ins:
        x.grad = None
    out = gru_sequence(*ins)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        ((out * weight).sum() + out[:, :, -1].square().sum()).backward()
    for g, x in zip(grads, ins):
        torch.testing.assert_close(x.grad, g, atol=0, rtol=0)


_FILLED_PROBE = """
import torch
torch.use_deterministic_algorithms(True)  # with the NaN fill of every new tensor on (torch's default)
assert torch.utils.deterministic.fill_uninitialized_memory
from uavlora_rllib.algorithms.common.gru_sequence import gru_sequence
u, b, t, h = 3, 4, 7, 8
ins = [torch.randn(s).requires_grad_() for s in [(u, b, t, 3 * h), (u, b, h), (u, 3 * h, h), (u, 3 * h)]]
out = gru_sequence(*ins)
(out * torch.randn_like(out)).sum().backward()
with torch.no_grad():
    no_backward = gru_sequence(*ins)
print(all(bool(x.isfinite().all()) for x in [out, no_backward] + [i.grad for i in ins]))
"""


def test_no_buffer_is_read_before_it_is_written():
    """With torch's NaN fill of new tensors on (trial processes turn it off, common/torch_process.py),
    every output and gradient is finite: a buffer read before it was written would show as NaN."""
    out = subprocess.run([sys.executable, "-c", _FILLED_PROBE], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True"]


def _node_names(root: torch.Tensor) -> list[str]:
    """The names of every autograd node behind `root`."""
    seen, stack, names = set(), [root.grad_fn], []
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        names.append(type(node).__name__)
        stack.extend(next_fn for next_fn, _ in node.next_functions)
    return names


@pytest.mark.parametrize("autocast", [False, True])
def test_agent_net_runs_one_node_except_under_autocast(autocast):
    torch.manual_seed(0)
    t = 6
    net = RecurrentAgentNet(5, 3, 7, fc_hidden=8, gru_hidden=8, share=False)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
        out, _ = net(torch.randn(2, t, 3, 5), net.initial_state(2))
    names = _node_names(out)
    sequence_nodes = sum(n == "_GRUSequenceBackward" for n in names)
    # the step loop: one recurrent product per step, plus the input projection and the output layer
    products = sum(n == "BaddbmmBackward0" for n in names)
    assert (sequence_nodes, products > t) == ((0, True) if autocast else (1, False))


def test_agent_net_in_float64_runs_the_sequence_in_float64():
    torch.manual_seed(0)
    net = RecurrentAgentNet(5, 3, 7, fc_hidden=8, gru_hidden=8, share=False).double()
    out, h_t = net(torch.randn(2, 4, 3, 5, dtype=torch.float64), net.initial_state(2).double())
    assert h_t.dtype == torch.float64 and out.isfinite().all()  # outputs leave as float32 by design
