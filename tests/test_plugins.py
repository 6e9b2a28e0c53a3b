"""An algorithm kept outside the package (README "Add an algorithm"): a module listed under a grid's
`plugins:` that declares and registers it under a name of its own, with nothing added to the
package's MODULES; and each mistake in such a module is one line naming it, exit code 2."""

from __future__ import annotations

import textwrap

import pytest
import yaml
from conftest import run_tune as _cli

# a plugin the README's way: tests/tune_stock_ppo.py's builder under a name of its own
REGISTERED = """
    from tune_stock_ppo import _entry
    from uavlora_rllib.algorithms.common import registry

    registry.register(_entry("{name}"))
"""
HPARAMS = """
    from pydantic import Field
    from pydantic.dataclasses import dataclass
    from uavlora_rllib.algorithms.common import registry

    @dataclass(config={{"extra": "forbid", "frozen": True}})
    class H:
        delta: float = Field({default}gt=0.0, description="a positive number [1]")

    registry.declare("{name}", H, {modes})
"""


def _plugin(tmp_path, monkeypatch, module: str, body: str) -> None:
    (tmp_path / f"{module}.py").write_text(textwrap.dedent(body))
    monkeypatch.syspath_prepend(str(tmp_path))


def _grid(tmp_path, plugin: str, algorithm: str) -> str:
    grid = {
        "experiment": "plug",
        "plugins": [plugin],
        "algorithms": {algorithm: None},
        "baselines": [],
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "stop": {"env_steps": 300},
        "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
        "storage": str(tmp_path / "ray_results"),
    }
    path = tmp_path / "grid.yaml"
    path.write_text(yaml.safe_dump(grid, sort_keys=False))
    return str(path)


def test_a_registered_plugin_algorithm_is_accepted_and_listed(tmp_path, monkeypatch, capsys):
    _plugin(tmp_path, monkeypatch, "plug_registered", REGISTERED.format(name="my_ppo"))
    grid = _grid(tmp_path, "plug_registered", "my_ppo")
    rc, out, err = _cli([grid, "--dry-run"], capsys)
    assert rc == 0, err
    assert "my_ppo" in out
    rc, out, err = _cli([grid, "--list-hparams", "my_ppo"], capsys)  # the grid's plugins make it listable
    assert rc == 0 and "my_ppo: hyperparameters" in out and "train_batch_size" in out, err


@pytest.mark.parametrize(
    "name, default, modes, message",
    [
        ("only_declared", "1.0, ", '("per_uav",)', "algorithms.only_declared: algorithm 'only_declared' is declared"),
        ("bad_modes", "1.0, ", '"per_uav"', "action_modes must be a non-empty tuple of ['per_uav', 'per_device']"),
        ("typo_modes", "1.0, ", '("per_ued",)', "got ('per_ued',)"),
        ("bad_default", "-1.0, ", '("per_uav",)', "algorithm 'bad_default'.delta: Input should be greater than 0"),
        ("mappo", "1.0, ", '("per_uav",)', "algorithm 'mappo' is built in; a plugin takes another name"),
        ("no_default", "", '("per_uav",)', "every hyperparameter needs a default; none for delta"),
    ],
)
def test_a_plugin_mistake_is_one_line(tmp_path, monkeypatch, capsys, name, default, modes, message):
    """Declared but never registered (it would pass a dry run and fail in every trial), action modes that
    are not a tuple of modes, a default outside its own constraint, a built-in's name."""
    module = f"plug_{name}"
    _plugin(tmp_path, monkeypatch, module, HPARAMS.format(name=name, default=default, modes=modes))
    rc, out, err = _cli([_grid(tmp_path, module, name), "--dry-run"], capsys)
    assert rc == 2 and out == "" and err.startswith("error: ") and err.count("\n") == 1, err
    assert message in err, err


REPLACING = """
    import dataclasses

    from pydantic.dataclasses import dataclass
    from tune_stock_ppo import StockPPOHparams, _entry
    from uavlora_rllib.algorithms.common import registry

    @dataclass(config={"extra": "forbid", "frozen": True})
    class Other(StockPPOHparams):
        pass

    registry.register(dataclasses.replace(_entry("stock_ppo"), hparams_cls=Other))
"""


def test_a_plugin_cannot_replace_a_registered_algorithm(tmp_path, monkeypatch, capsys):
    _plugin(tmp_path, monkeypatch, "plug_twice", REPLACING)
    grid = _grid(tmp_path, "plug_twice", "stock_ppo")
    data = yaml.safe_load(open(grid))
    data["plugins"] = ["tune_stock_ppo", "plug_twice"]  # stock_ppo registered first, then another class
    open(grid, "w").write(yaml.safe_dump(data))
    rc, _, err = _cli([grid, "--dry-run"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "algorithm 'stock_ppo' is already taken by tune_stock_ppo" in err, err


def test_a_closed_pipe_is_not_blamed_on_the_cluster(tmp_path):
    """`--dry-run | head -1`: the reader closed stdout; no error line, no traceback, the shell's 141."""
    import os
    import subprocess
    import sys

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.run(
        f"{sys.executable} -m uavlora_rllib.tune tune_configs/paper_fig3b.yaml --dry-run | head -c 1 >/dev/null; "
        'echo "${PIPESTATUS[0]}" >&2',
        shell=True,
        executable="/bin/bash",
        cwd=repo,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.stderr.strip().splitlines()[-1] == "141", proc.stderr
    assert "error" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr


BASELINE = """
    from uavlora_rllib.baselines.policies import FixedPolicy, register_baseline

    def smallest_sf(scenario, seed):
        return FixedPolicy(scenario)

    register_baseline("{name}", smallest_sf)
"""


def test_a_plugin_baseline_runs_in_a_grid_and_in_evaluate(tmp_path, monkeypatch, capsys):
    """README "Add a baseline": registered by a plugin module, it is a grid baseline (its Ray task imports the
    grid's plugins on whatever node it runs) and an `evaluate --plugin` policy."""
    import sys

    from uavlora_rllib import evaluate
    from uavlora_rllib.baselines import policies
    from uavlora_rllib.experiment.baseline_tasks import evaluate_baseline
    from uavlora_rllib.experiment.grid import baseline_runs, load_grid

    _plugin(tmp_path, monkeypatch, "plug_baseline", BASELINE.format(name="my_fixed"))
    grid = _grid(tmp_path, "plug_baseline", "mappo")
    data = yaml.safe_load(open(grid))
    data["baselines"] = ["my_fixed", "fixed"]
    data["scenario"] = {"episode_len": 5}
    open(grid, "w").write(yaml.safe_dump(data))
    rc, out, err = _cli([grid, "--dry-run"], capsys)
    assert rc == 0 and "my_fixed" in out, err
    spec = next(s for s in baseline_runs(load_grid(grid)) if s.baseline == "my_fixed")
    assert spec.plugins == ("plug_baseline",)
    policies._PLUGIN_BASELINES.pop("my_fixed")  # as in a fresh worker process
    sys.modules.pop("plug_baseline")
    ours = evaluate_baseline(spec, 1)
    fixed = evaluate_baseline(next(s for s in baseline_runs(load_grid(grid)) if s.baseline == "fixed"), 1)
    assert ours["ee_sys_mean"] == pytest.approx(fixed["ee_sys_mean"])  # the same policy under its own name
    argv = ["--plugin", "plug_baseline", "--policy", "my_fixed", "--n-eds", "6", "--episodes", "1", "--json"]
    assert evaluate.main(argv) == 0
    assert evaluate.main(["--policy", "no_such_baseline", "--episodes", "1"]) == 2
    assert "neither a baseline (random, fixed, adr, best_fixed, greedy, optimal, my_fixed)" in capsys.readouterr().err


def test_a_plugin_baseline_cannot_take_a_built_in_name(tmp_path, monkeypatch, capsys):
    _plugin(tmp_path, monkeypatch, "plug_greedy", BASELINE.format(name="greedy"))
    rc, _, err = _cli([_grid(tmp_path, "plug_greedy", "mappo"), "--dry-run"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "baseline 'greedy' is built in; a plugin takes another name" in err


SUBCLASSED = """
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.algorithms.mappo.mappo import MAPPOConfig

    class MyMAPPO(MAPPOConfig):  # the README's own pattern, under a built-in's name
        pass

    registry.register_algorithm("mappo", MyMAPPO)
"""


def test_a_plugin_cannot_take_a_built_ins_name_with_its_classes(tmp_path, monkeypatch, capsys):
    """Reusing the built-in's hyperparameter class (through a config subclass) is still another algorithm."""
    _plugin(tmp_path, monkeypatch, "plug_mymappo", SUBCLASSED)
    rc, _, err = _cli([_grid(tmp_path, "plug_mymappo", "mappo"), "--dry-run"], capsys)
    assert rc == 2 and err.count("\n") == 1 and "algorithm 'mappo' is built in; a plugin takes another name" in err


def test_a_plugin_baselines_error_is_one_line(tmp_path, monkeypatch, capsys):
    _plugin(
        tmp_path,
        monkeypatch,
        "plug_bad_baseline",
        """
        from uavlora_rllib.baselines.policies import register_baseline

        def build(scenario, seed):
            raise ValueError("plays per_device scenarios only")

        register_baseline("picky", build)
        """,
    )
    grid = _grid(tmp_path, "plug_bad_baseline", "mappo")
    data = yaml.safe_load(open(grid))
    data["baselines"] = ["picky"]
    open(grid, "w").write(yaml.safe_dump(data))
    rc, _, err = _cli([grid, "--dry-run"], capsys)
    assert rc == 2 and err.count("\n") == 1, err
    assert "baseline 'picky' (a plugin's): ValueError: plays per_device scenarios only" in err


def test_a_broken_pipe_that_is_not_stdout_is_an_error(tmp_path, monkeypatch, capsys):
    from uavlora_rllib import tune as tune_cli

    def broken(path):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(tune_cli, "load_grid", broken)
    rc, out, err = _cli([_grid(tmp_path, "plug_registered", "mappo"), "--dry-run"], capsys)
    assert rc == 2 and err.startswith("error: broken pipe:") and err.count("\n") == 1, err
