"""The README cannot rot: every command it shows is checked here.

Each `python -m MODULE ...` line of README.md (code blocks and inline code) is parsed. Its module
must exist and every `--flag` it uses must appear in that CLI's `--help`. The commands that are
cheap are then run for real in a subprocess, with small arguments where the README's would take
minutes (fewer episodes or steps), and must exit 0. The rest (a whole grid, a cluster, a
checkpoint path with placeholders) are covered by the flag check here and run end to end by
tests/test_tune.py, tests/test_cluster.py and tests/test_algorithm_matrix.py. `make` targets the
README names must exist in the Makefile.
"""

from __future__ import annotations

import functools
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def _code(text: str) -> list[str]:
    """The README's code: each line of a fenced block (a backslash continuation joined, a trailing
    `# comment` dropped) and each inline code span read whole (a span may wrap a line)."""
    fenced = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.M | re.S)
    lines = [
        " ".join(re.split(r"\s#", line)[0].split())
        for block in fenced
        for line in block.replace("\\\n", " ").splitlines()
    ]
    prose = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.M | re.S)
    spans = [" ".join(span.split()) for span in re.findall(r"`([^`]+)`", prose)]
    return [c for c in lines + spans if c]


def _commands(text: str) -> set[str]:
    """Every `python -m ...` of the README's code, from `python` on (also after `ray job submit --`)."""
    return {c[c.index("python -m ") :] for c in _code(text) if "python -m " in c and "<name>" not in c}


def _make_targets(text: str) -> set[str]:
    return {m.group(1) for c in _code(text) if (m := re.match(r"make ([\w-]+)", c))}


COMMANDS = sorted(_commands(README))
MAKE_TARGETS = sorted(_make_targets(README))
ENV = {**os.environ, "PYTHONWARNINGS": "ignore", "RAY_ADDRESS": "local"}


def _argv(command: str) -> list[str]:
    argv = shlex.split(command)
    assert argv[:2] == ["python", "-m"], command
    return argv[2:]


@functools.cache
def _help(module: str, sub: str | None) -> str:
    argv = [sys.executable, "-m", module] + ([sub] if sub else []) + ["--help"]
    proc = subprocess.run(argv, capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=180)
    assert proc.returncode == 0, f"{' '.join(argv[1:])}: exit {proc.returncode}\n{proc.stderr[-2000:]}"
    return proc.stdout


def test_a_wrapped_inline_command_is_read_whole():
    text = (
        "Try (`python -m m --a\n  1 --b`, `ray job submit -- python -m n`), `make\ntest-slow`, then\n"
        "```bash\npython -m m --c 2   # a comment naming python -m x\nray job submit -- python -m m \\\n  --d 3\n"
        "make demo  # note\n```\n"
    )
    assert _commands(text) == {"python -m m --a 1 --b", "python -m n", "python -m m --c 2", "python -m m --d 3"}
    assert _make_targets(text) == {"test-slow", "demo"}


def test_the_readme_shows_commands():
    modules = {_argv(c)[0] for c in COMMANDS}
    # the entry points the README promises (a regex that stopped matching would pass vacuously)
    assert {
        "uavlora_rllib.tune",
        "uavlora_rllib.evaluate",
        "analysis.report",
        "analysis.animate",
        "analysis.archive",
        "uavlora_rllib.bench",
        "uavlora_rllib.bench_train",
    } <= modules
    assert {"demo", "test"} <= set(MAKE_TARGETS)


@pytest.mark.parametrize("target", MAKE_TARGETS)
def test_make_targets_exist(target):
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert re.search(rf"^{target}:", makefile, re.M), f"README names `make {target}`, the Makefile has no such target"


@pytest.mark.parametrize("command", COMMANDS)
def test_every_flag_is_accepted(command):
    argv = _argv(command)
    module, rest = argv[0], argv[1:]
    with_subcommands = ("uavlora_rllib.bench", "analysis.archive")
    sub = rest[0] if module in with_subcommands and rest and not rest[0].startswith("-") else None
    text = _help(module, sub)
    for flag in (a.split("=")[0] for a in rest if a.startswith("--")):
        assert re.search(rf"(^|[\s\[,]){re.escape(flag)}\b", text), f"{command}: {flag} is not in `{module} --help`"


def _small(command: str, tmp: Path) -> list[str] | None:
    """The command with small arguments, or None where it is not cheap to run here."""
    argv = _argv(command)
    module, rest = argv[0], argv[1:]
    if "<" in command or "--address" in rest or "--resume" in rest:
        return None  # placeholders, a cluster, or an experiment that must exist first
    if module == "uavlora_rllib.tune":
        if "--list-hparams" in rest:
            return argv
        if "--dry-run" in rest:  # the grid path is relative to the repository
            return [module] + [str(ROOT / a) if a.endswith(".yaml") else a for a in rest]
        return None  # a whole grid: test_tune.py runs a tiny one end to end
    if module == "uavlora_rllib.evaluate":
        return argv + ["--episodes", "2"]  # argparse: the last --episodes wins
    if module == "analysis.animate":
        return [a if a != "ep.gif" else str(tmp / "ep.gif") for a in argv] + ["--steps", "3"]
    if module == "uavlora_rllib.bench":
        return argv + ["--quick", "--repeats", "1"]
    if module == "uavlora_rllib.bench_train":
        return argv + ["--iterations", "1", "--envs-per-runner", "2", "--episode-len", "10", "--num-cpus", "1"]
    return None  # analysis.report needs an experiment: tests/test_analysis*.py run it on stores


RUNNABLE = [c for c in COMMANDS if _small(c, Path("/tmp")) is not None]


@pytest.mark.slow
@pytest.mark.parametrize("command", RUNNABLE)
def test_cheap_commands_run(command, tmp_path):
    argv = _small(command, tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", *argv], capture_output=True, text=True, env=ENV, cwd=tmp_path, timeout=600
    )
    assert proc.returncode == 0, f"{' '.join(argv)}: exit {proc.returncode}\n{proc.stderr[-3000:]}"
    if argv[0] == "analysis.animate":
        assert (tmp_path / "ep.gif").stat().st_size > 0


def test_some_commands_run_for_real():
    """The cheap set is not empty (the README keeps showing runnable commands)."""
    runnable = {_argv(c)[0] for c in RUNNABLE}
    assert {"uavlora_rllib.tune", "uavlora_rllib.evaluate", "analysis.animate"} <= runnable
