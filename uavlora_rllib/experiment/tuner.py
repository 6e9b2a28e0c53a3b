"""The Ray Tune side of a grid run: each trial's config and resources, trial names, the status
table, and the Tuner (new, or restored for --resume)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

from uavlora_rllib.experiment.grid import (
    GridConfig,
    TrialSpec,
    algorithm_overrides,
    eval_interval,
    hparams_dict,
    is_sweep,
    trial_count,
    trial_run_name,
)


def trial_config(spec: TrialSpec, grid: GridConfig, sweeping: bool = False) -> dict[str, Any]:
    """What one trial needs (and what its MLflow run records), plain data only; a sampled
    hyperparameter is a Tune search space in ``overrides`` (resolved per trial by Tune) and
    named in ``sampled``."""
    from uavlora_rllib.experiment import periodic_eval  # imports RLlib: not at module import

    overrides = {
        k: (spec.spaces[k].to_tune() if k in spec.spaces else v)
        for k, v in algorithm_overrides(grid, spec.algorithm).items()
    }
    return {
        "algorithm": spec.algorithm,
        "seed": spec.seed,
        "n_eds": spec.n_eds,
        "n_uavs": spec.n_uavs,
        "scenario": spec.scenario.to_dict(),
        "overrides": overrides,
        "sampled": sorted(spec.spaces),
        "sweep": sweeping,
        "hparams": hparams_dict(spec.hparams),
        "resources": dataclasses.asdict(grid.resources),
        "budget_env_steps": grid.stop.env_steps,
        "eval_episodes": grid.evaluation.episodes,
        "eval_interval_env_steps": periodic_eval.resolve_interval(
            grid.evaluation.interval_env_steps, grid.stop.env_steps
        ),
        "plugins": list(grid.plugins),
    }


def grid_identity(grid: GridConfig, specs: list[TrialSpec]) -> dict[str, Any]:
    """What a Tune experiment fixes when it starts, which `--resume` restores and cannot change:
    every trial's config (a sampled hyperparameter as its space), the samples, the scheduler and
    the search algorithm. Plain JSON data; `digest` is its SHA-256 (16 hex digits)."""
    import hashlib
    import json

    configs = []
    for spec in specs:
        config = trial_config(spec, grid, is_sweep(grid, specs))
        config["overrides"] = {
            k: ({"space": spec.spaces[k].kind, "values": list(spec.spaces[k].values)} if k in spec.spaces else v)
            for k, v in config["overrides"].items()
        }
        configs.append(config)
    body = {
        "trials": configs,
        "num_samples": grid.num_samples,
        "scheduler": dataclasses.asdict(grid.scheduler) if grid.scheduler else None,
        "search_alg": dataclasses.asdict(grid.search_alg) if grid.search_alg else None,
    }
    text = json.dumps(body, sort_keys=True, default=str)
    return {
        "digest": hashlib.sha256(text.encode()).hexdigest()[:16],
        "trials": str(trial_count(grid, specs)),
        "budget": str(grid.stop.env_steps),
    }


def trial_resources(grid: GridConfig):
    from ray.tune import PlacementGroupFactory

    # the trial process, env runners and remote learners (GPUs included), in RLlib's own layout
    return PlacementGroupFactory(grid.resources.bundles(), strategy="PACK")


def _trial_name(trial) -> str:
    return trial_run_name(trial.config.get("trial", trial.config), trial.trial_id)


def _trial_dirname(trial) -> str:
    return f"{_trial_name(trial)}_{trial.trial_id}"


def status_reporter(sampled: Sequence[str] = ()):
    """Tune's status table: one row per trial, with its name, algorithm, V, U, seed and progress.

    Ray 2.60's default table ("new output") shows the grid-search value, here the whole
    trial dict, cut short; the CLIReporter shows chosen config and metric columns instead.
    Tune uses it only with RAY_AIR_NEW_OUTPUT=0 (read when `fit` starts: the driver sets
    it before `fit`, for restored experiments too, whose pickled run config holds this reporter).
    Its EE column is the latest greedy evaluation (sweep.SWEEP_METRIC, in every result from the first
    evaluation on; blank before, and until the final one with evaluation.interval_env_steps 0): what the
    project judges by, and not blank, as the training EE is after an iteration that ended no episode.
    """
    from ray.tune import CLIReporter

    from uavlora_rllib.experiment.sweep import SWEEP_METRIC

    return CLIReporter(
        parameter_columns={
            "trial/algorithm": "algorithm",
            "trial/n_eds": "V",
            "trial/n_uavs": "U",
            "trial/seed": "seed",
            **{f"trial/overrides/{k}": k for k in sampled},
        },
        metric_columns={"env_steps": "env steps", SWEEP_METRIC: "greedy EE"},
        max_report_frequency=30,
        sort_by_metric=False,
    )


def make_tuner(grid: GridConfig, specs: list[TrialSpec], storage: str, uri: str, grid_file: str, commit: str):
    from ray import tune

    from uavlora_rllib.experiment import sweep
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback
    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    callback = MlflowTrialCallback(
        uri,
        grid.experiment,
        grid_file,
        commit,
        retry_timeout_s=grid.mlflow.retry_timeout_s,
        checkpoint_artifact_max_mb=grid.mlflow.checkpoint_artifact_max_mb,
    )
    sweeping = is_sweep(grid, specs)
    configs = [trial_config(s, grid, sweeping) for s in specs]
    # a search algorithm suggests the sampled values of one grid point (sweep.check_sweep)
    param_space = {"trial": configs[0] if grid.search_alg is not None else tune.grid_search(configs)}
    spaces = {k: v for s in specs for k, v in s.spaces.items()}
    return tune.Tuner(
        tune.with_resources(UavLoraTrainable, trial_resources(grid)),
        param_space=param_space,
        tune_config=tune.TuneConfig(
            num_samples=grid.num_samples,
            scheduler=sweep.make_scheduler(grid, spaces, eval_interval(grid)),
            search_alg=sweep.make_search_alg(grid),
            max_concurrent_trials=grid.max_concurrent_trials,
            trial_name_creator=_trial_name,
            trial_dirname_creator=_trial_dirname,
            reuse_actors=True,
        ),
        run_config=tune.RunConfig(
            name=grid.experiment,
            storage_path=storage,
            callbacks=[callback],
            checkpoint_config=tune.CheckpointConfig(
                checkpoint_frequency=grid.checkpoint_every,
                checkpoint_at_end=True,
                # PBT restores a trial from another's checkpoint some iterations later: keep them all
                num_to_keep=None if grid.scheduler is not None and grid.scheduler.type == "pbt" else 2,
            ),
            failure_config=tune.FailureConfig(max_failures=grid.failure.max_failures),
            progress_reporter=status_reporter(sorted(spaces)),
            verbose=1,
        ),
    )


def tuner_for(
    grid: GridConfig,
    specs: list[TrialSpec],
    storage: str,
    uri: str,
    grid_file: str,
    exp_path: str,
    commit: str,
    restore: bool,
):
    """The Tuner of the grid: restored from `exp_path` (--resume), or new."""
    from ray import tune

    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    if restore:
        from uavlora_rllib.experiment.mlflow_callback import resuming_into

        trainable = tune.with_resources(UavLoraTrainable, trial_resources(grid))
        with resuming_into(uri, grid_file):  # the grid's store and file now, not those pickled with it
            return tune.Tuner.restore(exp_path, trainable, resume_unfinished=True, resume_errored=True)
    return make_tuner(grid, specs, storage, uri, grid_file, commit)
