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
from uavlora_rllib.algorithms.common.threads import set_torch_threads
from uavlora_rllib.experiment import cluster
from uavlora_rllib.experiment.grid import import_plugins


class UavLoraTrainable(tune.Trainable):
    """One trial: build the registry entry's algorithm, train to the budget, evaluate."""

    def setup(self, config: dict) -> None:
        import uavlora_rllib.envs.multi_agent  # noqa: F401  (registers the "uavlora" env)
        from uavlora_rllib.experiment import periodic_eval
        from uavlora_rllib.experiment.quiet import quiet_known_warnings
        from uavlora_rllib.sim.scenario import ScenarioConfig

        quiet_known_warnings()
        cfg = config.get("trial", config)
        self.cfg = cfg
        import_plugins(cfg.get("plugins", []))
        resources = registry.Resources(**cfg["resources"])
        set_torch_threads(resources.torch_threads)
        self.entry = registry.get(cfg["algorithm"])
        self.scenario = ScenarioConfig.from_dict(cfg["scenario"])
        hparams = self.entry.hparams(cfg["overrides"])
        algo_config = self.entry.build(self.scenario, hparams, resources, int(cfg["seed"]))
        periodic_eval.attach(algo_config, periodic_eval.PeriodicEvalSettings(
            self.scenario, int(cfg.get("eval_interval_env_steps", 0)), int(cfg["eval_episodes"]), int(cfg["seed"])))
        self.algo = algo_config.build_algo()
        self._last_steps: int | None = 0
        self._node_id = cluster.node_id()  # which raylet ran it (two may share a host)

    def step(self) -> dict:
        from uavlora_rllib.experiment import periodic_eval
        from uavlora_rllib.experiment.run_schema import ENV_STEPS, lookup, number, training_summary

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
        self._last_steps = steps
        if steps >= int(self.cfg["budget_env_steps"]):
            out.update(self.evaluate())
            out["done"] = True
        return out

    def evaluate(self) -> dict:
        from uavlora_rllib.experiment.evaluation import run_episodes
        from uavlora_rllib.experiment.run_schema import eval_metrics

        policy = self.entry.greedy_policy(self.algo, self.scenario)
        res = run_episodes(policy, self.scenario, int(self.cfg["eval_episodes"]), int(self.cfg["seed"]))
        return eval_metrics(res.summary())

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        self.algo.save_to_path(checkpoint_dir)

    def load_checkpoint(self, checkpoint: Any) -> None:
        path = checkpoint if isinstance(checkpoint, (str, os.PathLike)) else checkpoint.get("checkpoint_dir")
        self.algo.restore_from_path(os.fspath(path))
        self._last_steps = None

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
