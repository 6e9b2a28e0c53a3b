"""deploy/: the cluster-launcher YAML and the KubeRay RayJob parse, install the project with
constraints.txt and run the real grid entry point on a grid that exists."""

from __future__ import annotations

import importlib.util
import json
import os
import re

import yaml

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEPLOY = os.path.join(REPO, "deploy")
ENTRY = "python -m uavlora_rllib.tune"


def load(name: str) -> dict:
    with open(os.path.join(DEPLOY, name)) as fh:
        return yaml.safe_load(fh)


def grid_of(command: str) -> str:
    m = re.search(re.escape(ENTRY) + r"\s+(\S+\.yaml)", command)
    assert m, command
    return m.group(1)


def test_entry_point_is_a_module():
    assert importlib.util.find_spec("uavlora_rllib.tune") is not None


def test_cluster_launcher_yaml_matches_rays_schema_and_installs_with_constraints():
    import jsonschema
    import ray.autoscaler

    config = load("ray-cluster.yaml")
    with open(os.path.join(os.path.dirname(ray.autoscaler.__file__), "ray-schema.json")) as fh:
        jsonschema.validate(config, json.load(fh))  # the schema `ray up` validates against
    setup = "\n".join(config["setup_commands"])
    assert "pip install" in setup and "-c ~/uavlora-rllib/constraints.txt" in setup
    assert any("RAY_AUTH_MODE=token" in c for c in config["head_start_ray_commands"])
    assert any("RAY_AUTH_MODE=token" in c for c in config["worker_start_ray_commands"])
    # the grid command in its usage block names the entry point and a grid of the repo
    with open(os.path.join(DEPLOY, "ray-cluster.yaml")) as fh:
        usage = " ".join(line.lstrip("# ").rstrip("\\\n") for line in fh if line.startswith("#"))
    assert ENTRY in usage and "--address auto" in usage
    assert os.path.exists(os.path.join(REPO, grid_of(usage)))


def test_rayjob_manifest_runs_a_grid_on_an_image_built_with_constraints():
    job = load("rayjob.yaml")
    assert job["apiVersion"] == "ray.io/v1" and job["kind"] == "RayJob"
    spec = job["spec"]
    assert spec["entrypoint"].startswith(ENTRY)
    assert os.path.exists(os.path.join(REPO, grid_of(spec["entrypoint"])))
    assert yaml.safe_load(spec["runtimeEnvYAML"])["env_vars"]["UAVLORA_LAUNCH_DIR"] == "/shared"
    cluster = spec["rayClusterSpec"]
    assert cluster["rayVersion"] == "2.60.0"
    pods = [cluster["headGroupSpec"]["template"]] + [g["template"] for g in cluster["workerGroupSpecs"]]
    for pod in pods:
        (container,) = pod["spec"]["containers"]
        env = {e["name"]: e for e in container["env"]}
        assert env["RAY_AUTH_MODE"]["value"] == "token" and "secretKeyRef" in env["RAY_AUTH_TOKEN"]["valueFrom"]
        assert {"name": "shared", "mountPath": "/shared"} in container["volumeMounts"]
    images = {p["spec"]["containers"][0]["image"] for p in pods}
    assert len(images) == 1  # head and workers run the same code
    with open(os.path.join(DEPLOY, "Dockerfile")) as fh:
        dockerfile = fh.read()
    assert "FROM rayproject/ray:2.60.0-py311" in dockerfile
    assert "pip install --no-cache-dir -c constraints.txt -e ." in dockerfile


def test_mlflow_server_asks_for_a_password_and_the_driver_brings_one():
    """deploy/ runs MLflow with its basic-auth app, secrets from Kubernetes secrets (never in the
    files), and hands the driver (RayJob head, cluster-launcher command) MLFLOW_TRACKING_* variables."""
    with open(os.path.join(DEPLOY, "mlflow-server.yaml")) as fh:
        docs = {d["kind"]: d for d in yaml.safe_load_all(fh)}
    assert set(docs) == {"ConfigMap", "Deployment", "Service"}
    ini = docs["ConfigMap"]["data"]["basic_auth.ini"]
    assert "mlflow.server.auth:authenticate_request_basic_auth" in ini and "admin_password" not in ini
    (container,) = docs["Deployment"]["spec"]["template"]["spec"]["containers"]
    command = " ".join(container["args"])
    assert "mlflow server --app-name basic-auth" in command and "--artifacts-destination" in command
    env = {e["name"]: e for e in container["env"]}
    for secret in ("MLFLOW_AUTH_ADMIN_PASSWORD", "MLFLOW_FLASK_SERVER_SECRET_KEY"):
        assert "secretKeyRef" in env[secret]["valueFrom"], secret
    assert env["MLFLOW_AUTH_CONFIG_PATH"]["value"].startswith("/etc/mlflow/")
    assert docs["Service"]["spec"]["ports"][0]["port"] == 5000

    head = load("rayjob.yaml")["spec"]["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["containers"][0]
    env = {e["name"]: e for e in head["env"]}
    for var in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD"):
        assert env[var]["valueFrom"]["secretKeyRef"]["name"] == "mlflow-driver", var

    config = load("ray-cluster.yaml")
    start = "\n".join(config["head_start_ray_commands"])
    assert "mlflow server --app-name basic-auth" in start and "MLFLOW_AUTH_CONFIG_PATH" in start
    with open(os.path.join(DEPLOY, "ray-cluster.yaml")) as fh:
        usage = " ".join(line.lstrip("# ").rstrip("\\\n") for line in fh if line.startswith("#"))
    assert "MLFLOW_TRACKING_USERNAME" in usage and "MLFLOW_TRACKING_PASSWORD" in usage
    with open(os.path.join(REPO, "pyproject.toml")) as fh:
        assert '"mlflow[auth]' in fh.read()  # the basic-auth app's Flask-WTF comes with the install
