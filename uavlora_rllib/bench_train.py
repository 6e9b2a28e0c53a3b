"""Training-throughput benchmark for any registered algorithm.

    python -m uavlora_rllib.bench_train ALGO [--iterations K] [--n-eds V --n-uavs U]
        [--episode-len T] [--envs-per-runner N] [--env-runners R] [--torch-threads K]
        [--learner-precision float32|bfloat16] [--set key=value ...]

Builds ALGO from the registry (hyperparameter overrides with --set, validated like the grid
YAML), trains K iterations after one warm-up iteration (`experiment.training_rate`, the
measurement the grid calibration uses too), and prints env steps per second end
to end (env steps sampled / wall-clock of the timed iterations) and how each iteration's
time splits between sampling and learning (RLlib's `timers`: env_runner_sampling_timer,
learner_update_timer, synch_weights). Also the wall-clock this rate implies for the paper's
T_max = 2M env steps, and for bfloat16 the route this CPU takes (docs/model.md#learner-precision).
Bad input (a flag, an unknown algorithm, a bad override, a scenario the algorithm does not
support) gives one line on stderr and exit code 2 before Ray starts.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import yaml

from uavlora_rllib.algorithms.common.registry import MAX_TORCH_THREADS
from uavlora_rllib.cli_args import SEED_MAX, Parser, UsageError, fail, int_in
from uavlora_rllib.experiment.grid import UniqueKeyLoader
from uavlora_rllib.sim.scenario import MAX_ENVS

T_MAX = 2_000_000


def _parse_set(items: list[str]) -> dict:
    """KEY=VALUE overrides, each VALUE read as the grid YAML reads it (so 1e-3 is a number, true a
    bool: the hyperparameter class then refuses a bool for a number)."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise UsageError(f"--set: expected key=value, got {item!r}")
        if key in out:
            raise UsageError(f"--set: {key!r} given twice")
        try:
            out[key] = yaml.load(value, Loader=UniqueKeyLoader)  # noqa: S506 (SafeLoader)
        except yaml.YAMLError as exc:
            raise UsageError(f"--set: {key}: cannot read the value {value!r}: {str(exc).splitlines()[0]}") from None
    return out


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m uavlora_rllib.bench_train", description=__doc__.split("\n")[0])
    p.add_argument("algo", help="a registered algorithm (python -m uavlora_rllib.tune --list-hparams ALGO)")
    p.add_argument(
        "--iterations",
        type=int_in(1, 100_000),
        default=5,
        help="timed training iterations, after one untimed warm-up iteration (default 5)",
    )
    p.add_argument("--n-eds", type=int_in(1), default=10, help="V, end devices (default 10)")
    p.add_argument("--n-uavs", type=int_in(1), default=2, help="U, UAVs (default 2)")
    p.add_argument("--episode-len", type=int_in(1), default=150, help="slots per episode (default 150)")
    p.add_argument(
        "--action-mode",
        choices=("per_uav", "per_device"),
        default="per_uav",
        help="the scenario's action mode (default per_uav)",
    )
    p.add_argument(
        "--envs-per-runner",
        type=int_in(1, MAX_ENVS),
        default=8,
        help="scenarios sampled at once per env runner, in one BatchCore (default 8)",
    )
    p.add_argument(
        "--env-runners",
        type=int_in(0, 10_000),
        default=0,
        help="remote env runners; 0 samples in the algorithm's own process (default 0)",
    )
    p.add_argument(
        "--torch-threads", type=int_in(1, MAX_TORCH_THREADS), default=1, help="torch threads of the learner (default 1)"
    )
    p.add_argument(
        "--learner-precision",
        choices=("float32", "bfloat16"),
        default="float32",
        help="number format of the learner's matrix products (resources.learner_precision; default float32)",
    )
    p.add_argument(
        "--num-cpus", type=int_in(1, 100_000), default=None, help="CPUs of the local Ray (default: all of this machine)"
    )
    p.add_argument("--seed", type=int_in(0, SEED_MAX), default=0, help="training seed (default 0)")
    p.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="hyperparameter overrides, e.g. --set lr=3e-4 share_actor=true",
    )
    p.add_argument("--json", action="store_true", help="print one JSON line as well")
    return p


def _resolve(args: argparse.Namespace):
    """(entry, scenario, hparams, resources) from the flags; UsageError / ConfigError if bad."""
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.config_errors import build
    from uavlora_rllib.sim.scenario import ScenarioConfig

    entry = registry.get(args.algo, path="algo")
    scenario = ScenarioConfig.from_dict(
        {"n_eds": args.n_eds, "n_uavs": args.n_uavs, "episode_len": args.episode_len, "action_mode": args.action_mode}
    )
    entry.check_scenario(scenario, prefix="--action-mode")
    hparams = entry.hparams(_parse_set(args.set), prefix="--set")
    resources = build(
        registry.Resources,
        {
            "num_env_runners": args.env_runners,
            "num_envs_per_env_runner": args.envs_per_runner,
            "torch_threads": args.torch_threads,
            "learner_precision": args.learner_precision,
        },
        "resources",
    )
    need = resources.num_cpus_per_learner + resources.num_env_runners * resources.num_cpus_per_env_runner
    cpus = args.num_cpus or os.cpu_count() or 1
    if need > cpus:  # Ray would wait for the missing CPUs forever
        raise UsageError(f"--env-runners: {args.env_runners} runners and a learner need {need:g} CPUs; Ray has {cpus}")
    entry.algorithm_config(scenario, hparams, resources, args.seed)  # the entry's own cross-checks, before Ray starts
    return entry, scenario, hparams, resources


_ROUTE_WORDS = {  # common/precision.py precision_name -> how bench_train says it
    "bfloat16/onednn": "bfloat16 by oneDNN's bfloat16 products",
    "bfloat16/autocast": "bfloat16 by torch.autocast (this CPU's oneDNN does not round)",
}


def precision_line(precision: str) -> str:
    """The learner's number format as bench_train runs it (its learner is this process's, on the CPU): for
    bfloat16, the route this CPU takes (common/precision.py), since the two differ in speed."""
    import torch

    from uavlora_rllib.algorithms.common.precision import precision_name

    name = precision_name(precision, torch.device("cpu"))
    return f"learner precision: {_ROUTE_WORDS.get(name, name)}"


def main(argv: list[str] | None = None) -> int:
    from uavlora_rllib.config_errors import ConfigError

    try:
        args = build_parser().parse_args(argv)
        entry, scenario, hparams, resources = _resolve(args)
    except (UsageError, ConfigError) as exc:
        return fail(exc)

    import ray

    from uavlora_rllib.experiment.training_rate import measure_training

    # "local": a private Ray even where `ray start` runs a cluster on this machine (a bare init attaches to it)
    ray.init(address="local", num_cpus=args.num_cpus, include_dashboard=False, log_to_driver=False)
    try:
        m = measure_training(entry, scenario, hparams, resources, args.seed, args.iterations)
    finally:
        ray.shutdown()

    rows, total, t_build = m.rows, m.total_s, m.build_s
    env_steps = m.env_steps
    rate = m.env_steps_per_s
    # Sum of the timed iterations' own timer values.
    last = {k: sum(r[k] for r in rows) for k in ("wall_s", "env_steps", "sample_s", "learn_s", "sync_s")}
    share = {k: last[k] / max(last["wall_s"], 1e-9) for k in ("sample_s", "learn_s", "sync_s")}
    print(
        f"{args.algo}: V={args.n_eds} U={args.n_uavs} T={args.episode_len} {args.action_mode} "
        f"runners={args.env_runners} envs/runner={args.envs_per_runner} hparams={_parse_set(args.set)}"
    )
    print(f"  {precision_line(resources.learner_precision)}")
    print(f"  build {t_build:.1f} s; {args.iterations} timed iterations, {env_steps} env steps in {total:.2f} s")
    print(f"  end to end: {rate:,.0f} env steps/s  -> 2M env steps in {T_MAX / rate / 3600:.2f} h")
    print(
        f"  per iteration: {total / args.iterations:.2f} s = sampling {last['sample_s'] / args.iterations:.2f} s "
        f"({share['sample_s']:.0%}), learning {last['learn_s'] / args.iterations:.2f} s ({share['learn_s']:.0%}), "
        f"weight sync {last['sync_s'] / args.iterations:.3f} s"
    )
    print(
        f"  sampling alone: {last['env_steps'] / max(last['sample_s'], 1e-9):,.0f} env steps/s; "
        f"learning alone: {last['env_steps'] / max(last['learn_s'], 1e-9):,.0f} env steps/s"
    )
    if args.json:
        print(json.dumps({"algo": args.algo, "env_steps_per_s": rate, "rows": rows, "build_s": t_build}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
