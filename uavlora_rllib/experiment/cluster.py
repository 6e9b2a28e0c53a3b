"""Reaching Ray: where relative paths point, how the driver connects, and what it checks first.

Four ways to run a grid (docs/cluster.md):

* no ``--address``: a private local Ray (``address="local"``), never a ``ray start`` cluster
  that happens to run on the machine;
* ``--address auto`` on a cluster node, or ``--address HOST:PORT`` (the head's GCS port);
* ``--address ray://HEAD:10001`` (Ray Client; needs the ``ray[client]`` extra);
* ``ray job submit -- python -m uavlora_rllib.tune GRID`` (Ray sets RAY_ADDRESS for the
  entrypoint, which is then used like ``--address``: `job_address`).

Everything that can fail before the first baseline or trial is checked here (`preflight`):
the connection, authentication, the Ray extras an address needs, and that one trial's
resource bundles fit the cluster at all (an infeasible bundle would otherwise wait forever).
"""

from __future__ import annotations

import importlib.util
import os
import socket
import time
import urllib.parse
from collections.abc import Mapping, Sequence
from typing import Any

from uavlora_rllib.config_errors import ConfigError

# Set by the user (e.g. in `ray job submit --runtime-env-json`) to the directory that relative
# paths in the grid mean; otherwise the current directory, except under Ray Jobs (below).
LAUNCH_DIR_ENV = "UAVLORA_LAUNCH_DIR"
# Ray Jobs runs the entrypoint with this variable set (job_supervisor.py); its working
# directory is then Ray's unpacked, read-only copy of --working-dir.
RAY_JOB_ENV = "RAY_JOB_CONFIG_JSON_ENV_VAR"


def under_ray_job() -> bool:
    return RAY_JOB_ENV in os.environ


def launch_dir() -> str | None:
    """The directory relative grid paths resolve against; None: none is known (Ray Jobs)."""
    given = os.environ.get(LAUNCH_DIR_ENV)
    if given:
        return os.path.abspath(os.path.expanduser(given))
    return None if under_ray_job() else os.getcwd()


def _relative_under_job(field: str, value: str) -> ConfigError:
    return ConfigError(
        f"{field}: {value!r} is relative, and under `ray job submit` the working directory is Ray's "
        f"read-only copy of --working-dir; use an absolute path on storage every node shares, an MLflow "
        f"server URI for mlflow.tracking_uri, or set {LAUNCH_DIR_ENV} in the job's runtime env "
        f'(--runtime-env-json \'{{"env_vars": {{"{LAUNCH_DIR_ENV}": "/shared/dir"}}}}\')'
    )


def resolve_path(value: str, field: str) -> str:
    """A storage path or URI: URIs unchanged, relative paths against `launch_dir()`."""
    if "://" in value:
        return value
    value = os.path.expanduser(value)
    if os.path.isabs(value):
        return os.path.normpath(value)
    base = launch_dir()
    if base is None:
        raise _relative_under_job(field, value)
    return os.path.normpath(os.path.join(base, value))


def resolve_tracking_uri(uri: str, field: str = "mlflow.tracking_uri") -> str:
    """sqlite:///relative.db -> sqlite:////<launch dir>/relative.db; other URIs unchanged."""
    prefix = "sqlite:///"
    if not uri.startswith(prefix) or ":memory:" in uri:
        return uri
    path = uri[len(prefix) :]
    if path.startswith("/"):
        return uri
    return prefix + resolve_path(path, field)


# --------------------------------------------------------------------------- connecting
def job_address(address: str | None) -> str | None:
    """The address to use: --address when given; under Ray Jobs, the job's own cluster (the GCS
    address Ray sets in RAY_ADDRESS for the entrypoint), not a private local Ray, which would
    neither use the cluster nor find the job's --working-dir package in its own GCS."""
    if address or not under_ray_job():
        return address
    return os.environ.get("RAY_ADDRESS") or "auto"


def address_kind(address: str | None) -> str:
    if not address:
        return "local"
    if address.startswith("ray://"):
        return "client"
    return "cluster"


def check_extras(address: str | None) -> None:
    """The Ray extras this kind of address needs are installed (before trying to connect)."""
    if address_kind(address) == "client" and importlib.util.find_spec("grpc") is None:
        raise ConfigError(
            f"--address {address}: Ray Client needs the ray[client] extra; install the project with "
            "`pip install -c constraints.txt -e .` (it pins ray[default,client,rllib,tune])"
        )


def check_address_args(address: str | None, num_cpus: int | None) -> None:
    """The --address / --num-cpus combination and the extras it needs (no connection yet)."""
    if address and num_cpus is not None:
        raise ConfigError("--num-cpus: only for a local Ray; with --address the cluster's nodes set their CPUs")
    check_extras(address)


CLIENT_START_TRIES = 3  # ray:// connects tried while the head's client server is still starting
# seconds a TCP connect to --address may take before the address counts as wrong: Ray itself retries a silent
# GCS address about 20 times at ~40 s each (RAY_NUM_REDIS_GET_RETRIES), some 14 minutes, before it gives up
REACH_TIMEOUT_S = 5.0


def check_reachable(address: str) -> None:
    """ConfigError naming --address unless something accepts a TCP connection at its HOST:PORT (`auto`,
    or an address without a port, is left to Ray)."""
    try:
        parts = urllib.parse.urlsplit(address if "://" in address else f"//{address}")
        host, port = parts.hostname, parts.port
    except ValueError:  # a port that is not a number: Ray names the address
        return
    if not host or port is None:
        return
    try:
        with socket.create_connection((host, port), timeout=REACH_TIMEOUT_S):
            pass
    except OSError as exc:
        raise ConfigError(
            f"--address {address}: cannot connect to the Ray cluster (nothing answers at {host}:{port} within "
            f"{REACH_TIMEOUT_S:g} s: {exc.strerror or type(exc).__name__}); check the address (`ray status` on the "
            "head prints it)"
        ) from None


def connect(address: str | None, num_cpus: int | None) -> None:
    """ray.init for the given --address; raises ConfigError with what to check on failure."""
    import ray

    from uavlora_rllib.experiment.quiet import SETUP_HOOK

    check_address_args(address, num_cpus)
    # every worker process of this job silences the known harmless library messages (a Ray
    # Jobs entrypoint runs inside the job's own runtime env, which is left as submitted)
    runtime_env = None if under_ray_job() else {"worker_process_setup_hook": SETUP_HOOK}
    if not address:
        # "local" always starts a new Ray: a bare ray.init() would attach to any `ray start`
        # cluster on this machine (and then refuse num_cpus)
        ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, runtime_env=runtime_env)
        return
    check_reachable(address)
    try:
        for attempt in range(CLIENT_START_TRIES):
            try:
                ray.init(address=address, runtime_env=runtime_env)
                break
            except ConnectionAbortedError as exc:
                # Ray Client's proxy starts one server process per client and gives up when that
                # takes too long (a busy head); that is worth another try, a refusal is not
                if (
                    not address.startswith("ray://")
                    or "Initialization failure" not in str(exc)
                    or attempt == CLIENT_START_TRIES - 1
                ):
                    raise
                time.sleep(2.0 * (attempt + 1))
    except Exception as exc:  # ConnectionError, AuthenticationError, TimeoutError, ValueError, ...
        first = " ".join(str(exc).split())[:300] or type(exc).__name__
        auth = ""
        if type(exc).__name__ == "AuthenticationError" or "auth" in first.lower() or isinstance(exc, ConnectionError):
            auth = (
                "; with token authentication (RAY_AUTH_MODE=token) this driver needs the cluster's token "
                "in RAY_AUTH_TOKEN, RAY_AUTH_TOKEN_PATH or ~/.ray/auth_token"
            )
        raise ConfigError(
            f"--address {address}: cannot connect to the Ray cluster ({type(exc).__name__}: {first}); "
            f"check the address (`ray status` on the head prints it){auth}"
        ) from None


# --------------------------------------------------------------------------- feasibility
def alive_nodes() -> list[dict[str, float]]:
    """Total resources of each alive node."""
    import ray

    return [dict(n.get("Resources", {})) for n in ray.nodes() if n.get("Alive")]


def _fits(bundle: Mapping[str, float], node: Mapping[str, float]) -> bool:
    return all(node.get(k, 0.0) + 1e-9 >= v for k, v in bundle.items() if v > 0)


def infeasible(bundles: Sequence[Mapping[str, float]], nodes: Sequence[Mapping[str, float]]) -> str | None:
    """Why one trial's placement group can never be scheduled on these nodes, or None.

    The trial's bundles are placed with PACK (one node when they fit, spread otherwise), so a
    trial is feasible when every bundle fits some node and all of them fit the cluster's
    totals. Occupied resources do not matter here: Tune waits for those to free up.
    """
    if not nodes:
        return "the cluster has no alive node"
    for i, b in enumerate(bundles):
        if not any(_fits(b, n) for n in nodes):
            biggest = {k: max(n.get(k, 0.0) for n in nodes) for k in b}
            return f"bundle {i} {dict(b)} fits no node (largest node has {biggest})"
    total: dict[str, float] = {}
    for b in bundles:
        for k, v in b.items():
            total[k] = total.get(k, 0.0) + v
    cluster = {k: sum(n.get(k, 0.0) for n in nodes) for k in total}
    short = {k: v for k, v in total.items() if cluster[k] + 1e-9 < v}
    if short:
        return f"one trial needs {total} but the whole cluster has {cluster}"
    return None


def preflight(bundles: Sequence[Mapping[str, float]], baseline_cpus: float, n_baselines: int) -> None:
    """After connecting, before anything runs: a trial and a baseline task can be scheduled."""
    nodes = alive_nodes()
    why = infeasible(bundles, nodes)
    if why:
        raise ConfigError(
            f"resources: a trial can never start: {why}; lower the trial's resources (num_cpus_per_learner, "
            "num_gpus_per_learner, num_learners, num_env_runners, num_cpus_per_env_runner), or add nodes"
        )
    if n_baselines and infeasible([{"CPU": baseline_cpus}], nodes):
        raise ConfigError(f"baselines: a baseline task needs {baseline_cpus} CPU and no node has that many")


def describe_cluster() -> str:
    nodes = alive_nodes()
    cpus = sum(n.get("CPU", 0.0) for n in nodes)
    gpus = sum(n.get("GPU", 0.0) for n in nodes)
    return f"{len(nodes)} node(s), {cpus:g} CPU, {gpus:g} GPU"


def node_id() -> str:
    """The Ray node this process runs on (recorded in every trial result)."""
    import ray

    return ray.get_runtime_context().get_node_id()


def as_bundles(pgf: Any) -> list[dict[str, float]]:
    return [dict(b) for b in pgf.bundles]
