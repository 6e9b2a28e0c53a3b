"""BENCHMARKS.md "Training cost vs U": how far one QMIX update at V=60/U=8 (per_uav, 16 episodes of 150 slots, the
registry's defaults) runs from the one-thread float32 product rate, and so the most a faster implementation of
the same arithmetic could give. The update's matrix FLOPs are counted by torch's FlopCounterMode (online agent net
and mixer forward, target agent net and mixer forward, backward); its time and the product rates (the GRU's
per-step product [8, 16, 128] x [8, 128, 384] and a wide [8, 2416, 128] x [8, 128, 384]) are measured
interleaved in one process.

    python docs/history/measurements/qmix_update_flops.py
"""

import time

import torch
from ray.rllib.core.columns import Columns
from torch.utils.flop_counter import FlopCounterMode

from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
from uavlora_rllib.algorithms.common.config import hparams_model_config, module_dims
from uavlora_rllib.algorithms.qmix.hparams import QMIXHParams
from uavlora_rllib.algorithms.qmix.qmix_module import Q_TOT, TARGET_Q_TOT_NEXT, QMixModule
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)
torch.manual_seed(0)
dims = module_dims(ScenarioConfig.from_dict({"n_eds": 60, "n_uavs": 8, "episode_len": 150}))
hp = QMIXHParams()
module = QMixModule(model_config=hparams_model_config(QMIXHParams, **dims, mixer="qmix", epsilon_anneal_env_steps=1))
module.make_target_networks()
B, T, U = hp.batch_size_episodes, 150, dims["n_agents"]
batch = {
    Columns.OBS: torch.randn(B, T + 1, U, dims["obs_dim"]),
    Columns.ACTIONS: torch.randint(0, dims["n_actions"], (B, T, U)),
    GLOBAL_STATE: torch.randn(B, T + 1, dims["state_dim"]),
}


def update() -> None:
    out = module._forward_train(batch)
    (out[Q_TOT] - out[TARGET_Q_TOT_NEXT]).square().mean().backward()


def seconds(fn, reps: int) -> float:
    t = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t) / reps


with FlopCounterMode(display=False) as counter:
    update()
flop = counter.get_total_flops()
step_x, step_w = torch.randn(U, B, 128), torch.randn(U, 128, 384)
wide_x = torch.randn(U, 2416, 128)
for _ in range(2):
    update()
for _ in range(3):
    t_update = seconds(update, 5)
    t_step = seconds(lambda: torch.bmm(step_x, step_w), 2000)
    t_wide = seconds(lambda: torch.bmm(wide_x, step_w), 50)
    step_rate = 2 * U * B * 128 * 384 / t_step / 1e9
    wide_rate = 2 * U * 2416 * 128 * 384 / t_wide / 1e9
    print(
        f"QMIX update: {flop / 1e9:.2f} GFLOP in {t_update * 1e3:.0f} ms = {flop / t_update / 1e9:.1f} GFLOP/s; "
        f"products: per-step GRU {step_rate:.0f} GFLOP/s, wide {wide_rate:.0f} GFLOP/s; every FLOP at the "
        f"per-step rate and nothing else: {flop / (step_rate * 1e9) * 1e3:.0f} ms ({t_update * step_rate * 1e9 / flop:.2f}x)"
    )
