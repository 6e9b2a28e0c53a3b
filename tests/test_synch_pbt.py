"""Synchronous PBT (experiment/synch_pbt.py): a trial still saving its pause checkpoint when the
population perturbs is exploited once the save has resolved, and trains to its budget.

The race, made certain: trial "low" reaches the perturbation time at once and writes its pause
checkpoint slowly; trial "high" arrives while that save is still running and perturbs the
population, with "low" in the lower quantile. Ray's PopulationBasedTraining (synch=True) leaves a
stop pending for "low", which its next checkpoint (one per iteration here, as in a grid with
`checkpoint_every: 1`) sets off: "low" ends TERMINATED short of its budget (CI run 20's failure)."""

from __future__ import annotations

import json
import os
import time

BUDGET = 4  # training iterations
INTERVAL = 2  # perturbations after iterations 2 and 4
SAVE_S = 4.0  # "low"'s checkpoint write at a perturbation: "high"'s two steps (0.5 s each) end inside it


def climber():
    """A Tune Trainable whose score is its config's, carried by its checkpoint (so a clone shows);
    built here so that importing this module does not import Ray Tune."""
    from ray import tune

    class Climber(tune.Trainable):
        def setup(self, config):
            self.t, self.score = 0, float(config["trial"]["score"])

        def step(self):
            time.sleep(self.config["trial"]["step_s"])
            self.t += 1
            return {"t": self.t, "score": self.score, "done": self.t >= BUDGET}

        def save_checkpoint(self, checkpoint_dir):
            if self.t % INTERVAL == 0:
                time.sleep(self.config["trial"]["save_s"])
            with open(os.path.join(checkpoint_dir, "state.json"), "w") as f:
                json.dump({"t": self.t, "score": self.score}, f)

        def load_checkpoint(self, checkpoint_dir):
            with open(os.path.join(checkpoint_dir, "state.json")) as f:
                state = json.load(f)
            self.t, self.score = state["t"], state["score"]

    return Climber


def test_a_trial_saving_at_the_perturbation_is_exploited_and_finishes(ray_session, tmp_path):
    from ray import tune

    from uavlora_rllib.experiment.synch_pbt import SynchronousPBT

    low = {"score": 0.0, "step_s": 0.0, "save_s": SAVE_S}
    high = {"score": 1.0, "step_s": 0.5, "save_s": 0.0}
    scheduler = SynchronousPBT(
        time_attr="t",
        metric="score",
        mode="max",
        perturbation_interval=INTERVAL,
        quantile_fraction=0.5,
        resample_probability=0.0,
        hyperparam_mutations={"lr": [0.5, 1.0, 2.0]},
    )
    tuner = tune.Tuner(
        climber(),
        param_space={"trial": tune.grid_search([low, high]), "lr": 1.0},
        tune_config=tune.TuneConfig(scheduler=scheduler, max_concurrent_trials=2, reuse_actors=False),
        run_config=tune.RunConfig(
            storage_path=str(tmp_path),
            name="race",
            verbose=0,
            checkpoint_config=tune.CheckpointConfig(checkpoint_frequency=1),
        ),
    )
    results = [r.metrics for r in tuner.fit()]  # in the order of the grid: low, high
    for metrics in results:
        assert metrics["t"] == BUDGET and metrics["done"], metrics  # both trained to the budget
    assert results[0]["score"] == 1.0  # and "low" went on from "high"'s checkpoint
    assert scheduler._num_perturbations >= 1
