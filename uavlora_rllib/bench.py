"""Simulator benchmark: env steps per second on one core's worth of threads.

    python -m uavlora_rllib.bench env [--quick] [--repeats R] [--write FILE]

Measures, for the paper scenario (V=10, U=2) and a large one (V=100, U=8):
* the single env through the PettingZoo ParallelEnv API (dict actions, random per_uav
  actions drawn in advance so that sampling is not timed; resets included);
* the batch core (`BatchCore.step`) at N = 1, 64, 1024 scenarios; env-steps/s = N * steps / time,
  over whole 32-step periods of the mobility-noise refills (one refill per period, as in a long run).
BLAS/OpenMP pools are limited to one thread before NumPy is imported. Each figure is the
best of R timed runs after a warm-up, both in wall-clock time and in this process's CPU
time (the machine may be shared; CPU time is the steadier figure then); the R runs are R
sweeps over all the rows (see `measure`). With --write, the
results replace the "## Simulator" section of FILE (other sections are kept).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402

import numpy as np  # noqa: E402

from uavlora_rllib.cli_args import Parser, UsageError, fail, int_in, write_problem  # noqa: E402
from uavlora_rllib.sim.core import BatchCore  # noqa: E402
from uavlora_rllib.sim.mobility import NOISE_CHUNK  # noqa: E402
from uavlora_rllib.sim.scenario import ScenarioConfig  # noqa: E402

SCENARIOS = ((10, 2), (100, 8))
BATCH_SIZES = (1, 64, 1024)
# Targets on one core (issue 2): env-steps/s.
TARGETS = {("core", 10, 2): 500_000, ("core", 100, 8): 100_000, ("api", 10, 2): 10_000}


@dataclass
class Row:
    kind: str  # "api" (single env, PettingZoo) or "core" (BatchCore)
    n_eds: int
    n_uavs: int
    n_envs: int
    steps: int
    seconds: float  # wall clock, best run
    cpu_seconds: float  # this process's CPU time, best run (robust when the machine is busy)

    @property
    def rate(self) -> float:
        return self.n_envs * self.steps / self.seconds

    @property
    def cpu_rate(self) -> float:
        return self.n_envs * self.steps / self.cpu_seconds


def _timed(body) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), time.process_time()
    body()
    return time.perf_counter() - w0, time.process_time() - c0


@dataclass
class Case:
    """One row of the benchmark: `run()` times one run (after its set-up) of the row `what`
    describes, Row's (kind, n_eds, n_uavs, n_envs, steps)."""

    what: tuple[str, int, int, int, int]
    run: Callable[[], tuple[float, float]]


def core_case(cfg: ScenarioConfig, n_envs: int, env_steps: int) -> Case:
    # Whole noise-refill periods: the reset draws the first NOISE_CHUNK steps of noise and
    # step NOISE_CHUNK k draws the next, so steps 1 .. NOISE_CHUNK m (after one untimed step)
    # hold exactly m refills, the share of a long run. (A window of fewer steps than one
    # period would time no refill at all.)
    periods = max(2, min(env_steps // n_envs, 3000) // NOISE_CHUNK)
    steps = periods * NOISE_CHUNK
    core = BatchCore(cfg, n_envs)
    actions = np.random.default_rng(0).integers(0, cfg.n_joint_actions, (steps + 1, n_envs, cfg.n_uavs))

    def body() -> None:
        for k in range(1, steps + 1):
            core.step(actions[k])

    def run() -> tuple[float, float]:
        core.reset(0)
        core.step(actions[0])
        return _timed(body)

    return Case(("core", cfg.n_eds, cfg.n_uavs, n_envs, steps), run)


def api_case(cfg: ScenarioConfig, steps: int) -> Case:
    from uavlora_rllib.envs.multi_agent import UavLoraParallelEnv

    env = UavLoraParallelEnv(cfg)
    agents = env.possible_agents
    draws = np.random.default_rng(0).integers(0, cfg.n_joint_actions, (steps, len(agents)))
    actions = [dict(zip(agents, (int(x) for x in row))) for row in draws]

    def body() -> None:
        for k in range(steps):
            env.step(actions[k])
            if not env.agents:
                env.reset(seed=k)

    def run() -> tuple[float, float]:
        env.reset(seed=0)
        return _timed(body)

    return Case(("api", cfg.n_eds, cfg.n_uavs, 1, steps), run)


def measure(cases: list[Case], repeats: int, report: Callable[[Row], None] | None = None) -> list[Row]:
    """Each case's best wall and CPU time over `repeats` timed runs, after a warm-up run each.
    The repeats are sweeps over all the cases, not back-to-back runs of one: on a shared
    machine a slow spell of a few seconds then costs one sweep's runs, not every run of one
    row."""
    for case in cases:
        case.run()  # warm-up (allocations, caches, first reset)
    best = [(np.inf, np.inf)] * len(cases)
    for _ in range(repeats):
        for i, case in enumerate(cases):
            wall, cpu = case.run()
            best[i] = (min(best[i][0], wall), min(best[i][1], cpu))
    rows = [Row(*c.what, *b) for c, b in zip(cases, best)]
    if report is not None:
        for row in rows:
            report(row)
    return rows


def machine() -> dict[str, str]:
    model = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "nproc": str(os.cpu_count()),
        "cpu": model,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "threads": "OMP/MKL/OPENBLAS_NUM_THREADS=1",
    }


def run_env_bench(quick: bool, repeats: int) -> list[Row]:
    cases: list[Case] = []
    for v, u in SCENARIOS:
        cfg = ScenarioConfig(n_eds=v, n_uavs=u)
        api_steps = 300 if quick else 2000
        cases.append(api_case(cfg, api_steps if v <= 10 else api_steps // 2))
        for n in BATCH_SIZES:
            env_steps = (20_000 if quick else 150_000) if v <= 10 else (2_000 if quick else 65_536)
            cases.append(core_case(cfg, n, env_steps))
    return measure(cases, repeats, report=lambda row: print(_fmt(row), flush=True))


def _target_text(row: Row) -> str:
    target = TARGETS.get((row.kind, row.n_eds, row.n_uavs))
    if target is None or (row.kind == "core" and row.n_envs != max(BATCH_SIZES)):
        return ""
    verdict = "met" if row.rate >= target else f"missed (wall clock at {row.rate / target:.0%} of it)"
    return f"target {target:,}: {verdict}"


def _fmt(row: Row) -> str:
    what = "single env, PettingZoo API" if row.kind == "api" else f"BatchCore N={row.n_envs}"
    return (
        f"V={row.n_eds:<4d} U={row.n_uavs:<2d} {what:<28s} {row.rate:>12,.0f} env-steps/s "
        f"({row.cpu_rate:,.0f} per CPU-s; {1e6 * row.seconds / row.steps:,.1f} us per step call)  {_target_text(row)}"
    )


def markdown(rows: list[Row], command: str, repeats: int = 5) -> str:
    m = machine()
    lines = [
        "## Simulator",
        "",
        f"Command: `{command}` (best of {repeats} timed runs per row, in {repeats} sweeps over the rows, "
        "after a warm-up; "
        f"{m['threads']}; per_uav mode, random actions drawn in advance; the PettingZoo loop "
        "includes its reset every 150 steps).",
        "",
        f"Machine: {m['nproc']} CPUs ({m['cpu']}), Python {m['python']}, NumPy {m['numpy']}. "
        "The machine is shared with other jobs: env-steps/s is wall clock; env-steps per CPU-second "
        "(this process's CPU time) is the steadier figure when the machine is busy.",
        "",
        "| scenario | what | env-steps/s | env-steps per CPU-s | us per step call | target (one core) |",
        "|---|---|---:|---:|---:|---|",
    ]
    for r in rows:
        what = "single env, PettingZoo API" if r.kind == "api" else f"BatchCore, N = {r.n_envs}"
        lines.append(
            f"| V={r.n_eds}, U={r.n_uavs} | {what} | {r.rate:,.0f} | {r.cpu_rate:,.0f} | {1e6 * r.seconds / r.steps:,.1f} | "
            f"{_target_text(r) or '-'} |"
        )
    return "\n".join(lines) + "\n"


def write_section(path: str, section: str) -> None:
    """Replace (or append) the '## Simulator' section of a markdown file."""
    text = open(path).read() if os.path.exists(path) else "# Benchmarks\n\n"
    pattern = re.compile(r"^## Simulator\n.*?(?=^## |\Z)", re.S | re.M)
    if pattern.search(text):
        text = pattern.sub(lambda _: section + "\n", text, count=1)
    else:
        text = text.rstrip("\n") + "\n\n" + section
    with open(path, "w") as fh:
        fh.write(text.rstrip("\n") + "\n")


def _writable_file(text: str) -> str:
    """--write FILE: a file (new or existing) in an existing directory, checked before the
    benchmark runs for minutes."""
    folder = os.path.dirname(os.path.abspath(text)) or "."
    if os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory; allowed: a markdown file")
    if not os.path.isdir(folder):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: {folder} is not a directory")
    problem = write_problem(folder)
    if problem:
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: {folder} is not writable ({problem})")
    if os.path.exists(text):  # its other sections are kept, so it must be readable UTF-8 text, and writable
        try:
            with open(text, "rb") as fh:
                fh.read().decode("utf-8")
            with open(text, "a"):
                pass
        except UnicodeDecodeError:
            raise argparse.ArgumentTypeError(f"{text!r} is not UTF-8 text; allowed: a markdown file") from None
        except OSError as exc:
            raise argparse.ArgumentTypeError(f"cannot write {text!r}: {exc.strerror or exc}") from None
    return text


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="python -m uavlora_rllib.bench", description="simulator benchmarks")
    sub = p.add_subparsers(dest="what", required=True, parser_class=Parser)
    env = sub.add_parser("env", help="env steps per second (single env API and batch core)")
    env.add_argument("--quick", action="store_true", help="fewer steps (a smoke run, noisier)")
    env.add_argument(
        "--repeats", type=int_in(1, 1000), default=None, help="timed runs per figure (default 5, 2 with --quick)"
    )
    env.add_argument(
        "--write",
        metavar="FILE",
        type=_writable_file,
        default=None,
        help="write the results into FILE's Simulator section",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except UsageError as exc:
        return fail(exc)
    m = machine()
    print(f"machine: {m['nproc']} CPUs ({m['cpu']}), Python {m['python']}, NumPy {m['numpy']}, {m['threads']}")
    # 5 sweeps by default: on a shared machine a slow spell of a few seconds can span several
    # runs of one row (see measure)
    repeats = args.repeats or (2 if args.quick else 5)
    rows = run_env_bench(args.quick, repeats)
    if args.write:
        command = "python -m uavlora_rllib.bench env" + (" --quick" if args.quick else "")
        command += f" --repeats {args.repeats}" if args.repeats else ""
        write_section(args.write, markdown(rows, command, repeats))
        print(f"wrote the Simulator section of {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
