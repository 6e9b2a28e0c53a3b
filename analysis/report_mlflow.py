"""Logging a report to MLflow: its files become artifacts of the grid's parent run, or of a summary
run in an experiment without one."""

from __future__ import annotations

import os
import shutil
import time
from typing import Any
from urllib.parse import urlparse

from analysis.report_files import OUTPUT_FILES
from analysis.runs import GRID_KIND, SUMMARY_KIND


def _local_path(uri: str) -> str | None:
    p = urlparse(uri)
    if p.scheme in ("", "file"):
        return p.path if p.scheme == "file" else uri
    return None


REPORT_ARTIFACT_DIR = "report"  # the report's folder among the grid parent run's artifacts


def _clear_local_artifacts(artifact_uri: str, sub: str = "") -> None:
    """Remove a run's previous artifacts (under `sub`) when they are stored locally, so that a new
    report replaces the old one instead of mixing with it (servers overwrite same-named files)."""
    local = _local_path(artifact_uri or "")
    target = os.path.join(local, sub) if local and sub else local
    if not target or not os.path.isdir(target):
        return
    for name in os.listdir(target):
        p = os.path.join(target, name)
        shutil.rmtree(p) if os.path.isdir(p) else os.remove(p)


def _tag_report(client, run_id: str, result: dict[str, Any]) -> None:
    client.set_tag(run_id, "report_generated_utc", time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
    client.set_tag(run_id, "report_runs", str(result["n_runs"]))
    client.set_tag(run_id, "report_warnings", str(len(result["warnings"])))


def log_summary(client, exp, summaries, out_dir: str, result: dict[str, Any]) -> str:
    """Log out_dir as artifacts of the grid's parent run (folder report/; the oldest parent when
    several) or, in an experiment without one, of its summary run (the newest is reused, older
    ones are deleted, the reused run's previous artifacts are removed when stored locally)."""
    parents = [r for r in summaries if r.data.tags.get("kind") == GRID_KIND]
    if parents:
        run_id = parents[0].info.run_id
        _clear_local_artifacts(parents[0].info.artifact_uri, REPORT_ARTIFACT_DIR)
        _tag_report(client, run_id, result)
        for name in OUTPUT_FILES:
            path = os.path.join(out_dir, name)
            if os.path.isfile(path):
                client.log_artifact(run_id, path, REPORT_ARTIFACT_DIR)
        return run_id  # its status is the grid's (FINISHED, KILLED, ...): left as it is
    summaries = [r for r in summaries if r.data.tags.get("kind") != GRID_KIND]
    if summaries:
        run_id = summaries[0].info.run_id
        for extra in summaries[1:]:
            client.delete_run(extra.info.run_id)
        _clear_local_artifacts(summaries[0].info.artifact_uri)
        client.update_run(run_id, status="RUNNING")
    else:
        run_id = client.create_run(exp.experiment_id, run_name="summary", tags={"kind": SUMMARY_KIND}).info.run_id
    client.set_tag(run_id, "kind", SUMMARY_KIND)
    _tag_report(client, run_id, result)
    for name in OUTPUT_FILES:
        path = os.path.join(out_dir, name)
        if os.path.isfile(path):
            client.log_artifact(run_id, path)
    client.set_terminated(run_id, "FINISHED")
    return run_id
