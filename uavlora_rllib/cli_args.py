"""Shared pieces of the command-line tools: one-line usage errors and typed argument parsers."""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from collections.abc import Callable
from typing import NoReturn

SEED_MAX = 2**32 - 1  # seeds are 32-bit everywhere (NumPy's legacy seeding, Ray, the grid's seeds)


class UsageError(Exception):
    """Bad command-line input; the tools print its message as one line and exit 2."""


# (old, new) prog prefix: ("python -m uavlora_rllib.tune", "uavlora tune") while the `uavlora`
# command runs a tool (cli.main), so that its usage lines name the command that was typed
PROG_ALIAS: tuple[str, str] | None = None


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors raise UsageError instead of printing usage and exiting."""

    def __init__(self, *args, **kwargs) -> None:
        prog = kwargs.get("prog")
        if PROG_ALIAS is not None and isinstance(prog, str) and prog.startswith(PROG_ALIAS[0]):
            kwargs["prog"] = PROG_ALIAS[1] + prog[len(PROG_ALIAS[0]) :]
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


def integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """A parser of integers in [low, high] (high None: no upper bound)."""

    def parse(text: str) -> int:
        value = integer(text)
        if value < low or (high is not None and value > high):
            allowed = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise argparse.ArgumentTypeError(f"must be an integer {allowed}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse names the type in some messages
    return parse


def positive_int(text: str) -> int:
    value = integer(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


seed = int_in(0, SEED_MAX)


def float_in(low: float, high: float, low_open: bool = False, high_open: bool = False) -> Callable[[str], float]:
    """A parser of finite numbers in the interval from low to high (each end open or closed)."""
    allowed = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {allowed}, got {text!r}") from None
        too_low = value <= low if low_open else value < low
        too_high = value >= high if high_open else value > high
        if not math.isfinite(value) or too_low or too_high:
            raise argparse.ArgumentTypeError(f"expected a number in {allowed}, got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


def fail(message: object, prog: str | None = None, code: int = 2) -> int:
    """Print `[prog: ]error: message` as ONE line on stderr (newlines in the message folded);
    return the exit code."""
    head = f"{prog}: error: " if prog else "error: "
    print(head + " ".join(str(message).split()), file=sys.stderr)
    return code


def write_problem(folder: str) -> str | None:
    """Why no file can be created in the existing directory `folder`, or None. A real create-and-delete
    (nothing remains): os.access says yes to root everywhere, /proc included."""
    if not os.path.isdir(folder):
        return f"{folder} is not a directory"
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-test-"):
            return None
    except OSError as exc:
        return exc.strerror or str(exc)


def nonempty_path(text: str) -> str:
    """A path flag's value: an empty one (--out "") would silently mean the default."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty path")
    return text
