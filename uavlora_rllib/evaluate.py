"""Execution-phase CLI: evaluate a baseline or a trained checkpoint on fresh episodes.

    python -m uavlora_rllib.evaluate --policy {random,fixed,adr,best_fixed,greedy,optimal|CHECKPOINT_DIR}
        [--n-eds V] [--n-uavs U] [--episodes K] [--seed S] [--json]
        [--scenario-yaml FILE] [--objective ee|reward] [--execution greedy|sampled]

Prints the paper's execution metrics (evaluation.run_episodes), each as the mean over
episodes with its 95% CI half-width; `--json` prints one JSON object instead. The references
(greedy, optimal) also print an upper bound on the per-slot optimum of the same slots
(baselines.bound), so their EE is bracketed. A checkpoint
runs greedy (argmax per UAV: the paper's execution phase) or, with `--execution sampled`, with
actions drawn from its trained distribution (seeded by --seed). Bad input
(a flag, the scenario YAML, a checkpoint that cannot be restored or that was trained for a
scenario whose observation or action spaces differ from this one) gives one line on stderr
and exit code 2, before anything runs. An evaluation estimated to take more than
LONG_SECONDS (baselines.policies.evaluation_seconds: `optimal` beyond U = 2, many episodes)
prints its estimate first and shows a progress bar on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from uavlora_rllib.baselines.policies import (
    BASELINES,
    OBJECTIVES,
    REFERENCES,
    baseline_names,
    evaluation_seconds,
    make_baseline,
)
from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in, positive_int, seed
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment.evaluation import BOUND_METRIC
from uavlora_rllib.experiment.grid import parse_yaml, read_yaml_text
from uavlora_rllib.sim.actions import ActionError
from uavlora_rllib.sim.scenario import ScenarioConfig, off_defaults

if TYPE_CHECKING:
    from uavlora_rllib.experiment.open_loop import OpenLoopCheck

PROG = "evaluate"
MAX_EPISODES = 1_000_000
LONG_SECONDS = 10.0  # evaluations estimated longer than this print the estimate and show progress

# (key in the JSON output, label, unit)
REPORTED = (
    ("ee_sys_mean", "EE_sys per slot", "bit/J"),
    ("ee_sys_episode_sum", "EE_sys episode sum", "bit/J"),
    ("success_rate", "success rate Xi", ""),
    ("mean_sinr_db", "mean SINR", "dB"),
    ("unassociated_frac", "unassociated fraction", ""),
    ("p_total_w", "P_total", "W"),
    ("reward_mean", "reward per slot", ""),
)
BOUND_ROW = (BOUND_METRIC, "EE_sys upper bound", "bit/J")  # references only


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m uavlora_rllib.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help=f"one of {', '.join(BASELINES)}, or a checkpoint directory")
    p.add_argument("--n-eds", type=positive_int, default=None, help="V (default: scenario's, 10)")
    p.add_argument("--n-uavs", type=positive_int, default=None, help="U (default: scenario's, 2)")
    p.add_argument("--episodes", type=int_in(1, MAX_EPISODES), default=10, help="episodes (default 10)")
    p.add_argument(
        "--seed", type=seed, default=0, help="evaluation seed in [0, 2^32 - 1] (episode seeds derive from it)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--scenario-yaml", default=None, help="YAML file of scenario fields (or with a 'scenario:' key)")
    p.add_argument(
        "--plugin",
        action="append",
        default=[],
        metavar="MODULE",
        help="import MODULE first (repeatable): a plugin's baseline (register_baseline) becomes a --policy",
    )
    p.add_argument(
        "--objective", choices=OBJECTIVES, default=None, help="the greedy and optimal baselines' objective (default ee)"
    )
    p.add_argument(
        "--execution",
        choices=("greedy", "sampled"),
        default="greedy",
        help="a checkpoint's actions: greedy (argmax, the paper's execution phase; default) or sampled "
        "from its policy (seeded by --seed)",
    )
    p.add_argument(
        "--open-loop",
        action="store_true",
        help="then play the episodes again and report how open-loop the policy is: the share of its decisions "
        "equal to its own modal action, and what that action earns replayed as a constant (docs/model.md)",
    )
    return p


def _load_yaml_scenario(path: str) -> dict[str, Any]:
    if os.path.isdir(path):
        raise UsageError(f"--scenario-yaml: {path} is a directory; expected a YAML file")
    if not os.path.isfile(path):
        raise UsageError(f"--scenario-yaml: file not found: {path}")
    try:  # UTF-8 only, no duplicate keys: the grid YAML's reader
        data = parse_yaml(read_yaml_text(path, "scenario file"), path) or {}
    except ConfigError as exc:
        raise UsageError(f"--scenario-yaml: {exc}") from None
    if not isinstance(data, Mapping):
        raise UsageError(f"--scenario-yaml: expected a mapping of scenario fields, got {type(data).__name__}")
    if "scenario" in data:
        ignored = sorted(str(k) for k in data if k != "scenario")
        if ignored:  # e.g. a grid YAML: its n_eds / n_uavs lists are not the scenario's
            print(
                f"note: --scenario-yaml: only its 'scenario:' is read; ignored: {', '.join(ignored)} "
                "(V and U: --n-eds / --n-uavs)",
                file=sys.stderr,
            )
        data = data["scenario"]
        if not isinstance(data, Mapping):
            raise UsageError(f"--scenario-yaml: 'scenario' must be a mapping, got {type(data).__name__}")
    return dict(data)


def load_checkpoint_policy(
    path: str, scenario_overrides: Mapping[str, Any] | None = None, explore: bool = False, seed: int = 0
):
    """Restore an RLlib checkpoint of this project and return (policy, scenario).

    The scenario is the algorithm's env_config["scenario"] with `scenario_overrides` (scenario
    field -> value, e.g. {"n_eds": 40}) applied; the policy is the registry entry's
    decentralised greedy policy for that scenario (evaluation.Policy), or with explore=True its
    sampled one (actions drawn from the trained distribution, seeded by `seed`).
    """
    import ray
    from ray.rllib.algorithms.algorithm import Algorithm

    from uavlora_rllib.algorithms.common.registry import entry_for_algorithm
    from uavlora_rllib.experiment import cluster
    from uavlora_rllib.experiment.quiet import quiet_known_warnings

    quiet_known_warnings()  # RLlib's notices on restoring, which need no action (experiment/quiet.py)
    _import_trial_plugins(path)  # before Ray starts: a missing module is one line
    if not ray.is_initialized():  # a private local Ray, not RLlib's bare ray.init(), which would attach to
        try:  # a `ray start` cluster on this machine, and start a dashboard
            cluster.connect(None, None)
        except Exception as exc:  # (RAY_TMPDIR unwritable, no free port, ...)
            first = (str(exc).strip().splitlines() or [""])[0]
            raise ConfigError(
                f"--policy: cannot start a local Ray to restore {path!r}: {type(exc).__name__}: {first}"
            ) from None
    try:
        algo = Algorithm.from_checkpoint(os.path.abspath(path))
    except Exception as exc:  # RLlib raises many kinds for a directory that is not its checkpoint
        first = (str(exc).strip().splitlines() or [""])[0]
        raise ConfigError(
            f"--policy: {path!r} is not a valid RLlib checkpoint: {type(exc).__name__}: {first}"
        ) from None
    env_config = algo.config.env_config or {}
    trained = env_config.get("scenario", {})
    trained = trained if isinstance(trained, ScenarioConfig) else ScenarioConfig.from_dict(trained)
    scenario = trained.replace(**dict(scenario_overrides)) if scenario_overrides else trained
    entry = entry_for_algorithm(algo)
    entry.check_scenario(scenario)
    problem = checkpoint_fit_problem(trained, scenario)
    if problem:
        raise ConfigError(f"--policy: the checkpoint at {path!r} {problem}")
    try:
        return entry.policy(algo, scenario, explore=explore, seed=seed), scenario
    except ValueError as exc:  # the entry's own check of the trained module against the scenario
        raise ConfigError(f"--policy: the checkpoint at {path!r} does not fit this scenario: {exc}") from None


def _import_trial_plugins(path: str) -> None:
    """Import the plugin modules a grid trial's checkpoint needs, as its trial did: the `plugins` of
    the trial config Tune keeps beside its checkpoints (params.json); a checkpoint outside a Tune
    trial needs none, or its modules imported by the caller."""
    params = os.path.join(os.path.dirname(os.path.abspath(path)), "params.json")
    try:
        with open(params) as fh:
            trial = json.load(fh).get("trial", {})
    except (OSError, ValueError, AttributeError):
        return
    plugins = trial.get("plugins", []) if isinstance(trial, Mapping) else []
    if plugins:
        from uavlora_rllib.experiment.grid import import_plugins

        import_plugins([str(m) for m in plugins], prefix=f"--policy: the checkpoint's trial's plugins (in {params})")


def checkpoint_fit_problem(trained: ScenarioConfig, scenario: ScenarioConfig) -> str | None:
    """Why a policy trained on `trained` cannot act in `scenario`, or None.

    A trained actor fixes the number of agents (UAVs), each agent's observation space and its
    action space; every other scenario field (V within the same quota, the channel, the
    rewards...) may change between training and evaluation (e.g. the paper's Fig. 3b)."""
    from uavlora_rllib.envs.multi_agent import action_space, observation_space

    def spaces(cfg: ScenarioConfig) -> tuple:
        return cfg.n_uavs, observation_space(cfg).shape, action_space(cfg)

    if spaces(trained) == spaces(scenario):
        return None
    differ = [
        f.name for f in dataclasses.fields(ScenarioConfig) if getattr(trained, f.name) != getattr(scenario, f.name)
    ]
    t_u, t_obs, t_act = spaces(trained)
    u, obs, act = spaces(scenario)
    quota = ""
    # derived from n_eds / n_uavs; the hint helps only where the UAVs are the trained ones
    if trained.quota != scenario.quota and "max_eds_per_uav" not in differ and t_u == u:
        quota = (
            f"; the quota max_eds_per_uav, ceil(1.5 V / U) unless set, moved {trained.quota} -> {scenario.quota}: "
            f"keep it by setting max_eds_per_uav: {trained.quota} in the scenario (evaluate: --scenario-yaml)"
        )
    return (
        f"was trained for {t_u} UAVs with observations {t_obs} and actions {t_act}; this scenario has "
        f"{u} UAVs, observations {obs} and actions {act} (scenario fields that differ: {', '.join(differ)}); "
        f"allowed: changes that keep n_uavs, the quota max_eds_per_uav, action_mode, sf_set, tp_dbm and bw_khz{quota}"
    )


def check_checkpoint_dir(path: str) -> None:
    """UsageError naming --policy unless `path` is an RLlib checkpoint directory (checked here: RLlib itself
    logs warnings and guesses before it gives up)."""
    if not os.path.exists(path):
        raise UsageError(
            f"--policy: {path!r} is neither a baseline ({', '.join(baseline_names())}) nor an existing checkpoint path"
        )
    if not os.path.isdir(path):
        raise UsageError(f"--policy: checkpoint path {path!r} is not a directory")
    if not os.path.isfile(os.path.join(path, "rllib_checkpoint.json")):
        inner = sorted(d for d in os.listdir(path) if d.startswith("checkpoint_"))
        hint = f"; it holds checkpoints, the latest is {os.path.join(path, inner[-1])}" if inner else ""
        raise UsageError(f"--policy: {path!r} is not an RLlib checkpoint (no rllib_checkpoint.json){hint}")


def _resolve(args: argparse.Namespace):
    overrides = {k: v for k, v in (("n_eds", args.n_eds), ("n_uavs", args.n_uavs)) if v is not None}
    if args.objective is not None and args.policy not in ("greedy", "optimal"):
        raise UsageError(f"--objective: applies to the greedy and optimal baselines only; --policy is {args.policy!r}")
    if args.policy in baseline_names():
        if args.execution != "greedy":
            raise UsageError(
                f"--execution: {args.execution!r} applies to a checkpoint; baselines have one execution mode"
            )
        base = _load_yaml_scenario(args.scenario_yaml) if args.scenario_yaml else {}
        cfg = ScenarioConfig.from_dict({**base, **overrides})
        return make_baseline(args.policy, cfg, seed=args.seed, objective=args.objective or "ee"), cfg
    check_checkpoint_dir(args.policy)
    if args.scenario_yaml:
        overrides = {**_load_yaml_scenario(args.scenario_yaml), **overrides}
    return load_checkpoint_policy(args.policy, overrides, explore=args.execution == "sampled", seed=args.seed)


def format_table(name: str, cfg: ScenarioConfig, summary: Mapping[str, Any]) -> str:
    head = (
        f"policy {name}  |  V={cfg.n_eds} U={cfg.n_uavs} T={cfg.episode_len} mode={cfg.action_mode}  |  "
        f"{summary['episodes']} episodes, mean +- 95% CI"
    )
    lines = [head]
    if changed := off_defaults(cfg, shown=("episode_len", "action_mode")):
        lines.append(f"scenario off the paper's defaults: {', '.join(changed)}")
    lines.append("-" * len(head))
    for key, label, unit in REPORTED + ((BOUND_ROW,) if BOUND_METRIC in summary else ()):
        lines.append(f"{label:<24}{summary[key]:>16.4f}  +- {summary['ci95'][key]:<12.4f}{unit}")
    return "\n".join(lines)


def json_summary(summary: Mapping[str, Any]) -> dict[str, Any]:
    keys = [k for k, _, _ in REPORTED] + ([BOUND_METRIC] if BOUND_METRIC in summary else [])
    out: dict[str, Any] = {k: float(summary[k]) for k in keys}
    out["ci95"] = {k: float(summary["ci95"][k]) for k in keys}
    out["episodes"] = int(summary["episodes"])
    return out


class _Progress:
    """Wraps a Policy and advances a tqdm bar by the episode-slots each act() plays (a batch
    of run_episodes' scenarios per call; the last batch may hold padding scenarios)."""

    def __init__(self, policy: Any, cfg: ScenarioConfig, episodes: int, bar: Any):
        self._policy, self._episodes, self._bar = policy, episodes, bar
        self._slot, self._batch_start, self._t = 0, 0, cfg.episode_len
        self.name = getattr(policy, "name", "policy")

    def reset(self, core: Any) -> None:
        self._policy.reset(core)

    def act(self, core: Any):
        actions = self._policy.act(core)
        real = min(core.n, self._episodes - self._batch_start)
        self._bar.update(real)
        self._slot += 1
        if self._slot == self._t:  # the batch's episodes are done; run_episodes resets the next
            self._slot, self._batch_start = 0, self._batch_start + core.n
        return actions


def run_with_progress(
    policy: Any,
    cfg: ScenarioConfig,
    episodes: int,
    seed: int,
    kind: str,
    label: str,
    prefix: str = "",
    out: Any = None,
    bound: Any = None,
    n_envs: int | None = None,
):
    """evaluation.run_episodes, plus, when the run is estimated to take more than LONG_SECONDS
    (baselines.policies.evaluation_seconds; `kind` a baseline name, or anything else for a
    learned policy), one line with the estimate and a tqdm progress bar on `out` (stderr).
    The bar only watches: the episodes, seeds and metrics are those of run_episodes. Usable
    by any driver that evaluates (e.g. the baseline phase of tune: `kind` = the baseline).
    `bound`: run_episodes' per-slot bound (None: not computed); `n_envs`: its batch (None: its default)."""
    from uavlora_rllib.experiment.evaluation import run_episodes

    estimate = evaluation_seconds(kind, cfg, episodes)
    if estimate <= LONG_SECONDS:
        return run_episodes(policy, cfg, episodes=episodes, seed=seed, n_envs=n_envs, bound=bound)
    from tqdm import tqdm

    out = out or sys.stderr
    what = f"{episodes} episodes x {cfg.episode_len} slots, V={cfg.n_eds} U={cfg.n_uavs}"
    if kind == "optimal":
        what += f", {cfg.n_joint_actions}^{cfg.n_uavs} = {cfg.n_joint_actions**cfg.n_uavs:,} joint actions per slot"
    print(f"{prefix}{label} on {what}: estimated {_duration(estimate)} on one core", file=out, flush=True)
    with tqdm(total=episodes * cfg.episode_len, unit="slot", desc=label, file=out, dynamic_ncols=True) as bar:
        progress = _Progress(policy, cfg, episodes, bar)
        return run_episodes(progress, cfg, episodes=episodes, seed=seed, n_envs=n_envs, bound=bound)


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"~{seconds:.0f} s"
    if seconds < 7200:
        return f"~{seconds / 60:.0f} min"
    return f"~{seconds / 3600:.1f} h"


def main(argv: Sequence[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        if args.plugin:
            from uavlora_rllib.experiment.grid import import_plugins

            import_plugins(args.plugin, prefix="--plugin")
        policy, cfg = _resolve(args)
        is_baseline = args.policy in baseline_names()
        kind = args.policy if is_baseline else "learned"
        label = args.policy if is_baseline else f"checkpoint ({args.execution})"
        from uavlora_rllib.baselines.bound import upper_bound_of_core

        bound = upper_bound_of_core if args.policy in REFERENCES else None

        def play(p: Any, n_envs: int | None = None):
            return run_with_progress(
                p, cfg, args.episodes, args.seed, kind, label, prefix=f"{PROG}: ", bound=bound, n_envs=n_envs
            )

        check = None
        if args.open_loop:  # the check plays the reported run itself, so both name the same EE
            from uavlora_rllib.experiment.open_loop import open_loop_check

            check = open_loop_check(policy, cfg, args.episodes, args.seed, play=play)
            result = check.result
        else:
            result = play(policy)
    except (UsageError, ConfigError) as exc:
        return fail(exc, PROG)
    except ActionError as exc:  # a policy whose actions do not fit the scenario's action space
        return fail(f"--policy: its actions do not fit this scenario: {exc}", PROG)
    except KeyboardInterrupt:
        return fail("interrupted", PROG, code=130)
    summary = result.summary()
    if args.json:
        out = json_summary(summary)
        if not all(math.isfinite(v) for k, v in out.items() if k not in ("ci95", "episodes")):
            print("evaluate: warning: non-finite metric in the summary", file=sys.stderr)
        if check is not None:
            out["open_loop"] = open_loop_json(check)
        print(json.dumps(out))
    else:
        name = getattr(policy, "name", args.policy)
        if not is_baseline:  # a checkpoint plays greedily or sampled: say which
            name = f"{name} ({args.execution} execution)"
        print(format_table(name, cfg, summary))
        if check is not None:
            print(open_loop_line(check))
    return 0


def open_loop_json(check: OpenLoopCheck) -> dict[str, Any]:
    return {
        "modal_share": check.modal_share,
        "policy_ee_sys_mean": check.policy_ee,
        "modal_ee_sys_mean": check.modal_ee,
        "modal_ratio": check.modal_ratio,
        "modal_action": check.action.tolist(),
    }


def open_loop_line(check: OpenLoopCheck) -> str:
    return (
        f"open-loop check: {check.modal_share:.1%} of the acting decisions equal the policy's modal action; "
        f"replayed as a constant it earns {check.modal_ee:.1f} bit/J, {check.modal_ratio:.3f} of the policy's "
        f"{check.policy_ee:.1f} on the same episodes"
    )


if __name__ == "__main__":
    sys.exit(main())
