"""The trial's final evaluation (experiment/trainable.py, UavLoraTrainable.evaluate) is the execution
phase of the final policy in both forms: the greedy policy (eval/*) and the seeded sampled policy
(eval_sampled/*) on the trial's evaluation episodes. Before, only eval/* was final, and a periodic
interval that missed the last iteration left an earlier policy's eval_sampled/* as the run's last."""

from __future__ import annotations

from types import SimpleNamespace

from uavlora_rllib.baselines.policies import make_baseline
from uavlora_rllib.experiment import periodic_eval
from uavlora_rllib.experiment.evaluation import run_episodes
from uavlora_rllib.experiment.run_schema import eval_metrics
from uavlora_rllib.experiment.trainable import UavLoraTrainable
from uavlora_rllib.sim.scenario import ScenarioConfig

SCEN = ScenarioConfig(n_eds=6, n_uavs=2, episode_len=5)


def test_final_evaluation_runs_the_greedy_and_the_sampled_policy(monkeypatch):
    # stand-ins for a trained algorithm's two policies: "fixed" as the greedy one, "random" (seeded) as the sampled
    built: list[tuple[bool, int]] = []

    def policy(algo, scenario, explore=False, seed=0):
        built.append((explore, seed))
        return make_baseline("random" if explore else "fixed", scenario, seed=seed)

    monkeypatch.setattr(
        "uavlora_rllib.algorithms.common.registry.entry_for_algorithm", lambda algo: SimpleNamespace(policy=policy)
    )
    trial = UavLoraTrainable.__new__(UavLoraTrainable)  # no Ray: the evaluation only reads these two
    trial.algo = object()
    trial._eval_settings = periodic_eval.PeriodicEvalSettings(SCEN, 7, 3, 11)  # an interval: not what decides
    out = trial.evaluate()
    assert built == [(False, 11), (True, 11)]
    greedy = eval_metrics(run_episodes(make_baseline("fixed", SCEN, seed=11), SCEN, 3, 11).summary())
    sampled = eval_metrics(run_episodes(make_baseline("random", SCEN, seed=11), SCEN, 3, 11).summary())
    assert {k: out[k] for k in greedy} == greedy and out["eval/episodes"] == 3.0
    assert {k[len("eval_sampled/") :]: v for k, v in out.items() if k.startswith("eval_sampled/")} == {
        k[len("eval/") :]: v for k, v in sampled.items()
    }
