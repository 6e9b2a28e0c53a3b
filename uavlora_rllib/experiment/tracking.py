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
  ``eval/<k>_ci95`` for k in `evaluation.EPISODE_METRICS`, and ``eval/episodes``; the
  reference baselines (greedy, optimal) also ``eval/ee_sys_upper_bound``; train runs
  also log them during training, step = env steps (experiment/periodic_eval.py), so the final
  evaluation is the last point of each series; ``eval_sampled/<k>`` likewise for algorithms
  with a sampled policy.

One run per trial, even across ``--resume``: the run is found again by its ``trial_id`` tag
(Tune keeps trial ids when it restores an experiment), reopened (status RUNNING) and
continued; training results already logged at a step are not logged twice. A run ends
FINISHED when its trial terminates, FAILED when it errors, and KILLED when the grid stops
(interrupt, crash) before the trial finished; `--resume` reopens KILLED runs.

Only the driver writes: the `MlflowTrialCallback` runs in the Tune driver loop, baseline
results arrive on a driver thread (`baseline_tasks.BaselinePool`), and both use the
`MlflowClient` API under one process-wide lock, so a SQLite database has a single writer.

Crash safety (a driver killed at any point, then the same command with ``--resume``):

* a trial's run is found again by its ``trial_id`` and adopted whatever its status; a train
  run whose Tune trial no longer exists (the driver died before Tune saved its state, so the
  trial starts again under a new id) is deleted and replaced, so that its metric history
  holds one training only;
* a baseline run is created, filled and ended in one go when its result arrives; one left
  unfinished by a killed driver is adopted (filled and ended) instead of duplicated;
* trials Tune restores as finished but whose run was not ended (the driver died in between,
  or MLflow was down) are completed from the trial's ``result.json`` (`reconcile_trial`).

Against an MLflow server every call is retried with exponential backoff for at most
``retry_timeout_s`` seconds (grid ``mlflow.retry_timeout_s``); then `TrackingUnavailable`
stops the driver with one clear line. Nothing is lost: Tune's results and checkpoints are on
storage, and ``--resume`` fills the runs in.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import threading
import time
from typing import Any, Iterable, Mapping

from ray.tune import Callback

from uavlora_rllib.experiment.evaluation import BOUND_METRIC, EPISODE_METRICS

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
UNFINISHED = ("RUNNING", "KILLED", "FAILED", "SCHEDULED")

# One writer at a time in this process (Tune callback thread + baseline results thread).
_WRITE_LOCK = threading.RLock()
DEFAULT_RETRY_TIMEOUT_S = 300.0


class TrackingUnavailable(RuntimeError):
    """MLflow stayed unreachable for the whole retry budget."""


def _transient(exc: BaseException) -> bool:
    """A failure worth retrying: the server or the database is away or busy, not a bad request."""
    if isinstance(exc, (ConnectionError, TimeoutError)):
        return True
    try:
        import requests

        if isinstance(exc, requests.exceptions.RequestException):
            return True
    except ImportError:  # pragma: no cover
        pass
    text = str(exc)
    markers = ("Max retries exceeded", "Connection refused", "Connection aborted", "API request to",
               "database is locked", "timed out", "Temporarily Unavailable", "503", "502", "504")
    return any(m in text for m in markers)


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
    for k in (*EPISODE_METRICS, BOUND_METRIC):
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

    def __init__(self, tracking_uri: str, experiment: str, grid_file: str, commit: str | None = None,
                 retry_timeout_s: float = DEFAULT_RETRY_TIMEOUT_S):
        from mlflow.tracking import MlflowClient

        if tracking_uri.startswith(("http://", "https://")):
            # MLflow's own HTTP retries (7, with growing sleeps) would hide the outage inside one
            # call for minutes; `_call` owns the retry budget instead, with a short per-request timeout.
            os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
            os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "20")
        self.tracking_uri = tracking_uri
        self.experiment = experiment
        self.grid_file = grid_file
        self.retry_timeout_s = float(retry_timeout_s)
        self.commit = commit or git_commit()
        self.client = MlflowClient(tracking_uri=tracking_uri)
        exp = self._call(self.client.get_experiment_by_name, experiment)
        if exp is None:
            self.experiment_id = self._call(self.client.create_experiment, experiment)
        else:
            if exp.lifecycle_stage == "deleted":
                self._call(self.client.restore_experiment, exp.experiment_id)
            self.experiment_id = exp.experiment_id

    def _call(self, fn, *args, **kwargs):
        """fn(*args) under the write lock, retried with backoff while MLflow is unreachable."""
        deadline = time.monotonic() + self.retry_timeout_s
        delay, attempts = 0.5, 0
        while True:
            attempts += 1
            try:
                with _WRITE_LOCK:
                    return fn(*args, **kwargs)
            except Exception as exc:
                if not _transient(exc):
                    raise
                left = deadline - time.monotonic()
                if left <= 0:
                    msg = " ".join(str(exc).split())[:200]
                    raise TrackingUnavailable(
                        f"mlflow.tracking_uri: MLflow at {self.tracking_uri} unreachable for "
                        f"{self.retry_timeout_s:.0f} s ({attempts} attempts; last error {type(exc).__name__}: {msg}). "
                        "Trial results and checkpoints are kept in Ray's storage: bring MLflow back and run "
                        "the same command with --resume to complete the runs"
                    ) from None
                time.sleep(min(delay, left))
                delay = min(delay * 2, 15.0)

    # ---- queries
    def search(self, filter_string: str = "") -> list:
        runs, token = [], None
        while True:
            page = self._call(
                self.client.search_runs,
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

    def identity_filter(self, kind: str, algorithm: str, seed: int, n_eds: int, n_uavs: int) -> str:
        return (
            f"tags.kind = '{kind}' and tags.algorithm = '{algorithm}' and tags.seed = '{seed}' "
            f"and tags.n_eds = '{n_eds}' and tags.n_uavs = '{n_uavs}'"
        )

    def last_logged_step(self, run) -> int:
        steps = [-1]
        for key in TRAIN_METRICS:
            if key in run.data.metrics:
                steps += [m.step for m in self._call(self.client.get_metric_history, run.info.run_id, key)]
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
        run = self._call(self.client.create_run, self.experiment_id, run_name=name, tags=dict(tags))
        self.log_params(run.info.run_id, params)
        return run.info.run_id

    def log_params(self, run_id: str, params: Mapping[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(k, v) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self._call(self.client.log_batch, run_id, params=items[i : i + 100])

    def log_metrics(self, run_id: str, metrics: Mapping[str, float], step: int) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, int(step)) for k, v in metrics.items()]
        for i in range(0, len(items), 1000):
            self._call(self.client.log_batch, run_id, metrics=items[i : i + 1000])

    def set_tag(self, run_id: str, key: str, value: str) -> None:
        self._call(self.client.set_tag, run_id, key, str(value)[:MAX_TAG_VAL_LENGTH])

    def reopen(self, run_id: str) -> None:
        self._call(self.client.update_run, run_id, status="RUNNING")

    def end(self, run_id: str, status: str) -> None:
        self._call(self.client.set_terminated, run_id, status=status)

    def delete(self, run_id: str) -> None:
        self._call(self.client.delete_run, run_id)

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
            self.identity_filter(KIND_BASELINE, name, seed, n_eds, n_uavs) + " and attributes.status = 'FINISHED'"
        )
        return any(dict(r.data.params) == dict(params) for r in runs)

    def _adoptable_baseline(self, name: str, seed: int, n_eds: int, n_uavs: int, params: Mapping[str, str]):
        """Unfinished baseline runs with this identity whose params agree with `params` (a
        killed driver may have logged only some of them): the first is adopted, the rest are
        leftovers of older crashes and are deleted so that one run remains."""
        runs = [
            r for r in self.search(self.identity_filter(KIND_BASELINE, name, seed, n_eds, n_uavs))
            if r.info.status in UNFINISHED and all(params.get(k) == v for k, v in r.data.params.items())
        ]
        for extra in runs[1:]:
            self.delete(extra.info.run_id)
        return runs[0] if runs else None

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
        """One baseline run: `evaluate()` -> summary (or an exception it raises), then the run
        is created (or an unfinished one adopted), filled with eval/* and ended FINISHED/FAILED.

        `budget` is the grid's training budget (tag budget_env_steps: which grid the baseline
        accompanies); nothing is trained, so no stop.env_steps param. The run is written only
        once the result exists, so an interrupted evaluation leaves no run behind.
        """
        error: Exception | None = None
        try:
            summary = evaluate()
        except Exception as exc:
            summary, error = None, exc
        tags = self.base_tags(KIND_BASELINE, name, seed, n_eds, n_uavs, budget)
        adopted = self._adoptable_baseline(name, seed, n_eds, n_uavs, params)
        if adopted is not None:
            run_id = adopted.info.run_id
            missing = {k: v for k, v in params.items() if k not in adopted.data.params}
            self.log_params(run_id, missing)
            for k, v in tags.items():
                self.set_tag(run_id, k, v)
            self.reopen(run_id)
        else:
            run_id = self.create_run(run_name, tags, params)
        if error is not None:
            self.set_tag(run_id, "error", " ".join(str(error).split()))
            self.end(run_id, "FAILED")
            raise error
        self.log_metrics(run_id, eval_metrics(summary), step=0)
        self.end(run_id, "FINISHED")
        return run_id

    # ---- trials
    def replace_orphans(self, cfg: Mapping[str, Any], trial_id: str) -> list[str]:
        """Delete unfinished train runs of this trial's identity that belong to another trial id.

        One grid has one trial per (algorithm, seed, V, U); an unfinished run of that identity
        under another trial id is a trial Tune no longer knows (the driver died before Tune
        saved it), whose training restarts from scratch under `trial_id`.
        """
        runs = self.search(
            self.identity_filter(KIND_TRAIN, cfg["algorithm"], cfg["seed"], cfg["n_eds"], cfg["n_uavs"])
        )
        gone = [r.info.run_id for r in runs if r.data.tags.get("trial_id") != trial_id and r.info.status in UNFINISHED]
        for run_id in gone:
            self.delete(run_id)
        return gone


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


# --------------------------------------------------------------------------- Tune callback
class MlflowTrialCallback(Callback):
    """Logs every trial of the grid to its one MLflow run (see the module docstring).

    A trial's config carries what the run needs: ``algorithm``, ``seed``, ``n_eds``,
    ``n_uavs``, ``scenario`` (dict), ``hparams`` (dict), ``resources`` (dict),
    ``budget_env_steps`` and ``eval_episodes``.
    """

    def __init__(self, tracking_uri: str, experiment: str, grid_file: str, commit: str | None = None,
                 retry_timeout_s: float = DEFAULT_RETRY_TIMEOUT_S):
        self.tracking_uri = tracking_uri
        self.experiment = experiment
        self.grid_file = grid_file
        self.commit = commit
        self.retry_timeout_s = retry_timeout_s
        self._tracker: Tracker | None = None
        self._runs: dict[str, str] = {}  # trial_id -> run_id
        self._last_step: dict[str, int] = {}  # trial_id -> highest env step with training metrics
        self._ended: set[str] = set()
        self._reconciled = False

    # Tune pickles callbacks into the experiment state; the client is rebuilt on demand.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_tracker=None, _runs={}, _last_step={}, _ended=set(), _reconciled=False)
        return state

    def __setstate__(self, state: dict) -> None:
        state.setdefault("retry_timeout_s", DEFAULT_RETRY_TIMEOUT_S)
        state.setdefault("_reconciled", False)
        self.__dict__.update(state)

    @property
    def tracker(self) -> Tracker:
        if self._tracker is None:
            self._tracker = Tracker(self.tracking_uri, self.experiment, self.grid_file, self.commit,
                                    retry_timeout_s=self.retry_timeout_s)
        return self._tracker

    def run_id(self, trial) -> str:
        """The trial's run: cached, found again by trial_id (resume, retry), or created."""
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

            replaced = self.tracker.replace_orphans(cfg, tid)
            if replaced:
                print(f"MLflow: replaced {len(replaced)} unfinished run(s) of a trial whose Tune state was lost "
                      f"({run_name(cfg['algorithm'], cfg['n_eds'], cfg['n_uavs'], cfg['seed'])})", flush=True)
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

    def _log_result(self, trial, result: Mapping[str, Any]) -> None:
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

    def reconcile_trial(self, trial) -> bool:
        """A trial Tune holds as finished whose run is not FINISHED: log what is missing from
        its result.json (or its last result) and end the run. True when something was done."""
        existing = self.tracker.run_for_trial(trial.trial_id)
        if existing is not None and existing.info.status == "FINISHED" and any(
            k.startswith(EVAL_PREFIX) for k in existing.data.metrics
        ):
            return False
        rows = read_trial_results(getattr(trial, "path", None)) or ([trial.last_result] if trial.last_result else [])
        for row in rows:
            self._log_result(trial, row)
        self._end(trial, "FINISHED")
        return True

    # ---- Tune hooks
    def on_step_begin(self, iteration, trials, **info):
        # the first step after Tuner.restore: trials restored as finished get no other hook
        if self._reconciled:
            return
        self._reconciled = True
        done = [t for t in trials if t.status == "TERMINATED"]
        fixed = sum(self.reconcile_trial(t) for t in done)
        if fixed:
            print(f"MLflow: completed {fixed} run(s) of trials that had finished while their driver died", flush=True)

    def on_trial_start(self, iteration, trials, trial, **info):
        self.run_id(trial)

    def on_trial_restore(self, iteration, trials, trial, **info):
        self.run_id(trial)

    def on_trial_recover(self, iteration, trials, trial, **info):
        # the trial failed (e.g. its node died) and Tune retries it from its last checkpoint
        # (failure.max_failures): the run stays open and continues; count the retries
        run_id = self.run_id(trial)
        self.tracker.set_tag(run_id, "retries", str(getattr(trial, "num_failures", 0)))

    def on_trial_result(self, iteration, trials, trial, result, **info):
        self._log_result(trial, result)

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
