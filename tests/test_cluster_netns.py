"""`ray job submit --working-dir .` of a small grid on a cluster that looks like two machines.

Head and worker run in two network namespaces (tests/netns.py), each with its own address and
Ray temp dir, with token auth and an `mlflow server` on the head. The head has no CPUs and the
grid's algorithm comes from a plugin that exists only in the working dir, so every trial must
run on the worker from the job's package. Skips, saying why, where namespaces cannot be made.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import pathlib
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import netns
import pytest
from conftest import TINY_MAPPO, write_tiny_grid

pytestmark = pytest.mark.slow

# the ports exist only inside the namespaces, so the defaults are private to this test
GCS_PORT, DASHBOARD_PORT, MLFLOW_PORT = 6379, 8265, 5000
PLUGIN = '''"""MAPPO registered as "mappo_wd": importable only from the job's working dir."""
from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.mappo.mappo import MAPPOConfig

registry.register_algorithm("mappo_wd", MAPPOConfig, ("per_uav",))
'''
RAY = [sys.executable, "-m", "ray.scripts.scripts"]  # not bin/ray: a copied venv's script shebangs may be stale


def wait_for_log(proc: subprocess.Popen, log: str, text: str, timeout_s: float) -> None:
    """Wait until `text` is in the `log` that `proc` writes; fail with its tail if `proc` exits first."""
    deadline = time.monotonic() + timeout_s
    while True:
        with open(log, errors="replace") as fh:
            content = fh.read()
        if text in content:
            return
        assert proc.poll() is None, f"{log}: exited {proc.returncode}:\n{content[-3000:]}"
        assert time.monotonic() < deadline, f"{log}: no {text!r} after {timeout_s} s:\n{content[-3000:]}"
        time.sleep(0.5)


def wait_for_http(host: netns.Host, url: str, proc: subprocess.Popen, timeout_s: float) -> None:
    """Poll `url` from inside `host` until it answers 200."""
    probe = "import sys, urllib.request; urllib.request.urlopen(sys.argv[1], timeout=2)"
    deadline = time.monotonic() + timeout_s
    while host.run([sys.executable, "-c", probe, url], capture_output=True).returncode != 0:
        assert proc.poll() is None, f"{url}: server exited {proc.returncode}"
        assert time.monotonic() < deadline, f"{url}: no answer after {timeout_s} s"
        time.sleep(0.5)


@pytest.fixture
def cluster(tmp_path):
    """A head (0 CPUs, dashboard, mlflow server) and a worker (2 CPUs) in two network namespaces."""
    tmp = tempfile.mkdtemp(prefix="rn", dir="/tmp")  # short: Ray's Unix socket paths have a length limit
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN_PATH")}
    env.update(
        RAY_AUTH_MODE="token",
        RAY_AUTH_TOKEN=secrets.token_hex(16),
        RAY_TMPDIR=tmp,
        RAY_GRACEFUL_SHUTDOWN_DRAIN_TIMEOUT_S="0",
    )
    nodes: list[subprocess.Popen] = []

    def stop_nodes() -> None:
        for proc in reversed(nodes):  # worker first; SIGTERM lets `ray start --block` end its node
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()

    with contextlib.ExitStack() as stack:
        stack.callback(shutil.rmtree, tmp, ignore_errors=True)
        try:
            head, worker = stack.enter_context(netns.two_hosts())
        except netns.Unavailable as exc:
            pytest.skip(f"no network namespaces here: {exc}")
        stack.callback(stop_nodes)  # before the hosts close, which SIGKILL whatever is left in them

        def start(host: netns.Host, name: str, argv: list[str]) -> tuple[subprocess.Popen, str]:
            log = os.path.join(tmp, f"{name}.log")
            with open(log, "w") as out:
                proc = host.popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT, cwd=tmp)
            return proc, log

        mlflow_uri = f"http://{head.address}:{MLFLOW_PORT}"
        mlflow, _ = start(
            head,
            "mlflow",
            [
                sys.executable,
                "-m",
                "mlflow",
                "server",
                "--backend-store-uri",
                f"sqlite:///{tmp_path / 'mlflow.db'}",
                "--host",
                head.address,
                "--port",
                str(MLFLOW_PORT),
                "--workers",
                "1",
            ],
        )
        for host, name, args in (
            (
                head,
                "head",
                [
                    "--head",
                    "--port",
                    str(GCS_PORT),
                    "--num-cpus",
                    "0",
                    "--include-dashboard",
                    "true",
                    "--dashboard-host",
                    head.address,
                    "--dashboard-port",
                    str(DASHBOARD_PORT),
                ],
            ),
            (worker, "worker", ["--address", f"{head.address}:{GCS_PORT}", "--num-cpus", "2"]),
        ):
            proc, log = start(
                host,
                name,
                [
                    *RAY,
                    "start",
                    "--block",
                    "--disable-usage-stats",
                    "--node-ip-address",
                    host.address,
                    "--temp-dir",
                    os.path.join(tmp, name),
                    *args,
                ],
            )
            nodes.append(proc)
            wait_for_log(proc, log, "block forever", 180)  # printed once the node is registered
        wait_for_http(head, f"{mlflow_uri}/health", mlflow, 120)
        yield {
            "head": head,
            "worker": worker,
            "env": env,
            "tmp": tmp,
            "mlflow_uri": mlflow_uri,
            "dashboard": f"http://{head.address}:{DASHBOARD_PORT}",
        }


def test_job_with_working_dir_across_hosts(cluster, tmp_path):
    worker = cluster["worker"]
    workdir = tmp_path / "job"
    workdir.mkdir()
    (workdir / "wd_plugin.py").write_text(PLUGIN)
    write_tiny_grid(
        workdir,
        "netns",
        mappo={},
        episode_len=10,
        budget=20,
        seeds=(0, 1),
        uri=cluster["mlflow_uri"],
        algorithms={"mappo_wd": TINY_MAPPO},
        plugins=["wd_plugin"],
        storage=str(tmp_path / "ray_results"),
    )

    deadline = time.monotonic() + 120
    while True:  # from the worker host, with a relative grid path inside the working dir
        job = worker.run(
            [
                *RAY,
                "job",
                "submit",
                "--address",
                cluster["dashboard"],
                "--working-dir",
                ".",
                "--",
                sys.executable,
                "-m",
                "uavlora_rllib.tune",
                "netns.yaml",
            ],
            cwd=workdir,
            env=cluster["env"],
            capture_output=True,
            text=True,
            timeout=600,
        )
        # the dashboard accepts jobs once its agent on the head is up
        if "No available agent to submit job" not in job.stderr or time.monotonic() > deadline:
            break
        time.sleep(2)
    out = job.stdout + job.stderr
    assert job.returncode == 0, out[-6000:]
    assert "succeeded" in out and "2/2 trials finished, 0 failed" in out, out[-6000:]
    assert "Ray: 2 node(s), 2 CPU" in out

    # every trial ran on the worker host, from the package its runtime-env agent unpacked
    rows = [
        json.loads(line)
        for path in glob.glob(str(tmp_path / "ray_results" / "netns" / "*" / "result.json"))
        for line in pathlib.Path(path).read_text().splitlines()
        if line.strip()
    ]
    assert rows and {r["node_ip"] for r in rows} == {worker.address}, {r.get("node_ip") for r in rows}
    unpacked = glob.glob(
        os.path.join(
            cluster["tmp"], "worker", "session_*", "runtime_resources", "working_dir_files", "*", "wd_plugin.py"
        )
    )
    assert unpacked, "no working_dir package on the worker node"

    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")  # the server's own store
    exp = client.get_experiment_by_name("netns")
    assert exp is not None
    runs = client.search_runs([exp.experiment_id], max_results=100)
    parent = [r for r in runs if r.data.tags.get("kind") == "grid"]
    assert len(parent) == 1 and parent[0].info.status == "FINISHED"
    nested = {r.info.run_name: r for r in runs if r.data.tags.get("kind") != "grid"}
    assert sorted(nested) == ["mappo_wd-V6-U2-s0", "mappo_wd-V6-U2-s1", "random-V6-U2-s0", "random-V6-U2-s1"]
    for r in nested.values():
        assert r.info.status == "FINISHED" and r.data.tags["mlflow.parentRunId"] == parent[0].info.run_id
    assert all("eval/ee_sys_mean" in r.data.metrics for name, r in nested.items() if name.startswith("mappo_wd"))
