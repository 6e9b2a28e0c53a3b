"""The report's table_cost (analysis/cost.py): what the runs took, from MLflow itself."""

from __future__ import annotations

import json
import math

import pytest

from analysis.cost import cost_md, cost_table, cost_totals
from analysis.runs import RunRecord, load_runs
from uavlora_rllib.experiment import run_schema, trial_clock
from uavlora_rllib.experiment.mlflow_client import Tracker
from uavlora_rllib.experiment.trial_clock import TrialClock


def _trial(seed: int, minutes: float, runners: int = 0, status: str = "FINISHED") -> RunRecord:
    start = 1_000_000
    return RunRecord(
        run_id=f"t{seed}{runners}", run_name="", status=status, start_time=start, kind="train", algorithm="mappo",
        seed=str(seed), n_eds=10, n_uavs=2,
        params={"resources.num_env_runners": str(runners), "resources.num_cpus_per_learner": "1.0",
                "resources.num_cpus_per_env_runner": "1.0", "resources.num_learners": "0"},
        end_time=int(start + minutes * 60_000) if status == "FINISHED" else None,
    )  # fmt: skip


def _baseline(seed: int, seconds: float | None) -> RunRecord:
    metrics = {} if seconds is None else {run_schema.EVAL_WALL_METRIC: seconds}
    return RunRecord(
        run_id=f"b{seed}", run_name="", status="FINISHED", start_time=0, kind="baseline", algorithm="greedy",
        seed=str(seed), n_eds=10, n_uavs=2, metrics=metrics, end_time=5,
    )  # fmt: skip


def test_trials_cost_their_run_time_times_reserved_cpus_and_baselines_their_evaluation():
    records = [
        _trial(0, 10.0), _trial(1, 20.0), _trial(2, 30.0, status="RUNNING"),  # unfinished: left out
        _baseline(0, 360.0), _baseline(1, None),  # logged before the metric: unmeasured
    ]  # fmt: skip
    rows = {r["name"]: r for r in cost_table(records)}
    mappo, greedy = rows["mappo"], rows["greedy"]
    assert (mappo["runs"], mappo["cpus_per_run"], mappo["unmeasured"]) == (2, 1.0, 0)
    assert (mappo["minutes_min"], mappo["minutes_median"], mappo["minutes_max"]) == (10.0, 15.0, 20.0)
    assert mappo["cpu_hours"] == pytest.approx(0.5)
    assert (greedy["runs"], greedy["unmeasured"], greedy["cpu_hours"]) == (2, 1, pytest.approx(0.1))
    assert cost_totals(list(rows.values())) == pytest.approx({"trials": 0.5, "baselines": 0.1, "total": 0.6})
    # two remote env runners besides the learner: the trial reserves 3 CPUs, as the dry run counts it
    three = cost_table([_trial(0, 20.0, runners=2)])[0]
    assert (three["cpus_per_run"], three["cpu_hours"]) == (3.0, pytest.approx(1.0))
    md = cost_md(list(rows.values()))
    assert "In all: 0.60 CPU-hours = trials 0.50 + baselines 0.100 (1 unmeasured runs not counted)" in md
    assert "| greedy | baseline | 2 |" in md
    assert cost_md([]).startswith("No finished runs")


def test_each_sampled_configuration_is_a_row_of_its_own():
    """A sweep's configurations cost differently (e.g. more updates per episode): one row each, named as the
    other tables name their cells."""
    runs = [_trial(0, 10.0), _trial(1, 40.0)]
    runs[0].params["hparam.lr"], runs[1].params["hparam.lr"] = "0.001", "0.01"
    rows = {r["name"]: r for r in cost_table(runs)}
    assert set(rows) == {"mappo[lr=0.001]", "mappo[lr=0.01]"} and rows["mappo[lr=0.01]"]["minutes_max"] == 40.0


def test_a_trial_with_its_working_time_is_costed_by_it_and_older_runs_by_their_span():
    paused = _trial(0, 30.0)  # resumed after a 20-minute pause: its run spans 30 min
    paused.metrics[run_schema.TRIAL_WALL_METRIC] = 600.0  # 10 min of its own work
    row = cost_table([paused, _trial(1, 12.0)])[0]  # seed 1 logged before the metric existed
    assert (row["minutes_min"], row["minutes_max"]) == (10.0, 12.0)
    assert row["by_span"] == 1
    assert "| 11.0 (10.0-12.0) | 0.367 | - | 1 |" in cost_md([row])
    assert row["cpu_hours"] == pytest.approx(22.0 / 60.0)


def test_the_trial_clock_sums_actors_and_leaves_out_the_pause(tmp_path):
    now = [100.0]
    first = TrialClock(lambda: now[0])
    now[0] += 50.0  # setup and training
    first.save(str(tmp_path))  # the last checkpoint
    now[0] += 7.0  # work after it, lost when the driver is interrupted
    now[0] += 1200.0  # the pause before --resume
    second = TrialClock(lambda: now[0])
    now[0] += 5.0  # the new actor builds the algorithm, then restores the checkpoint
    second.load(str(tmp_path))
    now[0] += 30.0
    assert second.seconds() == pytest.approx(85.0)
    (tmp_path / "old").mkdir()  # a checkpoint from before the clock: no earlier time
    second.load(str(tmp_path / "old"))
    assert second.seconds() == pytest.approx(35.0)
    assert json.loads((tmp_path / trial_clock.FILE).read_text()) == {trial_clock.KEY: 50.0}


def test_a_baseline_run_records_its_evaluation_time(tmp_path):
    """log_baseline writes the evaluation's own seconds (the task's _wall_s), and the report reads them back."""
    grid_file = tmp_path / "g.yaml"
    grid_file.write_text("experiment: cost\n")
    tracker = Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "cost", str(grid_file), commit="c0ffee", retry_timeout_s=5)
    tracker.open_grid_run()
    summary = {"ee_sys_mean": 2.0, "episodes": 1, "_wall_s": 42.5}
    params = {"scenario.n_eds": "6", "scenario.n_uavs": "2", "eval.episodes": "1"}
    tracker.log_baseline("random", "random-V6-U2-s0", 0, 6, 2, params, lambda: summary, budget=100)
    records, _ = load_runs(tracker.client, tracker.experiment_id)
    (row,) = cost_table(records)
    assert (row["name"], row["kind"], row["runs"], row["unmeasured"]) == ("random", "baseline", 1, 0)
    assert row["minutes_median"] == pytest.approx(42.5 / 60) and math.isclose(row["cpu_hours"], 42.5 / 3600)
