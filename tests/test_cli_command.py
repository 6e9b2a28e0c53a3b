"""The `uavlora` console command and the quick paths of the CLIs: `--help` imports neither Ray
nor torch (issue 25 item 5), subcommands are the tools' own mains, `--version` is the
installed version, bad input is one line and exit code 2."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

import uavlora_rllib
from uavlora_rllib import cli

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONWARNINGS": "ignore"}
HEAVY = ("ray", "torch")


def _imported(argv: list[str]) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run `python -X importtime ARGV`; the top-level packages it imported."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", *argv], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=300
    )
    names = set(re.findall(r"^import time:\s+\d+ \|\s+\d+ \|\s*([\w.]+)", proc.stderr, re.M))
    return proc, {n.split(".")[0] for n in names}


@pytest.mark.parametrize(
    "argv",
    [
        ["-m", "uavlora_rllib.tune", "--help"],
        ["-m", "uavlora_rllib", "--help"],
        ["-m", "uavlora_rllib", "tune", "--help"],
        ["-m", "uavlora_rllib", "--version"],
        # issue 25: the typed configs live in modules without RLlib (registry.spec)
        ["-m", "uavlora_rllib.tune", "--list-hparams", "coma"],
        ["-m", "uavlora_rllib.tune", "tune_configs/learning_per_device_10x2_lora_phy.yaml", "--dry-run"],
    ],
    ids=["tune", "uavlora", "uavlora-tune", "version", "list-hparams", "dry-run-all-five"],
)
def test_help_imports_neither_ray_nor_torch(argv):
    proc, packages = _imported(argv)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "uavlora_rllib" in packages  # the import log was read
    assert not packages & set(HEAVY), sorted(packages & set(HEAVY))
    if argv[-1] == "--help" and "tune" in " ".join(argv):
        assert "--dry-run" in proc.stdout and "--list-hparams" in proc.stdout


def test_tune_module_keeps_the_trainable_name():
    """Old references (pickled Tune state, scripts) still find `uavlora_rllib.tune.UavLoraTrainable`."""
    from uavlora_rllib import tune
    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    assert tune.UavLoraTrainable is UavLoraTrainable
    with pytest.raises(AttributeError):
        tune.NoSuchName  # noqa: B018


def test_console_script_is_declared():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]["scripts"]
    assert scripts == {"uavlora": "uavlora_rllib.cli:main"}


def test_version_is_the_installed_one(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out == f"uavlora {metadata.version('uavlora-rllib')}\n"
    assert metadata.version("uavlora-rllib") == uavlora_rllib.__version__


def test_installed_console_script_runs():
    """The script pip wrote next to this interpreter (absent in a venv installed before it was declared)."""
    script = Path(sys.executable).with_name("uavlora")
    if not script.exists():
        pytest.skip(f"{script} not installed: rerun `make install`")
    proc = subprocess.run([str(script), "--version"], capture_output=True, text=True, env=ENV, timeout=120)
    assert proc.returncode == 0 and proc.stdout.startswith("uavlora "), proc.stderr


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_each_command_is_the_tools_own_cli(name, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main([name, "--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: uavlora {name}")
    # python -m keeps its own name
    from uavlora_rllib import cli_args

    assert cli_args.PROG_ALIAS is None
    module = __import__(cli.COMMANDS[name][0], fromlist=["build_parser"])
    assert module.build_parser().prog == f"python -m {cli.COMMANDS[name][0]}"


def test_subcommand_exit_codes_pass_through(capsys):
    assert cli.main(["tune", "--list-hparams", "no_such_algo"]) == 2
    assert "--list-hparams: unknown algorithm 'no_such_algo'" in capsys.readouterr().err


@pytest.mark.parametrize("argv, code", [(["tun"], 2), ([], 2), (["--help"], 0)])
def test_usage_and_unknown_commands(argv, code, capsys):
    assert cli.main(argv) == code
    captured = capsys.readouterr()
    if argv == ["tun"]:
        err = captured.err.strip()
        assert "\n" not in err
        assert (
            err
            == "uavlora: error: command: unknown 'tun'; allowed: tune, evaluate, report, archive, animate, bench, bench_train (or --version)"
        )
    else:
        text = captured.out or captured.err
        assert text.startswith("usage: uavlora") and all(n in text for n in cli.COMMANDS)


def test_readme_uavlora_lines_run():
    """Each `uavlora ...` command line in README.md names a subcommand and exits 0."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    lines = re.findall(r"^uavlora ([^#\n]+)", readme, re.M)
    assert lines, "the README shows the console command"
    for line in lines:
        argv = line.split()
        assert argv[0] in cli.COMMANDS or argv[0] in ("--help", "--version"), line
        proc = subprocess.run(
            [sys.executable, "-m", "uavlora_rllib", *argv],
            capture_output=True,
            text=True,
            env=ENV,
            cwd=ROOT,
            timeout=300,
        )
        assert proc.returncode == 0, f"uavlora {line}: {proc.stderr[-2000:]}"
