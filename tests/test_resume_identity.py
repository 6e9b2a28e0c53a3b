"""`--resume` of a changed grid (experiment.driver, tuner.grid_identity): Tune restores only the
trials an experiment started with, so the driver keeps what fixed them as tags of the grid run and
refuses a resume from another grid in one line, before it touches anything."""

from __future__ import annotations

import pytest

from tests.conftest import write_tiny_grid
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment.driver import _check_same_grid
from uavlora_rllib.experiment.grid import load_grid, trials
from uavlora_rllib.experiment.tuner import grid_identity

MAPPO = {"batch_episodes": 2, "num_epochs": 1, "num_minibatches": 1}


def _identity(tmp_path, name="g", **changes):
    kwargs = {"mappo": MAPPO, "episode_len": 8, "budget": 64, "seeds": (0,), **changes}
    grid = load_grid(write_tiny_grid(tmp_path, name, **kwargs))
    return grid, grid_identity(grid, trials(grid))


def _tags(identity):
    return {f"grid_{k}": v for k, v in identity.items()}


@pytest.mark.parametrize(
    "changes",
    [
        {"seeds": (0, 1)},
        {"budget": 128},
        {"mappo": {**MAPPO, "lr": 1e-3}},
        {"scenario": {"episode_len": 8, "action_mode": "per_device"}},
        {"evaluation": {"episodes": 3}},
        {"num_samples": 2, "mappo": {**MAPPO, "lr": {"loguniform": [1e-4, 1e-3]}}},
    ],
    ids=["seed", "budget", "hparam", "scenario", "eval", "sweep"],
)
def test_what_tune_fixed_changes_the_identity(tmp_path, changes):
    _, before = _identity(tmp_path)
    _, after = _identity(tmp_path, **changes)
    assert after["digest"] != before["digest"]


def test_what_resume_may_change_keeps_it(tmp_path):
    """Where the results go, how many trials run at once, checkpoints and baselines are the driver's
    settings now, not the trials'."""
    _, before = _identity(tmp_path)
    moved = tmp_path / "moved"
    moved.mkdir()
    _, after = _identity(
        moved, max_concurrent_trials=1, checkpoint_every=5, baselines=("random", "fixed"), failure={"max_failures": 2}
    )
    assert after == before


def test_a_changed_grid_is_refused_naming_what_changed(tmp_path):
    grid, started = _identity(tmp_path)
    _check_same_grid(_tags(started), _tags(started), grid)  # the same grid: resumed
    _check_same_grid({"kind": "grid"}, _tags(started), grid)  # started before the tags were kept: not checked
    grid2, now = _identity(tmp_path, seeds=(0, 1), budget=128)
    with pytest.raises(ConfigError) as exc:
        _check_same_grid(_tags(started), _tags(now), grid2)
    msg = str(exc.value)
    assert msg.startswith("--resume: this grid is not the one experiment 'g' started with")
    assert "trials 1 -> 2" in msg and "stop.env_steps 64 -> 128" in msg and "new `experiment` name" in msg
    _, lr = _identity(tmp_path, mappo={**MAPPO, "lr": 1e-3})
    with pytest.raises(
        ConfigError, match=r"started with \(the trials' settings: a hyperparameter \(a plugin's default too\)"
    ):
        _check_same_grid(_tags(started), _tags(lr), grid)
