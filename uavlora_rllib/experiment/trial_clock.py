"""A trial's own working time [s]: the wall-clock time of every actor that ran it, from its setup
on, summed over interruptions, so that a pause between SIGINT and `--resume` is not counted
(docs/cluster.md#what-a-grid-costs; the report's table_cost reads it, analysis/cost.py).

The running total is written beside each checkpoint and read back when the trial restores it, as
Tune's own `time_total_s` is (which leaves out setup and checkpoints, so it is not used here). Work
done after the last checkpoint of an interrupted actor is not counted; a trial that restores
another trial's checkpoint (PBT's exploit) carries that trial's total, as `time_total_s` does.
Imports neither Ray nor torch.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable

FILE = "uavlora_trial_clock.json"  # beside the algorithm's files in a checkpoint directory
KEY = "trial_wall_s"


class TrialClock:
    """Started when an actor sets a trial up; `seconds()` is the trial's working time so far."""

    def __init__(self, now: Callable[[], float] = time.monotonic) -> None:
        self._now = now
        self._started = now()
        self._before = 0.0  # earlier actors' time, from the restored checkpoint

    def seconds(self) -> float:
        return self._before + (self._now() - self._started)

    def save(self, checkpoint_dir: str) -> None:
        with open(os.path.join(checkpoint_dir, FILE), "w", encoding="utf-8") as fh:
            json.dump({KEY: self.seconds()}, fh)

    def load(self, checkpoint_dir: str) -> None:
        """Take the earlier actors' time from a checkpoint; one without the file (written before
        this clock existed) leaves it at 0."""
        try:
            with open(os.path.join(checkpoint_dir, FILE), encoding="utf-8") as fh:
                self._before = float(json.load(fh)[KEY])
        except (OSError, ValueError, KeyError, TypeError):
            self._before = 0.0
