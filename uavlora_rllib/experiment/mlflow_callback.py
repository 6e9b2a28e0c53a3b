"""The Tune callback that logs every trial of a grid to its one MLflow run, from the driver.

One run per trial, even across ``--resume``: the run is found again by its ``trial_id`` tag
(Tune keeps trial ids when it restores an experiment), reopened (status RUNNING) and
continued; training results already logged at a step are not logged twice. A run ends
FINISHED when its trial terminates, FAILED when it errors, and KILLED when the grid stops
(interrupt, crash) before the trial finished; `--resume` reopens KILLED runs.

Crash safety (a driver killed at any point, then the same command with ``--resume``): a
trial's run is found again by its ``trial_id`` and adopted whatever its status; trials Tune
restores as finished but whose run was not ended (the driver died in between, or MLflow was
down) are completed from the trial's ``result.json`` (`MlflowTrialCallback.reconcile_trial`: the rows after
the run's last logged step, so no point is logged twice).
Artifacts (`run_schema`): ``trial_config.yaml`` when the run is created or adopted; when the
trial ends, ``curves.csv`` (from the run's own metric histories, so it holds exactly what the UI
draws) and, for a FINISHED trial, its final checkpoint as ``checkpoint/`` when that is on a
local or shared filesystem and small enough (``mlflow.checkpoint_artifact_max_mb``), else a
``checkpoint_artifact`` tag saying why not. Each goes to a fixed artifact path, so a repeat
(``--resume`` after a crash) replaces instead of duplicating, and a checkpoint already uploaded
(tag ``checkpoint_artifact_source``) is not uploaded again.
The runs' fields: `run_schema`; the retrying writer: `mlflow_client.Tracker`.

The store is the one the resuming driver names: Tune pickles this callback, tracking URI and grid
file included, into the experiment state, and `--resume` unpickles it inside `resuming_into(uri,
grid_file)`, which puts the grid's current (absolute) URI and file in place of the pickled ones.
Without it an experiment copied or moved with its store (another checkout, a cluster's shared disk)
would go on logging into the old path while the driver's banner names the new one. A run created
before the move keeps its `grid_file` tag.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping
from typing import Any

from ray.tune import Callback

from uavlora_rllib.experiment.mlflow_client import DEFAULT_RETRY_TIMEOUT_S, Tracker
from uavlora_rllib.experiment.run_schema import (
    CHECKPOINT_ARTIFACT,
    CURVES_ARTIFACT,
    ENV_STEPS,
    EVAL_INTERVAL_PARAM,
    EVAL_PREFIX,
    KIND_TRAIN,
    PLUGINS_ON_RESUME_TAG,
    PLUGINS_TAG,
    PRECISION_ROUTE,
    TRIAL_CONFIG_ARTIFACT,
    curves_csv,
    identity_params,
    metrics_to_log,
    number,
    plugin_digests,
    read_trial_results,
    run_params,
    sampled_params,
    trial_config_yaml,
)

DEFAULT_CHECKPOINT_ARTIFACT_MAX_MB = 50.0  # grid mlflow.checkpoint_artifact_max_mb
_RESUMING: dict[str, str] = {}  # set by `resuming_into` while Tune unpickles the experiment


@contextlib.contextmanager
def resuming_into(tracking_uri: str, grid_file: str) -> Iterator[None]:
    """Callbacks unpickled inside (Tuner.restore) log to `tracking_uri`, the resuming grid's store,
    and tag the runs they create with `grid_file`."""
    _RESUMING.update(tracking_uri=tracking_uri, grid_file=grid_file)
    try:
        yield
    finally:
        _RESUMING.clear()


def checkpoint_uri(checkpoint) -> str:
    """Where a Tune checkpoint lies: its path on a local/shared filesystem, else a URI (s3://, gs://)."""
    path = str(checkpoint.path)
    kind = str(getattr(getattr(checkpoint, "filesystem", None), "type_name", "local") or "local")
    if kind == "local" or kind.startswith("py::"):
        return path
    scheme = {"gcs": "gs"}.get(kind, kind)  # pyarrow's GcsFileSystem is "gcs"; its URIs are gs://
    return f"{scheme}://{path.lstrip('/')}"


def directory_stat(path: str) -> tuple[float, int]:
    """Size of the files under `path` in MB (10^6 bytes), and the newest one's modification time [ns]:
    a checkpoint written again at the same path (a trial that redid iterations after a resume) is newer."""
    total, newest = 0, 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                st = os.stat(os.path.join(root, name))
            except OSError:
                continue
            total, newest = total + st.st_size, max(newest, st.st_mtime_ns)
    return total / 1e6, newest


class MlflowTrialCallback(Callback):
    """Logs every trial of the grid to its one MLflow run (see the module docstring).

    A trial's config carries what the run needs: ``algorithm``, ``seed``, ``n_eds``,
    ``n_uavs``, ``scenario`` (dict), ``hparams`` (dict), ``resources`` (dict),
    ``budget_env_steps`` and ``eval_episodes``.
    """

    def __init__(
        self,
        tracking_uri: str,
        experiment: str,
        grid_file: str,
        commit: str | None = None,
        retry_timeout_s: float = DEFAULT_RETRY_TIMEOUT_S,
        checkpoint_artifact_max_mb: float = DEFAULT_CHECKPOINT_ARTIFACT_MAX_MB,
    ):
        self.tracking_uri = tracking_uri
        self.experiment = experiment
        self.grid_file = grid_file
        self.commit = commit
        self.retry_timeout_s = retry_timeout_s
        self.checkpoint_artifact_max_mb = checkpoint_artifact_max_mb
        self._tracker: Tracker | None = None
        self._runs: dict[str, str] = {}  # trial_id -> run_id
        self._last_step: dict[str, int] = {}  # trial_id -> highest env step with training metrics
        self._ended: set[str] = set()
        self._routes: dict[str, set[str]] = {}  # trial_id -> the routes in its PRECISION_ROUTE tag
        self._reconciled = False

    # Tune pickles callbacks into the experiment state; the client is rebuilt on demand.
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.update(_tracker=None, _runs={}, _last_step={}, _ended=set(), _routes={}, _reconciled=False)
        return state

    def __setstate__(self, state: dict) -> None:
        state.setdefault("retry_timeout_s", DEFAULT_RETRY_TIMEOUT_S)
        state.setdefault("_reconciled", False)
        state.setdefault("_routes", {})
        state.setdefault("checkpoint_artifact_max_mb", DEFAULT_CHECKPOINT_ARTIFACT_MAX_MB)
        state.update(_RESUMING)
        self.__dict__.update(state)

    @property
    def tracker(self) -> Tracker:
        if self._tracker is None:
            self._tracker = Tracker(
                self.tracking_uri, self.experiment, self.grid_file, self.commit, retry_timeout_s=self.retry_timeout_s
            )
        return self._tracker

    def run_id(self, trial) -> str:
        """The trial's run: cached, found again by trial_id (resume, retry), or created."""
        tid = trial.trial_id
        if tid in self._runs:
            return self._runs[tid]
        cfg = trial.config.get("trial", trial.config)
        existing = self.tracker.run_for_trial(tid)
        identity = identity_params(cfg["algorithm"], cfg["seed"], cfg["n_eds"], cfg["n_uavs"])
        plugins = plugin_digests(list(cfg.get("plugins", [])))
        if existing is not None:
            run_id = existing.info.run_id
            started = existing.data.tags.get(PLUGINS_TAG)  # None: a run from before this tag, not compared
            if started is not None and plugins != started and existing.data.tags.get(PLUGINS_ON_RESUME_TAG) != plugins:
                # the run trained partly with other plugin code: kept visible beside what it started with
                self.tracker.set_tag(run_id, PLUGINS_ON_RESUME_TAG, plugins)
                print(
                    f"MLflow: run {existing.info.run_name}: plugin code changed since it started ({started or 'none'}"
                    f" -> {plugins or 'none'}); tag {PLUGINS_ON_RESUME_TAG}",
                    flush=True,
                )
            self._last_step[tid] = self.tracker.last_logged_step(existing)
            self.tracker.set_parent(existing)  # a run written before parents existed
            missing = {k: v for k, v in identity.items() if k not in existing.data.params}
            if missing:
                self.tracker.log_params(run_id, missing)
            if existing.info.status != "RUNNING":
                self.tracker.reopen(run_id)
        else:
            from uavlora_rllib.experiment.grid import run_name, trial_run_name
            from uavlora_rllib.experiment.sweep import sampled_values

            # in a sweep several trials share (algorithm, seed, V, U): a sibling's run is no orphan
            replaced = [] if cfg.get("sweep") else self.tracker.replace_orphans(cfg, tid)
            if replaced:
                print(
                    f"MLflow: replaced {len(replaced)} unfinished run(s) of a trial whose Tune state was lost "
                    f"({run_name(cfg['algorithm'], cfg['n_eds'], cfg['n_uavs'], cfg['seed'])})",
                    flush=True,
                )
            tags = self.tracker.base_tags(
                KIND_TRAIN, cfg["algorithm"], cfg["seed"], cfg["n_eds"], cfg["n_uavs"], cfg["budget_env_steps"]
            )
            tags["trial_id"] = tid
            tags["checkpoint"] = ""
            tags[PLUGINS_TAG] = plugins
            sampled = sampled_values(cfg)  # a sweep's values for this trial, as Tune resolved them
            params = {
                **identity,
                **run_params(
                    cfg["scenario"],
                    cfg["budget_env_steps"],
                    cfg["eval_episodes"],
                    {**cfg["hparams"], **sampled},
                    cfg["resources"],
                ),
            }
            params.update(sampled_params(sampled))
            if "eval_interval_env_steps" in cfg:  # where the periodic evaluations fall (analysis/export.py)
                params[EVAL_INTERVAL_PARAM] = str(int(cfg["eval_interval_env_steps"]))
            name = trial_run_name(cfg, tid)
            run_id = self.tracker.create_run(name, tags, params)
            self._last_step[tid] = -1
        self.tracker.log_text(run_id, trial_config_yaml(cfg, tid), TRIAL_CONFIG_ARTIFACT)
        self._runs[tid] = run_id
        self._ended.discard(tid)
        return run_id

    def _end(self, trial, status: str) -> None:
        run_id = self.run_id(trial)
        self._update_checkpoint(trial)
        # artifacts before the status: a driver killed in between leaves the run unfinished, and
        # --resume (reconcile_trial) logs them again to the same paths
        self.tracker.log_text(run_id, curves_csv(self.tracker.metric_histories(run_id)), CURVES_ARTIFACT)
        if status == "FINISHED":
            self._log_final_checkpoint(trial, run_id)
        self.tracker.end(run_id, status)
        self._ended.add(trial.trial_id)

    def _update_checkpoint(self, trial) -> None:
        ckpt = getattr(trial, "checkpoint", None)
        if getattr(ckpt, "path", None):
            self.tracker.set_tag(self.run_id(trial), "checkpoint", checkpoint_uri(ckpt))

    def _log_final_checkpoint(self, trial, run_id: str) -> None:
        """The final checkpoint as the run's ``checkpoint/`` artifact when it is on a local or
        shared filesystem and at most `checkpoint_artifact_max_mb` MB (once per checkpoint: tags
        ``checkpoint_artifact_source`` and ``checkpoint_artifact_written_ns``, its path and its newest
        file's time); else tag ``checkpoint_artifact`` says why not, and the ``checkpoint`` tag is the pointer. Cloud checkpoints are not copied through the driver."""
        ckpt = getattr(trial, "checkpoint", None)
        if not getattr(ckpt, "path", None):
            return
        where = checkpoint_uri(ckpt)
        limit = float(self.checkpoint_artifact_max_mb)
        if "://" in where:
            reason = "not uploaded: on cloud storage (tag checkpoint is its URI)"
        elif not os.path.isdir(where):
            reason = "not uploaded: not visible from the driver (tag checkpoint is its path)"
        elif limit <= 0:
            reason = "not uploaded: mlflow.checkpoint_artifact_max_mb is 0 (tag checkpoint is its path)"
        else:
            size, written = directory_stat(where)
            if size > limit:
                reason = (
                    f"not uploaded: {size:.1f} MB > mlflow.checkpoint_artifact_max_mb {limit:g} "
                    "(tag checkpoint is its path)"
                )
            else:
                tags = self.tracker.get_run(run_id).data.tags
                # once per checkpoint: again only for another one, or the same path written again
                uploaded = (tags.get("checkpoint_artifact_source"), tags.get("checkpoint_artifact_written_ns"))
                if uploaded != (where, str(written)):
                    self.tracker.log_artifacts(run_id, where, CHECKPOINT_ARTIFACT)
                    self.tracker.set_tag(run_id, "checkpoint_artifact_source", where)
                    self.tracker.set_tag(run_id, "checkpoint_artifact_written_ns", str(written))
                reason = f"{CHECKPOINT_ARTIFACT}/"
        self.tracker.set_tag(run_id, "checkpoint_artifact", reason)

    def _log_result(self, trial, result: Mapping[str, Any]) -> None:
        run_id = self.run_id(trial)
        step = int(number(result.get(ENV_STEPS)) or 0)
        train, evals = metrics_to_log(result)
        tid = trial.trial_id
        if step <= self._last_step.get(tid, -1):
            train = {}  # already logged before an interrupt (resumed from an earlier checkpoint)
        else:
            self._last_step[tid] = step
        if train or evals:
            self.tracker.log_metrics(run_id, {**train, **evals}, step)
        if isinstance(result.get(PRECISION_ROUTE), str) and result[PRECISION_ROUTE]:
            self._tag_routes(tid, run_id, set(result[PRECISION_ROUTE].split(",")))

    def _tag_routes(self, tid: str, run_id: str, routes: set[str]) -> None:
        """PRECISION_ROUTE: every route the trial's learners have run in, also before a move to another
        node (the run's tag read once per driver); set only when it grows."""
        if tid not in self._routes:
            recorded = self.tracker.get_run(run_id).data.tags.get(PRECISION_ROUTE, "")
            self._routes[tid] = {r for r in recorded.split(",") if r}
        if not routes <= self._routes[tid]:
            self._routes[tid] |= routes
            self.tracker.set_tag(run_id, PRECISION_ROUTE, ",".join(sorted(self._routes[tid])))

    def reconcile_trial(self, trial) -> bool:
        """A trial Tune holds as finished whose run is not FINISHED: log what is missing from
        its result.json (or its last result) and end the run. True when something was done."""
        existing = self.tracker.run_for_trial(trial.trial_id)
        if (
            existing is not None
            and existing.info.status == "FINISHED"
            and any(k.startswith(EVAL_PREFIX) for k in existing.data.metrics)
        ):
            return False
        self.run_id(trial)  # found again: _last_step is then the last step the run holds
        logged = self._last_step.get(trial.trial_id, -1)
        rows = read_trial_results(getattr(trial, "path", None)) or ([trial.last_result] if trial.last_result else [])
        for row in rows:
            # a row's metrics are logged in one batch: rows up to the run's last step are there already
            if int(number(row.get(ENV_STEPS)) or 0) > logged:
                self._log_result(trial, row)
        self._end(trial, "FINISHED")
        return True

    # ---- Tune hooks
    def _reconcile(self, trials) -> None:
        """Once per driver: complete the runs of trials restored as finished (they get no other hook)."""
        if self._reconciled:
            return
        self._reconciled = True
        done = [t for t in trials if t.status == "TERMINATED"]
        fixed = sum(self.reconcile_trial(t) for t in done)
        if fixed:
            print(f"MLflow: completed {fixed} run(s) of trials that had finished while their driver died", flush=True)

    def on_step_begin(self, iteration, trials, **info):
        # the first step after Tuner.restore
        self._reconcile(trials)

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
        # every trial was restored as finished: Tune ran no step, so reconcile here
        self._reconcile(trials)
        # Trials that did not finish (interrupted grid): their runs are KILLED until --resume.
        for trial in trials:
            tid = trial.trial_id
            if tid in self._runs and tid not in self._ended:
                self._update_checkpoint(trial)
                self.tracker.end(self._runs[tid], "KILLED")
                self._ended.add(tid)
