"""What a finished grid cost, measured, beside what `tune GRID.yaml --dry-run` estimated (issue 25).

    python docs/history/measurements/grid_cost.py EXPERIMENT TRACKING_URI [DRIVER_LOG]

Trial time: each trial run's MLflow start-to-end (created when the trial starts, ended when it stops: build,
training, periodic and final evaluations, checkpoints), x 1 CPU (every paper grid reserves one CPU per trial).
Baseline time: the driver's "baseline NAME: evaluated in S s" lines (their MLflow runs are written only
when each ends). Wall: the grid's parent run, start to end. Prints one line per algorithm and the totals.
"""

import re
import sys
from collections import defaultdict

import mlflow

experiment, uri = sys.argv[1], sys.argv[2]
client = mlflow.MlflowClient(uri)
exp = client.get_experiment_by_name(experiment)
if exp is None:
    sys.exit(f"no experiment {experiment!r} in {uri}")
runs = client.search_runs([exp.experiment_id], max_results=10_000)
per_algo: dict[str, list[float]] = defaultdict(list)
wall = None
for run in runs:
    tags, info = run.data.tags, run.info
    if info.end_time is None:
        print(f"{info.run_name}: {info.status}, not ended: left out")
        continue
    seconds = (info.end_time - info.start_time) / 1000
    if "trial_id" in tags:
        per_algo[tags["algorithm"]].append(seconds)
    elif info.run_name == experiment:  # the grid's parent run
        wall = seconds
for algo, secs in sorted(per_algo.items()):
    print(f"{algo:6s} {len(secs)} trials, {min(secs):.0f}-{max(secs):.0f} s each, {sum(secs) / 3600:.3f} CPU-h")
trial_h = sum(sum(s) for s in per_algo.values()) / 3600
base_h = 0.0
if len(sys.argv) > 3:
    with open(sys.argv[3]) as f:
        base_h = sum(float(s) for s in re.findall(r"^baseline \S+: evaluated in ([0-9.]+) s", f.read(), re.M)) / 3600
print(f"trials {trial_h:.3f} CPU-h + baselines {base_h:.3f} CPU-h = {trial_h + base_h:.3f} CPU-h; "
      f"wall {wall / 3600 if wall else float('nan'):.3f} h")
