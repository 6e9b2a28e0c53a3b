"""Reading experiments' runs from MLflow (MlflowClient only; never Ray's result folders).

One report may join several experiments from several tracking URIs (`resolve_sources`): a
sweep split over experiments, or over clusters with their own MLflow stores. Every RunRecord
names the experiment and URI it came from.

The schema is the Tune callback's (README / issue 6): tags kind, algorithm, seed, n_eds,
n_uavs, git_commit, grid_file, trial_id, checkpoint, budget_env_steps; params
"scenario.<field>", "stop.env_steps", "eval.episodes", ...; execution metrics "eval/<k>";
training curves with step = env steps. A grid's parent run (kind=grid, the trials and
baselines nested under it) and runs tagged kind=summary (the report's home in experiments
written before parents existed) are left out of the records.
"""

from __future__ import annotations

import ast
import fnmatch
import json
import logging
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from uavlora_rllib.cli_args import UsageError, write_problem

SUMMARY_KIND = "summary"
GRID_KIND = "grid"  # run_schema.KIND_GRID: the grid's parent run, which holds the report's files
EVAL_PREFIX = "eval/"
EE_KEY = "eval/ee_sys_mean"
SAMPLED_EE_KEY = "eval_sampled/ee_sys_mean"  # execution with actions drawn from the trained policy


class ReportError(UsageError):
    """Bad user input (experiment, tracking URI, flags): printed as one line, exit code 2 (the
    command-line tools' one usage-error family, cli_args.UsageError)."""


@dataclass
class RunRecord:
    run_id: str
    run_name: str
    status: str
    start_time: int
    kind: str
    algorithm: str | None
    seed: str | None
    n_eds: int | None
    n_uavs: int | None
    tags: dict[str, str] = field(default_factory=dict)
    params: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, float] = field(default_factory=dict)
    experiment: str = ""  # the MLflow experiment it was read from
    source: int = 0  # index of its Source (experiment + tracking URI) in the report's list
    end_time: int | None = None  # ms since the epoch; None while the run is unfinished

    @property
    def seed_key(self) -> str:
        """What tells a cell's runs apart: its seed, or its id where it logged none."""
        return str(self.seed) if self.seed is not None else self.run_id

    @property
    def label(self) -> str:
        """Short human description for warnings."""
        name = f" ({self.run_name})" if self.run_name else ""
        where = f" [{self.experiment}]" if self.experiment else ""
        return (
            f"run {self.run_id[:8]}{name}{where}: kind={self.kind} algorithm={self.algorithm} seed={self.seed} "
            f"V={self.n_eds} U={self.n_uavs} status={self.status}"
        )

    @property
    def scenario_key(self) -> tuple[int, int] | None:
        if self.n_eds is None or self.n_uavs is None:
            return None
        return (self.n_eds, self.n_uavs)

    def eval_metrics(self) -> dict[str, float]:
        return {k: v for k, v in self.metrics.items() if k.startswith(EVAL_PREFIX)}

    @property
    def ee(self) -> float:
        v = self.metrics.get(EE_KEY)
        return float(v) if v is not None else math.nan

    @property
    def has_eval(self) -> bool:
        return math.isfinite(self.ee)


def check_writable_folder(folder: str, flag: str) -> None:
    """Create `folder` if missing, then write and remove a file in it; ReportError naming `flag`
    when either fails. A real write, because os.access says yes to root even where writing fails
    (a read-only mount, /proc)."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise ReportError(f"{flag}: cannot create the folder {folder!r}: {exc.strerror or exc}") from None
    problem = write_problem(folder)
    if problem:
        raise ReportError(f"{flag}: cannot write to the folder {folder!r}: {problem}")


def check_out_file(path: str, flag: str = "--out") -> None:
    """ReportError naming `flag` unless `path` can become an output file (not a folder; its folder created and
    writable): checked before the work that writes it."""
    if os.path.isdir(path):
        raise ReportError(f"{flag}: {path} is a directory; expected a file name")
    check_writable_folder(os.path.dirname(os.path.abspath(path)), flag)


def _quiet_mlflow() -> None:
    # Fail fast on an unreachable server instead of retrying for minutes (user settings win).
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "15")
    for name in ("mlflow", "alembic", "sqlalchemy"):
        logging.getLogger(name).setLevel(logging.ERROR)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}".strip()


def sqlite_path(uri: str) -> str | None:
    """The database file of a sqlite:/// URI (None for other URIs or in-memory databases)."""
    if not uri.startswith("sqlite:"):
        return None
    rest = uri[len("sqlite:") :]
    if not rest.startswith("///"):
        return None
    path = rest[3:].split("?", 1)[0]
    if path in ("", ":memory:"):
        return None
    return path


def connect(tracking_uri: str):
    """An MlflowClient that has answered once; ReportError naming the URI otherwise."""
    _quiet_mlflow()
    path = sqlite_path(tracking_uri)
    if path is not None and os.path.isdir(path):
        raise ReportError(
            f"--tracking-uri: {tracking_uri!r} names the directory {os.path.abspath(path)}; "
            "expected an MLflow sqlite database file, e.g. sqlite:///mlflow.db"
        )
    if tracking_uri.startswith("sqlite:") and path is not None and not os.path.isfile(path):
        raise ReportError(
            f"tracking URI {tracking_uri!r} is unreachable: database file {os.path.abspath(path)} does not exist"
        )
    if tracking_uri.startswith("file:") or ("://" not in tracking_uri and not tracking_uri.startswith("sqlite:")):
        raise ReportError(
            f"tracking URI {tracking_uri!r} is not supported: use a database or server URI such as "
            "sqlite:///mlflow.db or http://host:5000"
        )
    from mlflow.tracking import MlflowClient

    try:
        client = MlflowClient(tracking_uri=tracking_uri)
        client.search_experiments(max_results=1)
    except Exception as exc:  # noqa: BLE001 - any failure here means "cannot reach it"
        status = getattr(exc, "get_http_status_code", lambda: None)()
        if status in (401, 403):  # MLflow's basic-auth app (docs/cluster.md#mlflow)
            raise ReportError(
                f"tracking URI {tracking_uri!r} refused the request (HTTP {status}): set "
                "MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD to a user of the server"
            ) from None
        raise ReportError(f"tracking URI {tracking_uri!r} is unreachable: {_first_line(exc)}") from None
    return client


def _as_int(text: Any) -> int | None:
    if text is None:
        return None
    try:
        return int(float(str(text)))
    except ValueError:
        return None


@dataclass(frozen=True)
class Source:
    """One experiment at one tracking URI, and the client that reads it."""

    tracking_uri: str
    experiment: Any  # mlflow.entities.Experiment
    client: Any = field(compare=False, repr=False)

    @property
    def name(self) -> str:
        return self.experiment.name


def resolve_sources(tracking_uris: list[str], patterns: list[str]) -> list[Source]:
    """Every active experiment, at any of the URIs, whose name equals one of the patterns or
    matches it as a shell glob (fnmatch: *, ?, [...]); each (URI, experiment) once, in the
    order given. ReportError when a URI is unreachable or a pattern matches nothing anywhere."""
    clients = {uri: connect(uri) for uri in dict.fromkeys(tracking_uris)}
    listing = {
        uri: [e for e in c.search_experiments() if getattr(e, "lifecycle_stage", "active") == "active"]
        for uri, c in clients.items()
    }
    out: list[Source] = []
    seen: set[tuple[str, str]] = set()
    for pattern in patterns:
        hits = 0
        for uri, exps in listing.items():
            for exp in sorted(exps, key=lambda e: e.name):
                if exp.name == pattern or fnmatch.fnmatchcase(exp.name, pattern):
                    hits += 1
                    if (uri, exp.experiment_id) not in seen:
                        seen.add((uri, exp.experiment_id))
                        out.append(Source(uri, exp, clients[uri]))
        if hits == 0:
            names = sorted({e.name for exps in listing.values() for e in exps})
            where = ", ".join(listing)
            existing = ", ".join(repr(n) for n in names) if names else "(none)"
            raise ReportError(f"--experiment: {pattern!r} not found at {where}; existing experiments: {existing}")
    return out


W1_PARAM = "scenario.reward.w1"


def resolved_params(params: Mapping[str, str]) -> dict[str, str]:
    """A run's params with a null reward.w1 (logged "None") replaced by the w1 the env applied, its
    rate model's default (ScenarioConfig.reward_weights), so that a run that left w1 unset and one
    that set that same value are the same scenario to every comparison of the report."""
    from uavlora_rllib.sim.scenario import DEFAULT_W1

    out = dict(params)
    rate = out.get("scenario.rate_model", "shannon")
    if out.get(W1_PARAM) == "None" and rate in DEFAULT_W1:
        out[W1_PARAM] = str(DEFAULT_W1[rate])
    return out


def _record(run) -> RunRecord:
    tags = dict(run.data.tags)
    params = resolved_params(run.data.params)
    n_eds = _as_int(tags.get("n_eds", params.get("scenario.n_eds")))
    n_uavs = _as_int(tags.get("n_uavs", params.get("scenario.n_uavs")))
    algorithm = tags.get("algorithm") or None
    return RunRecord(
        run_id=run.info.run_id,
        run_name=run.info.run_name or tags.get("mlflow.runName", ""),
        status=str(run.info.status),
        start_time=int(run.info.start_time or 0),
        end_time=int(run.info.end_time) if run.info.end_time else None,
        kind=tags.get("kind", "train"),
        algorithm=algorithm.strip() if algorithm else None,
        seed=tags.get("seed"),
        n_eds=n_eds,
        n_uavs=n_uavs,
        tags=tags,
        params=params,
        metrics={k: float(v) for k, v in run.data.metrics.items()},
    )


def load_runs(client, experiment_id: str, experiment: str = "", source: int = 0) -> tuple[list[RunRecord], list[Any]]:
    """All active runs of the experiment as RunRecords (grid parents and summary runs excluded),
    and those excluded runs themselves (raw MLflow Run objects: grid parents oldest first, then
    summary runs newest first): where the report logs its files (`analysis.report_mlflow.log_summary`)."""
    records: list[RunRecord] = []
    summaries: list[Any] = []
    parents: list[Any] = []
    token = None
    while True:
        page = client.search_runs([experiment_id], max_results=1000, page_token=token)
        for run in page:
            kind = run.data.tags.get("kind")
            if kind == GRID_KIND:
                parents.append(run)
            elif kind == SUMMARY_KIND:
                summaries.append(run)
            else:
                rec = _record(run)
                rec.experiment, rec.source = experiment, source
                records.append(rec)
        token = getattr(page, "token", None)
        if not token:
            break
    summaries.sort(key=lambda r: r.info.start_time or 0, reverse=True)
    parents.sort(key=lambda r: (r.info.start_time or 0, r.info.run_id))
    records.sort(key=lambda r: (r.start_time, r.run_id))
    return records, parents + summaries


def metric_history(client, run_id: str, key: str) -> tuple[list[float], list[float]]:
    """(steps, values) of a metric, sorted by step, last value kept for a repeated step."""
    hist = client.get_metric_history(run_id, key)
    by_step: dict[int, tuple[int, float]] = {}
    for m in hist:
        prev = by_step.get(m.step)
        if prev is None or m.timestamp >= prev[0]:
            by_step[m.step] = (m.timestamp, float(m.value))
    steps = sorted(by_step)
    vals = [by_step[s][1] for s in steps]
    keep = [i for i, v in enumerate(vals) if math.isfinite(v)]
    return [float(steps[i]) for i in keep], [vals[i] for i in keep]


def _parse_param(text: str) -> Any:
    try:
        return json.loads(text)
    except (ValueError, TypeError):
        pass
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def section_dict(params: dict[str, str], section: str, derived: tuple[str, ...] = ()) -> dict[str, Any]:
    """Nested fields of one config section from its "<section>.<field>[.<sub>]" params, values parsed
    back from their logged text; top-level fields named in `derived` (computed, not settable) dropped."""
    out: dict[str, Any] = {}
    for key, text in params.items():
        if not key.startswith(f"{section}."):
            continue
        parts = key.split(".")[1:]
        if len(parts) == 1 and parts[0] in derived:
            continue
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                break
        else:
            node[parts[-1]] = _parse_param(text)
    return out


def scenario_dict(params: dict[str, str]) -> dict[str, Any]:
    """The scenario's fields from its "scenario.*" params (the derived 'quota' dropped)."""
    return section_dict(params, "scenario", derived=("quota",))
