"""The evaluate CLI: JSON output, table output, and one-line errors with exit code 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from uavlora_rllib.evaluate import main

KEYS = ("ee_sys_mean", "ee_sys_episode_sum", "success_rate", "mean_sinr_db", "unassociated_frac", "p_total_w", "reward_mean")


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
    assert main(["--policy", "greedy", "--episodes", "2", "--seed", "1", "--json", "--scenario-yaml", str(yaml_file)]) == 0
    out = _check_json(capsys.readouterr().out, 2)
    assert out["ee_sys_mean"] > 0 and 0.0 <= out["success_rate"] <= 1.0
    assert out["ee_sys_episode_sum"] == pytest.approx(5 * out["ee_sys_mean"])


def test_table_in_process(capsys, tmp_path):
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("episode_len: 3\n")
    assert main(["--policy", "fixed", "--n-eds", "4", "--n-uavs", "1", "--episodes", "2", "--scenario-yaml", str(yaml_file)]) == 0
    text = capsys.readouterr().out
    assert "V=4 U=1 T=3" in text
    for label in ("EE_sys per slot", "success rate Xi", "mean SINR", "unassociated fraction", "P_total", "reward per slot"):
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


def test_subprocess_json_and_error():
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    ok = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.evaluate", "--policy", "adr", "--episodes", "2", "--json"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert ok.returncode == 0, ok.stderr
    _check_json(ok.stdout, 2)
    bad = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.evaluate", "--policy", "random", "--n-eds", "0"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert bad.returncode == 2
    assert "--n-eds" in bad.stderr and "Traceback" not in bad.stderr
