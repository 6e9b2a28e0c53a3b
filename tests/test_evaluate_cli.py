"""The evaluate CLI: JSON output, table output, and one-line errors with exit code 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from uavlora_rllib.evaluate import main

KEYS = (
    "ee_sys_mean",
    "ee_sys_episode_sum",
    "success_rate",
    "mean_sinr_db",
    "unassociated_frac",
    "p_total_w",
    "reward_mean",
)


def _check_json(text: str, episodes: int) -> dict:
    out = json.loads(text)
    for k in KEYS:
        assert isinstance(out[k], float), k
        assert isinstance(out["ci95"][k], float), k
    assert out["episodes"] == episodes
    return out


def test_json_in_process(capsys, tmp_path):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("scenario:\n  episode_len: 5\n  n_eds: 6\n")
    assert (
        main(["--policy", "greedy", "--episodes", "2", "--seed", "1", "--json", "--scenario-yaml", str(yaml_file)]) == 0
    )
    out = _check_json(capsys.readouterr().out, 2)
    assert out["ee_sys_mean"] > 0 and 0.0 <= out["success_rate"] <= 1.0
    assert out["ee_sys_episode_sum"] == pytest.approx(5 * out["ee_sys_mean"])


def test_references_print_the_upper_bound_and_best_fixed_runs(capsys, tmp_path):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("episode_len: 4\nn_eds: 5\naction_mode: per_device\n")
    assert main(["--policy", "greedy", "--episodes", "2", "--json", "--scenario-yaml", str(yaml_file)]) == 0
    out = _check_json(capsys.readouterr().out, 2)
    assert out["ee_sys_upper_bound"] >= out["ee_sys_mean"] > 0
    assert main(["--policy", "greedy", "--episodes", "2", "--scenario-yaml", str(yaml_file)]) == 0
    assert "EE_sys upper bound" in capsys.readouterr().out
    assert main(["--policy", "best_fixed", "--episodes", "2", "--json", "--scenario-yaml", str(yaml_file)]) == 0
    out = _check_json(capsys.readouterr().out, 2)
    assert out["ee_sys_mean"] > 0 and "ee_sys_upper_bound" not in out


def test_table_in_process(capsys, tmp_path):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("episode_len: 3\n")
    assert (
        main(
            ["--policy", "fixed", "--n-eds", "4", "--n-uavs", "1", "--episodes", "2", "--scenario-yaml", str(yaml_file)]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "V=4 U=1 T=3" in text
    assert "off the paper's defaults" not in text  # only T changed, and the header shows it
    yaml_file.write_text("episode_len: 3\nrate_model: lora_phy\nreward: {w1: 0.1}\n")
    assert (
        main(
            ["--policy", "fixed", "--n-eds", "4", "--n-uavs", "1", "--episodes", "1", "--scenario-yaml", str(yaml_file)]
        )
        == 0
    )
    assert "scenario off the paper's defaults: rate_model=lora_phy, reward.w1=0.1\n" in capsys.readouterr().out
    for label in (
        "EE_sys per slot",
        "success rate Xi",
        "mean SINR",
        "unassociated fraction",
        "P_total",
        "reward per slot",
    ):
        assert label in text


@pytest.mark.parametrize(
    "argv, field",
    [
        (["--policy", "fixed", "--n-eds", "0"], "--n-eds"),
        (["--policy", "fixed", "--n-uavs", "-1"], "--n-uavs"),
        (["--policy", "fixed", "--episodes", "x"], "--episodes"),
        (["--policy", "nope"], "--policy"),
        (["--policy", "/no/such/checkpoint/dir"], "--policy"),
        (["--policy", "optimal", "--n-uavs", "4"], "n_uavs"),
        (["--policy", "greedy", "--objective", "bits"], "--objective"),
        (["--policy", "fixed", "--scenario-yaml", "/no/such.yaml"], "--scenario-yaml"),
        ([], "--policy"),
        (["--policy", "fixed", "--seed", "-1"], "--seed: must be an integer in [0, 4294967295], got -1"),
        (["--policy", "fixed", "--seed", str(2**32)], "--seed: must be an integer in [0, 4294967295]"),
        (["--policy", "fixed", "--seed", "1.5"], "--seed: expected an integer"),
        (["--policy", "fixed", "--episodes", "0"], "--episodes: must be an integer in [1, 1000000], got 0"),
        (["--policy", "fixed", "--execution", "sampled"], "--execution: 'sampled' applies to a checkpoint"),
        (["--policy", "fixed", "--execution", "argmax"], "--execution"),
        (["--policy", "random", "--objective", "reward"], "--objective: applies to the greedy and optimal baselines"),
        (["--policy", "fixed", "--scenario-yaml", "/tmp"], "--scenario-yaml: /tmp is a directory"),
    ],
)
def test_bad_args_exit_2_with_field_name(capsys, argv, field):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert field in err
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_bad_yaml_field(capsys, tmp_path):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("n_edz: 5\n")
    assert main(["--policy", "fixed", "--scenario-yaml", str(yaml_file)]) == 2
    assert "scenario.n_edz" in capsys.readouterr().err


def test_a_grid_yaml_gives_its_scenario_and_names_what_is_ignored(capsys, tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text("experiment: x\nn_eds: [40]\nscenario: {episode_len: 3}\n")
    assert main(["--policy", "fixed", "--scenario-yaml", str(grid), "--episodes", "1", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "ignored: experiment, n_eds (V and U: --n-eds / --n-uavs)" in err
    summary = json.loads(out)
    assert round(summary["ee_sys_episode_sum"] / summary["ee_sys_mean"]) == 3  # its scenario's 3 slots were played


def test_subprocess_json_and_error():
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    ok = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.evaluate", "--policy", "adr", "--episodes", "2", "--json"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert ok.returncode == 0, ok.stderr
    _check_json(ok.stdout, 2)
    bad = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.evaluate", "--policy", "random", "--n-eds", "0"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert bad.returncode == 2
    assert "--n-eds" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize(
    "content, message",
    [
        (
            b"episode_len: 3\nepisode_len: 4\n",
            "line 2, column 1: YAML error: duplicate key 'episode_len' (first given on line 1)",
        ),
        (b"episode_len: 3\n# \xff\n", "the scenario file is not UTF-8 text (byte 0xff at offset 17)"),
        (b"episode_len: true\n", "scenario.episode_len: expected an integer in [1, 1e+06], got True (bool)"),
        (b"noise_dbm: .nan\n", "scenario.noise_dbm: expected a finite number in [-200, 30], got nan"),
    ],
)
def test_bad_scenario_yaml_is_one_line(capsys, tmp_path, content, message):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_bytes(content)
    assert main(["--policy", "fixed", "--scenario-yaml", str(yaml_file)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evaluate: error: ") and err.count("\n") == 1 and message in err, err


def test_actions_outside_the_space_are_one_line(capsys, monkeypatch):
    """A policy whose actions do not fit the scenario (sim.actions.ActionError) is an input error."""
    import uavlora_rllib.evaluate as evaluate_cli
    from uavlora_rllib.sim.scenario import ScenarioConfig

    class Oversized:
        name = "oversized"

        def reset(self, core):
            pass

        def act(self, core):
            return np.full((core.n, core.cfg.n_uavs), 90, dtype=np.int64)  # 90 actions with sf_set [7]: 0..14

    cfg = ScenarioConfig(sf_set=(7,), episode_len=2)
    monkeypatch.setattr(evaluate_cli, "_resolve", lambda args: (Oversized(), cfg))
    assert main(["--policy", "fixed"]) == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("evaluate: error: --policy: its actions do not fit this scenario: ") and err.count("\n") == 1
    ), err


def test_cost_estimate_grows_with_the_search():
    from uavlora_rllib.baselines.policies import evaluation_seconds
    from uavlora_rllib.evaluate import LONG_SECONDS
    from uavlora_rllib.sim.scenario import ScenarioConfig

    u2, u3 = ScenarioConfig(n_uavs=2), ScenarioConfig(n_uavs=3)
    assert evaluation_seconds("optimal", u3, 10) == pytest.approx(90 * evaluation_seconds("optimal", u2, 10), rel=1e-3)
    assert evaluation_seconds("optimal", u3, 10) > 60 * LONG_SECONDS  # the case: many minutes
    assert evaluation_seconds("optimal", ScenarioConfig(n_uavs=1), 10) < LONG_SECONDS  # quick: no bar
    assert evaluation_seconds("random", u2, 100_000) > LONG_SECONDS  # many episodes of a cheap policy
    assert evaluation_seconds("greedy", u3, 10) < evaluation_seconds("optimal", u3, 10)
    pd = ScenarioConfig(n_eds=3, n_uavs=1, action_mode="per_device")
    assert evaluation_seconds("optimal", pd, 10) > evaluation_seconds("greedy", pd, 10)
    assert evaluation_seconds("best_fixed", ScenarioConfig(n_uavs=2), 10) > evaluation_seconds("fixed", u2, 10)


def test_long_evaluation_prints_estimate_and_progress_same_numbers(capsys, monkeypatch):
    """Past LONG_SECONDS the CLI prints its estimate, then a progress bar that reaches every
    episode-slot, on stderr; the metrics are those of the quiet run (the bar only watches)."""
    import uavlora_rllib.evaluate as evaluate_cli

    argv = ["--policy", "greedy", "--n-eds", "5", "--episodes", "3", "--json", "--seed", "4"]
    assert main(argv) == 0
    quiet = capsys.readouterr()
    assert quiet.err == ""
    monkeypatch.setattr(evaluate_cli, "LONG_SECONDS", 0.0)
    assert main(argv) == 0
    loud = capsys.readouterr()
    assert json.loads(loud.out) == json.loads(quiet.out)
    first = loud.err.splitlines()[0]
    assert first.startswith("evaluate: greedy on 3 episodes x 150 slots, V=5 U=2: estimated ~"), first
    assert "450/450" in loud.err  # 3 episodes x 150 slots, all counted


def test_checkpoint_fit_check():
    from uavlora_rllib.evaluate import checkpoint_fit_problem
    from uavlora_rllib.sim.scenario import ScenarioConfig

    trained = ScenarioConfig(n_eds=10, n_uavs=2, max_eds_per_uav=8)
    assert checkpoint_fit_problem(trained, trained) is None
    # V may change at a fixed quota (Fig. 3b evaluates across V); so may the channel and rewards
    assert checkpoint_fit_problem(trained, trained.replace(n_eds=40, noise_dbm=-110.0, reward={"w1": 1.0})) is None
    for change, field in [
        ({"sf_set": [7]}, "sf_set"),
        ({"n_uavs": 3}, "n_uavs"),
        ({"max_eds_per_uav": 9}, "max_eds_per_uav"),
    ]:
        problem = checkpoint_fit_problem(trained, trained.replace(**change))
        assert problem and "was trained for 2 UAVs" in problem and field in problem.split("differ: ")[1], problem
    # a quota derived from V (ceil(1.5 V / U): 8 at V=10, 15 at V=20) is named, with how to keep it
    derived = ScenarioConfig(n_eds=10, n_uavs=2)
    problem = checkpoint_fit_problem(derived, derived.replace(n_eds=20))
    assert problem and "moved 8 -> 15: keep it by setting max_eds_per_uav: 8 in the scenario" in problem, problem
    # ... but not where the UAVs changed too, which no quota setting can undo
    problem = checkpoint_fit_problem(derived, derived.replace(n_uavs=3))
    assert problem and "was trained for 2 UAVs" in problem and "keep it by setting" not in problem, problem


def test_a_trials_plugins_are_imported_before_its_checkpoint(tmp_path, monkeypatch):
    """A grid trial's checkpoint of a plugin algorithm restores only with the plugin's module
    imported: evaluate imports the modules its trial listed (params.json beside the checkpoint),
    and a module it cannot import is one line naming it, before Ray starts."""
    import json
    import sys

    from uavlora_rllib.config_errors import ConfigError
    from uavlora_rllib.evaluate import _import_trial_plugins

    checkpoint = tmp_path / "trial" / "checkpoint_000001"
    checkpoint.mkdir(parents=True)
    params = tmp_path / "trial" / "params.json"
    params.write_text(json.dumps({"trial": {"algorithm": "stock_ppo", "plugins": ["tune_stock_ppo"]}}))
    monkeypatch.syspath_prepend(os.path.dirname(os.path.abspath(__file__)))
    monkeypatch.delitem(sys.modules, "tune_stock_ppo", raising=False)
    _import_trial_plugins(str(checkpoint))
    assert "tune_stock_ppo" in sys.modules
    params.write_text(json.dumps({"trial": {"algorithm": "mine", "plugins": ["no_such_plugin_xyz"]}}))
    with pytest.raises(
        ConfigError, match=r"plugins \(in .*params.json\)\.0: cannot import module 'no_such_plugin_xyz'"
    ):
        _import_trial_plugins(str(checkpoint))
    _import_trial_plugins(str(tmp_path / "elsewhere" / "checkpoint"))  # no trial config: nothing to import


@pytest.mark.slow
def test_checkpoint_on_a_scenario_it_was_not_trained_for(ray_session, tmp_path, capsys):
    """A real checkpoint: evaluating it on its own scenario works; on one whose spaces differ
    (sf_set [7], another U) it is one line and exit 2, before any episode runs."""
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.sim.scenario import ScenarioConfig

    entry = registry.get("mappo")
    cfg = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=4)
    hp = entry.hparams({"num_epochs": 1, "num_minibatches": 1, "batch_episodes": 2, "max_seq_len": 4, "gru_hidden": 8})
    algo = entry.build(cfg, hp, registry.Resources(num_envs_per_env_runner=2), 0).build_algo()
    ckpt = str(tmp_path / "ckpt")
    try:  # the shared Ray outlives this test: the algorithm's actors must not
        algo.train()
        algo.save_to_path(ckpt)
    finally:
        algo.stop()
    assert main(["--policy", ckpt, "--episodes", "1", "--json"]) == 0
    capsys.readouterr()
    (tmp_path / "s.yaml").write_text("sf_set: [7]\n")
    for extra, field in [(["--scenario-yaml", str(tmp_path / "s.yaml")], "sf_set"), (["--n-uavs", "3"], "n_uavs")]:
        assert main(["--policy", ckpt, "--episodes", "1", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("evaluate: error: --policy: the checkpoint at") and err.count("\n") == 1, err
        assert field in err.split("differ: ")[1], err


def test_directory_that_is_not_a_checkpoint(capsys, tmp_path):
    assert main(["--policy", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert (
        err == f"evaluate: error: --policy: {str(tmp_path)!r} is not an RLlib checkpoint (no rllib_checkpoint.json)\n"
    )
    for name in ("checkpoint_000002", "checkpoint_000010"):  # a Tune trial directory
        (tmp_path / name).mkdir()
    assert main(["--policy", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.rstrip().endswith(f"the latest is {tmp_path / 'checkpoint_000010'}"), err
