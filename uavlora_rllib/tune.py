"""Run a grid YAML: baseline evaluations, then one Ray Tune trial per algorithm x seed x V x U.

    python -m uavlora_rllib.tune GRID.yaml [--resume] [--dry-run] [--address ADDR]
                                           [--storage DIR] [--num-cpus N]

* The grid is validated first (`grid.load_grid`); a bad grid prints ONE line on stderr and
  exits with code 2 before Ray starts. ``--dry-run`` prints the trial table and the baseline
  evaluations and exits 0 without starting Ray.
* Baselines (``baselines:``) are evaluated on the driver, one MLflow run (kind=baseline) per
  baseline x seed x V x U; a FINISHED run with the same scenario is not redone.
* Training: one `UavLoraTrainable` trial per `grid.trials` entry, resources per trial from
  ``resources:`` (1 learner bundle + one bundle per env runner), a checkpoint every
  ``checkpoint_every`` iterations and at the end, stop at ``stop.env_steps`` env steps
  sampled, then the execution-phase evaluation (the entry's greedy policy, the trial's seed,
  ``evaluation.episodes`` episodes) reported as ``eval/*``. `tracking.MlflowTrialCallback`
  logs everything to MLflow from the driver.
* ``--resume`` restores the Tune experiment ``<storage>/<experiment>``: finished trials are
  not rerun, interrupted or errored ones continue from their last checkpoint, and each trial
  keeps its one MLflow run (found again by its trial_id tag). Without ``--resume`` an
  existing experiment directory is an error (no silent second copy of the grid).
* Interrupt with Ctrl+C (SIGINT) once: Tune saves the experiment state and the MLflow runs of
  unfinished trials are marked KILLED; ``--resume`` picks them up. Exit codes: 0 all trials
  finished, 1 some trial failed, 130 interrupted, 2 bad input.

On a Ray cluster (``--address auto`` or ``ray://host:10001``): the project must be installed
on every node (same venv), ``storage`` (or ``--storage``) must be a path every node can
reach (NFS mount, or a cloud URI such as ``s3://bucket/ray_results``), and the MLflow URI
is written by the driver only (a sqlite file on the driver's disk, or an MLflow server).
Algorithms registered through ``plugins:`` must be importable on every node.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from typing import Any, Sequence

from ray import tune

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in
from uavlora_rllib.experiment.grid import (
    GridConfig,
    algorithm_overrides,
    TrialSpec,
    baseline_runs,
    hparams_dict,
    check_local_resources,
    check_storage,
    import_plugins,
    load_grid,
    run_name,
    trials,
)

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130


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
    p.add_argument("--dry-run", action="store_true", help="print the trials and baseline runs, start nothing")
    p.add_argument("--address", default=None, help="Ray cluster address (default: start a local Ray)")
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
    path = override or grid.storage
    return path if "://" in path else os.path.abspath(os.path.expanduser(path))


def absolute_tracking_uri(uri: str) -> str:
    """sqlite:///relative.db -> sqlite:////abs/relative.db (resolved against the working dir)."""
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri.startswith(prefix + "/") and ":memory:" not in uri:
        return prefix + os.path.abspath(uri[len(prefix) :])
    return uri


def describe_uri(uri: str) -> str:
    return uri[len("sqlite:///") :] if uri.startswith("sqlite:///") else uri


# --------------------------------------------------------------------------- dry run
def trial_table(grid: GridConfig, specs: list[TrialSpec]) -> str:
    base = baseline_runs(grid)
    lines = [
        f"experiment {grid.experiment!r}: {len(specs)} trials = {len(grid.algorithms)} algorithms x "
        f"{len(grid.seeds)} seeds x {len(grid.n_eds)} n_eds x {len(grid.n_uavs)} n_uavs; "
        f"{len(base)} baseline evaluations",
        f"{'#':>4}  {'algorithm':<12} {'seed':>6} {'n_eds':>6} {'n_uavs':>6} {'budget_env_steps':>17}",
    ]
    for i, s in enumerate(specs, 1):
        lines.append(f"{i:>4}  {s.algorithm:<12} {s.seed:>6} {s.n_eds:>6} {s.n_uavs:>6} {grid.stop.env_steps:>17}")
    lines.append(f"baseline evaluations ({grid.evaluation.episodes} episodes each):")
    if base:
        lines.append(f"{'#':>4}  {'baseline':<12} {'seed':>6} {'n_eds':>6} {'n_uavs':>6}")
        for i, b in enumerate(base, 1):
            lines.append(f"{i:>4}  {b.baseline:<12} {b.seed:>6} {b.n_eds:>6} {b.n_uavs:>6}")
    else:
        lines.append("   (none)")
    return "\n".join(lines)


# --------------------------------------------------------------------------- the trainable
def trial_config(spec: TrialSpec, grid: GridConfig) -> dict[str, Any]:
    """What one trial needs (and what its MLflow run records), plain data only."""
    from uavlora_rllib.experiment import periodic_eval  # imports RLlib: not at module import

    return {
        "algorithm": spec.algorithm,
        "seed": spec.seed,
        "n_eds": spec.n_eds,
        "n_uavs": spec.n_uavs,
        "scenario": spec.scenario.to_dict(),
        "overrides": algorithm_overrides(grid, spec.algorithm, registry.get(spec.algorithm)),
        "hparams": hparams_dict(spec.hparams),
        "resources": dataclasses.asdict(grid.resources),
        "budget_env_steps": grid.stop.env_steps,
        "eval_episodes": grid.evaluation.episodes,
        "eval_interval_env_steps": periodic_eval.resolve_interval(grid.evaluation.interval_env_steps, grid.stop.env_steps),
        "plugins": list(grid.plugins),
    }


class UavLoraTrainable(tune.Trainable):
    """One trial: build the registry entry's algorithm, train to the budget, evaluate."""

    def setup(self, config: dict) -> None:
        import torch

        from uavlora_rllib.sim.scenario import ScenarioConfig

        import uavlora_rllib.envs.multi_agent  # noqa: F401  (registers the "uavlora" env)
        from uavlora_rllib.experiment import periodic_eval

        cfg = config.get("trial", config)
        self.cfg = cfg
        import_plugins(cfg.get("plugins", []))
        resources = registry.Resources(**cfg["resources"])
        torch.set_num_threads(resources.torch_threads)
        self.entry = registry.get(cfg["algorithm"])
        self.scenario = ScenarioConfig.from_dict(cfg["scenario"])
        hparams = self.entry.hparams(cfg["overrides"])
        algo_config = self.entry.build(self.scenario, hparams, resources, int(cfg["seed"]))
        periodic_eval.attach(algo_config, periodic_eval.PeriodicEvalSettings(
            self.scenario, int(cfg.get("eval_interval_env_steps", 0)), int(cfg["eval_episodes"]), int(cfg["seed"])))
        self.algo = algo_config.build_algo()
        self._last_steps: int | None = 0

    def step(self) -> dict:
        from uavlora_rllib.experiment import periodic_eval
        from uavlora_rllib.experiment.tracking import ENV_STEPS, _lookup, _number, training_summary

        t0 = time.perf_counter()
        result = self.algo.train()
        dt = max(time.perf_counter() - t0, 1e-9)
        out = training_summary(result)
        out.update(periodic_eval.metrics_from_result(result))  # the greedy-policy curve's points
        steps = out[ENV_STEPS]
        if self._last_steps is not None:
            sampled = steps - self._last_steps
        else:  # first iteration after a restore
            sampled = _number(_lookup(result, "env_runners/num_env_steps_sampled")) or 0
        out["env_steps_per_s"] = float(sampled) / dt
        self._last_steps = steps
        if steps >= int(self.cfg["budget_env_steps"]):
            out.update(self.evaluate())
            out["done"] = True
        return out

    def evaluate(self) -> dict:
        from uavlora_rllib.experiment.evaluation import run_episodes
        from uavlora_rllib.experiment.tracking import eval_metrics

        policy = self.entry.greedy_policy(self.algo, self.scenario)
        res = run_episodes(policy, self.scenario, int(self.cfg["eval_episodes"]), int(self.cfg["seed"]))
        return eval_metrics(res.summary())

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        self.algo.save_to_path(checkpoint_dir)

    def load_checkpoint(self, checkpoint: Any) -> None:
        path = checkpoint if isinstance(checkpoint, (str, os.PathLike)) else checkpoint.get("checkpoint_dir")
        self.algo.restore_from_path(os.fspath(path))
        self._last_steps = None

    def reset_config(self, new_config: dict) -> bool:
        """Reuse this actor for the next trial (saves a process start and the RLlib import)."""
        self.cleanup()
        self.setup(new_config)
        return True

    def cleanup(self) -> None:
        algo = getattr(self, "algo", None)
        if algo is not None:
            algo.stop()
            self.algo = None


def trial_resources(grid: GridConfig):
    from ray.tune import PlacementGroupFactory

    r = grid.resources
    bundles = [{"CPU": r.num_cpus_per_learner}] + [{"CPU": r.num_cpus_per_env_runner}] * r.num_env_runners
    return PlacementGroupFactory(bundles, strategy="PACK")


def _trial_name(trial) -> str:
    c = trial.config.get("trial", trial.config)
    return run_name(c["algorithm"], c["n_eds"], c["n_uavs"], c["seed"])


def _trial_dirname(trial) -> str:
    return f"{_trial_name(trial)}_{trial.trial_id}"


# --------------------------------------------------------------------------- phases
def run_baselines(grid: GridConfig, tracker, out=None) -> None:
    from uavlora_rllib.baselines.policies import make_baseline
    from uavlora_rllib.evaluate import run_with_progress
    from uavlora_rllib.experiment.tracking import run_params

    out = out or sys.stdout
    episodes = grid.evaluation.episodes
    for b in baseline_runs(grid):
        params = run_params(b.scenario, None, episodes)
        if tracker.finished_baseline(b.baseline, b.seed, b.n_eds, b.n_uavs, params):
            print(f"baseline {b.name}: already in MLflow, skipped", file=out, flush=True)
            continue
        t0 = time.perf_counter()

        def evaluate(b=b):
            policy = make_baseline(b.baseline, b.scenario, seed=b.seed)
            # run_episodes, with an estimate and a progress bar on stderr when it is long (optimal)
            return run_with_progress(policy, b.scenario, episodes, b.seed, b.baseline, f"baseline {b.name}").summary()

        tracker.log_baseline(b.baseline, b.name, b.seed, b.n_eds, b.n_uavs, params, evaluate, grid.stop.env_steps)
        print(f"baseline {b.name}: evaluated in {time.perf_counter() - t0:.1f} s", file=out, flush=True)


def run_grid(grid: GridConfig, grid_file: str, args: argparse.Namespace) -> int:
    import ray

    from uavlora_rllib.experiment.tracking import MlflowTrialCallback, Tracker

    specs = trials(grid)
    storage = storage_path(grid, args.storage)
    exp_path = os.path.join(storage, grid.experiment) if "://" not in storage else f"{storage}/{grid.experiment}"
    uri = absolute_tracking_uri(grid.mlflow.tracking_uri)
    trainable = tune.with_resources(UavLoraTrainable, trial_resources(grid))

    if args.resume:
        if not tune.Tuner.can_restore(exp_path):
            raise ConfigError(f"--resume: no Tune experiment to resume at {exp_path}")
    elif "://" not in exp_path and os.path.exists(os.path.join(exp_path, "tuner.pkl")):
        raise ConfigError(
            f"storage: the experiment {exp_path} exists already; continue it with --resume, "
            "or change experiment/--storage, or delete it"
        )
    if args.address and "://" not in storage:
        print(f"note: on a cluster, storage {storage} must be a path shared by every node", file=sys.stderr)

    tracker = Tracker(uri, grid.experiment, grid_file)
    t_start = time.perf_counter()
    try:
        run_baselines(grid, tracker)
    except KeyboardInterrupt:
        # Tune has not started: nothing to resume; finished baseline runs are skipped next time
        print("interrupted during the baseline evaluations; run the same command again", file=sys.stderr)
        return EXIT_INTERRUPTED

    started_ray = False
    if not ray.is_initialized():
        if args.address:
            ray.init(address=args.address)
        else:
            ray.init(num_cpus=args.num_cpus, include_dashboard=False)
        started_ray = True
    try:
        if args.resume:
            tuner = tune.Tuner.restore(exp_path, trainable, resume_unfinished=True, resume_errored=True)
        else:
            callback = MlflowTrialCallback(uri, grid.experiment, grid_file, tracker.commit)
            tuner = tune.Tuner(
                trainable,
                param_space={"trial": tune.grid_search([trial_config(s, grid) for s in specs])},
                tune_config=tune.TuneConfig(
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
                        checkpoint_frequency=grid.checkpoint_every, checkpoint_at_end=True, num_to_keep=2
                    ),
                    verbose=1,
                ),
            )
        results = tuner.fit()
    finally:
        # no run may stay RUNNING once the grid stops (the callback closes its own; this
        # catches any left by a crash)
        closed = tracker.close_running("KILLED")
        if closed:
            print(f"marked {len(closed)} unfinished MLflow run(s) KILLED", file=sys.stderr)
        if started_ray:
            ray.shutdown()

    done = sum(1 for r in results if r.metrics and r.metrics.get("done"))
    failed = len(results.errors)
    wall = time.perf_counter() - t_start
    print(f"\n{done}/{len(specs)} trials finished, {failed} failed, in {wall:.0f} s")
    print(f"MLflow: {describe_uri(uri)} (experiment {grid.experiment!r}; view with: mlflow ui --backend-store-uri {uri})")
    print(f"Ray results and checkpoints: {exp_path}")
    if failed:
        return EXIT_FAILED
    if done < len(specs):
        print(f"interrupted: continue with  python -m uavlora_rllib.tune {grid_file} --resume", file=sys.stderr)
        return EXIT_INTERRUPTED
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        if args.list_hparams is not None:
            from uavlora_rllib.algorithms.common.config import describe_hparams

            entry = registry.get(args.list_hparams, path="--list-hparams")
            print(f"{entry.name}: hyperparameters (grid YAML `algorithms.{entry.name}:`)\n")
            print(describe_hparams(entry.hparams_cls))
            return EXIT_OK
        if args.grid is None:
            raise UsageError("grid: a grid YAML is required (or --list-hparams ALGO)")
        grid = load_grid(args.grid)
        if not args.address:  # a local Ray: a trial that needs more CPUs than it has never starts
            try:
                check_local_resources(grid, args.num_cpus or os.cpu_count() or 1)
            except ConfigError as exc:
                raise ConfigError(f"{args.grid}: {exc}") from None
        specs = trials(grid)
        if args.dry_run:
            print(trial_table(grid, specs))
            return EXIT_OK
        return run_grid(grid, args.grid, args)
    except (UsageError, ConfigError) as exc:
        return fail(exc, code=EXIT_USAGE)
    except ConnectionError as exc:  # ray.init(address=...) found no cluster there
        return fail(f"--address: cannot connect to a Ray cluster at {args.address!r}: {exc}", code=EXIT_USAGE)


if __name__ == "__main__":
    sys.exit(main())
