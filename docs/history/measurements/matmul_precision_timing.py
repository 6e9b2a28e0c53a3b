"""Time of single float32 products at V=60/U=8's shapes under learner_precision float32 and bfloat16
(common/precision.py's oneDNN route: oneDNN rounds the inputs to bfloat16 on a CPU with AMX),
and the bfloat16 result's largest difference from float32's, relative to float32's largest entry
(BENCHMARKS.md "Training cost vs U"). One thread.

    python docs/history/measurements/matmul_precision_timing.py [--repeats 15]
"""

from __future__ import annotations

import argparse

import torch
from gru_sequence_timing import median_ms  # this folder's: the script's own folder is on sys.path

from uavlora_rllib.algorithms.common.precision import onednn_bfloat16, onednn_rounds_in_bfloat16
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process

U, ROWS, SEQ, FC, H, STATE = 8, 608, 19, 128, 128, 1981  # MAPPO's minibatch: 19 sequences of 32 slots


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    setup_torch_process(1)
    print(f"this CPU's oneDNN rounds to bfloat16: {onednn_rounds_in_bfloat16()}")
    gen = torch.Generator().manual_seed(0)
    z, w_ih = torch.randn(U, ROWS, FC, generator=gen), torch.randn(U, 3 * H, FC, generator=gen)
    d_gi, h = torch.randn(U, ROWS, 3 * H, generator=gen), torch.randn(U, SEQ, H, generator=gen)
    w_hh_t = torch.randn(U, 3 * H, H, generator=gen).transpose(1, 2).contiguous()  # as gru_sequence lays it out
    state, w_c, d_c = (
        torch.randn(ROWS, STATE, generator=gen),
        torch.randn(H, STATE, generator=gen),
        torch.randn(ROWS, H, generator=gen),
    )
    products = {
        "GRU input projection [8, 608, 128] x [8, 128, 384]": lambda: torch.bmm(z, w_ih.transpose(1, 2)),
        "its weight gradient [8, 384, 608] x [8, 608, 128]": lambda: torch.bmm(d_gi.transpose(1, 2), z),
        "its input gradient [8, 608, 384] x [8, 384, 128]": lambda: torch.bmm(d_gi, w_ih),
        "GRU per-step product [8, 19, 128] x [8, 128, 384]": lambda: torch.bmm(h, w_hh_t),
        "central critic's first layer [608, 1981] x [1981, 128]": lambda: state @ w_c.t(),
        "its weight gradient [128, 608] x [608, 1981]": lambda: d_c.t() @ state,
    }
    for label, fn in products.items():
        exact, f32_ms = fn(), median_ms(fn, args.repeats)
        with onednn_bfloat16():
            diff = float((fn() - exact).abs().max() / exact.abs().max())
            bf16_ms = median_ms(fn, args.repeats)
        print(f"{label}: float32 {f32_ms:.3f} ms, bfloat16 {bf16_ms:.3f} ms ({f32_ms / bf16_ms:.2f}x; diff {diff:.1e})")


if __name__ == "__main__":
    main()
