"""The grid calibration and `tune --dry-run`'s cost estimate (issue 25 item 4): cells ignore the
seed and follow what sets a trial's speed, the estimate is the hand-computed arithmetic on a
hand-written calibration, missing cells are named (never guessed), the file is written
atomically, bad flags are one line and exit code 2. Only the last test starts Ray (slow)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
import yaml

from uavlora_rllib import tune as tune_cli
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import calibration, cost
from uavlora_rllib.experiment.grid import load_grid, trials
from uavlora_rllib.experiment.training_rate import measure_training

VERSION = calibration.package_version()


def grid_data(tmp_path, **changes) -> dict:
    data = {
        "experiment": "calib",
        "algorithms": {"mappo": None},
        "baselines": ["random"],
        "seeds": [0, 1],
        "n_eds": [4],
        "n_uavs": [2],
        "scenario": {"episode_len": 5},
        "stop": {"env_steps": 12000},
        "resources": {
            "num_env_runners": 2,
            "num_envs_per_env_runner": 4,
            "num_cpus_per_env_runner": 1,
            "num_cpus_per_learner": 1,
        },
        "evaluation": {"episodes": 4},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
    }
    data.update(changes)
    return data


def write_grid(tmp_path, data, name="grid.yaml") -> str:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return str(path)


@pytest.fixture
def calib_file(tmp_path, monkeypatch):
    path = tmp_path / "cache" / "calibration.json"
    monkeypatch.setenv(calibration.PATH_ENV, str(path))
    return path


def train_record(cell, machine, **fields) -> dict:
    return {
        "cell_key": cell.key,
        "kind": "train",
        "label": cell.label,
        "cell": dict(cell.content),
        "machine": machine,
        "version": VERSION,
        "measured_at": "2026-01-01T00:00:00+00:00",
        "learning_started": True,
        **fields,
    }


def baseline_record(cell, machine, seconds: float, episodes: int) -> dict:
    return {
        "cell_key": cell.key,
        "kind": "baseline",
        "label": cell.label,
        "cell": dict(cell.content),
        "machine": machine,
        "version": VERSION,
        "measured_at": "2026-01-01T00:00:00+00:00",
        "seconds": seconds,
        "timed_episodes": episodes,
        "timed_s": seconds,
        "episodes": episodes,
    }


# the hand-computed case: 12000 env steps at 100 env steps/s (300 per iteration, so 40
# iterations), an evaluation every 12000 / 20 = 600 env steps: the first iteration's and one per
# 600 steps, 1 + 20 = 21 evaluations of 6 s; build 42 s, final evaluation 2 s:
# wall = 42 + 120 + 21 x 6 + 2 = 290 s per trial; 3 CPUs (learner + 2 env runners) x 2 seeds
# -> 1740 CPU-s; 2 random baselines of 30 s on 1 CPU -> 60 CPU-s; 1800 CPU-s = 0.50 CPU-hours.
HAND = {
    "env_steps_per_s": 100.0,
    "env_steps_per_iteration": 300.0,
    "seconds_per_iteration": 3.0,
    "build_s": 42.0,
    "periodic_eval_s": 6.0,
    "final_eval_s": 2.0,
    "eval_episodes": 4,
    "iterations": 2,
    "warmup_iterations": 1,
}


def write_hand_calibration(tmp_path, calib_file, machine) -> tuple:
    grid = load_grid(write_grid(tmp_path, grid_data(tmp_path)))
    specs = trials(grid)
    [(tcell, _)] = calibration.grid_train_cells(grid, specs).values()
    [(bcell, _)] = calibration.grid_baseline_cells(grid).values()
    store = calibration.Store(str(calib_file))
    store.put(train_record(tcell, machine, **HAND))
    store.put(baseline_record(bcell, machine, 30.0, 4))
    return grid, specs


def test_a_write_keeps_the_files_mode(tmp_path, calib_file):
    """The file is replaced atomically by a temporary one; it keeps the mode it had (a shared
    $UAVLORA_CALIBRATION stays readable to the others), and a new file gets the umask's."""
    import stat

    machine = calibration.this_machine()
    old = os.umask(0o022)
    try:
        write_hand_calibration(tmp_path, calib_file, machine)
        assert stat.S_IMODE(os.stat(calib_file).st_mode) == 0o644
        os.chmod(calib_file, 0o664)
        write_hand_calibration(tmp_path, calib_file, machine)
        assert stat.S_IMODE(os.stat(calib_file).st_mode) == 0o664
    finally:
        os.umask(old)


# --------------------------------------------------------------------------- cells
def test_cell_key_ignores_the_seed_and_follows_what_sets_the_speed(tmp_path):
    def keys(**changes):
        grid = load_grid(write_grid(tmp_path, grid_data(tmp_path, **changes)))
        return [calibration.train_cell(s, grid.resources).key for s in trials(grid)]

    base = keys()
    assert len(base) == 2 and base[0] == base[1]  # two seeds, one cell
    assert keys(seeds=[7])[0] == base[0]
    assert keys(algorithms={"mappo": {"lr": 3e-4}})[0] != base[0]  # a hyperparameter
    assert keys(algorithms={"ippo": None})[0] != base[0]  # the algorithm
    assert keys(n_eds=[5])[0] != base[0]  # the scenario
    assert keys(scenario={"episode_len": 6})[0] != base[0]
    assert keys(scenario={"episode_len": 5, "action_mode": "per_device"})[0] != base[0]
    res = dict(grid_data(tmp_path)["resources"])
    assert keys(resources={**res, "num_envs_per_env_runner": 2})[0] != base[0]
    assert keys(resources={**res, "torch_threads": 2})[0] != base[0]
    assert keys(resources={**res, "num_cpus_per_env_runner": 2})[0] == base[0]  # a reservation, not a speed
    assert keys(evaluation={"episodes": 7})[0] == base[0]  # evaluation time is scaled by episodes
    assert keys(stop={"env_steps": 99})[0] == base[0]


def test_cell_key_does_not_depend_on_dict_order():
    assert calibration.cell_key("train", {"a": 1, "b": {"x": 1, "y": 2}}) == calibration.cell_key(
        "train", {"b": {"y": 2, "x": 1}, "a": 1}
    )


# --------------------------------------------------------------------------- arithmetic
@pytest.mark.parametrize(
    "budget, interval, per_iteration, expected",
    [(12000, 600, 300, 21), (12000, 0, 300, 0), (1000, 10, 300, 4), (1000, 1000, 1000, 1), (1000, 300, 250, 4)],
)
def test_periodic_evaluations(budget, interval, per_iteration, expected):
    # (1000, 10, 300): every one of the 4 iterations evaluates; (1000, 300, 250): at 250, 500, 750, 1000
    assert cost.periodic_evaluations(budget, interval, per_iteration) == expected


def test_estimate_is_the_hand_computed_arithmetic(tmp_path, calib_file):
    machine = calibration.this_machine()
    grid, specs = write_hand_calibration(tmp_path, calib_file, machine)
    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert est.complete and est.cpus_per_trial == 3
    assert [r.wall_s for r in est.rows] == [290.0, 290.0]
    assert est.trial_cpu_s() == 1740.0 and est.baseline_cpu_s() == 60.0
    assert cost.wall_clock_s(est, 3, None) == (600.0, 1)  # one trial at a time: 580 s of trials; 1800 CPU-s / 3
    assert cost.wall_clock_s(est, 6, None) == (300.0, 2)  # two at once: 290 s; 1800 / 6 = 300
    assert cost.wall_clock_s(est, 6, 1) == (580.0, 1)  # max_concurrent_trials 1
    assert cost.wall_clock_s(est, 30, None)[1] == 2  # 10 slots, 2 trials
    assert math.isnan(cost.wall_clock_s(est, 2, None)[0])  # a trial needs 3 CPUs
    assert est.notes == []


def test_dry_run_prints_the_estimate(tmp_path, calib_file, capsys):
    import ray

    write_hand_calibration(tmp_path, calib_file, calibration.this_machine())
    rc = tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run", "--num-cpus", "3"])
    out = capsys.readouterr().out
    assert rc == 0
    rows = [ln.split() for ln in out.splitlines() if ln.split()[1:2] in (["mappo-V4-U2-s0"], ["mappo-V4-U2-s1"])]
    assert rows == [
        ["1", "mappo-V4-U2-s0", "100", "0.08", "3", "0.24"],
        ["2", "mappo-V4-U2-s1", "100", "0.08", "3", "0.24"],
    ]
    assert "grid: 0.50 CPU-hours = 2 trials 0.48 (wall x 3 CPUs each) + baselines 0.02" in out
    assert "wall-clock: about 0.17 h on 3 CPUs (--num-cpus) (1 trial(s) at once" in out
    assert "another machine" not in out and "not calibrated" not in out
    assert not ray.is_initialized()


def test_another_machines_calibration_is_used_and_said_once(tmp_path, calib_file, capsys):
    other = {"cpu_model": "Some Other CPU 9000", "cpus": 64}
    write_hand_calibration(tmp_path, calib_file, other)
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run", "--num-cpus", "6"]) == 0
    out = capsys.readouterr().out
    notes = [ln for ln in out.splitlines() if "another machine" in ln]
    assert notes == [
        f"note: measured on another machine (Some Other CPU 9000, 64 CPUs); this one is "
        f"{calibration.describe_machine(calibration.this_machine())}"
    ]
    assert "grid: 0.50 CPU-hours" in out and "wall-clock: about 0.08 h (5.0 min) on 6 CPUs" in out


def test_evaluation_time_is_scaled_by_episodes(tmp_path, calib_file):
    machine = calibration.this_machine()
    write_hand_calibration(tmp_path, calib_file, machine)
    grid = load_grid(write_grid(tmp_path, grid_data(tmp_path, evaluation={"episodes": 8}), "g8.yaml"))
    est = cost.estimate(grid, trials(grid), calibration.Store.load(str(calib_file)), machine, VERSION)
    assert est.rows[0].wall_s == 42 + 120 + 21 * 12 + 4
    # a budget that is not a whole number of iterations: the iteration that crosses it runs in full
    odd = load_grid(write_grid(tmp_path, grid_data(tmp_path, stop={"env_steps": 11_950}), "odd.yaml"))
    record = calibration.Store.load(str(calib_file)).nearest(est.rows[0].cell, machine, VERSION)
    assert cost.trial_seconds(record.record, odd.stop.env_steps, 0, 4) == 42 + 120 + 2
    assert any("scaled by episodes from [4] to the grid's 8" in n for n in est.notes)
    assert not est.complete  # the baseline cell holds its episodes: 8 is another cell


def test_dry_run_without_calibration_names_the_cells_and_the_command(tmp_path, calib_file, capsys):
    path = write_grid(tmp_path, grid_data(tmp_path))
    assert tune_cli.main([path, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "not calibrated: none of the grid's 1 trial cell(s) and 1 baseline cell(s)" in out
    assert f"calibrate with: python -m uavlora_rllib.tune {path} --calibrate" in out
    assert "CPU-hours" not in out  # nothing invented
    assert not calib_file.exists()


def test_partly_calibrated_grid_lists_the_rest(tmp_path, calib_file, capsys):
    write_hand_calibration(tmp_path, calib_file, calibration.this_machine())
    path = write_grid(tmp_path, grid_data(tmp_path, n_uavs=[2, 3]), "two.yaml")
    assert tune_cli.main([path, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "not calibrated: 1 trial cell(s), 1 baseline cell(s)" in out
    assert "mappo V=4 U=3 per_uav T=5 runners=2 envs/runner=4 (trials 2, 4)" in out
    assert "partial: 0.50 CPU-hours for the calibrated part only (2 of 4 trials" in out
    assert "\ngrid:" not in out and "wall-clock" not in out


def test_records_of_other_code_stand_in_marked_approximate(tmp_path, calib_file, capsys):
    write_hand_calibration(tmp_path, calib_file, calibration.this_machine())
    data = json.loads(calib_file.read_text())
    for rec in data["records"].values():
        rec["version"] = "0.1.0+0123456789ab"
    calib_file.write_text(json.dumps(data))
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run", "--num-cpus", "3"]) == 0
    out = capsys.readouterr().out
    assert "grid: 0.50 CPU-hours" in out  # the same figures ...
    assert [ln.split()[-1] for ln in out.splitlines() if "mappo-V4-U2-s" in ln] == ["~", "~"]  # ... marked
    assert (
        f"note: approximate for trials 1-2: measured with other code (0.1.0+0123456789ab, 2026-01-01; "
        f"this is {VERSION})" in out
    )
    assert "note: approximate baselines (random): measured with other code" in out
    assert "measured 2026-01-01):" in out  # the header dates the records used
    # --calibrate measures this code: the old records do not count as done
    store = calibration.Store.load(str(calib_file))
    assert not any(store.has(r["cell_key"], calibration.this_machine(), VERSION) for r in store.records.values())


def test_the_code_version_follows_the_sources(tmp_path, monkeypatch):
    import uavlora_rllib

    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "a.py").write_text("x = 1\n")
    (pkg / "notes.txt").write_text("not code")
    (pkg / "sub" / ".#a.py").symlink_to(tmp_path / "gone")  # an editor's lock file: a dangling link
    (pkg / "sub" / "b.py").symlink_to(tmp_path / "gone-too")  # a dangling link: not code either
    (pkg / "sub" / ".a.py.swp.py").write_text("an editor's copy")
    monkeypatch.setattr(uavlora_rllib, "__file__", str(pkg / "__init__.py"))

    def digest() -> str:
        calibration.code_digest.cache_clear()
        return calibration.code_digest()

    try:
        first = digest()
        assert digest() == first and len(first) == 12
        (pkg / "notes.txt").write_text("still not code")
        (pkg / "sub" / ".a.py.swp.py").write_text("another copy")
        assert digest() == first
        (pkg / "sub" / "a.py").write_text("x = 2\n")
        assert digest() != first
    finally:
        monkeypatch.undo()
        calibration.code_digest.cache_clear()
    assert calibration.package_version() == f"{uavlora_rllib.__version__}+{calibration.code_digest()}" == VERSION
    assert {"torch", "ray", "numpy"} <= set(calibration.SPEED_DISTRIBUTIONS)


def test_unusable_records_are_ignored_and_counted(tmp_path, calib_file, capsys):
    machine = calibration.this_machine()
    write_hand_calibration(tmp_path, calib_file, machine)
    data = json.loads(calib_file.read_text())
    [(rid, train)] = [(k, r) for k, r in data["records"].items() if r["kind"] == "train"]
    data["records"]["junk"] = "oops"
    data["records"]["no-final"] = {k: v for k, v in train.items() if k != "final_eval_s"}
    data["records"]["zero-rate"] = {**train, "env_steps_per_s": 0}
    data["records"]["nan-build"] = {**train, "build_s": float("nan")}
    data["records"]["bool-episodes"] = {**train, "eval_episodes": True}
    data["records"]["null-hparams"] = {**train, "cell": {**train["cell"], "hparams": None}}
    del data["records"][rid]
    calib_file.write_text(json.dumps(data))
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "note: 6 record(s) of the calibration file cannot be read (damaged or edited) and are ignored" in out
    assert "not calibrated: 1 trial cell(s), 0 baseline cell(s)" in out
    assert calibration.usable(train) and not calibration.usable({**train, "kind": "other"})


def record_with_hparams(cell, machine, hparams, measured_at, rate) -> dict:
    """A record of `cell`'s content with other hyperparameters (so another cell key)."""
    other = calibration.Cell("train", {**cell.content, "hparams": hparams}, cell.label)
    return {**train_record(other, machine, **{**HAND, "env_steps_per_s": rate}), "measured_at": measured_at}


def test_a_record_with_other_hyperparameters_is_used_and_named(tmp_path, calib_file, capsys):
    # what adding a hyperparameter does to every earlier record: its cell key changes
    machine = calibration.this_machine()
    grid = load_grid(write_grid(tmp_path, grid_data(tmp_path)))
    specs = trials(grid)
    [(tcell, _)] = calibration.grid_train_cells(grid, specs).values()
    [(bcell, _)] = calibration.grid_baseline_cells(grid).values()
    hp = dict(tcell.content["hparams"])
    lr, clip = hp["lr"], hp.pop("grad_clip")  # the record predates grad_clip and used another lr
    store = calibration.Store(str(calib_file))
    store.put(record_with_hparams(tcell, machine, {**hp, "lr": lr * 2}, "2026-01-01T00:00:00+00:00", 100.0))
    store.put(record_with_hparams(tcell, machine, {**hp, "lr": lr * 3}, "2026-02-01T00:00:00+00:00", 50.0))
    # closer in hyperparameters, but another scenario: never used
    far = calibration.Cell("train", {**tcell.content, "scenario": {**tcell.content["scenario"], "n_eds": 5}}, "far")
    store.put(train_record(far, machine, **{**HAND, "env_steps_per_s": 1.0}))
    store.put(baseline_record(bcell, machine, 30.0, 4))

    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert est.complete and len(est.approximate) == 2
    assert [r.record["env_steps_per_s"] for r in est.rows] == [50.0, 50.0]  # the newest of the two equally near
    assert est.rows[0].match.differs == {"grad_clip": ("unset", clip), "lr": (lr * 3, lr)}
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run", "--num-cpus", "3"]) == 0
    out = capsys.readouterr().out
    assert (
        f"note: approximate for trials 1-2 (mappo): measured with other hyperparameters, grad_clip unset "
        f"(now {json.dumps(clip)}), lr {json.dumps(lr * 3)} (now {json.dumps(lr)})" in out
    )
    assert [ln.split()[-1] for ln in out.splitlines() if "mappo-V4-U2-s" in ln] == ["~", "~"]
    assert "approximate: 2 trial(s) (marked ~)" in out and "--calibrate" in out
    assert "\ngrid:" in out and "not calibrated" not in out

    # the exact cell, once measured, replaces the approximation; --calibrate would still measure it
    assert not store.has(tcell.key, machine, VERSION)
    store.put(train_record(tcell, machine, **HAND))
    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert est.approximate == [] and [r.wall_s for r in est.rows] == [290.0, 290.0] and est.notes == []


def test_the_nearest_record_has_the_fewest_differences_then_this_machine():
    machine, other = calibration.this_machine(), {"cpu_model": "Other", "cpus": 64}
    cell = calibration.Cell("train", {"algorithm": "a", "hparams": {"x": 1, "y": 2}, "scenario": {}}, "c")
    store = calibration.Store("unused.json")
    for name, hp, where in [
        ("two", {"x": 0, "y": 0}, machine),
        ("one-other", {"x": 1}, other),
        ("one", {"y": 2}, machine),
    ]:
        rec = record_with_hparams(cell, where, hp, "2026-01-01T00:00:00+00:00", 1.0)
        store.records[name] = {**rec, "label": name}
    # the exact cell, measured with other code: after this code's records that differ in neutral fields only
    exact_old = record_with_hparams(cell, machine, {"x": 1, "y": 2}, "2026-03-01T00:00:00+00:00", 1.0)
    store.records["exact-old"] = {**exact_old, "label": "exact-old", "version": "9.9"}
    match = store.nearest(cell, machine, VERSION, neutral={"x", "y"})
    assert match.record["label"] == "one" and match.differs == {"x": ("unset", 1)} and not match.other_code
    assert store.nearest(cell, machine, VERSION, neutral={"y"}).record["label"] == "one-other"  # x may not
    exact = store.nearest(cell, machine, VERSION)  # no neutral field: only the exact cell, here of other code
    assert exact.record["label"] == "exact-old" and exact.other_code and exact.differs == {}
    assert store.nearest(cell, machine, "9.9", neutral={"x", "y"}).record["label"] == "exact-old"
    old = store.nearest(cell, machine, "8.8", neutral={"x", "y"})
    assert old.other_code and old.record["label"] == "exact-old"  # all of other code: the fewest differences
    assert store.nearest(calibration.Cell("baseline", {}, "b"), machine, VERSION) is None


def test_a_speed_hyperparameter_never_stands_in(tmp_path, calib_file, capsys):
    # a record one field away (num_epochs, which sets the update's cost) and one two fields away (lr and gamma,
    # which do not): only the second may price the trial
    machine = calibration.this_machine()
    grid = load_grid(write_grid(tmp_path, grid_data(tmp_path)))
    specs = trials(grid)
    [(tcell, _)] = calibration.grid_train_cells(grid, specs).values()
    hp = dict(tcell.content["hparams"])
    store = calibration.Store(str(calib_file))
    store.put(record_with_hparams(tcell, machine, {**hp, "num_epochs": 4}, "2026-01-01T00:00:00+00:00", 400.0))
    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert [r.record for r in est.rows] == [None, None]
    store.put(record_with_hparams(tcell, machine, {**hp, "lr": 1.0, "gamma": 0.5}, "2026-01-01T00:00:00+00:00", 100.0))
    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert [r.record["env_steps_per_s"] for r in est.rows] == [100.0, 100.0]
    assert set(est.rows[0].match.differs) == {"lr", "gamma"}


def test_scenario_constants_stand_in_geometry_does_not(tmp_path, calib_file, capsys):
    machine = calibration.this_machine()
    grid = load_grid(write_grid(tmp_path, grid_data(tmp_path)))
    specs = trials(grid)
    [(tcell, _)] = calibration.grid_train_cells(grid, specs).values()
    [(bcell, _)] = calibration.grid_baseline_cells(grid).values()
    store = calibration.Store(str(calib_file))

    def moved(cell, **scenario):
        return calibration.Cell(cell.kind, {**cell.content, "scenario": {**cell.content["scenario"], **scenario}}, "m")

    reward = {**tcell.content["scenario"]["reward"], "w1": 0.5}
    store.put(train_record(moved(tcell, altitude_m=120.0), machine, **HAND))  # geometry: never a stand-in
    store.put(baseline_record(moved(bcell, altitude_m=120.0), machine, 30.0, 4))
    est = cost.estimate(grid, specs, calibration.Store.load(str(calib_file)), machine, VERSION)
    assert [r.record for r in est.rows] == [None, None] and est.baselines[0].record is None
    store.put(train_record(moved(tcell, reward=reward), machine, **HAND))
    store.put(baseline_record(moved(bcell, reward=reward), machine, 30.0, 4))  # a baseline's searches follow it
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--dry-run", "--num-cpus", "3"]) == 0
    out = capsys.readouterr().out
    old, now = json.dumps(reward), json.dumps(tcell.content["scenario"]["reward"])
    assert (
        f"note: approximate for trials 1-2 (mappo): measured with other scenario constants, scenario.reward {old} (now {now})"
        in out
    )
    assert "not calibrated: 0 trial cell(s), 1 baseline cell(s)" in out


def test_every_speed_neutral_scenario_name_is_a_field():
    import dataclasses

    from uavlora_rllib.sim.scenario import ScenarioConfig

    assert ScenarioConfig.SPEED_NEUTRAL <= {f.name for f in dataclasses.fields(ScenarioConfig)}
    speed = {"n_eds", "n_uavs", "episode_len", "action_mode", "area_m", "altitude_m", "comm_range_m", "mobility"}
    link_stage = {"los_a", "los_b", "eta_los_db", "eta_nlos_db"}  # physics/links.py picks its computation by them
    assert not (speed | link_stage) & ScenarioConfig.SPEED_NEUTRAL


def test_every_speed_neutral_name_is_a_hyperparameter():
    import dataclasses

    from uavlora_rllib.algorithms.common import registry

    for name in registry.built_in():
        cls = registry.spec(name).hparams_cls
        neutral = getattr(cls, "SPEED_NEUTRAL", frozenset())
        assert neutral <= {f.name for f in dataclasses.fields(cls)}, name
        assert neutral, f"{name}: declares no speed-neutral hyperparameter"


# --------------------------------------------------------------------------- the file
def test_store_writes_atomically_and_keeps_other_records(tmp_path):
    path = tmp_path / "sub" / "calibration.json"
    machine = calibration.this_machine()
    a = calibration.Cell("baseline", {"x": 1}, "a")
    b = calibration.Cell("baseline", {"x": 2}, "b")
    calibration.Store(str(path)).put(baseline_record(a, machine, 1.0, 1))
    stale = calibration.Store(str(path))  # holds no records: put re-reads the file first
    stale.put(baseline_record(b, machine, 2.0, 1))
    loaded = calibration.Store.load(str(path))
    assert {r["label"] for r in loaded.records.values()} == {"a", "b"}
    assert loaded.find(a.key, machine, VERSION)["seconds"] == 1.0
    assert loaded.find(a.key, machine, "9.9") is None
    assert sorted(os.listdir(path.parent)) == ["calibration.json", "calibration.json.lock"]  # no temp file left


def test_unreadable_calibration(tmp_path, calib_file, capsys):
    calib_file.parent.mkdir(parents=True)
    calib_file.write_text("{not json")
    with pytest.raises(ConfigError, match="cannot read it"):
        calibration.Store.load(str(calib_file))
    path = write_grid(tmp_path, grid_data(tmp_path))
    assert tune_cli.main([path, "--dry-run"]) == 0  # a preview still works, and says so
    assert f"note: calibration file {calib_file}: cannot read it" in capsys.readouterr().out
    assert tune_cli.main([path, "--calibrate"]) == 2  # never overwritten
    err = capsys.readouterr().err
    assert err.startswith("error: calibration file") and err.count("\n") == 1
    assert calib_file.read_text() == "{not json"


# --------------------------------------------------------------------------- flags
@pytest.mark.parametrize(
    "extra, message",
    [
        (
            ["--calibrate", "--calibrate-iterations", "0"],
            "--calibrate-iterations: must be an integer in [1, 100], got 0",
        ),
        (["--calibrate", "--calibrate-iterations", "x"], "--calibrate-iterations: expected an integer, got 'x'"),
        (["--calibrate-iterations", "3"], "--calibrate-iterations: only with --calibrate"),
        (["--calibrate", "--resume"], "--calibrate: measures this machine in a private local Ray"),
        (["--calibrate", "--address", "auto"], "drop --resume and --address"),
    ],
)
def test_bad_calibrate_flags(tmp_path, calib_file, capsys, extra, message):
    import ray

    rc = tune_cli.main([write_grid(tmp_path, grid_data(tmp_path)), *extra])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and err.count("\n") == 1 and message in err, err
    assert not ray.is_initialized() and not calib_file.exists()


def _fake_measurements(monkeypatch, rate: float = 100.0) -> list[str]:
    """measure_* replaced (no Ray): each call appends the spec's name; trials measure `rate`."""
    import ray

    measured: list[str] = []

    def fake_train(grid, spec, iterations):
        measured.append(spec.name)
        return {**HAND, "env_steps_per_s": rate, "iterations": iterations, "learning_started": True}

    def fake_baseline(spec, episodes):
        measured.append(spec.name)
        return {"seconds": 30.0, "timed_episodes": episodes, "timed_s": 30.0, "episodes": episodes}

    monkeypatch.setattr(calibration, "measure_train_cell", fake_train)
    monkeypatch.setattr(calibration, "measure_baseline_cell", fake_baseline)
    monkeypatch.setattr(ray, "init", lambda **kw: None)
    monkeypatch.setattr(ray, "shutdown", lambda: None)
    return measured


def test_calibrate_measures_each_cell_once_and_records_it(tmp_path, calib_file, capsys, monkeypatch):
    """The calibration's bookkeeping, with the measurements replaced (no Ray)."""
    measured = _fake_measurements(monkeypatch)
    path = write_grid(tmp_path, grid_data(tmp_path))
    assert tune_cli.main([path, "--calibrate", "--calibrate-iterations", "3", "--num-cpus", "3"]) == 0
    out = capsys.readouterr().out
    assert measured == ["mappo-V4-U2-s0", "random-V4-U2-s0"]  # one per cell, not per seed
    records = json.loads(calib_file.read_text())["records"]
    assert {r["kind"] for r in records.values()} == {"train", "baseline"}
    assert next(r for r in records.values() if r["kind"] == "train")["iterations"] == 3
    assert "grid: 0.50 CPU-hours" in out  # then the dry run, from what was written
    assert tune_cli.main([path, "--calibrate"]) == 0  # a second run keeps what is there
    assert measured == ["mappo-V4-U2-s0", "random-V4-U2-s0"]
    assert "0 trial cells and 0 baseline cells to measure" in capsys.readouterr().out


def test_an_unusable_measurement_is_not_recorded(tmp_path, calib_file, capsys, monkeypatch):
    measured = _fake_measurements(monkeypatch, rate=0.0)  # e.g. no env step was timed
    path = write_grid(tmp_path, grid_data(tmp_path))
    assert tune_cli.main([path, "--calibrate"]) == 0
    out = capsys.readouterr().out
    assert "mappo V=4 U=2 per_uav T=5 runners=2 envs/runner=4: not recorded, the measurement is unusable" in out
    assert [r["kind"] for r in json.loads(calib_file.read_text())["records"].values()] == ["baseline"]
    assert tune_cli.main([path, "--calibrate"]) == 0  # so the next calibration measures it again
    assert measured == ["mappo-V4-U2-s0", "random-V4-U2-s0", "mappo-V4-U2-s0"]


def test_calibrate_refuses_an_unwritable_file_before_measuring(tmp_path, capsys, monkeypatch):
    measured = _fake_measurements(monkeypatch)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv(calibration.PATH_ENV, str(blocker / "calibration.json"))  # its directory is a file
    assert tune_cli.main([write_grid(tmp_path, grid_data(tmp_path)), "--calibrate"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: calibration file {blocker / 'calibration.json'}: cannot write there")
    assert err.count("\n") == 1 and f"${calibration.PATH_ENV}" in err and measured == []


def test_a_second_calibration_into_the_same_file_is_refused(tmp_path, calib_file, capsys, monkeypatch):
    import fcntl

    measured = _fake_measurements(monkeypatch)
    calib_file.parent.mkdir(parents=True)
    with open(str(calib_file) + ".calibrating", "a") as held:  # what a running --calibrate holds
        fcntl.flock(held, fcntl.LOCK_EX)
        assert tune_cli.main([write_grid(tmp_path, grid_data(tmp_path)), "--calibrate"]) == 2
    err = capsys.readouterr().err
    assert "another --calibrate is measuring into it" in err and err.count("\n") == 1 and measured == []
    assert tune_cli.main([str(tmp_path / "grid.yaml"), "--calibrate"]) == 0  # once it has ended
    assert len(measured) == 2


def test_calibrate_on_a_busy_machine_says_so(tmp_path, calib_file, capsys, monkeypatch):
    _fake_measurements(monkeypatch)
    monkeypatch.setattr(os, "getloadavg", lambda: (4.0 * (os.cpu_count() or 1), 0.0, 0.0))
    assert tune_cli.main([write_grid(tmp_path, grid_data(tmp_path)), "--calibrate"]) == 0
    assert "other work shares the cores, so the rates measured now will be low" in capsys.readouterr().out


def test_notes_of_schedulers_sweeps_and_gpus(tmp_path, calib_file):
    machine = calibration.this_machine()
    write_hand_calibration(tmp_path, calib_file, machine)
    store = calibration.Store.load(str(calib_file))

    def notes(**changes) -> list[str]:
        grid = load_grid(write_grid(tmp_path, grid_data(tmp_path, **changes), "n.yaml"))
        return cost.estimate(grid, trials(grid), store, machine, VERSION).notes

    pbt = notes(scheduler={"type": "pbt"}, algorithms={"mappo": {"lr": {"uniform": [1e-4, 1e-3]}}})
    assert "note: the pbt scheduler pauses and rebuilds trials at each perturbation: a lower bound" in pbt
    assert "note: sampled hyperparameters are calibrated at their defaults" in pbt  # lr: speed-neutral, no more
    asha = notes(scheduler={"type": "asha"}, algorithms={"mappo": {"num_epochs": {"grid_search": [4, 16]}}})
    assert "note: the asha scheduler stops some trials early: an upper bound" in asha
    assert any("num_epochs change(s) how long a step takes" in n for n in asha)
    gpus = notes(resources={**grid_data(tmp_path)["resources"], "num_learners": 1, "num_gpus_per_learner": 1})
    assert "note: the wall-clock counts CPUs only; trials that reserve GPUs also wait for free GPUs" in gpus


# --------------------------------------------------------------------------- measurement
class _FakeAlgo:
    """train() results as RLlib reports them: 10 env steps, the learner timer once learning starts."""

    def __init__(self, learns_from: int):
        self.calls, self.learns_from, self.stopped = 0, learns_from, False

    def train(self) -> dict:
        self.calls += 1
        timers = {"env_runner_sampling_timer": 0.1}
        if self.calls >= self.learns_from:
            timers["learner_update_timer"] = 0.2
        return {"timers": timers, "env_runners": {"num_env_steps_sampled": 10}}

    def stop(self) -> None:
        self.stopped = True


class _FakeEntry:
    def __init__(self, algo):
        self.algo = algo

    def algorithm_config(self, scenario, hparams, resources, seed):
        return self

    def build_algo(self):
        return self.algo


class _Resources:
    torch_threads = None


@pytest.mark.parametrize("until_learning, learns_from, warmup", [(False, 3, 1), (True, 3, 3), (True, 1, 1)])
def test_measure_training_warms_up_then_times(until_learning, learns_from, warmup):
    algo = _FakeAlgo(learns_from)
    m = measure_training(
        _FakeEntry(algo), None, None, _Resources(), 0, 2, warmup_until_learning=until_learning, after=lambda a: a.calls
    )
    assert m.warmup_iterations == warmup and len(m.rows) == 2 and m.env_steps == 20
    assert m.after == warmup + 2 and algo.stopped
    assert m.learning_started == (warmup + 2 >= learns_from)
    assert m.env_steps_per_iteration == 10 and m.env_steps_per_s > 0


def test_cost_modules_import_neither_ray_nor_torch():
    code = (
        "import sys, uavlora_rllib.experiment.cost, uavlora_rllib.experiment.calibration; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'ray', 'torch'}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.strip() == "[]"


# --------------------------------------------------------------------------- for real
@pytest.mark.slow
def test_calibrate_a_tiny_grid_then_dry_run(tmp_path, calib_file, capsys):
    data = grid_data(
        tmp_path,
        algorithms={"mappo": {"batch_episodes": 4, "num_minibatches": 1, "num_epochs": 1}},
        resources={"num_env_runners": 0, "num_envs_per_env_runner": 2},
        stop={"env_steps": 1000},
        evaluation={"episodes": 2},
    )
    path = write_grid(tmp_path, data)
    assert tune_cli.main([path, "--calibrate", "--calibrate-iterations", "1"]) == 0
    out = capsys.readouterr().out
    records = json.loads(calib_file.read_text())["records"]
    assert sorted(r["kind"] for r in records.values()) == ["baseline", "train"]
    train = next(r for r in records.values() if r["kind"] == "train")
    assert train["env_steps_per_s"] > 0 and train["iterations"] == 1 and train["machine"] == calibration.this_machine()
    assert "grid: " in out and "CPU-hours" in out
    assert tune_cli.main([path, "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "grid: " in out and "wall-clock: about" in out and "not calibrated" not in out
