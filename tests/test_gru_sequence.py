"""The two implementations of the GRU recurrence (common/gru_sequence.py) are one function.

`gru_sequence` (one autograd node, backward written out) against `gru_steps` (the step loop that
autograd differentiates): outputs and the gradients of all four inputs agree, its backward passes
gradcheck in float64, and `RecurrentAgentNet` runs it except under autocast
(docs/model.md#batched-agent-networks).
"""

from __future__ import annotations

import pytest
import torch

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.gru_sequence import gru_sequence, gru_steps


def _inputs(u: int, t: int, b: int, h: int, dtype: torch.dtype, seed: int = 0) -> list[torch.Tensor]:
    """gi, h0, w_hh, b_hh of nn.GRU's scale (weights ~ U(-1/sqrt(H), 1/sqrt(H))), all requiring grad."""
    gen = torch.Generator().manual_seed(seed)
    bound = h**-0.5
    shapes = [(u, t, b, 3 * h), (u, b, h), (u, 3 * h, h), (u, 3 * h)]
    scales = [1.0, 1.0, bound, bound]
    return [((torch.rand(s, generator=gen, dtype=dtype) * 2 - 1) * c).requires_grad_() for s, c in zip(shapes, scales)]


@pytest.mark.parametrize("t", [1, 2, 3, 9])
def test_sequence_matches_steps_outputs_and_gradients(t):
    u, b, h = 3, 4, 8
    ins_seq, ins_steps = _inputs(u, t, b, h, torch.float32), _inputs(u, t, b, h, torch.float32)
    weight = torch.randn(u, t, b, h, generator=torch.Generator().manual_seed(1))
    out_seq, out_steps = gru_sequence(*ins_seq), gru_steps(*ins_steps)
    torch.testing.assert_close(out_seq, out_steps, atol=1e-6, rtol=1e-5)
    # every step's output weighed differently, plus the last state on its own (a recurrent carry)
    for out in (out_seq, out_steps):
        ((out * weight).sum() + out[:, -1].square().sum()).backward()
    for name, a, ref in zip(("gi", "h0", "w_hh", "b_hh"), ins_seq, ins_steps):
        torch.testing.assert_close(a.grad, ref.grad, atol=1e-5, rtol=1e-5, msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("t", [1, 2, 4])
def test_sequence_backward_passes_gradcheck(t):
    assert torch.autograd.gradcheck(gru_sequence, tuple(_inputs(2, t, 3, 4, torch.float64)))


def test_sequence_without_gradient_is_the_same_function():
    ins = _inputs(2, 5, 3, 4, torch.float32)
    with torch.no_grad():
        out = gru_sequence(*ins)
    assert not out.requires_grad
    torch.testing.assert_close(out, gru_sequence(*ins).detach(), atol=0, rtol=0)


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
