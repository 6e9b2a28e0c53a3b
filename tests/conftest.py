"""Shared helpers for the foundation's tests (physics, association, mobility, envs, config).

Kept deliberately small: builders for scenarios and random actions, an episode runner that
records everything a test may want to compare bit for bit, tiny grids, and the one local Ray
that the tests needing Ray share (`ray_session`, `ray_address`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from uavlora_rllib.sim.actions import per_device_action_len
from uavlora_rllib.sim.association import UNASSOCIATED
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig


def make_cfg(**fields: Any) -> ScenarioConfig:
    """A validated ScenarioConfig from keyword fields (nested groups as dicts)."""
    return ScenarioConfig.from_dict(fields)


def random_actions(cfg: ScenarioConfig, n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly random valid actions for a batch of n scenarios: [n, U] or [n, U, 2 quota + 1]."""
    if cfg.action_mode == "per_uav":
        return rng.integers(0, cfg.n_joint_actions, size=(n, cfg.n_uavs), dtype=np.int64)
    highs = np.array([cfg.n_sf, cfg.n_tp] * cfg.quota + [cfg.n_bw])
    assert highs.shape == (per_device_action_len(cfg),)
    return (rng.random((n, cfg.n_uavs, highs.size)) * highs).astype(np.int64)


def run_core(cfg: ScenarioConfig, n: int, seed, actions: list[np.ndarray]) -> dict[str, list[np.ndarray]]:
    """Reset a BatchCore(n) with `seed`, play `actions` (one [n, ...] array per step) and record
    obs, state, positions, serving, reward, truncated and every metric, each as a list of copies."""
    core = BatchCore(cfg, n)
    rec: dict[str, list[np.ndarray]] = {"obs": [core.reset(seed).copy()], "state": [core.state().copy()]}
    rec["ed_xy"] = [core.ed_xy.copy()]
    rec["serving"] = [core.serving.copy()]
    for a in actions:
        res = core.step(a)
        rec["obs"].append(res.obs.copy())
        rec["state"].append(core.state().copy())
        rec["ed_xy"].append(core.ed_xy.copy())
        rec["serving"].append(core.serving.copy())
        rec.setdefault("reward", []).append(res.reward.copy())
        rec.setdefault("truncated", []).append(res.truncated.copy())
        for k, v in res.metrics.items():
            rec.setdefault("m_" + k, []).append(np.asarray(v).copy())
    return rec


def reference_greedy(g: np.ndarray, d: np.ndarray, r_comm: float, quota: int) -> list[int]:
    """docs/model.md#association, one scenario, plain Python: EDs in descending order of their best in-range gain
    (ties: lower ED index first); each takes its max-gain in-range UAV with free quota (ties:
    lower UAV index); none left -> unassociated."""
    n_uavs, n_eds = g.shape
    best = []
    for v in range(n_eds):
        in_range = [g[u, v] for u in range(n_uavs) if d[u, v] <= r_comm]
        best.append(max(in_range) if in_range else -np.inf)
    order = sorted(range(n_eds), key=lambda v: -best[v])  # sorted() is stable
    load = [0] * n_uavs
    serving = [UNASSOCIATED] * n_eds
    for v in order:
        choice, choice_gain = None, -np.inf
        for u in range(n_uavs):
            if d[u, v] <= r_comm and load[u] < quota and g[u, v] > choice_gain:
                choice, choice_gain = u, g[u, v]
        if choice is not None:
            serving[v] = choice
            load[choice] += 1
    return serving


@pytest.fixture
def paper_cfg() -> ScenarioConfig:
    return ScenarioConfig()


# MAPPO at its smallest, for tests that need a grid to run, not to learn: 2 episodes per
# iteration, one epoch of one minibatch, 8-unit networks.
TINY_MAPPO = {
    "batch_episodes": 2,
    "num_epochs": 1,
    "num_minibatches": 1,
    "gru_hidden": 8,
    "fc_hidden": 8,
    "critic_hidden": 8,
    "max_seq_len": 10,
}


def finished_record(i: int, algorithm: str, *, kind="train", seed="0", scen=(10, 2), params=None, metrics=None):
    """A FINISHED run as analysis.runs reads one from MLflow (id r<i>, started at i): the analysis
    tests' hand-made stores."""
    from analysis.runs import RunRecord

    return RunRecord(
        run_id=f"r{i}",
        run_name="",
        status="FINISHED",
        start_time=i,
        kind=kind,
        algorithm=algorithm,
        seed=seed,
        n_eds=scen[0],
        n_uavs=scen[1],
        params=dict(params or {}),
        metrics=dict(metrics or {}),
    )


def write_tiny_grid(
    tmp_path,
    name: str,
    *,
    mappo: dict,
    episode_len: int,
    budget: int,
    seeds=(0,),
    baselines=("random",),
    episodes: int = 1,
    uri: str | None = None,
    **extra: Any,
) -> str:
    """A grid YAML of tiny MAPPO trials on V=6, U=2 (seconds per trial), with its storage and
    sqlite MLflow store under tmp_path; `extra` adds or replaces top-level grid keys. The Tune,
    cluster and bookkeeping tests build their grids here."""
    import yaml

    grid = {
        "experiment": name,
        "algorithms": {"mappo": mappo},
        "baselines": list(baselines),
        "seeds": list(seeds),
        "n_eds": [6],
        "n_uavs": [2],
        "scenario": {"episode_len": episode_len},
        "stop": {"env_steps": budget},
        "checkpoint_every": 1,
        "evaluation": {"episodes": episodes},
        "resources": {"num_env_runners": 0, "num_envs_per_env_runner": 2, "torch_threads": 1},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": uri or f"sqlite:///{tmp_path / 'mlflow.db'}"},
        **extra,
    }
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(grid, sort_keys=False))
    return str(path)


def wait_for_mlflow_server(
    uri: str, proc: subprocess.Popen, timeout_s: float, why: Callable[[], str] = lambda: ""
) -> None:
    """Poll `uri`/health until the `mlflow server` answers 200; fail if `proc` exits first (with
    `why()`, e.g. the tail of its log) or after `timeout_s` seconds."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(f"{uri}/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        assert proc.poll() is None, f"mlflow server exited {why()}"
        assert time.monotonic() < deadline, "mlflow server did not come up"
        time.sleep(0.5)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The tests that use the session's Ray (`ray_session`) run last, each group in its usual order:
    Ray starts once, and the tests before them run in a process without Ray (several assert that
    nothing started one; the cluster tests start their own)."""
    items.sort(key=lambda item: "ray_session" in getattr(item, "fixturenames", ()))


@dataclasses.dataclass(frozen=True)
class SharedRay:
    """The test session's local Ray: its GCS address and the environment its processes started with."""

    address: str
    env: dict[str, str]


@contextlib.contextmanager
def environ(values: dict[str, str]):
    """`os.environ` with `values` set, restored on exit."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.fixture(scope="session")
def ray_session():
    """The one local Ray of a test session, for every test that needs Ray in-process (RLlib
    algorithms, Tune, the tune CLI's main): started on first use with 2 CPUs (the CI machine's),
    a private RAY_TMPDIR (short, for socket paths; never somebody else's `ray start` cluster) and
    PYTHONPATH with tests/ and the repo (so that workers import the test plugins), shut down when
    the session ends. A Ray this process is already connected to is reused and left running.
    Tests of clusters of their own (test_cluster*) start those in subprocesses instead."""
    import ray

    tests_dir = os.path.dirname(os.path.abspath(__file__))
    pythonpath = os.pathsep.join(p for p in (tests_dir, os.path.dirname(tests_dir), os.environ.get("PYTHONPATH")) if p)
    if ray.is_initialized():
        yield SharedRay(ray.get_runtime_context().gcs_address, {"PYTHONPATH": pythonpath})
        return
    env = {"RAY_TMPDIR": tempfile.mkdtemp(prefix="rt", dir="/tmp"), "PYTHONPATH": pythonpath}
    with environ(env):  # Ray's processes keep the environment they start with
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield SharedRay(ray.get_runtime_context().gcs_address, env)
    ray.shutdown()


@pytest.fixture(scope="module")
def ray_address(ray_session: SharedRay):
    """The session's Ray (`ray_session`) as an address for drivers started against it (the tune CLI
    with --address, in a subprocess or in-process): its RAY_TMPDIR and PYTHONPATH are set for the
    module, so that those drivers inherit them."""
    with environ(ray_session.env):
        yield ray_session.address


def write_grid(tmp_path, data, name: str = "grid.yaml") -> str:
    """A grid YAML (a mapping, or text as is) written under tmp_path; its path."""
    import yaml

    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))
    return str(path)


def run_tune(argv, capsys) -> tuple[int, str, str]:
    """`python -m uavlora_rllib.tune ARGV` in this process: (exit code, stdout, stderr)."""
    from uavlora_rllib import tune as tune_cli

    rc = tune_cli.main(argv)
    out, err = capsys.readouterr()
    return rc, out, err
