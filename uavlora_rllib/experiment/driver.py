"""One grid run of `python -m uavlora_rllib.tune`, phase by phase: paths and the driver lock,
the connection to Ray, the preflight checks, MLflow, the baselines, Tune, and the outcome."""

from __future__ import annotations

import argparse
import os
import sys
import time

from uavlora_rllib.cli_args import write_problem
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import cluster
from uavlora_rllib.experiment.grid import GridConfig, TrialSpec, baseline_runs, trial_count, trials
from uavlora_rllib.experiment.tuner import grid_identity, trial_resources, tuner_for

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_BROKEN_PIPE = 141  # stdout closed by its reader (`| head`): 128 + SIGPIPE, as a shell's commands end


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
    except OSError as exc:
        raise ConfigError(f"storage: cannot write to {storage}: {exc.strerror or exc}") from None
    problem = write_problem(storage)
    if problem:
        raise ConfigError(f"storage: cannot write to {storage}: {problem}")


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


def _run_locked(
    grid: GridConfig,
    grid_file: str,
    args: argparse.Namespace,
    specs: list[TrialSpec],
    storage: str,
    exp_path: str,
    uri: str,
) -> int:
    """Connect, check, then run the baselines and the trials (the driver lock is held)."""
    import ray

    restorable = _check_resume(args, exp_path, storage)
    started_ray = _connect_ray(args)
    _sigterm_as_ctrl_c()  # after Ray's start, which installs its own (a core dump, exit 134)
    pool = tracker = None
    grid_status = "KILLED"  # the parent run's status when this driver stops (FINISHED, FAILED, KILLED)
    t_start = time.perf_counter()
    try:
        _preflight(grid)
        if args.address and "://" not in storage:  # (after connecting: a failed connect stays one line)
            print(f"note: on a cluster, storage {storage} must be a path shared by every node", file=sys.stderr)
        tracker = _open_tracker(grid, grid_file, uri, grid_identity(grid, specs), args.resume and restorable)
        pool = _start_baselines(grid, tracker)
        tuner = tuner_for(grid, specs, storage, uri, grid_file, exp_path, tracker.commit, args.resume and restorable)
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
        print(
            f"note: no Tune state at {exp_path} yet (the grid stopped before Tune started): starting the trials",
            file=sys.stderr,
        )
    return restorable


def _sigterm_as_ctrl_c() -> None:
    """SIGTERM (`kill`, a job scheduler, Kubernetes) stops the grid as one Ctrl+C does: Tune saves
    its state, unfinished runs are marked KILLED, exit 130, resumable. The handler sends this
    process SIGINT, whose handler is Tune's inside fit() and KeyboardInterrupt elsewhere."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, lambda signum, frame: os.kill(os.getpid(), signal.SIGINT))


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


def _open_tracker(grid: GridConfig, grid_file: str, uri: str, identity: dict[str, str], restoring: bool):
    """The grid's MLflow experiment; MLflow unreachable is a failed preflight check (exit code 2).
    A grid that restores Tune state must be the grid the experiment started with (`identity`,
    tuner.grid_identity, kept as tags of the grid run): Tune restores the trials it started with
    and would leave the new ones unrun, reporting the grid interrupted at every --resume."""
    from uavlora_rllib.experiment.mlflow_client import Tracker, TrackingUnavailable

    try:
        tracker = Tracker(uri, grid.experiment, grid_file, retry_timeout_s=grid.mlflow.retry_timeout_s)
        tags = {f"grid_{k}": v for k, v in identity.items()}
        if restoring:
            _check_same_grid(tracker.get_run(tracker.grid_run()).data.tags, tags, grid)
        tracker.open_grid_run()  # the parent of this grid's runs (kept by --resume)
        if not restoring:
            for key, value in tags.items():
                tracker.set_tag(tracker.grid_run(), key, value)
        return tracker
    except TrackingUnavailable as exc:  # unreachable, or refused (TrackingRefused: credentials)
        raise ConfigError(str(exc)) from None


def _check_same_grid(started: dict[str, str], now: dict[str, str], grid: GridConfig) -> None:
    """ConfigError (nothing touched yet) where the experiment was started from another grid; an
    experiment started before these tags were kept is not checked."""
    if "grid_digest" not in started or started["grid_digest"] == now["grid_digest"]:
        return
    changed = [
        f"{what} {started.get(key)} -> {now[key]}"
        for what, key in (("trials", "grid_trials"), ("stop.env_steps", "grid_budget"))
        if started.get(key) != now[key]
    ] or ["the trials' settings: a hyperparameter (a plugin's default too), the scenario, resources or evaluation"]
    raise ConfigError(
        f"--resume: this grid is not the one experiment {grid.experiment!r} started with ({', '.join(changed)}); "
        "a resumed experiment runs only the trials it started with: restore that YAML (the grid run's "
        "grid.yaml in MLflow), or run the changed grid under a new `experiment` name"
    )


def _start_baselines(grid: GridConfig, tracker):
    """The baseline evaluations not yet FINISHED in MLflow, started as Ray tasks."""
    from uavlora_rllib.experiment.baseline_tasks import BaselinePool, baseline_logger, baselines_to_run

    return BaselinePool(
        baselines_to_run(grid, tracker), grid.evaluation.episodes, baseline_logger(grid, tracker)
    ).start()


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


def _report(
    grid: GridConfig,
    args: argparse.Namespace,
    specs: list[TrialSpec],
    uri: str,
    exp_path: str,
    results,
    pool,
    done: int,
    interrupted: bool,
    wall: float,
) -> int:
    """Print the grid's outcome and where its results are; the exit code."""
    failed = len(results.errors)
    print(f"\n{done}/{trial_count(grid, specs)} trials finished, {failed} failed, in {wall:.0f} s")
    if pool.failed:
        print(f"{len(pool.failed)} baseline evaluation(s) failed: {', '.join(n for n, _ in pool.failed)}")
    print(
        f"MLflow: {describe_uri(uri)} (experiment {grid.experiment!r}; view with: mlflow ui --backend-store-uri {uri})"
    )
    print(f"Ray results and checkpoints: {exp_path}")
    if failed or pool.failed:
        return EXIT_FAILED
    if interrupted:
        print(f"interrupted: continue with  python -m uavlora_rllib.tune {args.grid} --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK
