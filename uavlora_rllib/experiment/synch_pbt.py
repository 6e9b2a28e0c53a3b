"""Synchronous PBT without the race that ends a trial short of its budget (see experiment/sweep.py).

In Ray Tune's synchronous PBT a trial that reaches the perturbation time before the others is
paused with a checkpoint; the last one to arrive perturbs the population. When that happens while
an early trial's pause checkpoint is still being written and that trial is in the lower quantile,
Ray's exploit pauses it again without a checkpoint; Tune turns the pending pause into a stop, and
the trial ends TERMINATED without its last results (seen in CI: a 120-step trial stopped at 60).
Here the exploit of such a trial waits until its save has resolved (it is then PAUSED) and runs
when the trial is next chosen to run, from the checkpoint and quantiles of the perturbation.

Its own module: it subclasses Ray Tune's scheduler, and `sweep` imports Ray Tune only to build one.
"""

from __future__ import annotations

from ray.rllib.utils.annotations import override
from ray.tune.experiment import Trial
from ray.tune.schedulers import PopulationBasedTraining


class SynchronousPBT(PopulationBasedTraining):
    """PopulationBasedTraining (synch=True) whose exploit of a trial still saving its pause
    checkpoint is deferred to when that trial is next chosen to run (module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(synch=True, **kwargs)
        self._deferred: dict[Trial, tuple[list[Trial], list[Trial]]] = {}  # trial -> (upper, lower)

    @override(PopulationBasedTraining)
    def _checkpoint_or_exploit(self, trial, tune_controller, upper_quantile, lower_quantile):
        if trial in lower_quantile and trial.status == Trial.RUNNING and trial.is_saving:
            # the population's checkpoints stay as this perturbation left them until this trial
            # trains again: the next perturbation needs it to report first
            self._deferred[trial] = (list(upper_quantile), list(lower_quantile))
            return
        super()._checkpoint_or_exploit(trial, tune_controller, upper_quantile, lower_quantile)

    @override(PopulationBasedTraining)
    def choose_trial_to_run(self, tune_controller):
        trial = super().choose_trial_to_run(tune_controller)
        quantiles = self._deferred.pop(trial, None) if trial is not None else None
        if quantiles is not None:
            super()._checkpoint_or_exploit(trial, tune_controller, *quantiles)
        return trial

    @override(PopulationBasedTraining)
    def on_trial_remove(self, tune_controller, trial) -> None:
        self._deferred.pop(trial, None)
        super().on_trial_remove(tune_controller, trial)
