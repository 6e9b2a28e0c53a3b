"""The GRU recurrence of U agents at once, the one place of its equations.

nn.GRU's recurrence (reset r, update z, new n; h' = n + z (h - n)) for U agents, each step one
batched product with the agents' stacked recurrent weights (docs/model.md#batched-agent-networks),
in two implementations of the same function (tests/test_gru_sequence.py):

`gru_steps` is the step loop of tensor operations, differentiated by autograd (~12 nodes per step).
`gru_sequence` is one autograd node with its backward pass written out:

* forward writes every step's state and gates into preallocated buffers, which backward reads
  (without a backward, as when acting or for QMIX's target network, one reused step buffer per gate);
* backward walks the steps in reverse with one batched product per step (the carried
  state's gradient) and computes the recurrent weight's gradient as ONE product over all
  T steps. Autograd's loop instead makes a [U, 3H, H] weight-gradient product per step and
  adds it into a running sum: T thin products and T sums of a weight-sized tensor, work that
  reads and writes memory more than it computes.

`RecurrentAgentNet` runs `gru_sequence`, and `gru_steps` under autocast on the inputs' device
(learner_precision bfloat16's autocast route, common/precision.py): there autocast casts each
step's product to bfloat16 while the gates stay float32. `gru_sequence` itself runs outside
autocast, forward and backward, so a gradient is never rounded to bfloat16 step after step. Under
the oneDNN route its products round their inputs and return float32, like the update's other large
products: the carried state and its gradient stay float32.

Layout: batch-major, [U, B, T, .] (agent, sequence, step), the rows of the agent network's other
layers, so no transpose is copied on the way in or out.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

_tanh_backward = torch.ops.aten.tanh_backward.grad_input  # g (1 - y^2), written into a given tensor
_sigmoid_backward = torch.ops.aten.sigmoid_backward.grad_input  # g y (1 - y)


def _recur(gi, h0, w_hh, b_hh, hs, rz_t, new_t, gh_t) -> None:
    """The forward recurrence, writing the state after each step into hs [U, B, T, H] and step t's
    gates r | z, candidate n and W_hh h + b_hh into rz_t[t], new_t[t], gh_t[t]: per-step views of
    buffers that backward reads, or, without a backward, the same small buffer every step."""
    t_len, hd = gi.shape[2], hs.shape[-1]
    w_t = w_hh.transpose(1, 2)
    if t_len > 2:  # the product reads a contiguous W^T faster; one copy pays off over a few steps
        w_t = w_t.contiguous()
    bias = b_hh.unsqueeze(1)
    gi_rz, gi_n = gi[..., : 2 * hd].unbind(2), gi[..., 2 * hd :].unbind(2)
    hs_t = hs.unbind(2)
    h = h0
    for t in range(t_len):
        gh_step = torch.baddbmm(bias, h, w_t, out=gh_t[t])
        r_z = torch.add(gi_rz[t], gh_step[..., : 2 * hd], out=rz_t[t]).sigmoid_()
        n = torch.addcmul(gi_n[t], r_z[..., :hd], gh_step[..., 2 * hd :], out=new_t[t]).tanh_()
        h = torch.lerp(n, h, r_z[..., hd:], out=hs_t[t])  # n + z (h - n)


class _GRUSequence(torch.autograd.Function):
    """gi [U, B, T, 3H] (the input projection W_ih x + b_ih of every step), h0 [U, B, H],
    w_hh [U, 3H, H], b_hh [U, 3H] -> hs [U, B, T, H], the state after each step."""

    @staticmethod
    def forward(ctx, gi, h0, w_hh, b_hh):
        u, b, t_len, g3 = gi.shape
        hs = gi.new_empty(u, b, t_len, g3 // 3)
        rz = gi.new_empty(u, b, t_len, 2 * g3 // 3)  # sigmoid gates r | z
        new = gi.new_empty(u, b, t_len, g3 // 3)  # candidate state n
        gh = gi.new_empty(t_len, u, b, g3)  # W_hh h + b_hh, step-major: each step's product writes in place
        _recur(gi, h0, w_hh, b_hh, hs, rz.unbind(2), new.unbind(2), gh.unbind(0))
        ctx.save_for_backward(h0, w_hh, hs, rz, new, gh)
        return hs

    @staticmethod
    @once_differentiable
    def backward(ctx, d_hs):
        h0, w_hh, hs, rz, new, gh = ctx.saved_tensors
        u, b, t_len, hd = hs.shape
        with torch.autocast(d_hs.device.type, enabled=False):
            h_prev = torch.cat([h0.unsqueeze(2), hs[:, :, :-1]], 2)  # the state each step started from
            h_minus_n = (h_prev - new).unbind(2)
            d_gh = hs.new_empty(u, b, t_len, 3 * hd)  # gradient of W_hh h + b_hh
            d_gi = hs.new_empty(u, b, t_len, 3 * hd)  # gradient of W_ih x + b_ih (r, z parts equal d_gh's)
            r_t, z_t, new_t = rz[..., :hd].unbind(2), rz[..., hd:].unbind(2), new.unbind(2)
            gh_n = gh[..., 2 * hd :].unbind(0)
            d_gh_t = d_gh.unbind(2)
            d_r, d_z, d_ghn = (d_gh[..., k * hd : (k + 1) * hd].unbind(2) for k in range(3))
            d_gin = d_gi[..., 2 * hd :].unbind(2)
            d_hs_t = d_hs.unbind(2)
            dh = d_hs_t[t_len - 1]  # gradient of the state after step t
            for t in range(t_len - 1, -1, -1):
                r, z = r_t[t], z_t[t]
                dh_z = dh * z  # h' = n + z (h - n): dh'/dh = z ...
                d_pre_n = _tanh_backward(dh - dh_z, new_t[t], grad_input=d_gin[t])  # ... dh'/dn = 1 - z
                torch.mul(d_pre_n, r, out=d_ghn[t])  # n = tanh(gi_n + r gh_n)
                _sigmoid_backward(d_pre_n * gh_n[t], r, grad_input=d_r[t])
                _sigmoid_backward(dh * h_minus_n[t], z, grad_input=d_z[t])
                dh = torch.baddbmm(dh_z, d_gh_t[t], w_hh)
                if t:
                    dh += d_hs_t[t - 1]
            d_gi[..., : 2 * hd] = d_gh[..., : 2 * hd]
            d_w = d_b = None
            if ctx.needs_input_grad[2]:
                d_w = torch.bmm(d_gh.view(u, b * t_len, 3 * hd).transpose(1, 2), h_prev.view(u, b * t_len, hd))
            if ctx.needs_input_grad[3]:
                d_b = d_gh.sum((1, 2))
        return d_gi, dh, d_w, d_b


def gru_sequence(gi: torch.Tensor, h0: torch.Tensor, w_hh: torch.Tensor, b_hh: torch.Tensor) -> torch.Tensor:
    """U GRUs over T steps: gi [U, B, T, 3H] = W_ih x + b_ih, h0 [U, B, H], w_hh [U, 3H, H] and
    b_hh [U, 3H] (nn.GRU's layouts, stacked over the agents), all of one dtype -> hs [U, B, T, H]."""
    with torch.autocast(gi.device.type, enabled=False):
        if torch.is_grad_enabled() and any(x.requires_grad for x in (gi, h0, w_hh, b_hh)):
            return _GRUSequence.apply(gi, h0, w_hh, b_hh)
        # no backward (acting, QMIX's target network): the gates need not outlive their step, so three
        # step-sized buffers serve every step and stay in cache (docs/model.md#batched-agent-networks)
        u, b, t_len, g3 = gi.shape
        hs = gi.new_empty(u, b, t_len, g3 // 3)
        rz, new, gh = gi.new_empty(u, b, 2 * g3 // 3), gi.new_empty(u, b, g3 // 3), gi.new_empty(u, b, g3)
        _recur(gi, h0, w_hh, b_hh, hs, [rz] * t_len, [new] * t_len, [gh] * t_len)
        return hs


def gru_steps(gi: torch.Tensor, h0: torch.Tensor, w_hh: torch.Tensor, b_hh: torch.Tensor) -> torch.Tensor:
    """`gru_sequence` as a loop of tensor operations that autograd differentiates, in nn.GRU's
    operation order. Each step's product is cast to the state's dtype: under autocast the product
    runs in bfloat16 and the gates and the carried state stay float32."""
    w_hh_t, bias = w_hh.transpose(1, 2), b_hh.unsqueeze(1)
    h, hs = h0, []
    for g in gi.unbind(2):  # unbind: one backward node for all steps
        i_r, i_z, i_n = g.chunk(3, -1)
        h_r, h_z, h_n = torch.baddbmm(bias, h, w_hh_t).to(h.dtype).chunk(3, -1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        h = n + z * (h - n)
        hs.append(h)
    return torch.stack(hs, dim=2)
