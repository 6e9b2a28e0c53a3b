"""The team view's one-piece connectors sample exactly what RLlib's default pipelines sample.

For every built-in learner and action mode: two env runners of the same trial config, one with
`envs/team_connectors` (what every trial uses) and one with RLlib's default env-to-module and
module-to-env pipelines, the same module weights and the same seeds, sample across episode ends
(the recurrent state restarts there) and on from where a call cut its episodes, in exploration and
greedily. Every episode they return must agree: observations, actions, rewards and every extra
model output (log-probabilities, the GRU state), values, dtypes, item types and structure. On
hand-built episodes the two pieces give what RLlib's default pipelines give, for a recurrent and a
feed-forward module (docs/model.md#acting-connectors). And acting builds no autograd graph
(docs/model.md#batched-agent-networks).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import tree

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)

SCENARIO = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=4)
N_ENVS = 4  # COMA samples whole rounds of all envs: a divisor of its 16 episodes per batch
CASES = [(name, mode) for name in registry.built_in() for mode in registry.get(name).action_modes]


def _runners(name: str, mode: str):
    from ray.rllib.env.single_agent_env_runner import SingleAgentEnvRunner

    entry = registry.get(name)
    resources = registry.Resources(num_envs_per_env_runner=N_ENVS)
    config = entry.build(SCENARIO.replace(action_mode=mode), entry.hparams({}), resources, 0)
    default = config.copy(copy_frozen=False).env_runners(
        env_to_module_connector=None,
        add_default_connectors_to_env_to_module_pipeline=True,
        module_to_env_connector=None,
        add_default_connectors_to_module_to_env_pipeline=True,
    )
    lean_runner, default_runner = SingleAgentEnvRunner(config=config), SingleAgentEnvRunner(config=default)
    default_runner.module.set_state(lean_runner.module.get_state())
    return lean_runner, default_runner


def _columns(episode) -> dict:
    out = {
        "obs": episode.get_observations(),
        "actions": episode.get_actions(),
        "rewards": episode.get_rewards(),
        "t_started": np.asarray(episode.t_started),
        "done": np.asarray(episode.is_done),
    }
    for key in sorted(episode.extra_model_outputs):
        out[key] = episode.get_extra_model_outputs(key)
    return out


def _assert_same(got, want, where: str) -> None:
    tree.assert_same_structure(got, want)
    for (path, a), b in zip(tree.flatten_with_path(got), tree.flatten(want)):
        assert type(a) is type(b), f"{where} {path}: {type(a)} != {type(b)}"
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where} {path}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        np.testing.assert_array_equal(a, b, err_msg=f"{where} {path}")


@pytest.mark.parametrize("name, mode", CASES, ids=[f"{n}-{m}" for n, m in CASES])
def test_team_connectors_sample_what_rllibs_default_pipelines_sample(ray_session, monkeypatch, name, mode):
    lean, default = _runners(name, mode)
    try:
        assert [type(c).__name__ for c in lean._env_to_module.connectors] == ["TeamEnvToModule"]
        assert [type(c).__name__ for c in lean._module_to_env.connectors] == ["TeamModuleToEnv"]
        assert len(default._env_to_module.connectors) > 1 and len(default._module_to_env.connectors) > 1
        steps = N_ENVS * (2 * SCENARIO.episode_len + 2)  # two episode ends per scenario, then a cut episode
        for explore in (True, False):
            # from a reset, then on from where the first call cut its episodes (the state from before the cut)
            for force_reset in (True, False):
                sampled = {}
                for key, runner in (("lean", lean), ("default", default)):
                    torch.manual_seed(7)
                    np.random.seed(7)
                    sampled[key] = runner.sample(num_timesteps=steps, explore=explore, force_reset=force_reset)
                assert len(sampled["lean"]) == len(sampled["default"]) >= 2 * N_ENVS
                for i, (a, b) in enumerate(zip(sampled["lean"], sampled["default"])):
                    _assert_same(_columns(a), _columns(b), f"explore={explore} reset={force_reset} episode {i}")
                assert any(len(e) == SCENARIO.episode_len and e.is_done for e in sampled["lean"])
                assert force_reset or any(e.t_started > 0 for e in sampled["lean"])  # continued chunks
        # acting builds no autograd graph: the GRU's saving Function (for a backward) never runs
        from uavlora_rllib.algorithms.common import gru_sequence

        def _no_backward_expected(*args):
            raise AssertionError("acting ran the GRU's saving autograd Function")

        monkeypatch.setattr(gru_sequence._GRUSequence, "apply", _no_backward_expected)
        module_cls = type(lean.module)
        for method in ("forward_exploration", "forward_inference"):  # and no output carries a graph
            forward = getattr(module_cls, method)

            def _checked(self, batch, _forward=forward, **kwargs):
                out = _forward(self, batch, **kwargs)
                assert not any(torch.is_tensor(x) and x.requires_grad for x in tree.flatten(out)), out.keys()
                return out

            monkeypatch.setattr(module_cls, method, _checked)
        for explore in (True, False):
            lean.sample(num_timesteps=steps, explore=explore, force_reset=True)
    finally:
        lean.stop()
        default.stop()


class _FakeModule:
    """What RLlib's default pieces and the team pieces ask of a module: a recurrent one or not."""

    framework = "torch"

    def __init__(self, stateful: bool):
        self.stateful = stateful

    def is_stateful(self):
        return self.stateful

    def get_initial_state(self):
        return {"h": torch.zeros(2, 4)}


@pytest.mark.parametrize("stateful", [True, False], ids=["recurrent", "feed-forward"])
def test_team_pieces_build_what_the_default_pipelines_build(stateful):
    """Hand-built episodes (one not yet stepped) and module outputs of every kind the pieces handle: a
    feed-forward module (no time rank; no built-in learner is one), a nested state, an [N] column, a
    float64 one, and an ACTIONS_FOR_ENV, against RLlib's default pipelines built by AlgorithmConfig."""
    import gymnasium as gym
    from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
    from ray.rllib.core.columns import Columns
    from ray.rllib.env.single_agent_episode import SingleAgentEpisode

    from uavlora_rllib.envs.team_connectors import TeamEnvToModule, TeamModuleToEnv

    obs_space, act_space = gym.spaces.Box(-1, 1, (2, 3), np.float32), gym.spaces.MultiDiscrete([5, 5])
    obs_space.seed(0)
    act_space.seed(0)
    rng = np.random.default_rng(0)
    episodes = []
    for length in (0, 1, 3):
        episode = SingleAgentEpisode(observation_space=obs_space, action_space=act_space)
        episode.add_env_reset(observation=obs_space.sample())
        for _ in range(length):
            extra = {Columns.ACTION_LOGP: rng.normal(size=2).astype(np.float32)}
            if stateful:
                extra[Columns.STATE_OUT] = {"h": rng.normal(size=(2, 4)).astype(np.float32)}
            episode.add_env_step(
                observation=obs_space.sample(), action=act_space.sample(), reward=1.0, extra_model_outputs=extra
            )
        episodes.append(episode)
    module, config = _FakeModule(stateful), AlgorithmConfig()
    spaces = {"__env_single__": (obs_space, act_space), "__env__": (obs_space, act_space)}
    shared: dict = {}
    want = config.build_env_to_module_connector(spaces=spaces)(
        rl_module=module, episodes=episodes, explore=True, shared_data=shared
    )
    got = TeamEnvToModule()(rl_module=module, batch={}, episodes=episodes, explore=True, shared_data={})
    _assert_same(tree.map_structure(np.asarray, got), tree.map_structure(np.asarray, want), "env-to-module")
    assert (Columns.STATE_IN in got) is stateful

    n, time = len(episodes), ((len(episodes), 1) if stateful else (len(episodes),))
    outputs = {
        Columns.ACTIONS: torch.randint(0, 5, time + (2,)),
        Columns.ACTION_LOGP: torch.randn(time + (2,)),
        "value": torch.randn(time, dtype=torch.float64),
        Columns.ACTIONS_FOR_ENV: torch.randint(0, 5, time + (2,)),
    }
    if stateful:
        outputs[Columns.STATE_OUT] = {"h": torch.randn(n, 2, 4)}
    want = config.build_module_to_env_connector(spaces=spaces)(
        rl_module=module, batch=dict(outputs), episodes=episodes, explore=True, shared_data=shared
    )
    got = TeamModuleToEnv()(rl_module=module, batch=dict(outputs), episodes=episodes, explore=True, shared_data={})
    # the default's normalize_actions makes ACTIONS_FOR_ENV a copy of ACTIONS; the team piece drops it (the
    # env runner then steps the env with ACTIONS)
    np.testing.assert_array_equal(want.pop(Columns.ACTIONS_FOR_ENV), want[Columns.ACTIONS])
    _assert_same(got, want, "module-to-env")


def test_team_module_to_env_refuses_an_env_whose_actions_are_not_discrete():
    import gymnasium as gym

    from uavlora_rllib.envs.team_connectors import team_module_to_env

    class _Env:
        single_action_space = gym.spaces.Box(-1, 1, (2,))

    with pytest.raises(ValueError, match="must be discrete"):
        team_module_to_env(_Env())


def test_module_to_env_samples_from_the_distribution_when_the_module_returns_no_actions():
    """A plugin module that returns only ACTION_DIST_INPUTS: RLlib's GetActions samples its actions."""
    from ray.rllib.core.columns import Columns

    from uavlora_rllib.envs.team_connectors import TeamModuleToEnv

    class _Dist:
        @staticmethod
        def from_logits(logits):
            return _Dist()

        def sample(self):
            return torch.tensor([[1], [0]])

        def logp(self, actions):
            return torch.zeros(actions.shape, dtype=torch.float32)

    class _Module:
        def is_stateful(self):
            return False

        def get_exploration_action_dist_cls(self):
            return _Dist

    out = TeamModuleToEnv()(
        rl_module=_Module(), batch={Columns.ACTION_DIST_INPUTS: torch.zeros(2, 1, 3)}, episodes=[0, 1], explore=True
    )
    np.testing.assert_array_equal(out[Columns.ACTIONS], [[1], [0]])
    assert [x.tolist() for x in out[Columns.ACTION_LOGP]] == [[0.0], [0.0]]
