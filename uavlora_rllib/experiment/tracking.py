"""MLflow tracking of a grid: one run per trial and per baseline evaluation, written by the driver.

The analysis step reads exactly this schema:

* experiment: the grid's `experiment`; run name ``{algorithm}-V{n_eds}-U{n_uavs}-s{seed}``.
* tags: ``kind`` ("train" | "baseline"), ``algorithm``, ``seed``, ``n_eds``, ``n_uavs``,
  ``git_commit``, ``grid_file``, ``budget_env_steps``; train runs also ``trial_id`` and
  ``checkpoint`` (the trial's last checkpoint, updated at every save and at the end).
* params: ``algo.<field>`` (hyperparameters; none for baselines), ``scenario.<field>``
  (`scenario.flatten`), ``resources.<field>`` (train runs), ``stop.env_steps``,
  ``eval.episodes``; values are strings, cut to MLflow's length limit.
* training metrics, step = env steps sampled so far: ``episode_return_mean``,
  ``ee_sys_mean`` and ``success_rate`` (when the algorithm logs them), ``env_steps_per_s``
  and every numeric learner stat as ``learner/<stat>`` (one policy module) or
  ``learner/<module>/<stat>`` (several), the all-modules stats as ``learner/all_modules/<stat>``.
* execution-phase evaluation (end of a trial, and baseline runs): ``eval/<k>`` and
  ``eval/<k>_ci95`` for k in `evaluation.EPISODE_METRICS`, and ``eval/episodes``; train runs
  also log them during training, step = env steps (experiment/periodic_eval.py), so the final
  evaluation is the last point of each series; ``eval_sampled/<k>`` likewise for algorithms
  with a sampled policy.

One run per trial, even across ``--resume``: the run is found again by its ``trial_id`` tag
(Tune keeps trial ids when it restores an experiment), reopened (status RUNNING) and
continued; training results already logged at a step are not logged twice. A run ends
FINISHED when its trial terminates, FAILED when it errors, and KILLED when the grid stops
(interrupt, crash) before the trial finished; `--resume` reopens KILLED runs.

Only the driver writes: the `MlflowTrialCallback` runs in the Tune driver loop and uses the
`MlflowClient` API with the grid's tracking URI, so a SQLite database has a single writer.
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import time
from typing import Any, Iterable, Mapping

from ray.tune import Callback

from uavlora_rllib.experiment.evaluation import EPISODE_METRICS

try:  # the limits of the installed mlflow; the values below are mlflow 3's
    from mlflow.utils.validation import MAX_ENTITY_KEY_LENGTH, MAX_PARAM_VAL_LENGTH
except ImportError:  # pragma: no cover
    MAX_PARAM_VAL_LENGTH, MAX_ENTITY_KEY_LENGTH = 6000, 250

MAX_TAG_VAL_LENGTH = 5000
TRAIN_METRICS = ("episode_return_mean", "ee_sys_mean", "success_rate", "env_steps_per_s")
ENV_STEPS = "env_steps"  # key of the env-step counter in the trainable's results
LEARNER_PREFIX = "learner/"
EVAL_PREFIX = "eval/"

KIND_TRAIN = "train"
KIND_BASELINE = "baseline"


# --------------------------------------------------------------------------- helpers
def git_commit(repo_dir: str | None = None) -> str:
    """`git rev-parse HEAD` of the project checkout, or "unknown"."""
    repo_dir = repo_dir or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        out = subprocess.run(
            ["git", "-C", repo_dir, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10, check=True
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


_BAD_CHARS = re.compile(r"[^/\w.\- ]")


def safe_name(name: str) -> str:
    """An MLflow-valid metric/param key: allowed characters only, a normalised relative path."""
    name = _BAD_CHARS.sub("_", str(name))
    parts = [p for p in name.split("/") if p not in ("", ".", "..")]
    return "/".join(parts)[:MAX_ENTITY_KEY_LENGTH] or "_"


def param_value(value: Any) -> str:
    return str(value)[:MAX_PARAM_VAL_LENGTH]


def _number(value: Any) -> float | None:
    """A finite float, or None (bools, strings, NaN, inf are not metrics)."""
    if isinstance(value, bool):
        return None
    try:
        x = float(value)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def flat_params(prefix: str, mapping: Mapping[str, Any]) -> dict[str, str]:
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


def eval_metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    """`EvalResult.summary()` -> {"eval/<k>", "eval/<k>_ci95", "eval/episodes"}."""
    out: dict[str, float] = {}
    ci = summary.get("ci95", {}) or {}
    for k in EPISODE_METRICS:
        if k in summary:
            out[f"{EVAL_PREFIX}{k}"] = float(summary[k])
        if k in ci:
            out[f"{EVAL_PREFIX}{k}_ci95"] = float(ci[k])
    if "episodes" in summary:
        out[f"{EVAL_PREFIX}episodes"] = float(summary["episodes"])
    return out


def _lookup(result: Mapping[str, Any], *paths: str) -> Any:
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
        x = _number(obj)
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
    steps = _lookup(result, "num_env_steps_sampled_lifetime", "env_runners/num_env_steps_sampled_lifetime")
    out[ENV_STEPS] = int(_number(steps) or 0)
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
        x = _number(_lookup(result, *paths))
        if x is not None:
            out[key] = x
    if env_steps_per_s is not None and _number(env_steps_per_s) is not None:
        out["env_steps_per_s"] = float(env_steps_per_s)
    out.update(learner_stats(result.get("learners")))
    return out


def metrics_to_log(result: Mapping[str, Any]) -> tuple[dict[str, float], dict[str, float]]:
    """A trial result -> (training metrics, eval metrics) of the schema; other keys are dropped."""
    train: dict[str, float] = {}
    evals: dict[str, float] = {}
    for key, value in result.items():
        x = _number(value)
        if x is None:
            continue
        if key in TRAIN_METRICS or key.startswith(LEARNER_PREFIX):
            train[safe_name(key)] = x
        elif key.startswith((EVAL_PREFIX, "eval_sampled/")):  # periodic_eval.EVAL_SAMPLED_PREFIX
            evals[safe_name(key)] = x
    return train, evals


# --------------------------------------------------------------------------- the store
class Tracker:
    """The grid's MLflow experiment, through `MlflowClient` (the only writer: the driver)."""

    def __init__(self, tracking_uri: str, experiment: str, grid_file: str, commit: str | None = None):
        from mlflow.tracking import MlflowClient

        self.tracking_uri = tracking_uri
        self.experiment = experiment
        self.grid_file = grid_file
        self.commit = commit or git_commit()
        self.client = MlflowClient(tracking_uri=tracking_uri)
        exp = self.client.get_experiment_by_name(experiment)
        if exp is None:
            self.experiment_id = self.client.create_experiment(experiment)
        else:
            if exp.lifecycle_stage == "deleted":
                self.client.restore_experiment(exp.experiment_id)
            self.experiment_id = exp.experiment_id

    # ---- queries
    def search(self, filter_string: str = "") -> list:
        runs, token = [], None
        while True:
            page = self.client.search_runs(
                [self.experiment_id], filter_string, max_results=1000, order_by=["attributes.start_time ASC"],
                page_token=token,
            )
            runs.extend(page)
            token = page.token
            if not token:
                return runs

    def run_for_trial(self, trial_id: str):
        runs = self.search(f"tags.trial_id = '{trial_id}'")
        return runs[0] if runs else None

    def last_logged_step(self, run) -> int:
        steps = [-1]
        for key in TRAIN_METRICS:
            if key in run.data.metrics:
                steps += [m.step for m in self.client.get_metric_history(run.info.run_id, key)]
        return max(steps)

    # ---- writes
    def base_tags(self, kind: str, algorithm: str, seed: int, n_eds: int, n_uavs: int, budget: int | None) -> dict:
        return {
            "kind": kind,
            "algorithm": str(algorithm),
            "seed": str(seed),
            "n_eds": str(n_eds),
            "n_uavs": str(n_uavs),
            "git_commit": self.commit,
            "grid_file": self.grid_file[:MAX_TAG_VAL_LENGTH],
            "budget_env_steps": str(budget if budget is not None else 0),
        }

    def create_run(self, name: str, tags: Mapping[str, str], params: Mapping[str, str]) -> str:
        run = self.client.create_run(self.experiment_id, run_name=name, tags=dict(tags))
        self.log_params(run.info.run_id, params)
        return run.info.run_id

    def log_params(self, run_id: str, params: Mapping[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(k, v) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i : i + 100])

    def log_metrics(self, run_id: str, metrics: Mapping[str, float], step: int) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, int(step)) for k, v in metrics.items()]
        for i in range(0, len(items), 1000):
            self.client.log_batch(run_id, metrics=items[i : i + 1000])

    def set_tag(self, run_id: str, key: str, value: str) -> None:
        self.client.set_tag(run_id, key, str(value)[:MAX_TAG_VAL_LENGTH])

    def reopen(self, run_id: str) -> None:
        self.client.update_run(run_id, status="RUNNING")

    def end(self, run_id: str, status: str) -> None:
        self.client.set_terminated(run_id, status=status)

    def close_running(self, status: str = "KILLED", keep: Iterable[str] = ()) -> list[str]:
        """Mark every run of the experiment still RUNNING (and not in `keep`) as `status`."""
        keep = set(keep)
        closed = []
        for run in self.search("attributes.status = 'RUNNING'"):
            if run.info.run_id not in keep:
                self.end(run.info.run_id, status)
                closed.append(run.info.run_id)
        return closed

    # ---- baselines
    def finished_baseline(self, name: str, seed: int, n_eds: int, n_uavs: int, params: Mapping[str, str]) -> bool:
        """A FINISHED baseline run with the same identity and params exists (skip on resume)."""
        runs = self.search(
            f"tags.kind = '{KIND_BASELINE}' and tags.algorithm = '{name}' and tags.seed = '{seed}' "
            f"and tags.n_eds = '{n_eds}' and tags.n_uavs = '{n_uavs}' and attributes.status = 'FINISHED'"
        )
        return any(dict(r.data.params) == dict(params) for r in runs)

    def log_baseline(
        self,
        name: str,
        run_name: str,
        seed: int,
        n_eds: int,
        n_uavs: int,
        params: Mapping[str, str],
        evaluate,
        budget: int | None = None,
    ) -> str:
        """One baseline run: create it, call `evaluate()` -> summary, log eval/*, end FINISHED/FAILED.

        `budget` is the grid's training budget (tag budget_env_steps: which grid the baseline
        accompanies); nothing is trained, so no stop.env_steps param.
        """
        tags = self.base_tags(KIND_BASELINE, name, seed, n_eds, n_uavs, budget)
        run_id = self.create_run(run_name, tags, params)
        try:
            summary = evaluate()
            self.log_metrics(run_id, eval_metrics(summary), step=0)
        except KeyboardInterrupt:
            self.end(run_id, "KILLED")
            raise
        except Exception:
            self.end(run_id, "FAILED")
            raise
        self.end(run_id, "FINISHED")
        return run_id


# --------------------------------------------------------------------------- Tune callback
class MlflowTrialCallback(Callback):
    """Logs every trial of the grid to its one MLflow run (see the module docstring).

    A trial's config carries what the run needs: ``algorithm``, ``seed``, ``n_eds``,
    ``n_uavs``, ``scenario`` (dict), ``hparams`` (dict), ``resources`` (dict),
    ``budget_env_steps`` and ``eval_episodes``.
    """

    def __init__(self, tracking_uri: str, experiment: str, grid_file: str, commit: str | None = None):
        self.tracking_uri = tracking_uri
        self.experiment = experiment
        self.grid_file = grid_file
        self.commit = commit
        self._tracker: Tracker | None = None
        self._runs: dict[str, str] = {}  # trial_id -> run_id
        self._last_step: dict[str, int] = {}  # trial_id -> highest env step with training metrics
        self._ended: set[str] = set()

    # Tune pickles callbacks into the experiment state; the client is rebuilt on demand.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_tracker=None, _runs={}, _last_step={}, _ended=set())
        return state

    @property
    def tracker(self) -> Tracker:
        if self._tracker is None:
            self._tracker = Tracker(self.tracking_uri, self.experiment, self.grid_file, self.commit)
        return self._tracker

    def run_id(self, trial) -> str:
        """The trial's run: cached, found again by trial_id (resume), or created."""
        tid = trial.trial_id
        if tid in self._runs:
            return self._runs[tid]
        cfg = trial.config.get("trial", trial.config)
        existing = self.tracker.run_for_trial(tid)
        if existing is not None:
            run_id = existing.info.run_id
            self._last_step[tid] = self.tracker.last_logged_step(existing)
            if existing.info.status != "RUNNING":
                self.tracker.reopen(run_id)
        else:
            from uavlora_rllib.experiment.grid import run_name

            tags = self.tracker.base_tags(
                KIND_TRAIN, cfg["algorithm"], cfg["seed"], cfg["n_eds"], cfg["n_uavs"], cfg["budget_env_steps"]
            )
            tags["trial_id"] = tid
            tags["checkpoint"] = ""
            params = run_params(
                cfg["scenario"], cfg["budget_env_steps"], cfg["eval_episodes"], cfg["hparams"], cfg["resources"]
            )
            name = run_name(cfg["algorithm"], cfg["n_eds"], cfg["n_uavs"], cfg["seed"])
            run_id = self.tracker.create_run(name, tags, params)
            self._last_step[tid] = -1
        self._runs[tid] = run_id
        self._ended.discard(tid)
        return run_id

    def _end(self, trial, status: str) -> None:
        run_id = self.run_id(trial)
        self._update_checkpoint(trial)
        self.tracker.end(run_id, status)
        self._ended.add(trial.trial_id)

    def _update_checkpoint(self, trial) -> None:
        ckpt = getattr(trial, "checkpoint", None)
        path = getattr(ckpt, "path", None)
        if path:
            self.tracker.set_tag(self.run_id(trial), "checkpoint", path)

    # ---- Tune hooks
    def on_trial_start(self, iteration, trials, trial, **info):
        self.run_id(trial)

    def on_trial_restore(self, iteration, trials, trial, **info):
        self.run_id(trial)

    def on_trial_result(self, iteration, trials, trial, result, **info):
        run_id = self.run_id(trial)
        step = int(_number(result.get(ENV_STEPS)) or 0)
        train, evals = metrics_to_log(result)
        tid = trial.trial_id
        if step <= self._last_step.get(tid, -1):
            train = {}  # already logged before an interrupt (resumed from an earlier checkpoint)
        else:
            self._last_step[tid] = step
        if train or evals:
            self.tracker.log_metrics(run_id, {**train, **evals}, step)

    def on_trial_save(self, iteration, trials, trial, **info):
        self._update_checkpoint(trial)

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._end(trial, "FINISHED")

    def on_trial_error(self, iteration, trials, trial, **info):
        self._end(trial, "FAILED")

    def on_experiment_end(self, trials, **info):
        # Trials that did not finish (interrupted grid): their runs are KILLED until --resume.
        for trial in trials:
            tid = trial.trial_id
            if tid in self._runs and tid not in self._ended:
                self._update_checkpoint(trial)
                self.tracker.end(self._runs[tid], "KILLED")
                self._ended.add(tid)
