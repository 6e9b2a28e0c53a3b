"""Episode animation: a GIF of the ED-UAV association, one frame per slot.

    python -m analysis.animate --policy {random,fixed,adr,best_fixed,greedy,optimal|CHECKPOINT_DIR}
        [--n-eds V] [--n-uavs U] [--seed S] [--steps K] [--fps F] [--out file.gif]

Plays K slots (default: the whole episode, T = episode_len) of one episode of the
PettingZoo env (`UavLoraParallelEnv(render_mode="rgb_array")`), the policy acting on the
env's batch core, and writes K + 1 frames: the env's render after reset, then after every
step. A baseline runs on the default scenario with --n-eds/--n-uavs applied; a checkpoint
runs on its own training scenario with those overrides (uavlora_rllib.evaluate).
Every expected failure (bad flag, unknown policy, a checkpoint that does not fit the scenario,
--out a folder or not writable) prints one error line on stderr, exit code 2. A progress bar
shows the slots played (on a terminal only).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

import numpy as np

from analysis.runs import check_writable_folder
from uavlora_rllib.cli_args import Parser, UsageError, int_in, positive_int, seed


def build_parser() -> argparse.ArgumentParser:
    from uavlora_rllib.baselines.policies import BASELINES

    p = Parser(prog="python -m analysis.animate", description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help=f"one of {', '.join(BASELINES)}, or a checkpoint directory")
    p.add_argument("--n-eds", type=positive_int, default=None, help="V (default: the scenario's)")
    p.add_argument("--n-uavs", type=positive_int, default=None, help="U (default: the scenario's)")
    p.add_argument("--seed", type=seed, default=0, help="episode seed in [0, 2^32 - 1] (default 0)")
    p.add_argument("--steps", type=positive_int, default=None, help="slots to play, <= episode_len (default: all)")
    # a GIF's frame delay is a whole number of hundredths of a second (10 ms at least): 100 fps at most
    p.add_argument("--fps", type=int_in(1, 100), default=8, help="frames per second in [1, 100] (default 8)")
    p.add_argument("--out", default="animation.gif", help="output GIF (default animation.gif)")
    return p


def resolve_policy(policy: str, n_eds: int | None, n_uavs: int | None, seed: int = 0):
    """(policy, scenario) for a baseline name or a checkpoint directory."""
    from uavlora_rllib.baselines.policies import BASELINES, make_baseline
    from uavlora_rllib.sim.scenario import ScenarioConfig

    overrides = {k: v for k, v in (("n_eds", n_eds), ("n_uavs", n_uavs)) if v is not None}
    if policy in BASELINES:
        cfg = ScenarioConfig.from_dict(overrides)
        return make_baseline(policy, cfg, seed=seed), cfg
    from uavlora_rllib.config_errors import ConfigError
    from uavlora_rllib.evaluate import check_checkpoint_dir, load_checkpoint_policy

    check_checkpoint_dir(policy)

    try:
        return load_checkpoint_policy(policy, overrides)
    except ConfigError:
        raise  # its message names --policy and the problem already
    except ValueError as exc:  # the trained network does not fit the scenario (shapes, action mode)
        raise UsageError(f"--policy: checkpoint {policy!r} does not fit the scenario: {exc}") from None


def check_out(path: str) -> None:
    """UsageError unless `path` can become a GIF file (not a folder; its folder created and writable)."""
    if not path.lower().endswith(".gif"):
        raise UsageError(f"--out: expected a .gif file name, got {path!r}")
    if os.path.isdir(path):
        raise UsageError(f"--out: {path!r} is a folder; expected a .gif file name")
    check_writable_folder(os.path.dirname(os.path.abspath(path)), "--out")


def record_frames(policy, cfg, seed: int, steps: int) -> list[np.ndarray]:
    """Render after reset and after each of `steps` steps: steps + 1 uint8 frames [H, W, 3]."""
    from tqdm import tqdm

    from uavlora_rllib.envs.multi_agent import UavLoraParallelEnv

    env = UavLoraParallelEnv(cfg, render_mode="rgb_array")
    env.reset(seed=seed)
    policy.reset(env.core)
    frames = [env.render()]
    for _ in tqdm(range(steps), desc="animate", unit="slot", disable=None, leave=False):
        acts = np.asarray(policy.act(env.core))[0]
        env.step({a: acts[i] for i, a in enumerate(env.possible_agents)})
        frames.append(env.render())
    env.close()
    return frames


def write_gif(frames: Sequence[np.ndarray], path: str, fps: int) -> None:
    import imageio.v3 as iio

    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)


def main(argv: Sequence[str] | None = None) -> int:
    from uavlora_rllib.config_errors import ConfigError

    try:
        args = build_parser().parse_args(argv)
        check_out(args.out)
        policy, cfg = resolve_policy(args.policy, args.n_eds, args.n_uavs, args.seed)
        steps = cfg.episode_len if args.steps is None else args.steps
        if steps > cfg.episode_len:
            raise UsageError(f"--steps: at most the episode length {cfg.episode_len}, got {steps}")
    except (UsageError, ConfigError) as exc:
        print(f"animate: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    frames = record_frames(policy, cfg, args.seed, steps)
    try:
        write_gif(frames, args.out, args.fps)
    except OSError as exc:  # e.g. the disk filled up
        print(f"animate: error: --out: cannot write {args.out!r}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(
        f"animate: {args.out} ({len(frames)} frames, policy {getattr(policy, 'name', args.policy)}, "
        f"V={cfg.n_eds} U={cfg.n_uavs}, seed {args.seed})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
