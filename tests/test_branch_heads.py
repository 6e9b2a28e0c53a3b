"""BranchHeads (common/branch_heads.py) is the MLP it documents, run batched: each agent's and
branch's head on its concatenated input [x_u ; r_{u,k} ; one-hot(k)], built and applied one by
one here, gives the same outputs and gradients."""

from __future__ import annotations

import pytest
import torch

from uavlora_rllib.algorithms.common.branch_heads import BranchHeads

B, T, U, K, IN_X, IN_R, HID, OUT = 3, 4, 3, 5, 8, 4, 16, 7


def _reference(heads: BranchHeads, x: torch.Tensor, r: torch.Tensor | None, k: int) -> torch.Tensor:
    """Every (agent, branch) head applied by itself to its concatenated input."""
    groups, branches = heads.w1.shape[:2]
    out = torch.empty(B, T, U, k, OUT)
    for u in range(U):
        for j in range(k):
            g, h = (0 if groups == 1 else u), (0 if branches == 1 else j)
            parts = [x[:, :, u]]
            if r is not None:
                parts.append(r[:, :, u, j])
            if heads.slot_ids:
                parts.append(torch.nn.functional.one_hot(torch.tensor(j), k).float().expand(B, T, k))
            hidden = torch.relu(torch.cat(parts, -1) @ heads.w1[g, h] + heads.b1[g, h])
            out[:, :, u, j] = hidden @ heads.w2[g, h] + heads.b2[g, h]
    return out


@pytest.mark.parametrize("groups", [1, U])
@pytest.mark.parametrize(
    "form",
    ["shared_with_slot_ids", "shared", "per_branch", "no_rows", "per_branch_no_rows"],
)
def test_batched_heads_are_the_per_head_mlp(groups, form):
    torch.manual_seed(0)
    branches = K if form.startswith("per_branch") else 1
    in_r = 0 if form.endswith("no_rows") else IN_R
    heads = BranchHeads(groups, branches, IN_X, in_r, HID, OUT, K if form == "shared_with_slot_ids" else 0)
    assert heads.w1.shape == (groups, branches, IN_X + in_r + heads.slot_ids, HID)
    k = 1 if form == "no_rows" else K
    x = torch.randn(U, B, T, IN_X).permute(1, 2, 0, 3).requires_grad_()  # agent-major, as the GRU's output
    r = None if form.endswith("no_rows") else torch.randn(B, T, U, K, IN_R)
    weight = torch.randn(B, T, U, k, OUT)
    results = []
    for fn in (heads, lambda *a: _reference(heads, *a)):
        heads.zero_grad()
        x.grad = None
        y = fn(x, r, k)
        (y * weight).sum().backward()
        results.append([y.detach()] + [p.grad.clone() for p in heads.parameters()] + [x.grad.clone()])
    assert results[0][0].shape == (B, T, U, k, OUT)
    for got, want in zip(*results):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_slot_ids_need_one_head_for_all_branches():
    with pytest.raises(ValueError, match="slot_ids"):
        BranchHeads(1, K, IN_X, IN_R, HID, OUT, K)


@pytest.mark.parametrize("form", ["shared_with_slot_ids", "per_branch"])
def test_under_bfloat16_autocast_the_output_and_its_bias_stay_float32(form):
    """The products run in bfloat16 but the last layer's bias is added in float32: the differences
    between a branch's outputs (what an argmax, a log-softmax or a dueling mean reads) keep their
    float32 accuracy even when a large bias would round them to bfloat16's spacing (0.125 at 30)."""
    torch.manual_seed(1)
    per_branch = form == "per_branch"
    heads = BranchHeads(U, K if per_branch else 1, IN_X, IN_R, HID, OUT, 0 if per_branch else K)
    with torch.no_grad():
        heads.b2 += 30.0
    x, r = torch.randn(B, T, U, IN_X), torch.randn(B, T, U, K, IN_R)
    want = heads(x, r, K)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = heads(x, r, K)
    assert got.dtype == torch.float32
    centred = [y - y.mean(-1, keepdim=True) for y in (got, want)]
    assert (centred[0] - centred[1]).abs().max() < 0.03


def test_a_wrong_branch_count_is_one_clear_error():
    x, r = torch.randn(B, T, U, IN_X), torch.randn(B, T, U, K, IN_R)
    with pytest.raises(ValueError, match="k: 4 branches asked of heads with branches=5"):
        BranchHeads(1, K, IN_X, IN_R, HID, OUT)(x, r[..., :4, :], 4)
    with pytest.raises(ValueError, match="k: 4 branches asked of heads with slot_ids=5"):
        BranchHeads(1, 1, IN_X, IN_R, HID, OUT, K)(x, r[..., :4, :], 4)
    with pytest.raises(ValueError, match=r"r: expected \[..., 5, 4\], got \(3, 4, 3, 5, 3\)"):
        BranchHeads(1, 1, IN_X, IN_R, HID, OUT)(x, r[..., :3], K)
