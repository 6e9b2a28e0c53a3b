"""Run a grid YAML: one Ray Tune trial per algorithm x seed x V x U, and the baseline evaluations.

    python -m uavlora_rllib.tune GRID.yaml [--resume] [--dry-run] [--address ADDR]
                                           [--storage DIR] [--num-cpus N]
    python -m uavlora_rllib.tune GRID.yaml --calibrate [--calibrate-iterations N]

* The grid is validated first (`grid.load_grid`); a bad grid prints ONE line on stderr and
  exits with code 2 before Ray starts. ``--dry-run`` prints the trial table, the baseline
  evaluations and the grid's estimated cost (experiment.cost, from the calibration that
  ``--calibrate`` measures on this machine: experiment.calibration) and exits 0 without starting Ray.
* Before any baseline or trial starts: the driver lock (one driver per experiment,
  `experiment.driver_lock`), the connection to Ray (`experiment.cluster`: a private local
  Ray without ``--address``; ``auto``, ``HOST:PORT`` or ``ray://HOST:10001`` otherwise; under
  ``ray job submit`` the job's cluster), that one trial's resources fit the cluster, and that
  MLflow answers. Any of these failing is one line and exit code 2.
* Baselines (``baselines:``) run as Ray tasks in parallel with the trials
  (`experiment.baseline_tasks`); each is one MLflow run (kind=baseline) written by the
  driver; a FINISHED run with the same scenario is not redone.
* Training: one `UavLoraTrainable` (experiment.trainable) trial per `grid.trials` entry, resources per trial from
  ``resources:`` (1 learner bundle + one bundle per env runner), a checkpoint every
  ``checkpoint_every`` iterations and at the end, stop at ``stop.env_steps`` env steps
  sampled, then the execution-phase evaluation (the entry's greedy policy, the trial's seed,
  ``evaluation.episodes`` episodes) reported as ``eval/*``. A trial that fails (its node
  died) is retried from its last checkpoint up to ``failure.max_failures`` times, into the
  same MLflow run. `mlflow_callback.MlflowTrialCallback` logs everything to MLflow from the driver;
  trials and baselines are nested under the grid's one parent run (docs/model.md#mlflow-runs).
* Sweeps (experiment/sweep.py): hyperparameters given as Tune search spaces are sampled per
  trial (``num_samples`` per grid point), optionally under a ``scheduler`` (asha, pbt,
  median_stopping) or a ``search_alg`` (optuna), all on the periodic greedy evaluation
  ``eval/ee_sys_mean``; trial and run names then end in the trial's number (``-t00003``).
* ``--resume`` restores the Tune experiment ``<storage>/<experiment>``: finished trials are
  not rerun, interrupted or errored ones continue from their last checkpoint, and each trial
  keeps its one MLflow run (found again by its trial_id tag). If the driver died before Tune
  saved anything, ``--resume`` starts the trials. Without ``--resume`` an existing
  experiment is an error (no silent second copy of the grid).
* Interrupt with Ctrl+C (SIGINT) once: Tune saves the experiment state and the MLflow runs of
  unfinished trials are marked KILLED; ``--resume`` picks them up. A driver killed outright
  (SIGKILL, lost machine) is also resumable: see `experiment.mlflow_callback`. Exit codes: 0 all
  trials and baselines finished, 1 some failed (or MLflow stayed unreachable), 130
  interrupted, 2 bad input or a failed preflight check.

Running on a cluster (shared storage, MLflow server, token auth, Ray Jobs, GPUs): docs/cluster.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from typing import Any

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import cluster
from uavlora_rllib.experiment.grid import (
    BaselineSpec,
    GridConfig,
    TrialSpec,
    algorithm_overrides,
    baseline_runs,
    check_local_resources,
    check_storage,
    eval_interval,
    hparams_dict,
    is_sweep,
    load_grid,
    trial_count,
    trial_run_name,
    trials,
)

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


def __getattr__(name: str) -> Any:
    """`UavLoraTrainable` lives in experiment.trainable (imports Ray Tune): loaded on first use."""
    if name == "UavLoraTrainable":
        from uavlora_rllib.experiment.trainable import UavLoraTrainable

        return UavLoraTrainable
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m uavlora_rllib.tune", description=__doc__.split("\n\n")[0])
    p.add_argument("grid", nargs="?", help="grid YAML (see tune_configs/)")
    p.add_argument(
        "--list-hparams",
        metavar="ALGO",
        default=None,
        help="print ALGO's hyperparameters (grid YAML algorithms.ALGO: ...) with types, defaults, units and "
        f"descriptions, and exit; ALGO one of {sorted(registry.MODULES)}",
    )
    p.add_argument("--resume", action="store_true", help="continue the grid's Tune experiment")
    p.add_argument("--dry-run", action="store_true",
                   help="print the trials, the baseline runs and the grid's estimated cost (from --calibrate), start nothing")
    p.add_argument("--calibrate", action="store_true",
                   help="measure on this machine what each distinct trial and baseline of the grid costs (short runs), "
                        "store it for --dry-run's estimate, then print the dry run")
    p.add_argument("--calibrate-iterations", type=int_in(1, 100), default=None, metavar="N",
                   help="with --calibrate: timed training iterations per trial cell, after the warm-up (default 2)")
    p.add_argument("--address", default=None,
                   help="Ray cluster address (default: start a local Ray; under `ray job submit`: the job's cluster)")
    p.add_argument(
        "--storage", type=_storage_arg, default=None, help="Ray results directory (overrides the grid's storage)"
    )
    p.add_argument("--num-cpus", type=int_in(1, 100_000), default=None, help="CPUs of the local Ray (default: all)")
    return p


def _storage_arg(text: str) -> str:
    try:
        return check_storage(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


# --------------------------------------------------------------------------- paths
def storage_path(grid: GridConfig, override: str | None) -> str:
    """The Ray storage dir: --storage or the grid's, relative to the launch dir (`cluster.resolve_path`)."""
    return cluster.resolve_path(override or grid.storage, "--storage" if override else "storage")


def experiment_path(storage: str, experiment: str) -> str:
    return f"{storage.rstrip('/')}/{experiment}" if "://" in storage else os.path.join(storage, experiment)


def absolute_tracking_uri(uri: str) -> str:
    """sqlite:///relative.db -> sqlite:////<launch dir>/relative.db (see `cluster.resolve_tracking_uri`)."""
    return cluster.resolve_tracking_uri(uri)


def describe_uri(uri: str) -> str:
    return uri[len("sqlite:///") :] if uri.startswith("sqlite:///") else uri


def check_storage_writable(storage: str) -> None:
    """A local storage dir must be creatable and writable (checked before anything runs)."""
    if "://" in storage:
        return
    try:
        os.makedirs(storage, exist_ok=True)
        probe = os.path.join(storage, f".write-test-{os.getpid()}")
        with open(probe, "w"):
            pass
        os.unlink(probe)
    except OSError as exc:
        raise ConfigError(f"storage: cannot write to {storage}: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------- dry run
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

    lines = [f"sweep: {trial_count(grid, specs)} trials = {len(specs)} grid points x grid_search values x "
             f"num_samples {grid.num_samples}" if grid.search_alg is None else
             f"sweep: {grid.num_samples} trials (num_samples) suggested by {grid.search_alg.type}"]
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
        lines.append(f"  search_alg: {grid.search_alg.type} ({grid.search_alg.sampler} sampler, seed {grid.search_alg.seed})")
    if grid.scheduler is not None or grid.search_alg is not None:
        lines.append(f"  metric: {sweep.METRIC} (max), the greedy policy evaluated every {eval_interval(grid)} env steps")
    return lines


# --------------------------------------------------------------------------- the trainable
def trial_config(spec: TrialSpec, grid: GridConfig, sweeping: bool = False) -> dict[str, Any]:
    """What one trial needs (and what its MLflow run records), plain data only; a sampled
    hyperparameter is a Tune search space in ``overrides`` (resolved per trial by Tune) and
    named in ``sampled``."""
    from uavlora_rllib.experiment import periodic_eval  # imports RLlib: not at module import

    overrides = {k: (spec.spaces[k].to_tune() if k in spec.spaces else v)
                 for k, v in algorithm_overrides(grid, spec.algorithm).items()}
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
        "eval_interval_env_steps": periodic_eval.resolve_interval(grid.evaluation.interval_env_steps, grid.stop.env_steps),
        "plugins": list(grid.plugins),
    }


def trial_resources(grid: GridConfig):
    from ray.tune import PlacementGroupFactory

    # the trial process, env runners and remote learners (GPUs included), in RLlib's own layout
    return PlacementGroupFactory(grid.resources.bundles(), strategy="PACK")


def _trial_name(trial) -> str:
    return trial_run_name(trial.config.get("trial", trial.config), trial.trial_id)


def _trial_dirname(trial) -> str:
    return f"{_trial_name(trial)}_{trial.trial_id}"


# --------------------------------------------------------------------------- phases
def baselines_to_run(grid: GridConfig, tracker, out=None) -> list[BaselineSpec]:
    """The grid's baseline runs that are not FINISHED in MLflow yet."""
    from uavlora_rllib.experiment.run_schema import run_params

    out = out or sys.stdout
    todo = []
    for b in baseline_runs(grid):
        params = run_params(b.scenario, None, grid.evaluation.episodes)
        if tracker.finished_baseline(b.baseline, b.seed, b.n_eds, b.n_uavs, params):
            print(f"baseline {b.name}: already in MLflow, skipped", file=out, flush=True)
        else:
            todo.append(b)
    return todo


def baseline_logger(grid: GridConfig, tracker):
    """(spec, summary or the task's exception) -> the baseline's one MLflow run."""
    from uavlora_rllib.experiment.run_schema import run_params

    def log(spec: BaselineSpec, result: Any) -> None:
        params = run_params(spec.scenario, None, grid.evaluation.episodes)

        def evaluate() -> dict:
            if isinstance(result, BaseException):
                raise result
            return result

        try:
            tracker.log_baseline(spec.baseline, spec.name, spec.seed, spec.n_eds, spec.n_uavs, params, evaluate,
                                 grid.stop.env_steps)
        except Exception as exc:
            if exc is not result:  # the evaluation's own error is recorded as a FAILED run
                raise

    return log


def status_reporter(sampled: Sequence[str] = ()):
    """Tune's status table: one row per trial, with its name, algorithm, V, U, seed and progress.

    Ray 2.60's default table ("new output") shows the grid-search value, here the whole
    trial dict, cut short; the CLIReporter shows chosen config and metric columns instead.
    Tune uses it only with RAY_AIR_NEW_OUTPUT=0 (read when `fit` starts: `_fit` sets
    it, for restored experiments too, whose pickled run config holds this reporter).
    """
    from ray.tune import CLIReporter

    return CLIReporter(
        parameter_columns={"trial/algorithm": "algorithm", "trial/n_eds": "V", "trial/n_uavs": "U",
                           "trial/seed": "seed", **{f"trial/overrides/{k}": k for k in sampled}},
        metric_columns={"env_steps": "env steps", "episode_return_mean": "return", "ee_sys_mean": "EE"},
        max_report_frequency=30,
        sort_by_metric=False,
    )


def make_tuner(grid: GridConfig, specs: list[TrialSpec], storage: str, uri: str, grid_file: str, commit: str):
    from ray import tune

    from uavlora_rllib.experiment import sweep
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback
    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    callback = MlflowTrialCallback(uri, grid.experiment, grid_file, commit, retry_timeout_s=grid.mlflow.retry_timeout_s,
                                   checkpoint_artifact_max_mb=grid.mlflow.checkpoint_artifact_max_mb)
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
                checkpoint_frequency=grid.checkpoint_every, checkpoint_at_end=True,
                # PBT restores a trial from another's checkpoint some iterations later: keep them all
                num_to_keep=None if grid.scheduler is not None and grid.scheduler.type == "pbt" else 2,
            ),
            failure_config=tune.FailureConfig(max_failures=grid.failure.max_failures),
            progress_reporter=status_reporter(sorted(spaces)),
            verbose=1,
        ),
    )


def _tracking_failure(exc: BaseException | None):
    """The TrackingUnavailable inside an exception chain (Tune wraps callback errors), or None."""
    from uavlora_rllib.experiment.mlflow_client import TrackingUnavailable

    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, TrackingUnavailable):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def run_grid(grid: GridConfig, grid_file: str, args: argparse.Namespace) -> int:
    from uavlora_rllib.experiment.driver_lock import DriverLock

    specs = trials(grid)
    storage = storage_path(grid, args.storage)
    exp_path = experiment_path(storage, grid.experiment)
    uri = absolute_tracking_uri(grid.mlflow.tracking_uri)
    cluster.check_address_args(args.address, args.num_cpus)
    check_storage_writable(storage)

    # one driver per experiment, held until this function returns (cloud storage: see docs)
    lock = DriverLock(storage, grid.experiment) if "://" not in storage else None
    if lock is not None:
        lock.acquire()
        if lock.taken_over is not None:
            print(f"note: took over the lock of a dead driver ({lock.taken_over.describe()})", file=sys.stderr)
    elif args.resume:
        print("note: cloud storage has no driver lock: run one driver per experiment", file=sys.stderr)
    try:
        return _run_locked(grid, grid_file, args, specs, storage, exp_path, uri)
    finally:
        if lock is not None:
            lock.release()


def _run_locked(grid: GridConfig, grid_file: str, args: argparse.Namespace, specs: list[TrialSpec], storage: str,
                exp_path: str, uri: str) -> int:
    """Connect, check, then run the baselines and the trials (the driver lock is held)."""
    import ray

    restorable = _check_resume(args, exp_path, storage)
    started_ray = _connect_ray(args)
    pool = tracker = None
    grid_status = "KILLED"  # the parent run's status when this driver stops (FINISHED, FAILED, KILLED)
    t_start = time.perf_counter()
    try:
        _preflight(grid)
        tracker = _open_tracker(grid, grid_file, uri)
        pool = _start_baselines(grid, tracker)
        tuner = _tuner_for(grid, specs, storage, uri, grid_file, exp_path, tracker.commit, args.resume and restorable)
        results = _fit(tuner, pool)
        if results is None:
            grid_status = "FAILED"
            return EXIT_FAILED
        done, interrupted = _progress(results, trial_count(grid, specs))
        _settle_baselines(pool, interrupted)
        if pool.error is not None:
            print(f"error: {pool.error}", file=sys.stderr)
            grid_status = "FAILED"
            return EXIT_FAILED
        if results.errors or pool.failed:
            grid_status = "FAILED"
        elif not interrupted:
            grid_status = "FINISHED"
    except KeyboardInterrupt:
        if pool is not None:
            pool.cancel()
        print(f"interrupted: continue with  python -m uavlora_rllib.tune {args.grid} --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        _close_unfinished_runs(tracker, grid_status)
        if started_ray:
            ray.shutdown()
    return _report(grid, args, specs, uri, exp_path, results, pool, done, interrupted, time.perf_counter() - t_start)


def _check_resume(args: argparse.Namespace, exp_path: str, storage: str) -> bool:
    """Whether Tune state exists at `exp_path`; an error when it does without --resume."""
    from ray import tune

    restorable = tune.Tuner.can_restore(exp_path)
    if not args.resume and restorable:
        raise ConfigError(
            f"storage: the experiment {exp_path} exists already; continue it with --resume, "
            "or change experiment/--storage, or delete it"
        )
    if args.resume and not restorable:
        print(f"note: no Tune state at {exp_path} yet (the grid stopped before Tune started): starting the trials",
              file=sys.stderr)
    if args.address and "://" not in storage:
        print(f"note: on a cluster, storage {storage} must be a path shared by every node", file=sys.stderr)
    return restorable


def _connect_ray(args: argparse.Namespace) -> bool:
    """Connect to Ray unless already connected; True when this driver did (and shuts it down)."""
    import ray

    if ray.is_initialized():
        return False
    cluster.connect(args.address, args.num_cpus)
    return True


def _preflight(grid: GridConfig) -> None:
    """One trial's and the baselines' resources fit the cluster; print what it is."""
    from uavlora_rllib.experiment.baseline_tasks import BASELINE_CPUS

    cluster.preflight(cluster.as_bundles(trial_resources(grid)), BASELINE_CPUS, len(baseline_runs(grid)))
    print(f"Ray: {cluster.describe_cluster()}", flush=True)


def _open_tracker(grid: GridConfig, grid_file: str, uri: str):
    """The grid's MLflow experiment; MLflow unreachable is a failed preflight check (exit code 2)."""
    from uavlora_rllib.experiment.mlflow_client import Tracker, TrackingUnavailable

    try:
        tracker = Tracker(uri, grid.experiment, grid_file, retry_timeout_s=grid.mlflow.retry_timeout_s)
        tracker.open_grid_run()  # the parent of this grid's runs (kept by --resume)
        return tracker
    except TrackingUnavailable as exc:  # unreachable, or refused (TrackingRefused: credentials)
        raise ConfigError(str(exc)) from None


def _start_baselines(grid: GridConfig, tracker):
    """The baseline evaluations not yet FINISHED in MLflow, started as Ray tasks."""
    from uavlora_rllib.experiment.baseline_tasks import BaselinePool

    return BaselinePool(baselines_to_run(grid, tracker), grid.evaluation.episodes,
                        baseline_logger(grid, tracker)).start()


def _tuner_for(grid: GridConfig, specs: list[TrialSpec], storage: str, uri: str, grid_file: str, exp_path: str,
               commit: str, restore: bool):
    """The Tuner of the grid: restored from `exp_path` (--resume), or new."""
    from ray import tune

    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    if restore:
        trainable = tune.with_resources(UavLoraTrainable, trial_resources(grid))
        return tune.Tuner.restore(exp_path, trainable, resume_unfinished=True, resume_errored=True)
    return make_tuner(grid, specs, storage, uri, grid_file, commit)


def _fit(tuner, pool):
    """tuner.fit()'s results, or None when MLflow stayed unreachable (baselines cancelled, error printed)."""
    os.environ["RAY_AIR_NEW_OUTPUT"] = "0"  # the table of `status_reporter`
    try:
        return tuner.fit()
    except Exception as exc:
        failure = _tracking_failure(exc)
        if failure is None:
            raise
        pool.cancel()
        print(f"error: {failure}", file=sys.stderr)
        return None


def _progress(results, total: int) -> tuple[int, bool]:
    """(trials done, whether the grid stopped before every one of its `total` trials finished or failed)."""
    done = sum(1 for r in results if r.metrics and r.metrics.get("done"))
    return done, done + len(results.errors) < total


def _settle_baselines(pool, interrupted: bool) -> None:
    """Cancel the baselines of an interrupted grid, or wait for the rest of them."""
    if interrupted:
        pool.cancel()
        return
    if pool.pending:
        print(f"waiting for {pool.pending} baseline evaluation(s)", flush=True)
    pool.wait()


def _close_unfinished_runs(tracker, grid_status: str = "KILLED") -> None:
    """No run stays RUNNING once the grid stops: the parent run ends as `grid_status`, any run left
    by a crash KILLED (the callback closes its own)."""
    from uavlora_rllib.experiment.mlflow_client import TrackingUnavailable

    if tracker is None:
        return
    tracker.retry_timeout_s = min(tracker.retry_timeout_s, 10.0)  # MLflow may be the reason we stop
    try:
        tracker.end(tracker.grid_run(), grid_status)
        closed = tracker.close_running("KILLED")
        if closed:
            print(f"marked {len(closed)} unfinished MLflow run(s) KILLED", file=sys.stderr)
    except TrackingUnavailable:
        print("MLflow unreachable: runs left RUNNING are adopted by --resume", file=sys.stderr)


def _report(grid: GridConfig, args: argparse.Namespace, specs: list[TrialSpec], uri: str, exp_path: str, results,
            pool, done: int, interrupted: bool, wall: float) -> int:
    """Print the grid's outcome and where its results are; the exit code."""
    failed = len(results.errors)
    print(f"\n{done}/{trial_count(grid, specs)} trials finished, {failed} failed, in {wall:.0f} s")
    if pool.failed:
        print(f"{len(pool.failed)} baseline evaluation(s) failed: {', '.join(n for n, _ in pool.failed)}")
    print(f"MLflow: {describe_uri(uri)} (experiment {grid.experiment!r}; view with: mlflow ui --backend-store-uri {uri})")
    print(f"Ray results and checkpoints: {exp_path}")
    if failed or pool.failed:
        return EXIT_FAILED
    if interrupted:
        print(f"interrupted: continue with  python -m uavlora_rllib.tune {args.grid} --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


def _calibrate(grid: GridConfig, specs: list[TrialSpec], args: argparse.Namespace) -> int | None:
    """--calibrate: measure the grid's cells on this machine (experiment.calibration); an exit
    code if interrupted, else None."""
    from uavlora_rllib.experiment import calibration

    if not args.calibrate:
        raise UsageError("--calibrate-iterations: only with --calibrate")
    if args.resume or args.address:
        raise UsageError("--calibrate: measures this machine in a private local Ray and runs no trial; "
                         "drop --resume and --address")
    try:
        calibration.calibrate(grid, specs, iterations=args.calibrate_iterations or calibration.DEFAULT_ITERATIONS,
                              num_cpus=args.num_cpus)
    except KeyboardInterrupt:
        print(f"interrupted: the cells measured so far are kept; measure the rest with  "
              f"python -m uavlora_rllib.tune {args.grid} --calibrate", file=sys.stderr)
        return EXIT_INTERRUPTED
    return None


def main(argv: Sequence[str] | None = None) -> int:
    from uavlora_rllib.experiment.quiet import quiet_known_warnings

    quiet_known_warnings()
    try:
        args = build_parser().parse_args(argv)
        args.address = cluster.job_address(args.address)
        if args.list_hparams is not None:
            from uavlora_rllib.algorithms.common.config import describe_hparams

            entry = registry.get(args.list_hparams, path="--list-hparams")
            print(f"{entry.name}: hyperparameters (grid YAML `algorithms.{entry.name}:`)\n")
            print(describe_hparams(entry.hparams_cls))
            return EXIT_OK
        if args.grid is None:
            raise UsageError("grid: a grid YAML is required (or --list-hparams ALGO)")
        grid = load_grid(args.grid)
        local_problem = None
        if not args.address:  # a local Ray: a trial that needs more CPUs than it has never starts
            try:
                check_local_resources(grid, args.num_cpus or os.cpu_count() or 1)
            except ConfigError as exc:
                local_problem = f"{args.grid}: {exc}"
        specs = trials(grid)
        if (args.calibrate or args.calibrate_iterations is not None) and _calibrate(grid, specs, args) is not None:
            return EXIT_INTERRUPTED
        if args.dry_run or args.calibrate:  # a preview (e.g. of a cluster grid on a laptop): say it, do not refuse
            from uavlora_rllib.experiment.cost import dry_run_report

            print(trial_table(grid, specs))
            if local_problem:
                print(f"note: a local run would be refused: {local_problem}")
            print(dry_run_report(grid, specs, args.grid, args.num_cpus))
            return EXIT_OK
        if local_problem:
            raise ConfigError(local_problem)
        return run_grid(grid, args.grid, args)
    except (UsageError, ConfigError) as exc:
        return fail(exc, code=EXIT_USAGE)
    except ConnectionError as exc:  # ray.init(address=...) found no cluster there
        return fail(f"--address: cannot connect to a Ray cluster at {args.address!r}: {exc}", code=EXIT_USAGE)


if __name__ == "__main__":
    sys.exit(main())
