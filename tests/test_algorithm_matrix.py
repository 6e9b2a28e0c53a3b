"""Every built-in algorithm x every action mode it supports, through the registry only.

For each (algorithm, action mode) pair of `registry.built_in()` (BenchMARL-style): build the
trial's config, run one training iteration on a tiny scenario (V=10, U=2, 10-slot episodes,
the algorithm's default hyperparameters), check the paper's training metrics, run the greedy
and the sampled policy, save a checkpoint, restore it and get the same greedy actions, and
evaluate the checkpoint with the evaluate CLI (its `main`, in this process: a subprocess would
start its own Ray for every case; tests/test_evaluate_cli.py covers the
subprocess path). A new algorithm in `registry.MODULES` is covered without new test code; the test plugins are
not (their configs follow RLlib's, not common/config.py's), whichever test module imported them first.

The resource tests build configs only (no Ray): `resources.num_learners` and
`resources.num_gpus_per_learner` reach every algorithm's AlgorithmConfig, and
`Resources.bundles()` is RLlib's own placement layout. One more test trains each algorithm
with a REMOTE learner actor (CPU) and checks that its policy reads the learner's weights.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

TINY = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=10)
RES = registry.Resources(num_envs_per_env_runner=4)
CASES = [(name, mode) for name in registry.built_in() for mode in registry.get(name).action_modes]
IDS = [f"{name}-{mode}" for name, mode in CASES]


def _build(name: str, scenario: ScenarioConfig, resources: registry.Resources = RES):
    entry = registry.get(name)
    return entry, entry.build(scenario, entry.hparams({}), resources, 0)


def _actions(policy, scenario: ScenarioConfig, seed: int = 123, steps: int = 6) -> np.ndarray:
    """The policy's actions over `steps` slots of 3 scenarios from one reset (GRU state carried)."""
    core = BatchCore(scenario, 3)
    core.reset(seed)
    policy.reset(core)
    out = []
    for _ in range(steps):
        a = policy.act(core)
        out.append(a)
        core.step(a)
    return np.stack(out)


def _check_actions(actions: np.ndarray, scenario: ScenarioConfig) -> None:
    from uavlora_rllib.envs.team import team_action_space

    space = team_action_space(scenario)
    assert actions.shape[1:] == (3,) + space.shape and actions.dtype == np.int64
    assert (actions >= 0).all() and (actions < space.nvec).all()


@pytest.mark.slow
@pytest.mark.parametrize("name, mode", CASES, ids=IDS)
def test_train_checkpoint_restore_evaluate(ray_session, tmp_path, capsys, name, mode):
    from ray.rllib.algorithms.algorithm import Algorithm

    from uavlora_rllib import evaluate

    scenario = TINY.replace(action_mode=mode)
    entry, config = _build(name, scenario)
    algo = config.build_algo()
    try:
        timed = []  # learning time is logged once per iteration: training_rate.this_iteration reads one entry
        log_time = algo.metrics.log_time
        algo.metrics.log_time = lambda key, *a, **k: timed.append(key) or log_time(key, *a, **k)
        result = algo.train()
        algo.metrics.log_time = log_time
        assert timed.count(("timers", "learner_update_timer")) <= 1
        assert "learner_update_timer" not in result["timers"] or timed.count(("timers", "learner_update_timer")) == 1
        runners = result["env_runners"]
        assert runners["num_env_steps_sampled_lifetime"] > 0
        # every algorithm logs the paper's metrics of its sampled episodes the same way
        assert runners["ee_sys_mean"] > 0 and 0.0 <= runners["success_rate"] <= 1.0
        greedy = _actions(entry.policy(algo, scenario), scenario)
        _check_actions(greedy, scenario)
        sampled = _actions(entry.policy(algo, scenario, explore=True, seed=5), scenario)
        _check_actions(sampled, scenario)
        # sampled execution is reproducible from its seed
        again = _actions(entry.policy(algo, scenario, explore=True, seed=5), scenario)
        np.testing.assert_array_equal(sampled, again)
        path = algo.save_to_path(str(tmp_path / "ckpt"))
    finally:
        algo.stop()

    from uavlora_rllib.experiment.evaluation import run_episodes

    restored = Algorithm.from_checkpoint(path)
    try:
        assert registry.entry_for_algorithm(restored) is entry and restored.iteration == 1
        np.testing.assert_array_equal(_actions(entry.greedy_policy(restored, scenario), scenario), greedy)
        want = {
            execution: run_episodes(
                entry.policy(restored, scenario, explore=execution == "sampled", seed=3), scenario, episodes=2, seed=3
            ).summary()["ee_sys_mean"]
            for execution in ("greedy", "sampled")
        }
        steps = runners["num_env_steps_sampled_lifetime"]  # it keeps training, its counters carry on
        assert restored.train()["env_runners"]["num_env_steps_sampled_lifetime"] > steps
    finally:
        restored.stop()

    for execution in ("greedy", "sampled"):  # the CLI's two execution modes are the registry's policies
        capsys.readouterr()
        argv = ["--policy", path, "--episodes", "2", "--seed", "3", "--execution", execution, "--json"]
        assert evaluate.main(argv) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert out["episodes"] == 2 and out["ee_sys_mean"] == pytest.approx(want[execution], rel=1e-12)


def test_sampled_execution_differs_from_greedy():
    """A sampled policy draws from the distribution: on an untrained (near-uniform) MAPPO actor
    over 90 actions it almost never repeats the argmax, and its draws depend on the seed."""
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from uavlora_rllib.algorithms.common.config import hparams_model_config
    from uavlora_rllib.algorithms.common.policy import ModulePolicy
    from uavlora_rllib.algorithms.mappo.mappo import MAPPOHParams
    from uavlora_rllib.algorithms.mappo.mappo_module import MAPPOTorchRLModule
    from uavlora_rllib.envs.team import team_action_space, team_observation_space
    from uavlora_rllib.sim.observation import state_dim

    torch.manual_seed(0)
    module = RLModuleSpec(
        module_class=MAPPOTorchRLModule,
        observation_space=team_observation_space(TINY),
        action_space=team_action_space(TINY),
        inference_only=True,
        model_config=hparams_model_config(MAPPOHParams, critic="central", state_dim=state_dim(TINY)),
    ).build()
    greedy = _actions(ModulePolicy(module, "g"), TINY)
    s1 = _actions(ModulePolicy(module, "s", explore=True, seed=1), TINY)
    s2 = _actions(ModulePolicy(module, "s", explore=True, seed=2), TINY)
    assert (s1 != greedy).mean() > 0.8 and (s1 != s2).mean() > 0.8


@pytest.mark.parametrize("name", registry.built_in())
def test_learner_resources_reach_the_algorithm_config(name):
    """resources.num_learners / num_gpus_per_learner / num_cpus_per_learner reach RLlib, and
    Resources.bundles() is what RLlib itself would reserve for the trial."""
    mode = registry.get(name).action_modes[0]
    res = registry.Resources(
        num_env_runners=2,
        num_envs_per_env_runner=4,
        num_cpus_per_env_runner=0.5,
        num_learners=2,
        num_gpus_per_learner=0.25,
        num_cpus_per_learner=3.0,
    )
    _, config = _build(name, TINY.replace(action_mode=mode), res)
    assert (config.num_learners, config.num_gpus_per_learner, config.num_cpus_per_learner) == (2, 0.25, 3.0)
    assert config.num_env_runners == 2 and config.num_cpus_per_env_runner == 0.5
    for r in (res, registry.Resources(num_gpus_per_learner=1.0), registry.Resources(num_env_runners=1)):
        _, config = _build(name, TINY.replace(action_mode=mode), r)
        assert r.bundles() == config.algo_class.default_resource_request(config).bundles


@pytest.mark.slow
@pytest.mark.parametrize("name", registry.built_in())
def test_policy_reads_weights_from_a_remote_learner(ray_session, name):
    """With num_learners=1 the learner is a Ray actor (no local learner object exists); the
    registry's policy still gets the trained weights (LearnerGroup.get_weights)."""
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.algorithms.common.policy import trained_module

    mode = registry.get(name).action_modes[0]
    scenario = TINY.replace(action_mode=mode)
    res = registry.Resources(num_envs_per_env_runner=4, num_learners=1, num_cpus_per_learner=0.5)
    entry, config = _build(name, scenario, res)
    algo = config.build_algo()
    try:
        algo.train()
        assert algo.learner_group.is_remote
        module = trained_module(algo)
        weights = algo.learner_group.get_weights([DEFAULT_MODULE_ID])[DEFAULT_MODULE_ID]
        for k, v in module.state_dict().items():
            torch.testing.assert_close(v, torch.as_tensor(weights[k]))
        _check_actions(_actions(entry.policy(algo, scenario), scenario), scenario)
    finally:
        algo.stop()


@pytest.mark.parametrize("name", registry.built_in())
def test_list_hparams_documents_every_field(name, capsys):
    """`tune --list-hparams ALGO` prints each hyperparameter with its default and a description
    (every field of every algorithm's typed config must have one)."""
    import dataclasses

    from uavlora_rllib import tune

    assert tune.main(["--list-hparams", name]) == 0
    text = capsys.readouterr().out
    fields = dataclasses.fields(registry.get(name).hparams_cls)
    for f in fields:
        assert f"\n{f.name} (" in text, f.name
    assert "(no description)" not in text and text.count("default ") == len(fields)
    assert "FieldInfo" not in text and "Annotated" not in text  # types as written, constraints in the descriptions
    assert tune.main(["--list-hparams", "no_such_algo"]) == 2
    assert "--list-hparams: unknown algorithm 'no_such_algo'" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(registry.HPARAMS_MODULES))
def test_declared_spec_is_the_registered_one(name):
    """A built-in's typed config and action modes, as its HPARAMS_MODULES module declares them (what grid
    checks, --dry-run and --list-hparams read without RLlib), are those its algorithm registers."""
    entry = registry.get(name)
    declared = registry._SPECS[name]
    assert (declared.hparams_cls, declared.action_modes) == (entry.hparams_cls, entry.action_modes)
    assert registry.HPARAMS_MODULES[name].rsplit(".", 1)[0] == registry.MODULES[name].rsplit(".", 1)[0]


@pytest.mark.parametrize("name", registry.built_in())
def test_learning_rates_are_bounded(name):
    """A learning rate of 1e300 (or any > 1) is refused at config load, naming the field, instead of
    reaching Adam and turning the losses into NaN."""
    import dataclasses

    from uavlora_rllib.config_errors import ConfigError

    entry = registry.get(name)
    lr_fields = [f.name for f in dataclasses.fields(entry.hparams_cls) if f.name == "lr" or f.name.startswith("lr_")]
    assert lr_fields, f"{name} has no learning-rate field"
    for field in lr_fields:
        with pytest.raises(ConfigError, match=f"algorithms.{name}.{field}"):
            entry.hparams({field: 1e300})


@pytest.mark.parametrize("name, mode", CASES, ids=IDS)
def test_a_config_from_before_a_field_existed_gets_its_default(name, mode):
    """A checkpoint's config holds the model_config of its day; a field added since (here: every
    field, dropped) reads as its typed default, which by convention is the former behaviour, and the
    module builds from it, while a field the trial set keeps its value (HParamsConfig._model_config_auto_includes)."""
    import dataclasses

    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    scenario = TINY.replace(action_mode=mode)
    entry, config = _build(name, scenario)
    defaults = dataclasses.asdict(entry.hparams_cls())
    for field in defaults:
        del config._model_config[field]  # as if every field were newer than the checkpoint
    assert {k: config.model_config[k] for k in defaults} == defaults
    spec = config.get_default_rl_module_spec()
    spec.observation_space, spec.action_space = team_observation_space(scenario), team_action_space(scenario)
    spec.model_config = config.model_config
    module = spec.build()
    assert sum(p.numel() for p in module.parameters()) > 0
    field = next(f for f, v in defaults.items() if isinstance(v, bool))
    config._model_config[field] = not defaults[field]
    assert config.model_config[field] is (not defaults[field])
