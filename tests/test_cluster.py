"""A real two-node Ray cluster on one host: every way to reach it, an MLflow server that goes
away, and a worker node killed mid-trial.

`ray.cluster_utils.Cluster` starts a head and a worker raylet (1 CPU each) with random ports,
a Ray Client server and the dashboard (Ray Jobs), under a private RAY_TMPDIR, so nothing here
can attach to another Ray on the machine. Every grid is run by a separate driver process, as
a user would, and MLflow is checked afterwards: one run per trial and per baseline, none left
RUNNING. The node-loss test runs last (it leaves the cluster with its head only).
"""

from __future__ import annotations

import glob
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time

import pytest
from conftest import TINY_MAPPO, wait_for_mlflow_server, write_tiny_grid

pytestmark = pytest.mark.slow

TESTS_DIR = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TESTS_DIR)
EPISODE_LEN = 10  # 20 env steps per training iteration


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def two_nodes():
    tmp = tempfile.mkdtemp(prefix="rc", dir="/tmp")  # Ray's socket paths must stay short
    saved = {
        k: os.environ.get(k)
        for k in ("RAY_TMPDIR", "PYTHONPATH", "RAY_ADDRESS", "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")
    }
    os.environ["RAY_TMPDIR"] = tmp
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (REPO, saved["PYTHONPATH"]) if p)
    os.environ.pop("RAY_ADDRESS", None)
    # token authentication, as docs/cluster.md asks: the nodes and every driver get the same
    # token, set explicitly (with RAY_AUTH_MODE unset, a token file in ~/.ray turns token auth
    # on for some processes and not for others)
    os.environ["RAY_AUTH_MODE"] = "token"
    os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(16)
    os.environ.pop("RAY_AUTH_TOKEN_PATH", None)
    client_port, dashboard_port = free_port(), free_port()
    ports = [client_port, dashboard_port, free_port(), free_port()]
    proc = subprocess.Popen(
        [sys.executable, os.path.join(TESTS_DIR, "two_node_cluster.py"), *map(str, ports)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    info = json.loads(proc.stdout.readline())
    info.update(proc=proc, tmp=tmp, client_port=client_port, dashboard=f"http://127.0.0.1:{dashboard_port}")
    try:
        yield info
    finally:
        proc.stdin.close()  # the helper shuts its cluster down
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def remove_worker(two_nodes) -> None:
    proc = two_nodes["proc"]
    proc.stdin.write("remove_worker\n")
    proc.stdin.flush()
    assert proc.stdout.readline().strip() == "removed"


def make_grid(tmp_path, name: str, *, seeds=(0,), budget=20, baselines=("random",), uri=None, **extra) -> str:
    return write_tiny_grid(
        tmp_path,
        name,
        mappo=TINY_MAPPO,
        episode_len=EPISODE_LEN,
        budget=budget,
        seeds=seeds,
        baselines=baselines,
        uri=uri,
        **extra,
    )


def driver(grid_file: str, *args: str, cwd=None, env_extra=None) -> subprocess.Popen:
    env = dict(os.environ, **(env_extra or {}))
    return subprocess.Popen(
        [sys.executable, "-m", "uavlora_rllib.tune", grid_file, *args],
        cwd=cwd or REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def finish(proc: subprocess.Popen, timeout: float = 600) -> str:
    try:
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
    return out


def runs_of(uri: str, experiment: str) -> list:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None, f"no MLflow experiment {experiment!r}"
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    parents = [r for r in runs if r.data.tags.get("kind") == "grid"]  # the grid's one parent run
    assert len(parents) == 1 and parents[0].info.status == "FINISHED", [
        (r.info.run_name, r.info.status) for r in parents
    ]
    runs = [r for r in runs if r.data.tags.get("kind") != "grid"]
    assert all(r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id for r in runs)
    return runs


def assert_one_finished_run_each(uri: str, experiment: str, trials: set[str], baselines: set[str]) -> list:
    runs = runs_of(uri, experiment)
    names = sorted(r.info.run_name for r in runs)
    assert names == sorted(trials | baselines), names
    assert all(r.info.status == "FINISHED" for r in runs), [(r.info.run_name, r.info.status) for r in runs]
    for r in runs:
        if r.data.tags["kind"] == "train":
            assert "eval/ee_sys_mean" in r.data.metrics
    return runs


def trial_rows(tmp_path, experiment: str) -> dict[str, list[dict]]:
    out = {}
    for path in glob.glob(str(tmp_path / "ray_results" / experiment / "mappo-*" / "result.json")):
        with open(path) as fh:
            out[os.path.basename(os.path.dirname(path))] = [json.loads(x) for x in fh if x.strip()]
    return out


@pytest.mark.parametrize("way", ["auto", "host_port", "ray_client"])
def test_reach_the_cluster(two_nodes, tmp_path, way):
    address = {
        "auto": "auto",
        "host_port": two_nodes["address"],
        "ray_client": f"ray://127.0.0.1:{two_nodes['client_port']}",
    }[way]
    grid = make_grid(tmp_path, f"reach_{way}")
    out = finish(driver(grid, "--address", address))
    assert "1/1 trials finished, 0 failed" in out, out[-4000:]
    assert "Ray: 2 node(s), 2 CPU" in out
    assert_one_finished_run_each(
        f"sqlite:///{tmp_path / 'mlflow.db'}", f"reach_{way}", {"mappo-V6-U2-s0"}, {"random-V6-U2-s0"}
    )


def test_wrong_token_is_one_clear_line(two_nodes, tmp_path):
    grid = make_grid(tmp_path, "token")
    out = finish(
        driver(grid, "--address", two_nodes["address"], env_extra={"RAY_AUTH_TOKEN": secrets.token_hex(16)}),
        timeout=300,
    )
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"error: --address {two_nodes['address']}: cannot connect"), out[-3000:]
    assert "RAY_AUTH_TOKEN" in last
    assert not (tmp_path / "mlflow.db").exists()


def test_ray_job_submit(two_nodes, tmp_path):
    """`ray job submit`: relative paths need UAVLORA_LAUNCH_DIR (else one clear error line)."""
    ray_bin = os.path.join(os.path.dirname(sys.executable), "ray")

    def submit(name: str, env_vars: dict) -> subprocess.CompletedProcess:
        # the grid by absolute path, without --working-dir (tests/test_cluster_netns.py submits one)
        grid = make_grid(tmp_path, name, uri="sqlite:///mlflow.db")
        deadline = time.monotonic() + 120
        while True:
            proc = subprocess.run(
                [
                    ray_bin,
                    "job",
                    "submit",
                    "--address",
                    two_nodes["dashboard"],
                    "--runtime-env-json",
                    json.dumps({"env_vars": env_vars}),
                    "--",
                    sys.executable,
                    "-m",
                    "uavlora_rllib.tune",
                    grid,
                ],
                capture_output=True,
                text=True,
                timeout=600,
                env=dict(os.environ),
            )
            # the dashboard accepts jobs once its agent on the head is up
            if "No available agent to submit job" not in proc.stderr or time.monotonic() > deadline:
                return proc
            time.sleep(2)

    bad = submit("job_bad", {})
    assert bad.returncode != 0
    assert "error: mlflow.tracking_uri:" in bad.stdout + bad.stderr and "UAVLORA_LAUNCH_DIR" in bad.stdout + bad.stderr
    assert "Traceback" not in bad.stdout
    good = submit("job", {"UAVLORA_LAUNCH_DIR": str(tmp_path)})
    assert good.returncode == 0, (good.stdout + good.stderr)[-4000:]
    assert "1/1 trials finished" in good.stdout
    assert "Ray: 2 node(s), 2 CPU" in good.stdout  # the job's cluster, not a private Ray on the head
    assert_one_finished_run_each(f"sqlite:///{tmp_path / 'mlflow.db'}", "job", {"mappo-V6-U2-s0"}, {"random-V6-U2-s0"})


@pytest.fixture
def mlflow_server(tmp_path):
    """A real `mlflow server` on a free port; start() / stop() by PID (restartable on the same db)."""
    port = free_port()
    db = tmp_path / "server.db"
    state = {"proc": None, "uri": f"http://127.0.0.1:{port}"}

    def start():
        proc = subprocess.Popen(
            # `python -m mlflow`, not bin/mlflow: a copied venv's script shebangs may be stale
            [
                sys.executable,
                "-m",
                "mlflow",
                "server",
                "--backend-store-uri",
                f"sqlite:///{db}",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--workers",
                "1",
            ],
            cwd=tmp_path,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        state["proc"] = proc
        wait_for_mlflow_server(state["uri"], proc, 120)

    def stop():
        proc = state["proc"]
        if proc is not None and proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)  # its own session: the server and its workers
            proc.wait()

    state.update(start=start, stop=stop)
    start()
    yield state
    stop()


def test_mlflow_server_goes_away_then_resume_completes(two_nodes, tmp_path, mlflow_server):
    from uavlora_rllib.experiment.mlflow_client import Tracker, TrackingUnavailable

    uri = mlflow_server["uri"]
    grid = make_grid(tmp_path, "server", budget=400, uri=uri, mlflow={"tracking_uri": uri, "retry_timeout_s": 5})
    proc = driver(grid, "--address", two_nodes["address"])
    pattern = str(tmp_path / "ray_results" / "server" / "mappo-*" / "checkpoint_*")
    deadline = time.monotonic() + 300
    while not glob.glob(pattern):
        assert proc.poll() is None, proc.stdout.read()[-4000:]
        assert time.monotonic() < deadline, "no checkpoint"
        time.sleep(0.2)
    mlflow_server["stop"]()
    out = finish(proc, timeout=300)  # bounded: retry_timeout_s, not forever
    assert proc.returncode == 1, out[-4000:]
    assert f"MLflow at {uri} unreachable for 5 s" in out and "--resume" in out

    # a bounded, clear failure from the tracker itself too
    t0 = time.monotonic()
    with pytest.raises(TrackingUnavailable, match="unreachable"):
        Tracker(uri, "server", grid, retry_timeout_s=2)
    assert time.monotonic() - t0 < 60

    mlflow_server["start"]()
    out = finish(driver(grid, "--resume", "--address", two_nodes["address"]))
    assert "1/1 trials finished, 0 failed" in out, out[-4000:]
    runs = assert_one_finished_run_each(uri, "server", {"mappo-V6-U2-s0"}, {"random-V6-U2-s0"})
    train = next(r for r in runs if r.data.tags["kind"] == "train")
    assert train.data.metrics["eval/episodes"] == 1


def test_worker_node_lost_mid_trial_is_retried(two_nodes, tmp_path):
    head_id, worker_id = two_nodes["head_id"], two_nodes["worker_id"]
    grid = make_grid(tmp_path, "lost", seeds=(0, 1), budget=600, baselines=(), failure={"max_failures": 2})
    proc = driver(grid, "--address", two_nodes["address"])
    deadline = time.monotonic() + 300
    victim = None
    while victim is None:
        assert proc.poll() is None, proc.stdout.read()[-4000:]
        assert time.monotonic() < deadline, "no trial checkpointed on the worker node"
        for name, rows in trial_rows(tmp_path, "lost").items():
            ckpts = glob.glob(str(tmp_path / "ray_results" / "lost" / name / "checkpoint_*"))
            if rows and rows[-1].get("node_id") == worker_id and ckpts and not rows[-1].get("done"):
                victim = name
        time.sleep(0.2)
    remove_worker(two_nodes)  # kills the worker's raylet and its trial
    out = finish(proc, timeout=600)
    assert proc.returncode == 0, out[-4000:]
    assert "2/2 trials finished, 0 failed" in out

    rows = trial_rows(tmp_path, "lost")
    assert {r["node_id"] for rs in rows.values() for r in rs} == {head_id, worker_id}  # both nodes trained
    victim_rows = rows[victim]
    assert victim_rows[-1]["done"] and victim_rows[-1]["node_id"] == head_id  # finished on the head
    # continued from its checkpoint: the retry did not start from iteration 1 again
    assert victim_rows[-1]["iterations_since_restore"] < victim_rows[-1]["training_iteration"]
    runs = assert_one_finished_run_each(
        f"sqlite:///{tmp_path / 'mlflow.db'}", "lost", {"mappo-V6-U2-s0", "mappo-V6-U2-s1"}, set()
    )
    retried = [r for r in runs if int(r.data.tags.get("retries", "0")) >= 1]
    assert len(retried) == 1 and victim.startswith(retried[0].info.run_name)
