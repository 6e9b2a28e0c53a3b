"""Execution-phase CLI: evaluate a baseline or a trained checkpoint on fresh episodes.

    python -m uavlora_rllib.evaluate --policy {random,fixed,adr,greedy,optimal|CHECKPOINT_DIR}
        [--n-eds V] [--n-uavs U] [--episodes K] [--seed S] [--json]
        [--scenario-yaml FILE] [--objective ee|reward]

Prints the paper's execution metrics (evaluation.run_episodes), each as the mean over
episodes with its 95% CI half-width; `--json` prints one JSON object instead. Bad input
gives one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import Any, Mapping, Sequence

import yaml

from uavlora_rllib.baselines.policies import BASELINES, OBJECTIVES, make_baseline
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig
from uavlora_rllib.cli_args import Parser, UsageError, integer, positive_int

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


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m uavlora_rllib.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help=f"one of {', '.join(BASELINES)}, or a checkpoint directory")
    p.add_argument("--n-eds", type=positive_int, default=None, help="V (default: scenario's, 10)")
    p.add_argument("--n-uavs", type=positive_int, default=None, help="U (default: scenario's, 2)")
    p.add_argument("--episodes", type=positive_int, default=10, help="episodes (default 10)")
    p.add_argument("--seed", type=integer, default=0, help="evaluation seed (episode seeds derive from it)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--scenario-yaml", default=None, help="YAML file of scenario fields (or with a 'scenario:' key)")
    p.add_argument("--objective", choices=OBJECTIVES, default="ee", help="greedy/optimal objective (default ee)")
    return p


def _load_yaml_scenario(path: str) -> dict[str, Any]:
    if not os.path.isfile(path):
        raise UsageError(f"--scenario-yaml: file not found: {path}")
    try:
        with open(path) as fh:
            data = yaml.safe_load(fh) or {}
    except yaml.YAMLError as exc:
        raise UsageError(f"--scenario-yaml: not valid YAML ({path}): {str(exc).splitlines()[0]}") from None
    if not isinstance(data, Mapping):
        raise UsageError(f"--scenario-yaml: expected a mapping of scenario fields, got {type(data).__name__}")
    if "scenario" in data:
        data = data["scenario"]
        if not isinstance(data, Mapping):
            raise UsageError(f"--scenario-yaml: 'scenario' must be a mapping, got {type(data).__name__}")
    return dict(data)


def load_checkpoint_policy(path: str, scenario_overrides: Mapping[str, Any] | None = None):
    """Restore an RLlib checkpoint of this project and return (policy, scenario).

    The scenario is the algorithm's env_config["scenario"] with `scenario_overrides` (scenario
    field -> value, e.g. {"n_eds": 40}) applied; the policy is the registry entry's
    decentralised greedy policy for that scenario (evaluation.Policy).
    """
    from ray.rllib.algorithms.algorithm import Algorithm

    from uavlora_rllib.algorithms.common.registry import entry_for_algorithm

    try:
        algo = Algorithm.from_checkpoint(os.path.abspath(path))
    except (ValueError, FileNotFoundError) as exc:  # RLlib's "not a valid checkpoint"
        raise ConfigError(f"--policy: {path!r} is not a valid RLlib checkpoint: {str(exc).splitlines()[0]}") from None
    env_config = algo.config.env_config or {}
    scenario = env_config.get("scenario", {})
    scenario = scenario if isinstance(scenario, ScenarioConfig) else ScenarioConfig.from_dict(scenario)
    if scenario_overrides:
        scenario = scenario.replace(**dict(scenario_overrides))
    entry = entry_for_algorithm(algo)
    entry.check_scenario(scenario)
    return entry.greedy_policy(algo, scenario), scenario


def _resolve(args: argparse.Namespace):
    overrides = {k: v for k, v in (("n_eds", args.n_eds), ("n_uavs", args.n_uavs)) if v is not None}
    if args.policy in BASELINES:
        base = _load_yaml_scenario(args.scenario_yaml) if args.scenario_yaml else {}
        cfg = ScenarioConfig.from_dict({**base, **overrides})
        return make_baseline(args.policy, cfg, seed=args.seed, objective=args.objective), cfg
    if not os.path.exists(args.policy):
        raise UsageError(
            f"--policy: {args.policy!r} is neither a baseline ({', '.join(BASELINES)}) nor an existing checkpoint path"
        )
    if not os.path.isdir(args.policy):
        raise UsageError(f"--policy: checkpoint path {args.policy!r} is not a directory")
    if args.scenario_yaml:
        overrides = {**_load_yaml_scenario(args.scenario_yaml), **overrides}
    return load_checkpoint_policy(args.policy, overrides)


def format_table(name: str, cfg: ScenarioConfig, summary: Mapping[str, Any]) -> str:
    head = (
        f"policy {name}  |  V={cfg.n_eds} U={cfg.n_uavs} T={cfg.episode_len} mode={cfg.action_mode}  |  "
        f"{summary['episodes']} episodes, mean +- 95% CI"
    )
    lines = [head, "-" * len(head)]
    for key, label, unit in REPORTED:
        lines.append(f"{label:<24}{summary[key]:>16.4f}  +- {summary['ci95'][key]:<12.4f}{unit}")
    return "\n".join(lines)


def json_summary(summary: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {k: float(summary[k]) for k, _, _ in REPORTED}
    out["ci95"] = {k: float(summary["ci95"][k]) for k, _, _ in REPORTED}
    out["episodes"] = int(summary["episodes"])
    return out


def main(argv: Sequence[str] | None = None) -> int:
    from uavlora_rllib.experiment.evaluation import run_episodes

    try:
        args = build_parser().parse_args(argv)
        policy, cfg = _resolve(args)
    except (UsageError, ConfigError) as exc:
        print(f"evaluate: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    result = run_episodes(policy, cfg, episodes=args.episodes, seed=args.seed)
    summary = result.summary()
    if args.json:
        out = json_summary(summary)
        if not all(math.isfinite(v) for k, v in out.items() if k not in ("ci95", "episodes")):
            print("evaluate: warning: non-finite metric in the summary", file=sys.stderr)
        print(json.dumps(out))
    else:
        print(format_table(getattr(policy, "name", args.policy), cfg, summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
