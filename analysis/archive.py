"""An experiment's MLflow runs as one file that can be committed, and back into any store.

    python -m analysis.archive export --experiment NAME [--tracking-uri URI] [--out FILE]
        [--max-artifact-kb 256]
    python -m analysis.archive restore FILE [FILE ...] [--tracking-uri URI]

A grid longer than one session keeps what it recorded only while its MLflow store lives, and a
store is a local, git-ignored file (docs/model.md#persistence-across-sessions). `export` writes
every active run of one experiment to a gzip'd JSON file: its info (name, status, start and end
time), tags, params, every metric's whole history (step, timestamp, value) and its artifacts up
to --max-artifact-kb each (larger ones, such as checkpoints, are listed as left out). `restore`
recreates the runs in a store (new run IDs, grid parents relinked) where `analysis.report`
reads them as if the grid had run there; it skips the runs that an earlier restore brought
(tag ``archive.source_run_id``), so it can be repeated. The MLflow project's own
mlflow-export-import (PyPI 1.2.0, the newest there) fails to import into an MLflow 3 store,
hence this module, on MlflowClient's public API only.

Both write nothing partial: `export` writes a temporary file and renames it; `restore` marks
a run as restored only when all of it is logged (a run cut off midway is deleted and redone).
Every expected failure prints one line on stderr, exit code 2.
"""

from __future__ import annotations

import base64
import gzip
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from analysis.runs import (
    ReportError,
    _quiet_mlflow,
    check_out_file,
    check_writable_folder,
    connect,
    resolve_sources,
    sqlite_path,
)
from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in, nonempty_path

FORMAT = "uavlora-rllib/mlflow-archive"
VERSION = 1
SOURCE_TAG = "archive.source_run_id"  # on a restored run: its run ID in the archived store
LEFT_OUT_TAG = "archive.artifacts_left_out"  # on a restored run: artifacts not in the archive
PARENT_TAG = "mlflow.parentRunId"  # MLflow's nesting tag: grid parent -> trials and baselines
DONE_TAG = "archive.restored"  # set last: a run without it was cut off and is redone
DEFAULT_MAX_ARTIFACT_KB = 256  # configs and reports pass; checkpoints (MBs) stay out
_BATCH = 1000  # MLflow's log_batch limit on metrics per call (params: 100)


def _artifact_files(client, run_id: str, path: str | None = None) -> list[tuple[str, int]]:
    out: list[tuple[str, int]] = []
    for info in client.list_artifacts(run_id, path):
        if info.is_dir:
            out += _artifact_files(client, run_id, info.path)
        else:
            out.append((info.path, int(info.file_size or 0)))
    return out


def _run_record(client, run, max_artifact_bytes: int) -> dict[str, Any]:
    run_id = run.info.run_id
    metrics = {
        key: [[m.step, m.timestamp, m.value] for m in client.get_metric_history(run_id, key)]
        for key in sorted(run.data.metrics)
    }
    artifacts: dict[str, str] = {}
    left_out: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for path, size in _artifact_files(client, run_id):
            if size > max_artifact_bytes:
                left_out[path] = size
                continue
            local = client.download_artifacts(run_id, path, tmp)
            with open(local, "rb") as fh:
                artifacts[path] = base64.b64encode(fh.read()).decode("ascii")
    return {
        "run_id": run_id,
        "run_name": run.info.run_name or "",
        "status": str(run.info.status),
        "start_time": run.info.start_time,
        "end_time": run.info.end_time,
        "tags": dict(run.data.tags),
        "params": dict(run.data.params),
        "metrics": metrics,
        "artifacts": artifacts,
        "artifacts_left_out": left_out,
    }


def export_experiment(tracking_uri: str, experiment: str, out: str, max_artifact_bytes: int) -> dict[str, Any]:
    """Write the experiment's active runs to `out` (gzip'd JSON, atomically); return the archive."""
    sources = resolve_sources([tracking_uri], [experiment])
    if len(sources) != 1:
        names = ", ".join(repr(s.name) for s in sources)
        raise ReportError(f"--experiment: {experiment!r} matches {len(sources)} experiments ({names}); name one")
    src = sources[0]
    client = src.client
    runs = []
    token = None
    while True:
        page = client.search_runs([src.experiment.experiment_id], max_results=1000, page_token=token)
        runs += list(page)
        token = getattr(page, "token", None)
        if not token:
            break
    runs.sort(key=lambda r: (r.info.start_time or 0, r.info.run_id))
    archive = {
        "format": FORMAT,
        "version": VERSION,
        "exported_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source_tracking_uri": tracking_uri,
        "experiment": {"name": src.name, "tags": dict(src.experiment.tags or {})},
        "runs": [_run_record(client, r, max_artifact_bytes) for r in runs],
    }
    folder = os.path.dirname(os.path.abspath(out))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".archive-", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0) as gz:
            gz.write(json.dumps(archive, sort_keys=True, indent=0).encode())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp's 0600 would hide a committed file from others
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return archive


def check_store(tracking_uri: str) -> None:
    """ReportError naming --tracking-uri unless its sqlite database can be created where it is
    missing (MLflow creates the file and its folders); an existing path, and other URIs, are
    checked when connecting."""
    db = sqlite_path(tracking_uri)
    if db is not None and not os.path.exists(db):
        check_writable_folder(os.path.dirname(os.path.abspath(db)), "--tracking-uri")


def read_archive(path: str) -> dict[str, Any]:
    """The archive in `path`; ReportError naming the file when it is missing or not an archive."""
    try:
        with gzip.open(path, "rb") as gz:
            data = json.loads(gz.read())
    except FileNotFoundError:
        raise ReportError(f"archive {path!r} does not exist") from None
    except (OSError, EOFError, ValueError) as exc:
        raise ReportError(f"archive {path!r} is not a gzip'd JSON archive ({type(exc).__name__})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ReportError(f"archive {path!r} is not a {FORMAT} file (written by python -m analysis.archive export)")
    if data.get("version") != VERSION:
        raise ReportError(f"archive {path!r} has version {data.get('version')!r}; this reader takes {VERSION}")
    return data


def _chunks(items: list, size: int):
    for i in range(0, len(items), size):
        yield items[i : i + size]


def _restore_run(client, experiment_id: str, rec: dict[str, Any], parent_id: str | None) -> str:
    from mlflow.entities import Metric, Param, RunTag

    tags = {k: v for k, v in rec["tags"].items() if k not in (PARENT_TAG, DONE_TAG)}
    tags[SOURCE_TAG] = rec["run_id"]
    if parent_id is not None:
        tags[PARENT_TAG] = parent_id
    if rec["artifacts_left_out"]:
        tags[LEFT_OUT_TAG] = ", ".join(f"{p} ({n} B)" for p, n in sorted(rec["artifacts_left_out"].items()))
    run = client.create_run(experiment_id, start_time=rec["start_time"], tags=tags, run_name=rec["run_name"] or None)
    run_id = run.info.run_id
    for chunk in _chunks([Param(k, v) for k, v in sorted(rec["params"].items())], 100):
        client.log_batch(run_id, params=chunk)
    metrics = [Metric(k, float(v), int(ts), int(step)) for k, hist in rec["metrics"].items() for step, ts, v in hist]
    for chunk in _chunks(metrics, _BATCH):
        client.log_batch(run_id, metrics=chunk)
    with tempfile.TemporaryDirectory() as tmp:
        for path, b64 in sorted(rec["artifacts"].items()):
            local = os.path.join(tmp, path)
            os.makedirs(os.path.dirname(local), exist_ok=True)
            with open(local, "wb") as fh:
                fh.write(base64.b64decode(b64))
            client.log_artifact(run_id, local, os.path.dirname(path) or None)
    client.log_batch(run_id, tags=[RunTag(DONE_TAG, "1")])
    if rec["status"] in ("FINISHED", "FAILED", "KILLED"):
        client.set_terminated(run_id, rec["status"], rec["end_time"])
    return run_id


def restore(tracking_uri: str, path: str) -> tuple[int, int]:
    """Recreate the archive's runs in the store at `tracking_uri`, in an experiment of the same
    name (created when missing); return (runs created, runs already there)."""
    data = read_archive(path)
    db = sqlite_path(tracking_uri)
    if db is not None and not os.path.exists(db):  # a new store: MLflow creates the file
        from mlflow.tracking import MlflowClient

        _quiet_mlflow()
        MlflowClient(tracking_uri=tracking_uri).search_experiments(max_results=1)
    client = connect(tracking_uri)
    name = data["experiment"]["name"]
    exp = client.get_experiment_by_name(name)
    if exp is None:
        exp_id = client.create_experiment(name)
    elif exp.lifecycle_stage != "active":
        raise ReportError(f"experiment {name!r} at {tracking_uri!r} is deleted: restore it or use another store")
    else:
        exp_id = exp.experiment_id
    for key, value in data["experiment"]["tags"].items():
        client.set_experiment_tag(exp_id, key, value)
    done: dict[str, str] = {}  # archived run ID -> its restored run ID
    for run in client.search_runs([exp_id], filter_string=f"tags.`{SOURCE_TAG}` != ''", max_results=50_000):
        if run.data.tags.get(DONE_TAG) == "1":
            done[run.data.tags[SOURCE_TAG]] = run.info.run_id
        else:  # cut off by an earlier restore: redo it whole
            client.delete_run(run.info.run_id)
    already = sum(1 for r in data["runs"] if r["run_id"] in done)
    # parents first, so that every nested run can name its parent's new ID
    pending = sorted(data["runs"], key=lambda r: PARENT_TAG in r["tags"])
    for rec in pending:
        if rec["run_id"] in done:
            continue
        parent = rec["tags"].get(PARENT_TAG)
        done[rec["run_id"]] = _restore_run(client, exp_id, rec, done.get(parent) if parent else None)
    return len(data["runs"]) - already, already


def build_parser() -> Parser:
    p = Parser(prog="python -m analysis.archive", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    ex = sub.add_parser("export", help="write one experiment's runs to an archive file")
    ex.add_argument("--experiment", required=True, help="MLflow experiment name (or a glob matching one)")
    ex.add_argument("--tracking-uri", default="sqlite:///mlflow.db", help="default sqlite:///mlflow.db")
    ex.add_argument(
        "--out", type=nonempty_path, default=None, help="archive file (default <experiment>.mlflow.json.gz)"
    )
    ex.add_argument(
        "--max-artifact-kb",
        type=int_in(0),
        default=DEFAULT_MAX_ARTIFACT_KB,
        help=f"largest artifact kept, in KiB (default {DEFAULT_MAX_ARTIFACT_KB}); larger ones are listed as left out",
    )
    rs = sub.add_parser("restore", help="recreate archived runs in a store")
    rs.add_argument("archives", nargs="+", metavar="FILE", help="archive files written by export")
    rs.add_argument("--tracking-uri", default="sqlite:///mlflow.db", help="default sqlite:///mlflow.db")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one line per command
    try:
        args = build_parser().parse_args(argv)
        if args.command == "export":
            out = args.out or f"{args.experiment}.mlflow.json.gz"
            check_out_file(out)  # before the export, not after it
            data = export_experiment(args.tracking_uri, args.experiment, out, args.max_artifact_kb * 1024)
            left = sum(len(r["artifacts_left_out"]) for r in data["runs"])
            print(
                f"archive: {out}: {len(data['runs'])} runs of {data['experiment']['name']!r} ({left} artifacts left out)"
            )
            return 0
        if args.command == "restore":
            for path in args.archives:
                read_archive(path)  # every file checked before any is restored
            check_store(args.tracking_uri)
            for path in args.archives:
                created, already = restore(args.tracking_uri, path)
                print(f"archive: {path}: {created} runs restored, {already} already there, at {args.tracking_uri}")
    except UsageError as exc:
        return fail(exc, "archive")
    except OSError as exc:
        return fail(f"cannot write: {exc}", "archive")
    return 0


if __name__ == "__main__":
    sys.exit(main())
