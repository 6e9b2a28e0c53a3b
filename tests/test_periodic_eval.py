"""The periodic greedy-policy evaluation during training (experiment/periodic_eval.py): its
schedule, how it attaches to an AlgorithmConfig, the grid field, and on a real MAPPO (tiny
scenario, local Ray) that every logged point equals an independent evaluation of the policy of
that iteration."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from conftest import TINY_MAPPO

from uavlora_rllib.experiment import periodic_eval as pe
from uavlora_rllib.experiment.run_schema import metrics_to_log
from uavlora_rllib.sim.scenario import ScenarioConfig

SCEN = ScenarioConfig.from_dict({"n_eds": 6, "n_uavs": 2, "episode_len": 10})


def test_schedule_first_iteration_then_every_interval(monkeypatch):
    calls = []

    def fake(algorithm, s):
        calls.append(algorithm.steps)
        return {"eval/ee_sys_mean": float(algorithm.steps)}

    monkeypatch.setattr(pe, "evaluate_policies", fake)
    cls = type("CB", (pe.PeriodicEvalCallback,), {"settings": pe.PeriodicEvalSettings(SCEN, 100, 2, 0)})
    cb = cls()
    logged = {}
    for steps in (20, 40, 120, 130, 199, 200, 460):
        result = {"env_runners": {"num_env_steps_sampled_lifetime": steps}}
        cb.on_train_result(algorithm=SimpleNamespace(steps=steps), metrics_logger=None, result=result)
        if "eval/ee_sys_mean" in result:
            logged[steps] = result["eval/ee_sys_mean"]
    # the first iteration, then the first iteration at or past each multiple of 100
    assert calls == [20, 120, 200, 460] and logged == {s: float(s) for s in calls}
    assert cb.evaluations == 4
    assert pe.metrics_from_result({"eval/x": 1.0, "eval_sampled/x": 2.0, "learner/y": 3.0}) == {
        "eval/x": 1.0,
        "eval_sampled/x": 2.0,
    }
    # the MLflow callback logs both prefixes as execution metrics
    assert metrics_to_log({"eval_sampled/ee_sys_mean": 2.0, "eval/ee_sys_mean": 1.0})[1] == {
        "eval_sampled/ee_sys_mean": 2.0,
        "eval/ee_sys_mean": 1.0,
    }


def test_resolve_interval_and_grid_field(tmp_path):
    from uavlora_rllib.config_errors import ConfigError
    from uavlora_rllib.experiment.grid import parse_grid

    assert pe.resolve_interval(None, 2_000_000) == 100_000
    assert pe.resolve_interval(None, 7) == 1
    assert pe.resolve_interval(0, 1000) == 0 and pe.resolve_interval(300, 1000) == 300
    base = {
        "experiment": "x",
        "algorithms": ["mappo"],
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "stop": {"env_steps": 400},
    }
    assert parse_grid(base).evaluation.interval_env_steps is None
    assert parse_grid({**base, "evaluation": {"interval_env_steps": 50}}).evaluation.interval_env_steps == 50
    with pytest.raises(ConfigError, match="evaluation.interval_env_steps"):
        parse_grid({**base, "evaluation": {"interval_env_steps": -1}})


def test_attach_keeps_the_algorithms_callbacks():
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.callbacks.callbacks import RLlibCallback

    class Own(RLlibCallback):
        pass

    def on_episode_end(**kw):
        return None

    cfg = PPOConfig().callbacks(Own, on_episode_end=on_episode_end)
    pe.attach(cfg, pe.PeriodicEvalSettings(SCEN, 50, 2, 3))
    classes = list(cfg.callbacks_class)
    assert classes[0] is Own and issubclass(classes[1], pe.PeriodicEvalCallback)
    assert classes[1].settings.interval_env_steps == 50 and classes[1].settings.seed == 3
    assert cfg.callbacks_on_episode_end is on_episode_end
    off = PPOConfig()
    pe.attach(off, pe.PeriodicEvalSettings(SCEN, 0, 2, 0))  # 0: no periodic evaluation
    assert off.callbacks_class is RLlibCallback


@pytest.mark.slow
def test_points_equal_an_independent_evaluation(ray_session, tmp_path, monkeypatch):
    """Real MAPPO, every iteration evaluated: each point is the greedy policy of that iteration on
    the fixed evaluation episodes, and eval_sampled/* is the seeded sampled policy on the same episodes."""
    from uavlora_rllib.algorithms.common import registry
    from uavlora_rllib.experiment.evaluation import run_episodes
    from uavlora_rllib.experiment.run_schema import eval_metrics

    if "mappo" not in registry.available():
        pytest.skip("mappo is not implemented")
    import uavlora_rllib.envs.multi_agent  # noqa: F401  (registers the env)

    entry = registry.get("mappo")
    hp = entry.hparams(TINY_MAPPO)
    cfg = entry.build(SCEN, hp, registry.Resources(num_env_runners=0, num_envs_per_env_runner=2), 0)
    pe.attach(cfg, pe.PeriodicEvalSettings(SCEN, 20, 3, 5))  # 20 env steps = every iteration
    algo = cfg.build_algo()
    try:
        for _ in range(2):
            result = algo.train()
            got = pe.metrics_from_result(result)
            want = eval_metrics(run_episodes(entry.greedy_policy(algo, SCEN), SCEN, 3, 5).summary())
            assert {k: got[k] for k in want} == pytest.approx(want, rel=1e-12)
            assert got["eval/episodes"] == 3.0
            sampled = entry.policy(algo, SCEN, explore=True, seed=5)
            want_s = eval_metrics(run_episodes(sampled, SCEN, 3, 5).summary())
            assert {
                k[len("eval_sampled/") :]: v for k, v in got.items() if k.startswith("eval_sampled/")
            } == pytest.approx({k[len("eval/") :]: v for k, v in want_s.items()}, rel=1e-12)
    finally:
        algo.stop()
