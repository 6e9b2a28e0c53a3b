"""docs/history/benchmarks-2026.md "Training cost vs U, float32 and bfloat16": GFLOP/s of MAPPO's actor update at V=60/U=8 (19 windows x 32 slots,
8 stacked per-agent GRU nets) against one-thread sgemm on wide products, interleaved in one process; each in
float32 and with bfloat16 products (the update under `resources.learner_precision: bfloat16`'s autocast, a
bfloat16 mm), docs/model.md#learner-precision.

    python docs/history/measurements/actor_update_flops.py
"""

import time

import torch

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.precision import autocast_for
from uavlora_rllib.envs.parallel import observation_space
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)
cfg = ScenarioConfig.from_dict({"n_eds": 60, "n_uavs": 8, "episode_len": 150})
D = observation_space(cfg).shape[-1]
U, B, T, H, N_OUT = 8, 19, 32, 128, 90  # MAPPO's defaults: 16 episodes / 4 minibatches in 32-slot windows
net = RecurrentAgentNet(D, U, N_OUT, fc_hidden=H, gru_hidden=H, share=False, out_hidden=H, out_gain=0.01)
obs, h0 = torch.randn(B, T, U, D), torch.zeros(B, U, H)
forward_flop = 2 * U * B * T * (D * H + 2 * H * 3 * H + H * H + H * N_OUT)  # input, GRU ih + hh, two output layers
a, b = torch.randn(2048, 2048), torch.randn(2048, 2048)
a16, b16 = a.bfloat16(), b.bfloat16()


def update(precision: str = "float32") -> None:
    with autocast_for(precision, torch.device("cpu")):
        out, _ = net(obs, h0)
        out.square().mean().backward()


def seconds(fn, reps: int) -> float:
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t) / reps


for _ in range(3):
    update()
    update("bfloat16")
    torch.mm(a, b)
    torch.mm(a16, b16)
for _ in range(3):
    tu, tg = seconds(update, 10), seconds(lambda: torch.mm(a, b), 5)
    tu16, tg16 = seconds(lambda: update("bfloat16"), 10), seconds(lambda: torch.mm(a16, b16), 5)
    print(
        f"obs_dim {D}: update float32 {tu * 1e3:.1f} ms, {3 * forward_flop / tu / 1e9:.1f} GFLOP/s (backward ~2x "
        f"forward), bfloat16 {tu16 * 1e3:.1f} ms ({tu / tu16:.2f}x); sgemm 2048^3 float32 "
        f"{2 * 2048**3 / tg / 1e9:.1f} GFLOP/s, bfloat16 {2 * 2048**3 / tg16 / 1e9:.1f} GFLOP/s"
    )
