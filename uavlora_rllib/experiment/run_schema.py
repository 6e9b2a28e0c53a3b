"""What an MLflow run of a grid holds, and how a trial's result dict maps onto it (docs/model.md#mlflow-runs).

The analysis step reads exactly this schema:

* experiment: the grid's `experiment`, holding one parent run per grid (tag ``kind`` = "grid",
  run name = the experiment) with the grid's train and baseline runs nested under it (tag
  ``mlflow.parentRunId``); run name ``{algorithm}-V{n_eds}-U{n_uavs}-s{seed}``. The parent holds
  the grid YAML (artifact ``grid.yaml``) and the report's files (artifact folder ``report/``,
  written by ``analysis.report``). Experiments written before the parent existed are flat (and
  may hold a ``kind`` = "summary" run instead); the report reads both.
* tags: ``kind`` ("train" | "baseline"), ``algorithm``, ``seed``, ``n_eds``, ``n_uavs``,
  ``git_commit``, ``grid_file``, ``budget_env_steps``, MLflow's own ``mlflow.source.name``
  (the command), ``mlflow.source.type`` (LOCAL), ``mlflow.source.git.commit`` and
  ``mlflow.user``; train runs also ``trial_id``, ``checkpoint`` (the trial's last checkpoint:
  a path, or a URI on cloud storage; updated at every save and at the end) and
  ``checkpoint_artifact`` (whether the final checkpoint was uploaded, see below).
* params: ``algorithm``, ``seed``, ``n_eds``, ``n_uavs`` (to filter and group by in the UI),
  ``algo.<field>`` (hyperparameters; none for baselines; a sweep's sampled values
  also as ``hparam.<field>``, with ``hparam/<field>`` metrics of the value trained with at
  each step, which PBT's mutations change), ``scenario.<field>``
  (`scenario.flatten`), ``resources.<field>`` (train runs), ``stop.env_steps``,
  ``eval.episodes``; values are strings, cut to MLflow's length limit.
* artifacts of a train run: ``trial_config.yaml`` (the resolved trial config it trained with),
  and once the trial ends ``curves.csv`` (every metric of the run, one row per env step) and,
  when it FINISHED, ``checkpoint/`` (its final RLlib checkpoint) if the checkpoint is on a local
  or shared filesystem and at most ``mlflow.checkpoint_artifact_max_mb`` MB; otherwise only the
  ``checkpoint`` tag points at it (docs/cluster.md#mlflow).
* training metrics, step = env steps sampled so far: ``episode_return_mean``,
  ``ee_sys_mean`` and ``success_rate`` (when the algorithm logs them), ``env_steps_per_s``
  and every numeric learner stat as ``learner/<stat>`` (one policy module) or
  ``learner/<module>/<stat>`` (several), the all-modules stats as ``learner/all_modules/<stat>``.
* execution-phase evaluation (end of a trial, and baseline runs): ``eval/<k>`` and
  ``eval/<k>_ci95`` for k in `evaluation.EPISODE_METRICS`, and ``eval/episodes``; the
  reference baselines (greedy, optimal) also ``eval/ee_sys_upper_bound``; train runs
  also log them during training, step = env steps (experiment/periodic_eval.py), so the final
  evaluation is the last point of each series; ``eval_sampled/<k>`` likewise for algorithms
  with a sampled policy. A baseline run logs its (constant) values at `reference_steps` of the
  grid's budget, so the UI's charts draw it as a flat line across the training range.

`mlflow_client.Tracker` writes runs of this schema; `mlflow_callback.MlflowTrialCallback`
fills the train runs from Tune's results; this module only maps dicts (no MLflow calls, no Ray).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Mapping
from typing import Any

from uavlora_rllib.experiment.evaluation import BOUND_METRIC, EPISODE_METRICS

try:  # the limits of the installed mlflow; the values below are mlflow 3's
    from mlflow.utils.validation import MAX_ENTITY_KEY_LENGTH, MAX_PARAM_VAL_LENGTH
except ImportError:  # pragma: no cover
    MAX_PARAM_VAL_LENGTH, MAX_ENTITY_KEY_LENGTH = 6000, 250

MAX_TAG_VAL_LENGTH = 5000
TRIAL_WALL_METRIC = "cost/trial_wall_s"  # a trial's own working time so far [s] (experiment/trial_clock.py)
TRAIN_METRICS = ("episode_return_mean", "ee_sys_mean", "success_rate", "env_steps_per_s", TRIAL_WALL_METRIC)
ENV_STEPS = "env_steps"  # key of the env-step counter in the trainable's results
# key of the learners' number format and route in the trainable's results, and the run's tag that records every
# one the trial ran in (common/precision.py precision_name; "a,b" when its learners, or its nodes over time, differ)
PRECISION_ROUTE = "learner_precision_route"
LEARNER_PREFIX = "learner/"
EVAL_PREFIX = "eval/"
HPARAM_PREFIX = "hparam/"  # a sampled hyperparameter's current value (experiment/sweep.py)
EVAL_WALL_METRIC = "cost/eval_wall_s"  # a baseline run's evaluation time on its one CPU [s] (analysis/cost.py)

KIND_TRAIN = "train"
KIND_BASELINE = "baseline"
KIND_GRID = "grid"  # the parent run of a grid's runs
PARENT_TAG = "mlflow.parentRunId"  # MLflow's nesting tag: the UI shows the run under its parent
IDENTITY_PARAMS = ("algorithm", "seed", "n_eds", "n_uavs")
REFERENCE_POINTS = 11  # steps a baseline's values are logged at: 0, budget/10, ..., budget
TRIAL_CONFIG_ARTIFACT = "trial_config.yaml"
CURVES_ARTIFACT = "curves.csv"
CHECKPOINT_ARTIFACT = "checkpoint"
GRID_ARTIFACT = "grid.yaml"


_BAD_CHARS = re.compile(r"[^/\w.\- ]")


def safe_name(name: str) -> str:
    """An MLflow-valid metric/param key: allowed characters only, a normalised relative path."""
    name = _BAD_CHARS.sub("_", str(name))
    parts = [p for p in name.split("/") if p not in ("", ".", "..")]
    return "/".join(parts)[:MAX_ENTITY_KEY_LENGTH] or "_"


def param_value(value: Any) -> str:
    """A param value as MLflow stores it: a string cut to its length limit."""
    return str(value)[:MAX_PARAM_VAL_LENGTH]


def number(value: Any) -> float | None:
    """A finite float, or None (bools, strings, NaN, inf are not metrics)."""
    if isinstance(value, bool):
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def flat_params(prefix: str, mapping: Mapping[str, Any]) -> dict[str, str]:
    """A nested mapping -> {"<prefix>.<path>": value string} (tuples as lists)."""
    out: dict[str, str] = {}

    def walk(obj: Any, path: str) -> None:
        if isinstance(obj, Mapping):
            for k, v in obj.items():
                walk(v, f"{path}.{k}")
        else:
            out[safe_name(path)] = param_value(list(obj) if isinstance(obj, tuple) else obj)

    walk(dict(mapping), prefix)
    return out


def run_params(
    scenario: Any,
    budget_env_steps: int | None,
    eval_episodes: int,
    hparams: Mapping[str, Any] | None = None,
    resources: Mapping[str, Any] | None = None,
) -> dict[str, str]:
    """The params of a run (see the module docstring)."""
    from uavlora_rllib.sim.scenario import ScenarioConfig, flatten

    if not isinstance(scenario, ScenarioConfig):
        scenario = ScenarioConfig.from_dict(scenario)
    params: dict[str, str] = {}
    if hparams is not None:
        params.update(flat_params("algo", hparams))
    params.update({safe_name(k): param_value(v) for k, v in flatten(scenario, "scenario").items()})
    if resources is not None:
        params.update(flat_params("resources", resources))
    if budget_env_steps is not None:
        params["stop.env_steps"] = str(int(budget_env_steps))
    params["eval.episodes"] = str(int(eval_episodes))
    return params


def sampled_params(sampled: Mapping[str, Any]) -> dict[str, str]:
    """``hparam.<name>``: the values a sweep sampled for a trial (its start; PBT's later
    mutations are the ``hparam/<name>`` metrics)."""
    return {safe_name(f"hparam.{k}"): param_value(v) for k, v in sampled.items()}


def eval_metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    """`EvalResult.summary()` -> {"eval/<k>", "eval/<k>_ci95", "eval/episodes"}."""
    out: dict[str, float] = {}
    ci = summary.get("ci95", {}) or {}
    for k in (*EPISODE_METRICS, BOUND_METRIC):
        if k in summary:
            out[f"{EVAL_PREFIX}{k}"] = float(summary[k])
        if k in ci:
            out[f"{EVAL_PREFIX}{k}_ci95"] = float(ci[k])
    if "episodes" in summary:
        out[f"{EVAL_PREFIX}episodes"] = float(summary["episodes"])
    return out


def lookup(result: Mapping[str, Any], *paths: str) -> Any:
    """First present value among slash paths into a nested (or already flat) result dict."""
    for path in paths:
        if path in result:
            return result[path]
        node: Any = result
        for part in path.split("/"):
            if not isinstance(node, Mapping) or part not in node:
                node = None
                break
            node = node[part]
        if node is not None:
            return node
    return None


def learner_stats(learners: Any) -> dict[str, float]:
    """RLlib's `learners` result -> {"learner/<name>": value} (numeric, finite, no timers)."""
    if not isinstance(learners, Mapping):
        return {}
    modules = [m for m in learners if m != "__all_modules__" and isinstance(learners[m], Mapping)]
    out: dict[str, float] = {}

    def walk(obj: Any, path: str) -> None:
        if isinstance(obj, Mapping):
            for k, v in obj.items():
                if "timer" in str(k):
                    continue
                walk(v, f"{path}/{k}" if path else str(k))
            return
        x = number(obj)
        if x is not None:
            out[safe_name(LEARNER_PREFIX + path)] = x

    for module_id, stats in learners.items():
        if module_id == "__all_modules__":
            walk(stats, "all_modules")
        elif len(modules) == 1:
            walk(stats, "")
        else:
            walk(stats, str(module_id))
    return out


def training_summary(result: Mapping[str, Any], env_steps_per_s: float | None = None) -> dict[str, Any]:
    """The flat dict the trainable reports from one `algo.train()` result (robust to missing keys)."""
    out: dict[str, Any] = {}
    steps = lookup(result, "num_env_steps_sampled_lifetime", "env_runners/num_env_steps_sampled_lifetime")
    out[ENV_STEPS] = int(number(steps) or 0)
    candidates = {
        "episode_return_mean": ("env_runners/episode_return_mean", "episode_return_mean"),
        "ee_sys_mean": (
            "env_runners/ee_sys_mean",
            "ee_sys_mean",
            "env_runners/sampled_ee_sys_mean",
            "sampled_ee_sys_mean",
        ),
        "success_rate": (
            "env_runners/success_rate",
            "env_runners/success_rate_mean",
            "success_rate",
            "env_runners/sampled_success_rate",
            "sampled_success_rate",
        ),
    }
    for key, paths in candidates.items():
        x = number(lookup(result, *paths))
        if x is not None:
            out[key] = x
    if env_steps_per_s is not None and number(env_steps_per_s) is not None:
        out["env_steps_per_s"] = float(env_steps_per_s)
    out.update(learner_stats(result.get("learners")))
    return out


def metrics_to_log(result: Mapping[str, Any]) -> tuple[dict[str, float], dict[str, float]]:
    """A trial result -> (training metrics, eval metrics) of the schema; other keys are dropped."""
    train: dict[str, float] = {}
    evals: dict[str, float] = {}
    for key, value in result.items():
        x = number(value)
        if x is None:
            continue
        if key in TRAIN_METRICS or key.startswith((LEARNER_PREFIX, HPARAM_PREFIX)):
            train[safe_name(key)] = x
        elif key.startswith((EVAL_PREFIX, "eval_sampled/")):  # periodic_eval.EVAL_SAMPLED_PREFIX
            evals[safe_name(key)] = x
    return train, evals


EVAL_INTERVAL_PARAM = "eval.interval_env_steps"  # a trial's env steps between greedy evaluations (0: none)
PLUGINS_TAG = "plugins"  # a trial's plugin modules as module@sha256[:12] of each one's source file
PLUGINS_ON_RESUME_TAG = "plugins_on_resume"  # the same, when a --resume found them changed


def plugin_digests(modules: list[str]) -> str:
    """`module@<12 hex digits of its source file's SHA-256>` per plugin module, comma-separated ("" for
    none): the git commit names the package's code, this names a plugin's, which lives outside it."""
    import hashlib
    import importlib.util

    out = []
    for module in modules:
        try:
            origin = getattr(importlib.util.find_spec(module), "origin", None)
            with open(str(origin), "rb") as fh:
                out.append(f"{module}@{hashlib.sha256(fh.read()).hexdigest()[:12]}")
        except (ImportError, OSError, ValueError):
            out.append(f"{module}@unknown")
    return ",".join(out)


def read_trial_results(trial_dir: str | None) -> list[dict]:
    """The rows of a trial's result.json (one JSON object per reported result), [] if absent."""
    if not trial_dir or "://" in trial_dir:
        return []
    path = os.path.join(trial_dir, "result.json")
    rows = []
    try:
        with open(path) as fh:
            for line in fh:
                line = line.strip()
                if line:
                    try:
                        rows.append(json.loads(line))
                    except ValueError:  # a line cut short by a kill
                        continue
    except OSError:
        return []
    return rows


def identity_params(algorithm: str, seed: int, n_eds: int, n_uavs: int) -> dict[str, str]:
    """The params a researcher filters and groups runs by (also tags, which resume matches on)."""
    return {"algorithm": str(algorithm), "seed": str(seed), "n_eds": str(n_eds), "n_uavs": str(n_uavs)}


def reference_steps(budget_env_steps: int | None, points: int = REFERENCE_POINTS) -> list[int]:
    """Env steps spanning [0, budget] at which a baseline logs its constant values: a flat
    reference line beside the learners' curves in the UI's charts (step 0 alone without a budget)."""
    if not budget_env_steps or budget_env_steps <= 0:
        return [0]
    return sorted({round(budget_env_steps * i / (points - 1)) for i in range(points)})


def _plain(value: Any) -> Any:
    """Plain YAML data: mappings, lists, str, numbers, bools, None (anything else as a string)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def trial_config_yaml(cfg: Mapping[str, Any], trial_id: str) -> str:
    """The trial's resolved config (what it trained with), as the YAML of its ``trial_config.yaml``."""
    import yaml

    doc = {"trial_id": trial_id, **_plain(cfg)}
    return "# the resolved config of this trial (uavlora_rllib.tune; docs/model.md#mlflow-runs)\n" + yaml.safe_dump(
        doc, sort_keys=False
    )


def curves_csv(histories: Mapping[str, list[tuple[int, float]]]) -> str:
    """{metric: [(step, value), ...]} -> a CSV with one row per step (env steps) and one column per
    metric (empty where a metric has no value at that step; the last value of a repeated step)."""
    import csv
    import io

    keys = sorted(histories)
    table: dict[int, dict[str, float]] = {}
    for key in keys:
        for step, value in histories[key]:
            table.setdefault(int(step), {})[key] = value
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow([ENV_STEPS, *keys])
    for step in sorted(table):
        row = table[step]
        writer.writerow([step, *(repr(row[k]) if k in row else "" for k in keys)])
    return buf.getvalue()
