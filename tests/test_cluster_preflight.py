"""Where relative grid paths point (local, Ray Jobs), and the checks made before anything runs."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile

import pytest
import yaml

from uavlora_rllib import tune as tune_cli
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import cluster

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def no_job_env(monkeypatch):
    monkeypatch.delenv(cluster.RAY_JOB_ENV, raising=False)
    monkeypatch.delenv(cluster.LAUNCH_DIR_ENV, raising=False)


def test_relative_paths_resolve_against_the_launch_dir(tmp_path, monkeypatch, no_job_env):
    monkeypatch.chdir(tmp_path)
    assert cluster.resolve_tracking_uri("sqlite:///mlflow.db") == f"sqlite:///{tmp_path}/mlflow.db"
    assert cluster.resolve_tracking_uri("sqlite:////abs/m.db") == "sqlite:////abs/m.db"
    assert cluster.resolve_tracking_uri("http://127.0.0.1:5000") == "http://127.0.0.1:5000"
    assert cluster.resolve_path("./ray_results", "storage") == str(tmp_path / "ray_results")
    assert cluster.resolve_path("s3://bucket/x", "storage") == "s3://bucket/x"
    monkeypatch.setenv(cluster.LAUNCH_DIR_ENV, "/shared/exp")
    assert cluster.resolve_tracking_uri("sqlite:///sub/m.db") == "sqlite:////shared/exp/sub/m.db"


def test_under_ray_jobs_a_relative_path_needs_the_launch_dir(tmp_path, monkeypatch, no_job_env, capsys):
    monkeypatch.setenv(cluster.RAY_JOB_ENV, "{}")  # what `ray job submit` sets for the entrypoint
    with pytest.raises(ConfigError, match=cluster.LAUNCH_DIR_ENV):
        cluster.resolve_tracking_uri("sqlite:///mlflow.db")
    assert cluster.resolve_path(str(tmp_path), "storage") == str(tmp_path)  # absolute: fine
    grid = {
        "experiment": "job",
        "algorithms": ["mappo"],
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "stop": {"env_steps": 20},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": "sqlite:///mlflow.db"},
    }
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(grid))
    assert tune_cli.main([str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: mlflow.tracking_uri:") and "read-only" in err


def test_under_ray_jobs_the_driver_uses_the_jobs_cluster(monkeypatch, no_job_env):
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    assert cluster.job_address(None) is None  # not a job: a private local Ray
    monkeypatch.setenv(cluster.RAY_JOB_ENV, "{}")
    assert cluster.job_address(None) == "10.0.0.1:6379"  # what the job supervisor set
    assert cluster.job_address("ray://head:10001") == "ray://head:10001"  # --address wins
    monkeypatch.delenv("RAY_ADDRESS")
    assert cluster.job_address(None) == "auto"


def test_infeasible_bundles_are_named():
    nodes = [{"CPU": 2.0}, {"CPU": 1.0, "GPU": 1.0}]
    assert cluster.infeasible([{"CPU": 2.0}, {"CPU": 1.0}], nodes) is None
    assert "fits no node" in cluster.infeasible([{"CPU": 4.0}], nodes)
    assert "fits no node" in cluster.infeasible([{"CPU": 1.0, "GPU": 2.0}], nodes)
    assert "whole cluster" in cluster.infeasible([{"CPU": 2.0}, {"CPU": 1.0}, {"CPU": 1.0}], nodes)
    assert cluster.infeasible([{"CPU": 1.0}], []) == "the cluster has no alive node"


def _grid(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text(
        yaml.safe_dump(
            {
                "experiment": "x",
                "algorithms": ["mappo"],
                "seeds": [0],
                "n_eds": [6],
                "n_uavs": [2],
                "stop": {"env_steps": 20},
                "storage": str(tmp_path / "r"),
                "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'm.db'}"},
            }
        )
    )
    return path


def test_address_flags_are_checked_first(tmp_path, capsys, monkeypatch):
    path = _grid(tmp_path)
    assert tune_cli.main([str(path), "--address", "auto", "--num-cpus", "2"]) == 2
    assert "--num-cpus: only for a local Ray" in capsys.readouterr().err
    # ray:// without the client extra: named before any connection attempt
    monkeypatch.setattr(cluster.importlib.util, "find_spec", lambda name: None)
    assert tune_cli.main([str(path), "--address", "ray://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "ray[client]" in err and err.count("\n") == 1
    assert not (tmp_path / "m.db").exists()


@pytest.mark.slow
def test_infeasible_trial_fails_before_any_baseline(tmp_path):
    """A trial bundle no node of the started Ray can hold (a GPU learner on a machine without
    GPUs, which the grid's static CPU check cannot see): exit 2 with the reason from the live
    cluster's resources, no MLflow run, no Tune dir. (A CPU bundle bigger than the machine is
    refused even earlier, before Ray starts: tests/test_grid.py.)"""
    grid = {
        "experiment": "big",
        "algorithms": ["mappo"],
        "baselines": ["random"],
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "stop": {"env_steps": 20},
        "resources": {"num_gpus_per_learner": 1, "num_env_runners": 0},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": "sqlite:///mlflow.db"},  # relative: lands in cwd = tmp_path
    }
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(grid))
    # Ray's socket paths must stay under 107 bytes: a short private temp dir
    env = dict(os.environ, PYTHONPATH=REPO, RAY_TMPDIR=tempfile.mkdtemp(prefix="rt", dir="/tmp"))
    # a RAY_ADDRESS in the environment must not make a local run attach anywhere
    env["RAY_ADDRESS"] = "127.0.0.1:1"
    env.pop(cluster.RAY_JOB_ENV, None)
    proc = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.tune", str(path), "--num-cpus", "1"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 2, proc.stderr[-3000:]
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: resources: a trial can never start") and "fits no node" in last
    assert not (tmp_path / "mlflow.db").exists()
    assert not (tmp_path / "ray_results" / "big").exists()


def test_an_address_where_nothing_listens_is_one_line_at_once(tmp_path, capsys):
    """Ray itself retries a silent GCS address for about 14 minutes; the driver says so in one line first."""
    with socket.socket() as probe:  # a port that was free a moment ago: nothing listens there
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    for address in (f"127.0.0.1:{port}", f"ray://127.0.0.1:{port}"):
        assert tune_cli.main([str(_grid(tmp_path)), "--address", address]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"error: --address {address}: cannot connect to the Ray cluster (nothing answers at "), (
            err
        )
        assert err.count("\n") == 1
    assert not (tmp_path / "m.db").exists()
