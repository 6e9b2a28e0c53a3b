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
  experiment is an error (no silent second copy of the grid), and so is ``--resume`` of a grid
  whose trials differ from those the experiment started with (Tune cannot add or change one).
* Interrupt with Ctrl+C (SIGINT) once, or SIGTERM (treated the same): Tune saves the experiment
  state and the MLflow runs of unfinished trials are marked KILLED; ``--resume`` picks them up. A driver killed outright
  (SIGKILL, lost machine) is also resumable: see `experiment.mlflow_callback`. Exit codes: 0 all
  trials and baselines finished, 1 some failed (or MLflow stayed unreachable), 130
  interrupted, 2 bad input or a failed preflight check.

This module is the command line; a run's phases are in `experiment.driver`, what it gives Tune
in `experiment.tuner`, and the --dry-run table in `experiment.dry_run`. Running on a cluster
(shared storage, MLflow server, token auth, Ray Jobs, GPUs): docs/cluster.md.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from typing import Any

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import cluster
from uavlora_rllib.experiment.driver import EXIT_BROKEN_PIPE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE, run_grid
from uavlora_rllib.experiment.dry_run import trial_table
from uavlora_rllib.experiment.grid import check_local_resources, check_storage, load_grid, trials


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
        f"descriptions, and exit; ALGO one of {sorted(registry.MODULES)}, or a plugin's (give the grid that lists it)",
    )
    p.add_argument("--resume", action="store_true", help="continue the grid's Tune experiment")
    p.add_argument(
        "--dry-run",
        action="store_true",
        help="print the trials, the baseline runs and the grid's estimated cost (from --calibrate), start nothing",
    )
    p.add_argument(
        "--calibrate",
        action="store_true",
        help="measure on this machine what each distinct trial and baseline of the grid costs (short runs), "
        "store it for --dry-run's estimate, then print the dry run",
    )
    p.add_argument(
        "--calibrate-iterations",
        type=int_in(1, 100),
        default=None,
        metavar="N",
        help="with --calibrate: timed training iterations per trial cell, after the warm-up (default 2)",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (default: start a local Ray; under `ray job submit`: the job's cluster)",
    )
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


def _calibrate(grid, specs, args: argparse.Namespace) -> int | None:
    """--calibrate: measure the grid's cells on this machine (experiment.calibration); an exit
    code if interrupted, else None."""
    from uavlora_rllib.experiment import calibration

    if not args.calibrate:
        raise UsageError("--calibrate-iterations: only with --calibrate")
    if args.resume or args.address:
        raise UsageError(
            "--calibrate: measures this machine in a private local Ray and runs no trial; drop --resume and --address"
        )
    try:
        calibration.calibrate(
            grid, specs, iterations=args.calibrate_iterations or calibration.DEFAULT_ITERATIONS, num_cpus=args.num_cpus
        )
    except KeyboardInterrupt:
        print(
            f"interrupted: the cells measured so far are kept; measure the rest with  "
            f"python -m uavlora_rllib.tune {args.grid} --calibrate",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    return None


def _stdout_closed() -> bool:
    """Whether stdout's reader has gone: the write end of a pipe whose reader closed it polls as an
    error (POLLERR), and a flush of what is still buffered fails."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        if any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0)):
            return True
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError, AttributeError):  # no real descriptor (a captured stdout)
        return False
    return False


def main(argv: Sequence[str] | None = None) -> int:
    from uavlora_rllib.experiment.quiet import quiet_known_warnings

    quiet_known_warnings()
    try:
        args = build_parser().parse_args(argv)
        if args.address is not None and not args.address.strip():
            raise UsageError(
                "--address: empty; allowed: auto, HOST:PORT or ray://HOST:10001 (or leave it out: a local Ray)"
            )
        if args.grid == "":
            raise UsageError("grid: empty path; give a grid YAML file")
        args.address = cluster.job_address(args.address)
        if args.list_hparams is not None:
            if args.grid is not None:  # its plugins' algorithms become listable; the rest of it is not read
                from uavlora_rllib.experiment.grid import import_grid_plugins

                import_grid_plugins(args.grid)
            from uavlora_rllib.algorithms.common.hparams import describe_hparams

            entry = registry.spec(args.list_hparams, path="--list-hparams")
            print(f"{entry.name}: hyperparameters (grid YAML `algorithms.{entry.name}:`)\n")
            print(describe_hparams(entry.hparams_cls))
            return EXIT_OK
        if args.grid is None:
            raise UsageError("grid: a grid YAML is required (or --list-hparams ALGO)")
        if args.dry_run and args.resume:  # a preview of the whole grid, not of what a resume would redo
            raise UsageError(
                "--dry-run: previews the grid and starts nothing, so --resume has nothing to resume; drop one of them"
            )
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
    except BrokenPipeError as exc:
        if not _stdout_closed():  # another pipe (a socket, a subprocess): an error like any other
            return fail(f"broken pipe: {exc}", code=EXIT_USAGE)
        # stdout closed early (`--dry-run | head`): nothing left to say, and no cluster to blame
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's own flush at exit must not fail
        return EXIT_BROKEN_PIPE
    except ConnectionError as exc:  # ray.init(address=...) found no cluster there
        return fail(f"--address: cannot connect to a Ray cluster at {args.address!r}: {exc}", code=EXIT_USAGE)


if __name__ == "__main__":
    sys.exit(main())
