"""The `uavlora` console command: the package's tools under one name (`uavlora tune GRID.yaml`).

    uavlora tune|evaluate|report|archive|animate|bench|bench_train [ARGS...]    (each: --help)
    uavlora --version

Each subcommand is the tool's own `main` (`python -m MODULE` keeps working, same arguments,
same exit codes: 0 done, 1 failed, 2 bad input). Nothing heavy is imported before a
subcommand is chosen, so `uavlora --help` and `uavlora tune --help` answer in about a second
(issue 25's target: under 2 s; `python -m uavlora_rllib.tune --help` imports neither Ray nor torch).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from uavlora_rllib import cli_args

PROG = "uavlora"
# subcommand -> (module whose main(argv) runs it, one-line description)
COMMANDS: dict[str, tuple[str, str]] = {
    "tune": ("uavlora_rllib.tune", "run a grid YAML with Ray Tune (trials, baselines, MLflow)"),
    "evaluate": ("uavlora_rllib.evaluate", "evaluate a baseline or a checkpoint on fresh episodes"),
    "report": ("analysis.report", "the paper's figures and tables from MLflow runs"),
    "archive": ("analysis.archive", "an experiment's MLflow runs to a file that can be committed, and back"),
    "animate": ("analysis.animate", "an episode as an animated GIF"),
    "bench": ("uavlora_rllib.bench", "simulator benchmarks"),
    "bench_train": ("uavlora_rllib.bench_train", "training throughput of any registered algorithm"),
}


def usage() -> str:
    width = max(map(len, COMMANDS))
    lines = [
        f"usage: {PROG} {{{','.join(COMMANDS)}}} [ARGS...] | --version",
        "",
        "Multi-agent RL for UAV-assisted LoRa networks on Ray RLlib.",
        "",
        "commands:",
    ]
    lines += [f"  {name:<{width}}  {what}  (python -m {module})" for name, (module, what) in COMMANDS.items()]
    lines += ["", f"{PROG} COMMAND --help shows a command's arguments."]
    return "\n".join(lines)


def version() -> str:
    """`uavlora --version`: the installed distribution's version (the package's own if not installed)."""
    from importlib import metadata

    try:
        return metadata.version("uavlora-rllib")
    except metadata.PackageNotFoundError:
        import uavlora_rllib

        return uavlora_rllib.__version__


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage(), file=sys.stdout if args else sys.stderr)
        return 0 if args else 2
    if args[0] == "--version":
        print(f"{PROG} {version()}")
        return 0
    name = args[0]
    if name not in COMMANDS:
        return cli_args.fail(f"command: unknown {name!r}; allowed: {', '.join(COMMANDS)} (or --version)", prog=PROG)
    module = COMMANDS[name][0]
    cli_args.PROG_ALIAS = (f"python -m {module}", f"{PROG} {name}")
    try:
        return int(importlib.import_module(module).main(args[1:]) or 0)
    finally:
        cli_args.PROG_ALIAS = None


if __name__ == "__main__":
    sys.exit(main())
