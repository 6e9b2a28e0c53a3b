"""The grid's MLflow experiment behind a retrying client: `Tracker`, the only writer of its runs.

Only the driver writes: the `mlflow_callback.MlflowTrialCallback` runs in the Tune driver
loop, baseline results arrive on a driver thread (`baseline_tasks.BaselinePool`), and both use
the `MlflowClient` API under one process-wide lock, so a SQLite database has a single writer.

Crash safety of the runs this module writes (a driver killed at any point, then the same
command with ``--resume``):

* a train run whose Tune trial no longer exists (the driver died before Tune saved its state,
  so the trial starts again under a new id) is deleted and replaced (`Tracker.replace_orphans`),
  so that its metric history holds one training only;
* a baseline run is created, filled and ended in one go when its result arrives; one left
  unfinished by a killed driver is adopted (filled and ended) instead of duplicated.

Against an MLflow server every call is retried with exponential backoff for at most
``retry_timeout_s`` seconds (grid ``mlflow.retry_timeout_s``) while the failure is `retryable`
(no answer, or HTTP 429/502/503/504, or a busy database); then `TrackingUnavailable` stops the
driver with one clear line. Nothing is lost: Tune's results and checkpoints are on storage, and
``--resume`` fills the runs in. A server that answers 401/403 (MLflow's basic-auth app without,
or with wrong, MLFLOW_TRACKING_USERNAME/PASSWORD) is not retried: `TrackingRefused`, one line.

Every run of the grid is nested under its one parent run (`Tracker.grid_run`, tag kind=grid),
found again by every later driver of the same experiment. Run fields: `run_schema`.
"""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import threading
import time
from collections.abc import Iterable, Mapping
from typing import Any

from uavlora_rllib.experiment.run_schema import (
    EVAL_WALL_METRIC,
    GRID_ARTIFACT,
    IDENTITY_PARAMS,
    KIND_BASELINE,
    KIND_GRID,
    KIND_TRAIN,
    MAX_TAG_VAL_LENGTH,
    PARENT_TAG,
    TRAIN_METRICS,
    eval_metrics,
    identity_params,
    reference_steps,
)

UNFINISHED = ("RUNNING", "KILLED", "FAILED", "SCHEDULED")
RETRYABLE_HTTP_STATUS = frozenset({429, 502, 503, 504})  # rate limited, bad gateway, unavailable, gateway timeout
SQLITE_BUSY_CODES = frozenset({sqlite3.SQLITE_BUSY, sqlite3.SQLITE_LOCKED})  # another connection holds a lock

# One writer at a time in this process (Tune callback thread + baseline results thread).
_WRITE_LOCK = threading.RLock()
DEFAULT_RETRY_TIMEOUT_S = 300.0


class TrackingUnavailable(RuntimeError):
    """MLflow stayed unreachable for the whole retry budget."""


class TrackingRefused(TrackingUnavailable):
    """The MLflow server answered 401/403: missing or wrong credentials (its basic-auth app)."""


def retryable(exc: BaseException) -> bool:
    """A failure worth retrying (MLflow or its database away or busy), judged from types and status codes."""
    for cause in reversed(_causes(exc)):  # the root cause says best what happened
        verdict = _verdict(cause)
        if verdict is not None:
            return verdict
    return False


def _causes(exc: BaseException | None) -> list[BaseException]:
    """`exc` and the exceptions it was raised from or while handling, outermost first."""
    chain: list[BaseException] = []
    while exc is not None and not any(exc is seen for seen in chain):
        chain.append(exc)
        exc = exc.__cause__ or exc.__context__
    return chain


def _verdict(exc: BaseException) -> bool | None:
    """Retryable (True) or not (False) from this exception alone; None when it does not tell."""
    from requests.exceptions import ChunkedEncodingError, Timeout
    from requests.exceptions import ConnectionError as RequestsConnectionError

    if isinstance(exc, sqlite3.Error):  # a local store: only a lock held by another connection passes
        code = getattr(exc, "sqlite_errorcode", None)
        return None if code is None else code in SQLITE_BUSY_CODES
    if isinstance(exc, (ConnectionError, TimeoutError, RequestsConnectionError, Timeout, ChunkedEncodingError)):
        return True  # no answer, or the connection dropped mid-answer
    status = _http_status(exc)
    return None if status is None else status in RETRYABLE_HTTP_STATUS


def _http_status(exc: BaseException) -> int | None:
    """The HTTP status code an exception carries: a reply's, an MLflow error code's, or urllib3's retry verdict's."""
    from mlflow.exceptions import MlflowException
    from requests.exceptions import RequestException
    from urllib3.exceptions import ResponseError

    if isinstance(exc, MlflowException):
        return int(exc.get_http_status_code())
    if isinstance(exc, RequestException):
        return None if exc.response is None else int(exc.response.status_code)
    if isinstance(exc, ResponseError):
        # urllib3 out of retries on a status (MLflow's own retries are off): the code exists only
        # in urllib3's fixed message template, so read it back through that template
        template = re.escape(ResponseError.SPECIFIC_ERROR).replace(re.escape("{status_code}"), r"(\d+)")
        match = re.fullmatch(template, str(exc))
        return int(match.group(1)) if match else None
    return None


def user_name() -> str:
    """Who launched the grid (MLflow's ``mlflow.user`` convention: the OS user), or "unknown"."""
    import getpass

    try:
        return getpass.getuser()
    except (KeyError, OSError):  # no passwd entry and no USER variable (some containers)
        return "unknown"


def git_repo_url(repo_dir: str | None = None) -> str | None:
    """The checkout's ``origin`` URL when it is a web or SSH address the UI can link to, else None."""
    repo_dir = repo_dir or os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        out = subprocess.run(
            ["git", "-C", repo_dir, "config", "--get", "remote.origin.url"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    url = out.stdout.strip()
    return url if url.startswith(("https://", "http://", "git@", "ssh://")) else None


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


def _without_identity(params: Mapping[str, str]) -> dict[str, str]:
    """Params without the identity ones (runs written before they were params lack them)."""
    return {k: v for k, v in params.items() if k not in IDENTITY_PARAMS}


class Tracker:
    """The grid's MLflow experiment, through `MlflowClient` (the only writer: the driver)."""

    def __init__(
        self,
        tracking_uri: str,
        experiment: str,
        grid_file: str,
        commit: str | None = None,
        retry_timeout_s: float = DEFAULT_RETRY_TIMEOUT_S,
    ):
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
        self.user = user_name()
        self.repo_url = git_repo_url()
        self._grid_run_id: str | None = None
        self.client = MlflowClient(tracking_uri=tracking_uri)
        exp = self._call(self.client.get_experiment_by_name, experiment)
        if exp is None:
            self.experiment_id = self._call(self._create_experiment, experiment)
        else:
            if exp.lifecycle_stage == "deleted":
                self._call(self.client.restore_experiment, exp.experiment_id)
            self.experiment_id = exp.experiment_id

    def _create_experiment(self, name: str) -> str:
        """create_experiment, idempotent: a retry after a timed-out create that the server did
        carry out (or another driver creating it at the same time) finds the experiment instead."""
        from mlflow.exceptions import MlflowException

        try:
            return self.client.create_experiment(name)
        except MlflowException as exc:
            if exc.error_code != "RESOURCE_ALREADY_EXISTS":
                raise
            exp = self.client.get_experiment_by_name(name)
            if exp is None:
                raise
            return exp.experiment_id

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
                status = _http_status(exc)
                if status in (401, 403):
                    raise TrackingRefused(
                        f"mlflow.tracking_uri: MLflow at {self.tracking_uri} refused the request (HTTP {status}: "
                        f"{'no or wrong credentials' if status == 401 else 'no permission'}); set "
                        "MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD to a user of its basic-auth app "
                        "(docs/cluster.md#mlflow)"
                    ) from None
                if not retryable(exc):
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
                [self.experiment_id],
                filter_string,
                max_results=1000,
                order_by=["attributes.start_time ASC"],
                page_token=token,
            )
            runs.extend(page)
            token = page.token
            if not token:
                return runs

    def get_run(self, run_id: str):
        return self._call(self.client.get_run, run_id)

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
    def source_tags(self) -> dict:
        """MLflow's standard source tags, so the UI's Source and User fields are filled: the command
        that ran the grid, the commit it ran at, and who ran it."""
        from mlflow.utils.mlflow_tags import (
            MLFLOW_GIT_COMMIT,
            MLFLOW_GIT_REPO_URL,
            MLFLOW_SOURCE_NAME,
            MLFLOW_SOURCE_TYPE,
            MLFLOW_USER,
        )

        tags = {
            MLFLOW_SOURCE_NAME: f"python -m uavlora_rllib.tune {self.grid_file}"[:MAX_TAG_VAL_LENGTH],
            MLFLOW_SOURCE_TYPE: "LOCAL",
            MLFLOW_GIT_COMMIT: self.commit,
            MLFLOW_USER: self.user,
        }
        if self.repo_url:
            tags[MLFLOW_GIT_REPO_URL] = self.repo_url
        return tags

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
            **self.source_tags(),
            PARENT_TAG: self.grid_run(),
        }

    def create_run(self, name: str, tags: Mapping[str, str], params: Mapping[str, str]) -> str:
        run = self._call(self.client.create_run, self.experiment_id, run_name=name, tags=dict(tags))
        self.log_params(run.info.run_id, params)
        return run.info.run_id

    # ---- the grid's parent run
    def grid_run(self) -> str:
        """The id of the grid's parent run (tag kind=grid), found again or created (with the grid
        YAML as its ``grid.yaml`` artifact): one per experiment, kept by every ``--resume``."""
        if self._grid_run_id is None:
            runs = self.search(f"tags.kind = '{KIND_GRID}'")  # oldest first
            if runs:
                self._grid_run_id = runs[0].info.run_id
            else:
                tags = {
                    "kind": KIND_GRID,
                    "git_commit": self.commit,
                    "grid_file": self.grid_file[:MAX_TAG_VAL_LENGTH],
                    **self.source_tags(),
                }
                run = self._call(self.client.create_run, self.experiment_id, run_name=self.experiment, tags=tags)
                self._grid_run_id = run.info.run_id
                if os.path.isfile(self.grid_file):
                    with open(self.grid_file) as fh:
                        self.log_text(self._grid_run_id, fh.read(), GRID_ARTIFACT)
        return self._grid_run_id

    def open_grid_run(self) -> str:
        """The parent run, RUNNING while this driver runs the grid (its commit tags updated)."""
        run_id = self.grid_run()
        for key, value in {"git_commit": self.commit, **self.source_tags()}.items():
            self.set_tag(run_id, key, value)
        self.reopen(run_id)
        return run_id

    def set_parent(self, run) -> None:
        """Nest an existing run (one written before parents existed, or adopted) under the grid run."""
        parent = self.grid_run()
        if run.data.tags.get(PARENT_TAG) != parent:
            self.set_tag(run.info.run_id, PARENT_TAG, parent)

    # ---- artifacts
    def log_text(self, run_id: str, text: str, artifact_file: str) -> None:
        """A small text artifact; logging the same file again replaces it (no duplicate)."""
        self._call(self.client.log_text, run_id, text, artifact_file)

    def log_artifacts(self, run_id: str, local_dir: str, artifact_path: str) -> None:
        self._call(self.client.log_artifacts, run_id, local_dir, artifact_path)

    def metric_histories(self, run_id: str) -> dict[str, list[tuple[int, float]]]:
        """Every metric of a run as [(step, value)] in logging order (for its ``curves.csv``)."""
        run = self._call(self.client.get_run, run_id)
        out = {}
        for key in run.data.metrics:
            hist = self._call(self.client.get_metric_history, run_id, key)
            out[key] = [(m.step, m.value) for m in sorted(hist, key=lambda m: (m.timestamp, m.step))]
        return out

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
        """A FINISHED baseline run with the same identity and params exists (skip on resume; a
        run written before parents existed is nested under the grid run then)."""
        runs = self.search(
            self.identity_filter(KIND_BASELINE, name, seed, n_eds, n_uavs) + " and attributes.status = 'FINISHED'"
        )
        for r in runs:
            if _without_identity(r.data.params) == _without_identity(params):
                self.set_parent(r)
                return True
        return False

    def _adoptable_baseline(self, name: str, seed: int, n_eds: int, n_uavs: int, params: Mapping[str, str]):
        """Unfinished baseline runs with this identity whose params agree with `params` (a
        killed driver may have logged only some of them): the first is adopted, the rest are
        leftovers of older crashes and are deleted so that one run remains."""
        runs = [
            r
            for r in self.search(self.identity_filter(KIND_BASELINE, name, seed, n_eds, n_uavs))
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
        accompanies); nothing is trained, so no stop.env_steps param, and the values are logged
        at `run_schema.reference_steps` of it (a flat line beside the learners' curves). The run
        is written only once the result exists, so an interrupted evaluation leaves no run behind.
        """
        error: Exception | None = None
        try:
            summary = evaluate()
        except Exception as exc:
            summary, error = None, exc
        params = {**identity_params(name, seed, n_eds, n_uavs), **params}
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
        metrics = eval_metrics(summary)
        for step in reference_steps(budget):  # a flat reference line across the training range
            self.log_metrics(run_id, metrics, step=step)
        if "_wall_s" in summary:  # the evaluation's own time on its one CPU (analysis/cost.py: the grid's cost)
            self.log_metrics(run_id, {EVAL_WALL_METRIC: float(summary["_wall_s"])}, step=0)
        self.end(run_id, "FINISHED")
        return run_id

    # ---- trials
    def replace_orphans(self, cfg: Mapping[str, Any], trial_id: str) -> list[str]:
        """Delete unfinished train runs of this trial's identity that belong to another trial id.

        One grid has one trial per (algorithm, seed, V, U); an unfinished run of that identity
        under another trial id is a trial Tune no longer knows (the driver died before Tune
        saved it), whose training restarts from scratch under `trial_id`.
        """
        runs = self.search(self.identity_filter(KIND_TRAIN, cfg["algorithm"], cfg["seed"], cfg["n_eds"], cfg["n_uavs"]))
        gone = [r.info.run_id for r in runs if r.data.tags.get("trial_id") != trial_id and r.info.status in UNFINISHED]
        for run_id in gone:
            self.delete(run_id)
        return gone
