"""MLflow runs a researcher can use from the UI alone (issue 26 item 2; run_schema).

Fast tests (a sqlite store, no Ray): the schema helpers, the grid's parent run and the nesting
of baseline runs, baselines as flat reference lines, runs of old flat experiments adopted, and
the report's files on the parent. The slow test starts a real `mlflow server` with MLflow's
basic-auth app (loopback, a free port, stopped by PID), runs a one-trial grid plus a baseline
against it with credentials from MLFLOW_TRACKING_USERNAME/PASSWORD, checks artifacts, params,
tags and nesting through the MLflow API, that an unauthenticated driver is refused with one
line, and that `--resume` keeps one run per trial, one parent and no duplicated artifact.
"""

from __future__ import annotations

import csv
import getpass
import io
import os
import signal
import socket
import subprocess
import sys
import time
from types import SimpleNamespace

import pytest
import yaml
from conftest import TINY_MAPPO, wait_for_mlflow_server, write_tiny_grid

from uavlora_rllib.experiment import run_schema
from uavlora_rllib.experiment.mlflow_client import Tracker, TrackingRefused, git_commit

SOURCE_TAGS = ("mlflow.source.name", "mlflow.source.type", "mlflow.source.git.commit", "mlflow.user")


# --------------------------------------------------------------------------- fast: schema helpers
def test_reference_steps_span_the_budget():
    assert run_schema.reference_steps(60) == [0, 6, 12, 18, 24, 30, 36, 42, 48, 54, 60]
    assert run_schema.reference_steps(3) == [0, 1, 2, 3]  # no repeated step
    assert run_schema.reference_steps(None) == [0] and run_schema.reference_steps(0) == [0]


def test_curves_csv_one_row_per_step_last_value_wins():
    text = run_schema.curves_csv({"ee_sys_mean": [(20, 1.0), (40, 2.0), (40, 2.5)], "eval/ee_sys_mean": [(40, 3.0)]})
    rows = list(csv.DictReader(io.StringIO(text)))
    assert [r["env_steps"] for r in rows] == ["20", "40"]
    assert rows[0]["eval/ee_sys_mean"] == "" and float(rows[1]["ee_sys_mean"]) == 2.5
    assert float(rows[1]["eval/ee_sys_mean"]) == 3.0


def test_trial_config_yaml_is_plain_yaml():
    cfg = {"algorithm": "mappo", "seed": 3, "hparams": {"lr": 3e-4, "sizes": (8, 8)}, "plugins": []}
    doc = yaml.safe_load(run_schema.trial_config_yaml(cfg, "abc_00000"))
    assert doc == {
        "trial_id": "abc_00000",
        "algorithm": "mappo",
        "seed": 3,
        "hparams": {"lr": 3e-4, "sizes": [8, 8]},
        "plugins": [],
    }


# --------------------------------------------------------------------------- fast: a sqlite store
BASE_PARAMS = {"scenario.n_eds": "6", "scenario.n_uavs": "2", "eval.episodes": "1"}
SUMMARY = {"ee_sys_mean": 2.0, "success_rate": 0.5, "episodes": 1, "ci95": {"ee_sys_mean": 0.1}}


@pytest.fixture
def sqlite_tracker(tmp_path):
    grid_file = tmp_path / "g.yaml"
    grid_file.write_text("experiment: nest\n")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    return Tracker(uri, "nest", str(grid_file), commit="c0ffee", retry_timeout_s=5)


def test_parent_run_nests_baselines_drawn_as_flat_lines(sqlite_tracker):
    t = sqlite_tracker
    parent = t.open_grid_run()
    assert t.grid_run() == parent and Tracker(t.tracking_uri, "nest", t.grid_file).grid_run() == parent  # found again
    run_id = t.log_baseline("random", "random-V6-U2-s0", 0, 6, 2, BASE_PARAMS, lambda: SUMMARY, budget=100)
    run = t.client.get_run(run_id)
    assert run.data.tags[run_schema.PARENT_TAG] == parent
    assert {k: run.data.params[k] for k in run_schema.IDENTITY_PARAMS} == {
        "algorithm": "random",
        "seed": "0",
        "n_eds": "6",
        "n_uavs": "2",
    }
    assert run.data.tags["mlflow.source.git.commit"] == "c0ffee" and run.data.tags["mlflow.source.type"] == "LOCAL"
    assert run.data.tags["mlflow.user"] == getpass.getuser()
    assert "uavlora_rllib.tune" in run.data.tags["mlflow.source.name"]
    hist = t.client.get_metric_history(run_id, "eval/ee_sys_mean")
    assert sorted(m.step for m in hist) == run_schema.reference_steps(100) and {m.value for m in hist} == {2.0}
    assert t.finished_baseline("random", 0, 6, 2, BASE_PARAMS)
    grid = t.client.get_run(parent)
    assert grid.data.tags["kind"] == "grid" and grid.info.run_name == "nest"
    assert [a.path for a in t.client.list_artifacts(parent)] == ["grid.yaml"]


def test_precision_route_tag_keeps_every_route_a_trial_ran_in(sqlite_tracker, monkeypatch):
    """The trial's results carry its learners' route; the run's tag holds every route seen, also across drivers
    (a resumed grid) and nodes (a recovered trial), and an empty or absent one changes nothing."""
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback

    t = sqlite_tracker
    t.open_grid_run()
    run_id = t.create_run("mappo-V6-U2-s0", t.base_tags("train", "mappo", 0, 6, 2, 100), BASE_PARAMS)
    trial = SimpleNamespace(trial_id="t0")

    def driver() -> MlflowTrialCallback:  # a fresh driver's callback on the same store and run
        cb = MlflowTrialCallback(t.tracking_uri, "nest", t.grid_file, commit="c0ffee")
        cb._tracker = t
        monkeypatch.setattr(cb, "run_id", lambda _trial: run_id)
        return cb

    def tag() -> str | None:
        return t.client.get_run(run_id).data.tags.get(run_schema.PRECISION_ROUTE)

    first = driver()
    first._log_result(trial, {run_schema.ENV_STEPS: 20})  # a result without the key (an older trainable)
    assert tag() is None
    for steps in (20, 40):
        first._log_result(trial, {run_schema.ENV_STEPS: steps, run_schema.PRECISION_ROUTE: "bfloat16/onednn"})
    first._log_result(trial, {run_schema.ENV_STEPS: 60, run_schema.PRECISION_ROUTE: ""})
    assert tag() == "bfloat16/onednn"
    second = driver()  # resumed, and the trial recovered on a node without AMX
    second._log_result(trial, {run_schema.ENV_STEPS: 80, run_schema.PRECISION_ROUTE: "bfloat16/autocast"})
    assert tag() == "bfloat16/autocast,bfloat16/onednn"
    driver()._log_result(trial, {run_schema.ENV_STEPS: 100, run_schema.PRECISION_ROUTE: "bfloat16/onednn"})
    assert tag() == "bfloat16/autocast,bfloat16/onednn"


def test_a_trials_plugin_code_is_recorded_and_a_change_on_resume_shown(sqlite_tracker, tmp_path, monkeypatch, capsys):
    """The git commit names the package's code, not a plugin's: each trial run records its plugins' source
    digests, and a resume that finds them changed tags the run (it trained partly with each) and says so."""
    from uavlora_rllib.experiment.grid import load_grid, trials
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback
    from uavlora_rllib.experiment.tuner import trial_config

    plugin = tmp_path / "my_loss_plugin.py"
    plugin.write_text("DELTA = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    t = sqlite_tracker
    t.open_grid_run()
    grid_file = write_tiny_grid(
        tmp_path, "nest", mappo=TINY_MAPPO, episode_len=4, budget=60, plugins=["my_loss_plugin"]
    )
    grid = load_grid(grid_file)
    trial = SimpleNamespace(trial_id="t1", config={"trial": trial_config(trials(grid)[0], grid)})

    def driver() -> MlflowTrialCallback:
        cb = MlflowTrialCallback(t.tracking_uri, "nest", t.grid_file, commit="c0ffee")
        cb._tracker = t
        return cb

    run_id = driver().run_id(trial)
    assert t.client.get_run(run_id).data.params[run_schema.EVAL_INTERVAL_PARAM] == "3"  # 60 // 20: the export's
    first = t.client.get_run(run_id).data.tags[run_schema.PLUGINS_TAG]
    assert first.startswith("my_loss_plugin@") and len(first.split("@")[1]) == 12
    assert (
        driver().run_id(trial) == run_id and run_schema.PLUGINS_ON_RESUME_TAG not in t.client.get_run(run_id).data.tags
    )
    plugin.write_text("DELTA = 2.0\n")  # edited between the interrupt and --resume
    capsys.readouterr()
    assert driver().run_id(trial) == run_id
    tags = t.client.get_run(run_id).data.tags
    assert tags[run_schema.PLUGINS_TAG] == first and tags[run_schema.PLUGINS_ON_RESUME_TAG] != first
    assert "plugin code changed since it started" in capsys.readouterr().out


def test_reconciling_a_finished_trial_logs_each_result_once(sqlite_tracker, tmp_path):
    """A trial that finished while its driver died: the next driver logs the results its run lacks
    from result.json, each evaluation point once (the rows logged before the death are not repeated)."""
    import json

    from uavlora_rllib.experiment.grid import load_grid, trials
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback
    from uavlora_rllib.experiment.tuner import trial_config

    t = sqlite_tracker
    t.open_grid_run()
    grid = load_grid(write_tiny_grid(tmp_path, "nest", mappo=TINY_MAPPO, episode_len=4, budget=60))
    trial = SimpleNamespace(
        trial_id="t0", config={"trial": trial_config(trials(grid)[0], grid)}, path=str(tmp_path), last_result={}
    )
    rows = [
        {run_schema.ENV_STEPS: s, run_schema.TRIAL_WALL_METRIC: s / 10, "eval/ee_sys_mean": s + 0.5}
        for s in (20, 40, 60)
    ]
    (tmp_path / "result.json").write_text("".join(json.dumps(r) + "\n" for r in rows))

    def driver() -> MlflowTrialCallback:
        cb = MlflowTrialCallback(t.tracking_uri, "nest", t.grid_file, commit="c0ffee")
        cb._tracker = t
        return cb

    first = driver()
    for row in rows[:2]:  # then the driver died: the trial's last result never reached MLflow
        first._log_result(trial, row)
    assert driver().reconcile_trial(trial)
    run = t.run_for_trial("t0")
    assert run.info.status == "FINISHED"
    history = t.client.get_metric_history(run.info.run_id, "eval/ee_sys_mean")
    assert sorted((m.step, m.value) for m in history) == [(20, 20.5), (40, 40.5), (60, 60.5)]
    assert not driver().reconcile_trial(trial)  # FINISHED with its evaluations: nothing to do


def test_final_checkpoint_uploaded_once_and_again_when_written_again(sqlite_tracker, tmp_path, monkeypatch):
    """A trial that redid its last iterations after a resume writes its final checkpoint again at the same
    path: the run's checkpoint/ artifact is then the new one (it is paired with the new final evaluation);
    the same checkpoint is not uploaded twice."""
    from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback

    t = sqlite_tracker
    t.open_grid_run()
    run_id = t.create_run("mappo-V6-U2-s0", t.base_tags("train", "mappo", 0, 6, 2, 100), BASE_PARAMS)
    ckpt = tmp_path / "checkpoint_000002"
    ckpt.mkdir()
    (ckpt / "state.txt").write_text("first pass")
    trial = SimpleNamespace(trial_id="t0", checkpoint=SimpleNamespace(path=str(ckpt)))
    cb = MlflowTrialCallback(t.tracking_uri, "nest", t.grid_file, commit="c0ffee")
    cb._tracker = t
    uploads = []
    real = t.log_artifacts
    monkeypatch.setattr(t, "log_artifacts", lambda *a, **k: uploads.append(a) or real(*a, **k))

    def artifact() -> str:
        return open(t.client.download_artifacts(run_id, "checkpoint/state.txt", str(tmp_path / "dl"))).read()

    cb._log_final_checkpoint(trial, run_id)
    cb._log_final_checkpoint(trial, run_id)  # the same checkpoint: once
    assert len(uploads) == 1 and artifact() == "first pass"
    (ckpt / "state.txt").write_text("second pass")
    os.utime(ckpt / "state.txt", ns=(time.time_ns() + 10**9,) * 2)  # written later, whatever the clock's grain
    cb._log_final_checkpoint(trial, run_id)
    assert len(uploads) == 2 and artifact() == "second pass"
    assert t.client.get_run(run_id).data.tags["checkpoint_artifact"] == "checkpoint/"


def test_creating_an_existing_experiment_finds_it(sqlite_tracker):
    """A create retried after a timeout the server did carry out (seen against a loaded server)."""
    assert sqlite_tracker._create_experiment("nest") == sqlite_tracker.experiment_id


def test_old_flat_baseline_is_recognised_and_nested(sqlite_tracker):
    t = sqlite_tracker
    old = t.client.create_run(
        t.experiment_id,
        run_name="random-V6-U2-s0",
        tags={"kind": "baseline", "algorithm": "random", "seed": "0", "n_eds": "6", "n_uavs": "2"},
    )
    for k, v in BASE_PARAMS.items():
        t.client.log_param(old.info.run_id, k, v)  # no identity params: written before they existed
    t.client.set_terminated(old.info.run_id, "FINISHED")
    assert t.finished_baseline("random", 0, 6, 2, BASE_PARAMS)  # not redone on --resume
    assert t.client.get_run(old.info.run_id).data.tags[run_schema.PARENT_TAG] == t.grid_run()


def test_report_files_go_to_the_parent(tmp_path, sqlite_tracker):
    """A nested experiment: the report skips the parent, logs its files under the parent's
    report/ (replaced by the next report), and creates no summary run."""
    from analysis import report

    t = sqlite_tracker
    parent = t.open_grid_run()
    for seed in (0, 1):
        for name, ee in (("random", 1.0 + seed), ("greedy", 3.0 + seed)):
            t.log_baseline(
                name,
                f"{name}-V6-U2-s{seed}",
                seed,
                6,
                2,
                BASE_PARAMS,
                lambda ee=ee: {**SUMMARY, "ee_sys_mean": ee},
                budget=100,
            )
    t.end(parent, "FINISHED")
    out = tmp_path / "rep"
    args = ["--experiment", "nest", "--tracking-uri", t.tracking_uri, "--out", str(out), "--no-fig2"]
    assert report.main(args) == 0
    runs = t.search()
    assert not [r for r in runs if r.data.tags.get("kind") == "summary"]
    names = {a.path for a in t.client.list_artifacts(parent, "report")}
    assert {"report/report.md", "report/table_ee.csv"} <= names
    assert "runs: 4 (baseline: 4)" in (out / "report.md").read_text()  # the parent is not a run of the grid
    assert t.client.get_run(parent).info.status == "FINISHED"  # the grid's status, untouched
    assert report.main(args) == 0
    assert {a.path for a in t.client.list_artifacts(parent, "report")} == names
    assert sorted(a.path for a in t.client.list_artifacts(parent)) == ["grid.yaml", "report"]


def test_refused_credentials_are_one_line(monkeypatch):
    """A 401 from the server is not retried and names the credential variables."""
    import requests
    from mlflow.utils.rest_utils import verify_rest_response

    from uavlora_rllib.experiment import mlflow_client

    t = Tracker.__new__(Tracker)
    t.tracking_uri, t.retry_timeout_s = "http://127.0.0.1:1", 5.0
    calls = []

    def refuse():  # what MLflow's REST client raises on the basic-auth app's answer
        calls.append(1)
        reply = requests.Response()
        reply.status_code, reply._content = 401, b"You are not authenticated."
        verify_rest_response(reply, "/api/2.0/mlflow/experiments/get-by-name")

    with pytest.raises(TrackingRefused) as info:
        mlflow_client.Tracker._call(t, refuse)
    msg = str(info.value)
    assert calls == [1]  # not retried
    assert "\n" not in msg and "HTTP 401" in msg and "MLFLOW_TRACKING_USERNAME" in msg


# --------------------------------------------------------------------------- slow: a real server
TINY_MAPPO = {**TINY_MAPPO, "lr": 3e-4}
EPISODE_LEN = 10
BUDGET = 40  # 2 iterations of 2 episodes
ADMIN, ADMIN_PW = "admin", "uavlora-admin-pw-0"  # the basic-auth app wants 12+ characters


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def auth_server(tmp_path_factory):
    """`mlflow server --app-name basic-auth` on loopback, a free port, its own session; killed by PID."""
    tmp = tmp_path_factory.mktemp("mlflow_server")
    (tmp / "auth.ini").write_text(
        "[mlflow]\ndefault_permission = READ\n"
        f"database_uri = sqlite:///{tmp / 'auth.db'}\nadmin_username = {ADMIN}\n"
        "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n"
        "auth_cache_ttl_seconds = 60\n"
    )  # one password hash a minute, not one per request: CI's CPUs
    port = free_port()
    env = dict(
        os.environ,
        MLFLOW_AUTH_CONFIG_PATH=str(tmp / "auth.ini"),
        MLFLOW_AUTH_ADMIN_PASSWORD=ADMIN_PW,
        MLFLOW_FLASK_SERVER_SECRET_KEY="test-only-secret",
        MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false",
    )  # no background job workers (7 processes)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mlflow",
            "server",
            "--app-name",
            "basic-auth",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
            "--backend-store-uri",
            f"sqlite:///{tmp / 'backend.db'}",
            "--artifacts-destination",
            str(tmp / "artifacts"),
        ],
        cwd=tmp,
        env=env,
        stdout=open(tmp / "server.log", "w"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    uri = f"http://127.0.0.1:{port}"
    try:
        wait_for_mlflow_server(uri, proc, 240, lambda: (tmp / "server.log").read_text()[-3000:])
        yield {"uri": uri, "tmp": tmp}
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # its own session: the server and its workers
        proc.wait()


def _artifacts(client, run_id: str, path: str | None = None) -> dict[str, int]:
    """{artifact path: size} of every file under `path`, recursively."""
    out = {}
    for a in client.list_artifacts(run_id, path):
        if a.is_dir:
            out.update(_artifacts(client, run_id, a.path))
        else:
            out[a.path] = a.file_size
    return out


@pytest.mark.slow
def test_grid_against_an_authenticated_server(auth_server, ray_address, tmp_path, monkeypatch, capsys):
    from mlflow.tracking import MlflowClient

    from uavlora_rllib import tune as tune_cli

    uri = auth_server["uri"]
    grid_file = write_tiny_grid(
        tmp_path, "ui", mappo=TINY_MAPPO, episode_len=EPISODE_LEN, budget=BUDGET, baselines=("random",), uri=uri
    )

    # no credentials: refused before anything runs, one line, exit code 2
    monkeypatch.delenv("MLFLOW_TRACKING_USERNAME", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD", raising=False)
    assert tune_cli.main([grid_file]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "HTTP 401" in err and "MLFLOW_TRACKING_PASSWORD" in err, err

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "120")  # a loaded CI machine answers slowly
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", ADMIN)
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", ADMIN_PW)
    t0 = time.perf_counter()
    rc = tune_cli.main([grid_file])
    out, err = capsys.readouterr()
    assert rc == 0, (out + err)[-3000:]
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("ui")
    runs = client.search_runs([exp.experiment_id])
    by_kind = {}
    for r in runs:
        by_kind.setdefault(r.data.tags["kind"], []).append(r)
    assert sorted(by_kind) == ["baseline", "grid", "train"] and all(len(v) == 1 for v in by_kind.values())
    (parent,), (train,), (base,) = by_kind["grid"], by_kind["train"], by_kind["baseline"]

    # nesting and the parent
    assert parent.info.run_name == "ui" and parent.info.status == "FINISHED"
    for r in (train, base):
        assert r.data.tags["mlflow.parentRunId"] == parent.info.run_id
    # params to filter and group by; MLflow's standard source tags
    assert {k: train.data.params[k] for k in run_schema.IDENTITY_PARAMS} == {
        "algorithm": "mappo",
        "seed": "0",
        "n_eds": "6",
        "n_uavs": "2",
    }
    assert base.data.params["algorithm"] == "random" and base.data.params["seed"] == "0"
    for r in (parent, train, base):
        tags = r.data.tags
        assert all(tags.get(k) for k in SOURCE_TAGS), tags
        assert tags["mlflow.source.git.commit"] == git_commit() and tags["mlflow.user"] == getpass.getuser()
        assert tags["mlflow.source.type"] == "LOCAL" and grid_file in tags["mlflow.source.name"]

    # a trial's artifacts: its resolved config, its curves, its final checkpoint
    files = _artifacts(client, train.info.run_id)
    assert {"trial_config.yaml", "curves.csv", "checkpoint/rllib_checkpoint.json"} <= set(files), files
    assert train.data.tags["checkpoint_artifact"] == "checkpoint/"
    assert train.data.tags["checkpoint_artifact_source"] == train.data.tags["checkpoint"]
    local = client.download_artifacts(train.info.run_id, "trial_config.yaml", str(tmp_path))
    cfg = yaml.safe_load(open(local))
    assert cfg["trial_id"] == train.data.tags["trial_id"] and cfg["algorithm"] == "mappo"
    assert cfg["hparams"]["lr"] == pytest.approx(3e-4) and cfg["n_eds"] == 6 and cfg["budget_env_steps"] == BUDGET
    local = client.download_artifacts(train.info.run_id, "curves.csv", str(tmp_path))
    rows = list(csv.DictReader(open(local)))
    assert int(rows[-1]["env_steps"]) >= BUDGET
    assert float(rows[-1]["eval/ee_sys_mean"]) == pytest.approx(train.data.metrics["eval/ee_sys_mean"])
    assert {"episode_return_mean", "learner/policy_loss"} <= set(rows[0])
    # the parent holds the grid; the baseline is a flat line across the budget
    assert _artifacts(client, parent.info.run_id) == {"grid.yaml": os.path.getsize(grid_file)}
    hist = client.get_metric_history(base.info.run_id, "eval/ee_sys_mean")
    assert sorted(m.step for m in hist) == run_schema.reference_steps(BUDGET) and len({m.value for m in hist}) == 1
    print(f"grid against the auth server: {time.perf_counter() - t0:.0f} s", file=sys.stderr)

    # --resume of a finished grid, after a driver died between the uploads and the FINISHED
    # status (simulated: the run set back to KILLED): one run each, one parent, the same artifacts
    before = {r.info.run_id: _artifacts(client, r.info.run_id) for r in runs}
    returns = len(client.get_metric_history(train.info.run_id, "episode_return_mean"))
    client.set_terminated(train.info.run_id, "KILLED")
    rc = tune_cli.main([grid_file, "--resume"])
    out, err = capsys.readouterr()
    assert rc == 0, (out + err)[-3000:]
    runs2 = client.search_runs([exp.experiment_id])
    assert sorted(r.info.run_id for r in runs2) == sorted(before)
    assert all(r.info.status == "FINISHED" for r in runs2)
    assert {r.info.run_id: _artifacts(client, r.info.run_id) for r in runs2} == before
    assert len(client.get_metric_history(train.info.run_id, "episode_return_mean")) == returns
    assert len(client.get_metric_history(base.info.run_id, "eval/ee_sys_mean")) == len(hist)

    # the report logs its files on the parent run; without credentials it is refused in one line
    from analysis import report

    args = ["--experiment", "ui", "--tracking-uri", uri, "--out", str(tmp_path / "report"), "--no-fig2"]
    assert report.main(args) == 0, capsys.readouterr().err[-2000:]
    capsys.readouterr()
    files = _artifacts(client, parent.info.run_id)
    assert {"grid.yaml", "report/report.md", "report/table_ee.csv"} <= set(files), files
    assert not [
        r for r in client.search_runs([exp.experiment_id]) if r.data.tags["kind"] not in ("grid", "train", "baseline")
    ]
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD")
    assert report.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "HTTP 401" in err and "MLFLOW_TRACKING_PASSWORD" in err, err
