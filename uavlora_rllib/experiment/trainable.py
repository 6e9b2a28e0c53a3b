"""One Tune trial of a grid: build the registry entry's algorithm, train to the budget, evaluate.

Its own module so that `python -m uavlora_rllib.tune --help`, `--list-hparams` and `--dry-run`
never import Ray Tune (seconds): only a run does (docs/model.md#execution-phase).
"""

from __future__ import annotations

import os
import time
from typing import Any

from ray import tune

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process
from uavlora_rllib.experiment import cluster
from uavlora_rllib.experiment.grid import import_plugins
from uavlora_rllib.experiment.trial_clock import TrialClock


class UavLoraTrainable(tune.Trainable):
    """One trial: build the registry entry's algorithm, train to the budget, evaluate."""

    def setup(self, config: dict) -> None:
        import uavlora_rllib.envs.multi_agent  # noqa: F401  (registers the "uavlora" env)
        from uavlora_rllib.experiment import periodic_eval
        from uavlora_rllib.experiment.quiet import quiet_known_warnings
        from uavlora_rllib.sim.scenario import ScenarioConfig

        self.clock = TrialClock()  # from here: building the algorithm counts
        quiet_known_warnings()
        cfg = config.get("trial", config)
        self.cfg = cfg
        import_plugins(cfg.get("plugins", []))
        resources = registry.Resources(**cfg["resources"])
        setup_torch_process(resources.torch_threads)
        self.entry = registry.get(cfg["algorithm"])
        self.scenario = ScenarioConfig.from_dict(cfg["scenario"])
        # overrides as Tune resolved them: sampled values (and PBT's mutations, which reach a
        # running trial through reset_config / a new actor, then restore) included
        self.hparams = self.entry.hparams(cfg["overrides"])
        algo_config = self.entry.algorithm_config(self.scenario, self.hparams, resources, int(cfg["seed"]))
        self._eval_settings = periodic_eval.PeriodicEvalSettings(
            self.scenario, int(cfg.get("eval_interval_env_steps", 0)), int(cfg["eval_episodes"]), int(cfg["seed"])
        )
        periodic_eval.attach(algo_config, self._eval_settings)
        self.algo = algo_config.build_algo()
        self._last_steps: int | None = 0
        self._latest_eval: float | None = None  # sweep.SWEEP_METRIC: the latest greedy evaluation
        self._node_id = cluster.node_id()  # which raylet ran it (two may share a host)
        self._precision_route = precision_routes(self.algo)

    def step(self) -> dict:
        from uavlora_rllib.experiment import periodic_eval
        from uavlora_rllib.experiment.run_schema import (
            ENV_STEPS,
            PRECISION_ROUTE,
            TRIAL_WALL_METRIC,
            lookup,
            number,
            training_summary,
        )

        t0 = time.perf_counter()
        result = self.algo.train()
        dt = max(time.perf_counter() - t0, 1e-9)
        out = training_summary(result)
        out.update(periodic_eval.metrics_from_result(result))  # the greedy-policy curve's points
        steps = out[ENV_STEPS]
        if self._last_steps is not None:
            sampled = steps - self._last_steps
        else:  # first iteration after a restore
            sampled = number(lookup(result, "env_runners/num_env_steps_sampled")) or 0
        out["env_steps_per_s"] = float(sampled) / dt
        out["node_id"] = self._node_id
        out[PRECISION_ROUTE] = self._precision_route
        self._last_steps = steps
        if steps >= int(self.cfg["budget_env_steps"]):
            out.update(self.evaluate())
            out["done"] = True
        out.update(self._sweep_metrics(out))
        out[TRIAL_WALL_METRIC] = self.clock.seconds()
        return out

    def _sweep_metrics(self, out: dict) -> dict:
        """The latest greedy evaluation in every result (sweep.SWEEP_METRIC, what schedulers and
        search algorithms read), and the current value of every sampled hyperparameter as the
        algorithm holds it (``hparam/<name>``, numeric ones; MLflow logs them as metrics, so a
        PBT mutation shows as a step in the series)."""
        from uavlora_rllib.experiment import periodic_eval, sweep
        from uavlora_rllib.experiment.run_schema import number

        extra: dict[str, Any] = {}
        if sweep.METRIC in out:
            self._latest_eval = float(out[sweep.METRIC])
        elif self._latest_eval is None and self._eval_settings.interval_env_steps > 0:
            # no evaluation since this actor started (e.g. restored elsewhere): one now
            self._latest_eval = float(periodic_eval.evaluate_policies(self.algo, self._eval_settings)[sweep.METRIC])
        if self._latest_eval is not None:
            extra[sweep.SWEEP_METRIC] = self._latest_eval
        held = getattr(self.algo.config, "hparams", None) or self.hparams
        for name in self.cfg.get("sampled", ()):
            value = number(getattr(held, name, None))
            if value is not None:
                extra[f"{sweep.HPARAM_PREFIX}{name}"] = value
        return extra

    def evaluate(self) -> dict:
        """The final execution-phase evaluation: the greedy and the sampled policy on the trial's
        evaluation episodes (periodic_eval.evaluate_policies), so that the run's last eval_sampled/*
        point is the final policy's as its eval/* is, whatever the periodic interval."""
        from uavlora_rllib.experiment import periodic_eval

        return periodic_eval.evaluate_policies(self.algo, self._eval_settings)

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        self.algo.save_to_path(checkpoint_dir)
        self.clock.save(checkpoint_dir)

    def load_checkpoint(self, checkpoint: Any) -> None:
        path = checkpoint if isinstance(checkpoint, (str, os.PathLike)) else checkpoint.get("checkpoint_dir")
        self.algo.restore_from_path(os.fspath(path))
        self.clock.load(os.fspath(path))
        self._last_steps = None
        # The optimizers' state in the checkpoint carries the learning rate they ran with; a
        # trial restored with another config (PBT's exploit: another trial's checkpoint, this
        # trial's mutated lr) must train with its own from the first update on.
        self.algo.learner_group.foreach_learner(_apply_configured_lr)

    def reset_config(self, new_config: dict) -> bool:
        """Reuse this actor for the next trial (saves a process start and the RLlib import)."""
        self.cleanup()
        self.setup(new_config)
        return True

    def cleanup(self) -> None:
        algo = getattr(self, "algo", None)
        if algo is not None:
            algo.stop()
            self.algo = None


def _apply_configured_lr(learner) -> None:
    """Set every optimizer's learning rate to the value its lr schedule (built from the
    learner's config) gives now, as RLlib does after each update."""
    for optimizer, schedule in getattr(learner, "_optimizer_lr_schedules", {}).items():
        learner._set_optimizer_lr(optimizer, lr=schedule.get_current_value())


def _learner_precision_name(learner) -> str:
    """A learner's number format and route (UavLoraLearner.precision_name); a plugin's own learner
    runs float32 (the registry refuses it bfloat16)."""
    name = getattr(learner, "precision_name", None)
    return name() if callable(name) else "float32"


def precision_routes(algo) -> str:
    """What the trial's learners run in, asked of each learner where it runs (its CPU decides the
    bfloat16 route): one name, or several joined by ',' when the learners' machines differ."""
    return ",".join(sorted({r.get() for r in algo.learner_group.foreach_learner(_learner_precision_name)}))
