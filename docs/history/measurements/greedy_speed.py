"""per_device `greedy` against its scorer at an older commit, interleaved in one process: seconds for
the same slots (batch of 10 scenarios, seeds 0-9) and whether every action is the same.

    python docs/history/measurements/greedy_speed.py COMMIT V U RATE_MODEL SLOTS [REPEATS]
"""

import importlib.util
import subprocess
import sys
import tempfile
import time

import numpy as np

from uavlora_rllib.baselines import slots as current
from uavlora_rllib.baselines.per_device import PerDeviceGreedy
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

commit, v, u, rate_model, n_slots = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
repeats = int(sys.argv[6]) if len(sys.argv) > 6 else 2
source = subprocess.run(
    ["git", "show", f"{commit}:uavlora_rllib/baselines/slots.py"], check=True, capture_output=True, text=True
).stdout
with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
    f.write(source)
spec = importlib.util.spec_from_file_location("slots_then", f.name)
then = importlib.util.module_from_spec(spec)
spec.loader.exec_module(then)

cfg = ScenarioConfig(n_eds=v, n_uavs=u, action_mode="per_device", rate_model=rate_model)
seconds: dict[str, list[float]] = {commit: [], "now": []}
actions = {}
for _ in range(repeats):
    for name, module in ((commit, then), ("now", current)):
        core = BatchCore(cfg, 10)
        core.reset(list(range(10)))
        greedy = PerDeviceGreedy(cfg)
        greedy._scorer = module.AllocationScorer(cfg, core.tables, "ee")
        start, played = time.perf_counter(), []
        for _ in range(n_slots):
            played.append(greedy.act(core))
            core.step(played[-1])
        seconds[name].append(time.perf_counter() - start)
        actions[name] = np.array(played)
print(f"V={v} U={u} {rate_model}, {n_slots} slots x 10 scenarios: " + ", ".join(f"{k} {min(s):.2f} s" for k, s in seconds.items())
      + f", ratio {min(seconds[commit]) / min(seconds['now']):.2f}, same actions: {bool((actions[commit] == actions['now']).all())}")
