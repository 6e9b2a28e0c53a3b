"""Forward+backward time of the GRU recurrence alone: `gru_steps` (autograd's step loop) against
`gru_sequence` (one autograd node), at MAPPO's minibatch shape and QMIX's episode batch at V=60/U=8
(BENCHMARKS.md "Training cost vs U"). One thread, as a trial runs; the two interleaved per round.

    python docs/history/measurements/gru_sequence_timing.py [--rounds 3]
"""

from __future__ import annotations

import argparse
import time

import torch

from uavlora_rllib.algorithms.common.gru_sequence import gru_sequence, gru_steps
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process

SHAPES = {"MAPPO minibatch": (8, 19, 32, 128), "QMIX batch": (8, 16, 151, 128)}  # U, B, T, H


def median_ms(fn, repeats: int) -> float:
    for _ in range(3):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return sorted(times)[repeats // 2] * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    setup_torch_process(1)
    torch.use_deterministic_algorithms(True)  # as RLlib's seeding leaves a trial
    for label, shape in SHAPES.items():
        for r in range(args.rounds):
            loop, node = (median_ms(one_update(shape, rec), args.repeats) for rec in (gru_steps, gru_sequence))
            print(
                f"{label} [U, B, T, H = {shape}] round {r + 1}: gru_steps {loop:.1f} ms, "
                f"gru_sequence {node:.1f} ms ({node / loop:.2f}x)"
            )


def one_update(shape: tuple[int, int, int, int], recurrence):
    """The input projection, the recurrence and a backward through both, on fixed random inputs."""
    u, b, t, h = shape
    gen = torch.Generator().manual_seed(0)
    rows = torch.randn(u, b * t, h, generator=gen)  # the first layer's output
    w_ih = (torch.randn(u, 3 * h, h, generator=gen) / h**0.5).requires_grad_()
    h0 = torch.randn(u, b, h, generator=gen)
    w_hh = (torch.randn(u, 3 * h, h, generator=gen) / h**0.5).requires_grad_()
    b_hh = torch.zeros(u, 3 * h, requires_grad=True)
    weight = torch.randn(u, b, t, h, generator=gen)

    def run() -> None:
        gi = torch.bmm(rows, w_ih.transpose(1, 2)).view(u, b, t, 3 * h)
        (recurrence(gi, h0, w_hh, b_hh) * weight).sum().backward()

    return run


if __name__ == "__main__":
    main()
