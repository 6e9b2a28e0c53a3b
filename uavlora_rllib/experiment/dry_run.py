"""The --dry-run preview of a grid: its trials, a sweep's spaces and the baseline evaluations."""

from __future__ import annotations

from uavlora_rllib.experiment.grid import (
    GridConfig,
    TrialSpec,
    baseline_runs,
    eval_interval,
    is_sweep,
    scenario_for,
    trial_count,
)
from uavlora_rllib.sim.scenario import off_defaults


def trial_table(grid: GridConfig, specs: list[TrialSpec]) -> str:
    base = baseline_runs(grid)
    what = "grid points" if is_sweep(grid, specs) else "trials"  # a sweep's trials: sweep_lines
    lines = [
        f"experiment {grid.experiment!r}: {len(specs)} {what} = {len(grid.algorithms)} algorithms x "
        f"{len(grid.seeds)} seeds x {len(grid.n_eds)} n_eds x {len(grid.n_uavs)} n_uavs; "
        f"{len(base)} baseline evaluations",
        f"{'#':>4}  {'algorithm':<12} {'seed':>6} {'n_eds':>6} {'n_uavs':>6} {'budget_env_steps':>17}",
    ]
    for i, s in enumerate(specs, 1):
        lines.append(f"{i:>4}  {s.algorithm:<12} {s.seed:>6} {s.n_eds:>6} {s.n_uavs:>6} {grid.stop.env_steps:>17}")
    changed = off_defaults(scenario_for(grid, specs[0].n_eds, specs[0].n_uavs)) if specs else []
    lines.append(f"scenario off the paper's defaults: {', '.join(changed)}" if changed else "scenario: the paper's")
    if is_sweep(grid, specs):
        lines += sweep_lines(grid, specs)
    lines.append(f"baseline evaluations ({grid.evaluation.episodes} episodes each):")
    if base:
        lines.append(f"{'#':>4}  {'baseline':<12} {'seed':>6} {'n_eds':>6} {'n_uavs':>6}")
        for i, b in enumerate(base, 1):
            lines.append(f"{i:>4}  {b.baseline:<12} {b.seed:>6} {b.n_eds:>6} {b.n_uavs:>6}")
    else:
        lines.append("   (none)")
    return "\n".join(lines)


def sweep_lines(grid: GridConfig, specs: list[TrialSpec]) -> list[str]:
    """The dry run's description of a sweep: spaces, samples, scheduler, search algorithm."""
    from uavlora_rllib.experiment import sweep

    searched = any(space.kind == "grid_search" for s in specs for space in s.spaces.values())
    lines = [
        f"sweep: {trial_count(grid, specs)} trials = {len(specs)} grid points"
        + (" x grid_search values" if searched else "")
        + f" x num_samples {grid.num_samples}"
        if grid.search_alg is None
        else f"sweep: {grid.num_samples} trials (num_samples) suggested by {grid.search_alg.type}"
    ]
    seen = set()
    for s in specs:
        for name, space in s.spaces.items():
            if (s.algorithm, name) not in seen:
                seen.add((s.algorithm, name))
                lines.append(f"  algorithms.{s.algorithm}.{name}: {space.describe()}")
    if grid.scheduler is not None:
        interval = grid.scheduler.interval(eval_interval(grid))
        what = "perturbation_interval" if grid.scheduler.type == "pbt" else "grace_period"
        lines.append(f"  scheduler: {grid.scheduler.type} ({what} {interval} env steps)")
    if grid.search_alg is not None:
        lines.append(
            f"  search_alg: {grid.search_alg.type} ({grid.search_alg.sampler} sampler, seed {grid.search_alg.seed})"
        )
    if grid.scheduler is not None or grid.search_alg is not None:
        lines.append(
            f"  metric: {sweep.METRIC} (max), the greedy policy evaluated every {eval_interval(grid)} env steps"
        )
    return lines
