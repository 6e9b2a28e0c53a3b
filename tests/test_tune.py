"""The Tune entry point end to end, with MLflow: a two-trial grid, and an interrupted grid resumed.

A real learner trains (the project's MAPPO on a tiny scenario, a few iterations); Ray runs
with 2 CPUs in this process, and the interrupted run is a second driver (a subprocess that
connects to it with --address, and receives SIGINT once its first trial has a checkpoint).
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from conftest import TINY_MAPPO, write_tiny_grid

from uavlora_rllib import tune as tune_cli
from uavlora_rllib.experiment import run_schema
from uavlora_rllib.experiment.evaluation import EPISODE_METRICS
from uavlora_rllib.experiment.mlflow_client import git_commit

pytestmark = pytest.mark.slow

ALGO = "mappo"
TINY_MAPPO = {**TINY_MAPPO, "lr": 3e-4}
EPISODE_LEN = 10  # 2 episodes of 10 slots = 20 env steps per training iteration


def make_grid(tmp_path, name: str, budget: int, max_concurrent: int | None = None) -> str:
    extra = {"max_concurrent_trials": max_concurrent} if max_concurrent else {}
    return write_tiny_grid(
        tmp_path,
        name,
        mappo=TINY_MAPPO,
        episode_len=EPISODE_LEN,
        budget=budget,
        seeds=(0, 1),
        baselines=("random", "fixed"),
        episodes=2,
        **extra,
    )


def mlflow_runs(tmp_path, experiment: str) -> list:
    """The grid's train and baseline runs, each checked to be nested under its one parent run."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name(experiment)
    assert exp is not None
    runs = client.search_runs([exp.experiment_id], max_results=1000)
    parents = [r for r in runs if r.data.tags.get("kind") == "grid"]
    assert len(parents) == 1 and parents[0].info.run_name == experiment, [r.info.run_name for r in parents]
    runs = [r for r in runs if r.data.tags.get("kind") != "grid"]
    assert all(r.data.tags["mlflow.parentRunId"] == parents[0].info.run_id for r in runs)
    return client, runs


def steps_of(client, run, key: str) -> list[int]:
    return [m.step for m in sorted(client.get_metric_history(run.info.run_id, key), key=lambda m: m.timestamp)]


def check_train_run(client, run, grid_file: str, budget: int) -> None:
    tags, params, metrics = run.data.tags, run.data.params, run.data.metrics
    assert run.info.status == "FINISHED"
    seed = tags["seed"]
    assert run.info.run_name == f"{ALGO}-V6-U2-s{seed}"
    assert tags["kind"] == "train" and tags["algorithm"] == ALGO
    assert tags[run_schema.PRECISION_ROUTE] == "float32"  # the grid's default, as the trial's learner ran it
    assert (tags["n_eds"], tags["n_uavs"]) == ("6", "2") and seed in ("0", "1")
    assert tags["git_commit"] == git_commit() and tags["git_commit"] != ""
    assert tags["grid_file"] == grid_file
    assert tags["budget_env_steps"] == str(budget)
    assert tags["trial_id"]
    assert os.path.basename(tags["checkpoint"]).startswith("checkpoint_") and os.path.isdir(tags["checkpoint"])
    assert f"{ALGO}-V6-U2-s{seed}_{tags['trial_id']}" in tags["checkpoint"]
    # params
    assert (params["algorithm"], params["seed"], params["n_eds"], params["n_uavs"]) == (ALGO, seed, "6", "2")
    assert params["algo.lr"] == "0.0003" and params["algo.batch_episodes"] == "2"
    assert params["algo.num_epochs"] == "1" and "algo.gamma" in params  # defaults too
    assert params["scenario.n_eds"] == "6" and params["scenario.n_uavs"] == "2"
    assert params["scenario.episode_len"] == str(EPISODE_LEN) and params["scenario.mobility.memory"] == "0.85"
    assert params["resources.num_env_runners"] == "0" and params["resources.torch_threads"] == "1"
    assert params["resources.num_envs_per_env_runner"] == "2"
    assert params["stop.env_steps"] == str(budget) and params["eval.episodes"] == "2"
    # training metrics, step = env steps sampled
    steps = steps_of(client, run, "episode_return_mean")
    assert steps == sorted(set(steps)) and steps[-1] >= budget and steps[0] > 0
    assert steps[0] % (2 * EPISODE_LEN) == 0
    for key in ("ee_sys_mean", "success_rate", "env_steps_per_s"):
        assert key in metrics, key
    assert metrics["env_steps_per_s"] > 0 and metrics["ee_sys_mean"] > 0 and 0 <= metrics["success_rate"] <= 1
    learner = [k for k in metrics if k.startswith("learner/")]
    assert "learner/policy_loss" in learner and "learner/entropy" in learner, learner
    assert steps_of(client, run, "learner/policy_loss")[-1] == steps[-1]
    # execution-phase evaluation
    check_eval(client, run)
    # the greedy policy's curve (experiment/periodic_eval.py, evaluation.interval_env_steps unset:
    # budget / 20): the first iteration, a point at least every interval, the final evaluation last
    ev = sorted(set(steps_of(client, run, "eval/ee_sys_mean")))
    interval = max(1, budget // 20)
    assert set(ev) <= set(steps) and ev[0] == steps[0] and ev[-1] == steps[-1]
    assert all(b - a <= interval + 2 * EPISODE_LEN for a, b in zip(ev, ev[1:])), ev
    sampled = steps_of(client, run, "eval_sampled/ee_sys_mean")
    assert sampled and sampled[-1] == steps[-1]  # the final evaluation plays the sampled policy too


def check_eval(client, run) -> None:
    metrics = run.data.metrics
    for k in EPISODE_METRICS:
        assert f"eval/{k}" in metrics and f"eval/{k}_ci95" in metrics, k
    assert metrics["eval/episodes"] == 2
    assert metrics["eval/ee_sys_mean"] > 0
    assert metrics["eval/ee_sys_episode_sum"] == pytest.approx(EPISODE_LEN * metrics["eval/ee_sys_mean"])


def check_baseline_runs(runs, budget: int) -> None:
    base = [r for r in runs if r.data.tags.get("kind") == "baseline"]
    assert sorted(r.info.run_name for r in base) == sorted(
        f"{b}-V6-U2-s{s}" for b in ("random", "fixed") for s in (0, 1)
    )
    for r in base:
        assert r.info.status == "FINISHED"
        assert r.data.tags["algorithm"] in ("random", "fixed") and r.data.tags["budget_env_steps"] == str(budget)
        assert r.data.tags["git_commit"] and r.data.tags["grid_file"]
        assert not any(k.startswith("algo.") for k in r.data.params)
        assert r.data.params["scenario.episode_len"] == str(EPISODE_LEN) and r.data.params["eval.episodes"] == "2"
        assert "eval/ee_sys_mean" in r.data.metrics and r.data.metrics["eval/episodes"] == 2


def last_result(trial_dir: str) -> dict:
    with open(os.path.join(trial_dir, "result.json")) as fh:
        return json.loads(fh.read().strip().splitlines()[-1])


def test_two_trial_grid_end_to_end(ray_address, tmp_path, capsys):
    budget = 60  # 3 iterations
    grid_file = make_grid(tmp_path, "e2e", budget)
    t0 = time.perf_counter()
    rc = tune_cli.main([grid_file])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    assert "2/2 trials finished, 0 failed" in out
    assert str(tmp_path / "mlflow.db") in out and str(tmp_path / "ray_results" / "e2e") in out
    client, runs = mlflow_runs(tmp_path, "e2e")
    train = [r for r in runs if r.data.tags.get("kind") == "train"]
    assert len(train) == 2
    assert {r.data.tags["seed"] for r in train} == {"0", "1"}
    assert len({r.data.tags["trial_id"] for r in train}) == 2
    for r in train:
        check_train_run(client, r, grid_file, budget)
    check_baseline_runs(runs, budget)
    assert not [r for r in runs if r.info.status == "RUNNING"]
    print(f"end-to-end grid: {time.perf_counter() - t0:.0f} s", file=sys.stderr)

    # a second plain run of the same grid is refused (it would duplicate the MLflow runs) ...
    rc = tune_cli.main([grid_file])
    _, err = capsys.readouterr()
    assert rc == 2 and "exists already" in err and "--resume" in err
    # ... and --resume of a finished grid reruns nothing and logs nothing new
    history = {r.info.run_id: len(client.get_metric_history(r.info.run_id, "episode_return_mean")) for r in train}
    rc = tune_cli.main([grid_file, "--resume"])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    assert out.count("already in MLflow, skipped") == 4
    client, runs2 = mlflow_runs(tmp_path, "e2e")
    assert sorted(r.info.run_id for r in runs2) == sorted(r.info.run_id for r in runs)
    assert all(r.info.status == "FINISHED" for r in runs2)
    assert {
        r.info.run_id: len(client.get_metric_history(r.info.run_id, "episode_return_mean")) for r in train
    } == history
    # --resume of an edited grid (a longer budget) is refused in one line, before anything is touched
    # (Tune would restore the two finished trials only and report the grid interrupted at every --resume)
    make_grid(tmp_path, "e2e", 2 * budget)
    rc = tune_cli.main([grid_file, "--resume"])
    _, err = capsys.readouterr()
    assert rc == 2 and "not the one experiment 'e2e' started with (stop.env_steps 60 -> 120)" in err, err[-3000:]
    client, runs3 = mlflow_runs(tmp_path, "e2e")
    assert {(r.info.run_id, r.info.status) for r in runs3} == {(r.info.run_id, r.info.status) for r in runs2}
    (parent,) = client.search_runs([runs3[0].info.experiment_id], "tags.kind = 'grid'")
    assert parent.info.status == "FINISHED"
    make_grid(tmp_path, "e2e", budget)

    # the evaluate CLI on a trial's final checkpoint replays that trial's execution phase exactly
    from uavlora_rllib import evaluate as evaluate_cli

    run = train[0]
    seed = run.data.tags["seed"]
    rc = evaluate_cli.main(["--policy", run.data.tags["checkpoint"], "--episodes", "2", "--seed", seed, "--json"])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    result = json.loads(out)
    assert result["episodes"] == 2
    assert result["ee_sys_mean"] == pytest.approx(run.data.metrics["eval/ee_sys_mean"], rel=1e-9)
    assert result["success_rate"] == pytest.approx(run.data.metrics["eval/success_rate"], rel=1e-9)


@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_interrupted_grid_resumes_with_one_run_per_trial(ray_address, tmp_path, capsys, stop):
    """Ctrl+C, or SIGTERM (a scheduler's stop), which the driver treats as one Ctrl+C."""
    budget = 600  # 30 iterations: the first trial is still training when the signal arrives
    grid_file = make_grid(tmp_path, "resume", budget, max_concurrent=1)
    env = dict(os.environ)
    proc = subprocess.Popen(
        [sys.executable, "-m", "uavlora_rllib.tune", grid_file, "--address", ray_address],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    pattern = str(tmp_path / "ray_results" / "resume" / f"{ALGO}-V6-U2-s0_*" / "checkpoint_*")
    deadline = time.monotonic() + 180
    try:
        while not glob.glob(pattern):
            assert proc.poll() is None, proc.stdout.read()[-3000:]
            assert time.monotonic() < deadline, "no checkpoint within 180 s"
            time.sleep(0.2)
        proc.send_signal(stop)
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out[-3000:]
    assert "--resume" in out

    client, runs = mlflow_runs(tmp_path, "resume")
    assert not [r for r in runs if r.info.status == "RUNNING"], "a run was left RUNNING after the interrupt"
    first = [r for r in runs if r.data.tags.get("kind") == "train" and r.data.tags["seed"] == "0"]
    assert len(first) == 1 and first[0].info.status == "KILLED", "interrupt came too late to test resume"
    interrupted_run_id = first[0].info.run_id

    # resumed from a copy (another checkout, a shared disk): experiment and store moved together, and the
    # grid names the new store, which the resumed trials log to (not the path pickled with the experiment)
    time.sleep(10)  # a pause before --resume, which the trial's working time leaves out
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copytree(tmp_path / "ray_results", moved / "ray_results")
    shutil.copy(tmp_path / "mlflow.db", moved / "mlflow.db")
    grid_file = make_grid(moved, "resume", budget, max_concurrent=1)
    rc = tune_cli.main([grid_file, "--resume"])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    assert "2/2 trials finished" in out
    _, left = mlflow_runs(tmp_path, "resume")  # the original store is as the interrupt left it
    assert next(r for r in left if r.info.run_id == interrupted_run_id).info.status == "KILLED"
    created_in = {"0": str(tmp_path / "resume.yaml"), "1": grid_file}  # seed 1's run is created after the move
    tmp_path = moved

    client, runs = mlflow_runs(tmp_path, "resume")
    train = [r for r in runs if r.data.tags.get("kind") == "train"]
    assert len(train) == 2, [(r.info.run_name, r.info.status) for r in train]
    assert len({r.data.tags["trial_id"] for r in train}) == 2
    assert not [r for r in runs if r.info.status != "FINISHED"]
    for r in train:
        check_train_run(client, r, created_in[r.data.tags["seed"]], budget)
    resumed = next(r for r in train if r.data.tags["seed"] == "0")
    assert resumed.info.run_id == interrupted_run_id  # the same MLflow run continued
    span_s = (resumed.info.end_time - resumed.info.start_time) / 1000.0
    assert 0 < resumed.data.metrics[run_schema.TRIAL_WALL_METRIC] < span_s - 10  # the pause is not counted
    check_baseline_runs(runs, budget)  # not redone on resume

    # the interrupted trial continued from its checkpoint instead of starting again
    (trial_dir,) = glob.glob(str(tmp_path / "ray_results" / "resume" / f"{ALGO}-V6-U2-s0_*"))
    last = last_result(trial_dir)
    assert last["env_steps"] >= budget and last["done"]
    assert last["iterations_since_restore"] < last["training_iteration"]


def _wait_for(predicate, what: str, proc=None, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if proc is not None:
            assert proc.poll() is None, proc.stdout.read()[-3000:]
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.2)


def test_sigkilled_driver_resumes_with_one_run_each_and_its_runs_adopted(ray_address, tmp_path, capsys):
    """SIGKILL (no cleanup at all) mid-trial: the lock is stale, a run is RUNNING; --resume adopts."""
    budget = 600
    grid_file = make_grid(tmp_path, "killed", budget, max_concurrent=1)
    proc = subprocess.Popen(
        [sys.executable, "-m", "uavlora_rllib.tune", grid_file, "--address", ray_address],
        cwd=tmp_path,
        env=dict(os.environ),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    exp_dir = tmp_path / "ray_results" / "killed"
    ckpt = str(exp_dir / f"{ALGO}-V6-U2-s0_*" / "checkpoint_*")

    def state_after_checkpoint() -> bool:
        # Tune's periodic experiment snapshot taken after the first checkpoint: the trial is in it
        ckpts, states = glob.glob(ckpt), glob.glob(str(exp_dir / "experiment_state-*.json"))
        return bool(ckpts and states) and max(map(os.path.getmtime, states)) > min(map(os.path.getmtime, ckpts))

    try:
        _wait_for(state_after_checkpoint, "checkpoint and experiment snapshot", proc)
        proc.kill()
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert os.path.exists(tmp_path / "ray_results" / ".killed.driver.json")  # the dead driver's lock
    client, runs = mlflow_runs(tmp_path, "killed")
    running = {r.info.run_name: r.info.run_id for r in runs if r.info.status == "RUNNING"}
    assert f"{ALGO}-V6-U2-s0" in running, [(r.info.run_name, r.info.status) for r in runs]

    rc = tune_cli.main([grid_file, "--resume"])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    assert "took over the lock of a dead driver" in err and "2/2 trials finished" in out
    client, runs = mlflow_runs(tmp_path, "killed")
    assert sorted(r.info.run_name for r in runs) == sorted(
        [f"{ALGO}-V6-U2-s{s}" for s in (0, 1)] + [f"{b}-V6-U2-s{s}" for b in ("random", "fixed") for s in (0, 1)]
    )
    assert all(r.info.status == "FINISHED" for r in runs)
    by_name = {r.info.run_name: r.info.run_id for r in runs}
    for name, run_id in running.items():
        assert by_name[name] == run_id  # adopted, not duplicated
    for r in runs:
        if r.data.tags["kind"] == "train":
            check_train_run(client, r, grid_file, budget)
    assert not os.path.exists(tmp_path / "ray_results" / ".killed.driver.json")  # released


def test_resume_before_tune_started_adopts_leftovers(ray_address, tmp_path, capsys):
    """A driver killed during the baselines, before Tune wrote anything: --resume starts the
    trials, adopts the RUNNING baseline run it left, and replaces a train run whose trial is lost."""
    from uavlora_rllib.experiment.driver_lock import lock_path
    from uavlora_rllib.experiment.grid import load_grid, scenario_for
    from uavlora_rllib.experiment.mlflow_client import Tracker
    from uavlora_rllib.experiment.run_schema import KIND_TRAIN, run_params

    budget = 40
    grid_file = make_grid(tmp_path, "early", budget)
    grid = load_grid(grid_file)
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "early", grid_file)
    scenario = scenario_for(grid, 6, 2)
    params = run_params(scenario, None, 2)
    partial = {k: params[k] for k in list(params)[:5]}  # killed in the middle of log_params
    left_baseline = tracker.create_run(
        "random-V6-U2-s0", tracker.base_tags("baseline", "random", 0, 6, 2, budget), partial
    )
    tags = tracker.base_tags(KIND_TRAIN, ALGO, 1, 6, 2, budget)
    tags["trial_id"] = "lost0001"
    lost_train = tracker.create_run(f"{ALGO}-V6-U2-s1", tags, {})
    os.makedirs(tmp_path / "ray_results", exist_ok=True)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    with open(lock_path(str(tmp_path / "ray_results"), "early"), "w") as fh:
        json.dump(
            {
                "host": __import__("socket").gethostname(),
                "pid": dead.pid,
                "token": "x",
                "started": time.time(),
                "heartbeat": time.time(),
            },
            fh,
        )
    assert not (tmp_path / "ray_results" / "early").exists()

    rc = tune_cli.main([grid_file, "--resume"])
    out, err = capsys.readouterr()
    assert rc == 0, err[-3000:]
    assert "no Tune state" in err and "took over the lock" in err and "2/2 trials finished" in out
    client, runs = mlflow_runs(tmp_path, "early")
    assert sorted(r.info.run_name for r in runs) == sorted(
        [f"{ALGO}-V6-U2-s{s}" for s in (0, 1)] + [f"{b}-V6-U2-s{s}" for b in ("random", "fixed") for s in (0, 1)]
    )
    assert all(r.info.status == "FINISHED" for r in runs)
    adopted = next(r for r in runs if r.info.run_name == "random-V6-U2-s0")
    assert adopted.info.run_id == left_baseline
    assert dict(adopted.data.params) == {"algorithm": "random", "seed": "0", "n_eds": "6", "n_uavs": "2", **params}
    assert "eval/ee_sys_mean" in adopted.data.metrics
    assert lost_train not in {r.info.run_id for r in runs}  # its trial no longer exists: replaced
    assert client.get_run(lost_train).info.lifecycle_stage == "deleted"
    check_baseline_runs(runs, budget)
