"""analysis.archive: an experiment exported to a file and restored into a fresh store reads the same
(runs, params, tags, whole metric histories, small artifacts, grid nesting), the report over it
writes the same tables, a restore repeats without duplicates, and a restore cut off midway is
redone. Real sqlite MLflow stores, no mocks."""

from __future__ import annotations

import gzip
import json
import time

import pytest

mlflow = pytest.importorskip("mlflow")
from mlflow.entities import Metric, Param  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from analysis import archive, report  # noqa: E402

EXP = "grid_to_archive"
EE = {"mappo": [100.0, 110.0], "qmix": [60.0, 70.0]}


def _store(tmp):
    uri = f"sqlite:///{tmp / 'src.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp = client.create_experiment(EXP, artifact_location=str(tmp / "art"))
    client.set_experiment_tag(exp, "note", "kept")
    parent = client.create_run(exp, run_name="grid", tags={"kind": "grid"}).info.run_id
    (tmp / "big.bin").write_bytes(b"x" * 3000)
    (tmp / "cfg.yaml").write_text("lr: 0.002\n")
    now = int(time.time() * 1000)

    def run(kind, alg, seed, ee, status="FINISHED"):
        tags = {"kind": kind, "algorithm": alg, "seed": str(seed), "n_eds": "10", "n_uavs": "2"}
        tags["mlflow.parentRunId"] = parent
        rid = client.create_run(exp, run_name=f"{alg}-s{seed}", tags=tags, start_time=now + seed).info.run_id
        metrics = [Metric("eval/ee_sys_mean", ee, now, 10_000)]
        if kind == "train":  # a periodic evaluation curve and a training curve, several points per key
            metrics += [Metric("eval/ee_sys_mean", ee * f, now + s, s) for s, f in ((0, 0.5), (5000, 0.75))]
            metrics += [Metric("episode_return_mean", 1.0 + s / 1000, now + s, s) for s in range(0, 10_001, 2500)]
        params = [Param("scenario.n_eds", "10"), Param("scenario.n_uavs", "2"), Param("eval.episodes", "10")]
        client.log_batch(rid, metrics=metrics, params=params)
        client.log_artifact(rid, str(tmp / "cfg.yaml"), "config")
        client.log_artifact(rid, str(tmp / "big.bin"))
        client.set_terminated(rid, status, now + 60_000)
        return rid

    for alg, values in EE.items():
        for seed, ee in enumerate(values):
            run("train", alg, seed, ee, status="KILLED" if (alg, seed) == ("qmix", 1) else "FINISHED")
    for seed in range(2):
        run("baseline", "greedy", seed, 150.0)
    client.set_terminated(parent, "FINISHED")
    return uri, client


def _runs(client):
    exp = client.get_experiment_by_name(EXP)
    return client.search_runs([exp.experiment_id], max_results=1000)


def _content(client, run):
    """Everything the archive promises to keep, keyed so that two stores compare equal."""
    tags = {k: v for k, v in run.data.tags.items() if not k.startswith("archive.") and k != "mlflow.parentRunId"}
    hist = {
        k: sorted((m.step, m.timestamp, m.value) for m in client.get_metric_history(run.info.run_id, k))
        for k in run.data.metrics
    }
    arts = sorted(a.path for a in client.list_artifacts(run.info.run_id, "config"))
    return (
        run.info.run_name,
        run.info.status,
        run.info.start_time,
        run.info.end_time,
        tags,
        dict(run.data.params),
        hist,
        arts,
    )


@pytest.fixture(scope="module")
def archived(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("archive")
    uri, client = _store(tmp)
    path = tmp / "grid.mlflow.json.gz"
    assert (
        archive.main(
            ["export", "--experiment", EXP, "--tracking-uri", uri, "--out", str(path), "--max-artifact-kb", "2"]
        )
        == 0
    )
    dst = f"sqlite:///{tmp / 'restored.db'}"  # a store that does not exist yet
    assert archive.main(["restore", str(path), "--tracking-uri", dst]) == 0
    return {"tmp": tmp, "src": (uri, client), "dst": (dst, MlflowClient(tracking_uri=dst)), "path": path}


def test_restored_runs_equal_the_archived_ones(archived):
    src, dst = archived["src"][1], archived["dst"][1]
    a, b = _runs(src), _runs(dst)
    assert len(a) == len(b) == 7
    by_source = {r.data.tags[archive.SOURCE_TAG]: r for r in b}
    for run in a:
        restored = by_source[run.info.run_id]
        assert _content(dst, restored) == _content(src, run)
        assert restored.data.tags.get(archive.DONE_TAG) == "1"
        if run.data.tags.get("kind") != "grid":  # nested under the restored parent, by its new ID
            parent = dst.get_run(restored.data.tags["mlflow.parentRunId"])
            assert parent.data.tags["kind"] == "grid" and parent.data.tags[archive.SOURCE_TAG] != parent.info.run_id
            assert "big.bin (3000 B)" in restored.data.tags[archive.LEFT_OUT_TAG]  # over --max-artifact-kb 2
            local = dst.download_artifacts(restored.info.run_id, "config/cfg.yaml", str(archived["tmp"]))
            assert open(local).read() == "lr: 0.002\n"
    assert dst.get_experiment_by_name(EXP).tags["note"] == "kept"


def test_report_over_the_restored_store_writes_the_same_tables(archived):
    outs = []
    for name in ("src", "dst"):
        out = archived["tmp"] / f"report_{name}"
        args = ["--experiment", EXP, "--tracking-uri", archived[name][0], "--out", str(out), "--no-fig2", "--no-log"]
        assert report.main(args) == 0
        outs.append(out)
    for table in ("table_ee.csv", "table_learning.csv", "fig3a_curves.csv"):
        assert (outs[0] / table).read_text() == (outs[1] / table).read_text()


def test_restore_again_adds_nothing_and_redoes_a_cut_off_run(archived, capsys):
    dst_uri, dst = archived["dst"]
    victim = next(r for r in _runs(dst) if r.info.run_name == "mappo-s1")
    dst.delete_tag(victim.info.run_id, archive.DONE_TAG)  # as if the restore had been killed midway
    capsys.readouterr()
    assert archive.main(["restore", str(archived["path"]), "--tracking-uri", dst_uri]) == 0
    assert "1 runs restored, 6 already there" in capsys.readouterr().out
    runs = _runs(dst)
    assert len(runs) == 7 and all(r.data.tags.get(archive.DONE_TAG) == "1" for r in runs)
    assert victim.info.run_id not in {r.info.run_id for r in runs}


def test_archive_is_deterministic_gzip_json(archived, tmp_path):
    data = json.loads(gzip.open(archived["path"]).read())
    assert data["format"] == archive.FORMAT and data["version"] == archive.VERSION
    assert gzip.open(archived["path"]).read() == gzip.open(archived["path"]).read()
    assert archived["path"].read_bytes()[4:8] == b"\0\0\0\0"  # gzip mtime 0: same runs, same bytes


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["restore", "missing.json.gz"], "archive 'missing.json.gz' does not exist"),
        (["restore", "pyproject.toml"], "is not a gzip'd JSON archive"),
        (["export", "--experiment", "nope"], "--experiment: 'nope' not found"),
        (["export", "--experiment", EXP, "--max-artifact-kb", "-1"], "--max-artifact-kb"),
        ([], "required: command"),
    ],
)
def test_bad_input_is_one_line_exit_2(argv, needle, archived, capsys, monkeypatch):
    if argv[:1] == ["export"]:
        argv = [*argv, "--tracking-uri", archived["src"][0]]
    monkeypatch.chdir(__file__.rsplit("/tests/", 1)[0])  # the repository: pyproject.toml is a file that is no archive
    assert archive.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1


def test_other_version_is_refused(tmp_path, capsys):
    path = tmp_path / "v2.json.gz"
    with gzip.open(path, "wb") as fh:
        fh.write(json.dumps({"format": archive.FORMAT, "version": 2}).encode())
    assert archive.main(["restore", str(path)]) == 2
    assert "has version 2; this reader takes 1" in capsys.readouterr().err
