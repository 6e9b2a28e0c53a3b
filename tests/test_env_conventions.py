"""The env views follow PettingZoo's and Gymnasium's conventions (docs/model.md#environments,
docs/model.md#seeds): the `uavlora_v0` factories, render modes, the seeding contract, the
Gymnasium id of the team view, and no Ray import on those paths."""

from __future__ import annotations

import subprocess
import sys
import warnings

import gymnasium
import numpy as np
import pytest
from conftest import make_cfg, random_actions
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import api_test, parallel_api_test, parallel_seed_test, render_test, seed_test

import uavlora_rllib
from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.envs import uavlora_v0
from uavlora_rllib.envs.multi_agent import UavLoraMultiAgentEnv
from uavlora_rllib.envs.parallel import UavLoraParallelEnv
from uavlora_rllib.envs.team import UavLoraTeamEnv, UavLoraTeamVectorEnv
from uavlora_rllib.sim.actions import ActionError
from uavlora_rllib.sim.core import BatchCore

MODES = ["per_uav", "per_device"]
SMALL = {"n_eds": 10, "n_uavs": 2, "episode_len": 12}


# ------------------------------------------------------------------ PettingZoo factories
@pytest.mark.parametrize("mode", MODES)
def test_pettingzoo_tests_pass_on_the_factories(mode):
    kw = {**SMALL, "action_mode": mode}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(uavlora_v0.parallel_env(**kw), num_cycles=30)
        api_test(uavlora_v0.env(**kw), num_cycles=30)
    # api_test's style advice on per_device's MultiDiscrete action space is no protocol slip
    advice = "Action space for each agent probably should be"
    pz = [str(w.message) for w in caught if "pettingzoo" in (w.filename or "") and advice not in str(w.message)]
    assert not pz, pz
    seed_test(lambda: uavlora_v0.env(**kw), num_cycles=30)
    parallel_seed_test(lambda: uavlora_v0.parallel_env(**kw), num_cycles=30)


def test_render_test_passes_for_every_render_mode(capsys):
    render_test(lambda render_mode=None: uavlora_v0.env(render_mode=render_mode, **SMALL))
    lines = capsys.readouterr().out.splitlines()
    # human mode: one line at the reset and one per slot played (render_test plays 4 slots)
    assert len(lines) == 5 and lines[0].startswith("[uavlora] reset; slot 0/12")
    assert all(line.startswith("[uavlora] played slot") and "EE_sys" in line for line in lines[1:])


def test_factories_metadata_and_keywords():
    par = uavlora_v0.parallel_env(n_eds=12, n_uavs=3, mobility={"dt_s": 0.25})
    assert isinstance(par, UavLoraParallelEnv) and par.possible_agents == ["uav_0", "uav_1", "uav_2"]
    assert par.scenario.n_eds == 12
    meta = par.metadata
    assert meta["name"] == "uavlora_v0" and meta["is_parallelizable"] is True
    assert meta["render_modes"] == ["human", "rgb_array"]
    assert meta["render_fps"] == 4.0  # real time: one frame per slot of dt_s = 0.25 s
    assert UavLoraParallelEnv.metadata["render_fps"] == 2  # the class's, for the default dt_s = 0.5 s
    # keywords on top of a scenario mapping; the AEC views wrap the same parallel env
    aec = uavlora_v0.env(scenario={"n_eds": 30, "n_uavs": 2}, n_uavs=4)
    assert isinstance(aec.unwrapped, UavLoraParallelEnv) and aec.unwrapped.scenario.n_eds == 30
    assert len(aec.possible_agents) == 4
    raw = uavlora_v0.raw_env(**SMALL)
    assert type(raw).__name__ == "parallel_to_aec_wrapper" and raw.metadata["render_fps"] == 2.0


@pytest.mark.parametrize(
    "make, kwargs, field",
    [
        (uavlora_v0.parallel_env, {"render_mode": "ansi"}, "render_mode"),
        (uavlora_v0.env, {"render_mode": "rgb_array_list"}, "render_mode"),
        (uavlora_v0.parallel_env, {"n_uavs": 0}, "scenario.n_uavs"),
        (uavlora_v0.parallel_env, {"n_edz": 5}, "n_edz"),
        (uavlora_rllib.envs.team.gym_env, {"render_mode": "ansi"}, "render_mode"),
        (uavlora_rllib.envs.team.gym_vector_env, {"render_mode": "rgb_array"}, "render_mode"),
        (uavlora_rllib.envs.team.gym_vector_env, {"num_envs": 10**12}, "num_envs"),
        (uavlora_rllib.envs.team.gym_vector_env, {"num_envs": 0}, "num_envs"),
        (uavlora_rllib.envs.team.gym_vector_env, {"num_envs": "4"}, "num_envs"),
        (uavlora_v0.parallel_env, {"scenario": [1, 2]}, "scenario"),
        (uavlora_rllib.envs.team.gym_env, {"scenario": "x"}, "scenario"),
    ],
)
def test_bad_input_is_one_error_naming_the_field(make, kwargs, field):
    with pytest.raises(ConfigError) as info:
        make(**kwargs)
    msg = str(info.value)
    assert field in msg and "\n" not in msg
    if field == "render_mode":
        assert "allowed: None" in msg


@pytest.mark.parametrize("seed", [-1, "a", 1.5, True])
@pytest.mark.parametrize(
    "make",
    [
        lambda: uavlora_v0.parallel_env(**SMALL),
        lambda: uavlora_rllib.envs.team.gym_env(**SMALL),
        lambda: uavlora_rllib.envs.team.gym_vector_env(num_envs=2, **SMALL),
    ],
)
def test_a_bad_reset_seed_is_one_error_naming_seed(make, seed):
    with pytest.raises(ConfigError, match=r"^seed: expected a non-negative integer or None, got "):
        make().reset(seed=seed)
    make().reset(seed=2**40)  # any size, as NumPy's SeedSequence (the evaluation's seeds pass 2^32)


def test_the_vector_env_takes_a_seed_per_scenario():
    vec = uavlora_rllib.envs.team.gym_vector_env(num_envs=2, **SMALL)
    first, _ = vec.reset(seed=[3, 7])  # Gymnasium's vector API: int | list[int] | None
    again, _ = vec.reset(seed=[3, 7])
    assert np.array_equal(first, again)
    with pytest.raises(ConfigError, match=r"^seed: expected a non-negative integer or None, got -7"):
        vec.reset(seed=[3, -7])


def test_the_team_env_refuses_fractional_actions_rather_than_truncating():
    env = uavlora_rllib.envs.team.gym_env(**SMALL)
    env.reset(seed=0)
    with pytest.raises(ActionError, match=r"^action: expected integers, got non-integer values \[0\.5, 1\.5\]"):
        env.step(np.array([0.5, 1.5]))
    env.step(np.array([0.0, 1.0]))  # whole-valued floats, as a policy may output, are actions
    vec = uavlora_rllib.envs.team.gym_vector_env(num_envs=2, **SMALL)
    vec.reset(seed=0)
    with pytest.raises(ActionError, match=r"non-integer values"):
        vec.step(np.array([[0, 1], [2.5, 0]]))


def test_human_mode_prints_one_line_per_slot(capsys):
    env = uavlora_v0.parallel_env(render_mode="human", **SMALL)
    env.reset(seed=3)
    for _ in range(SMALL["episode_len"]):
        env.step({a: 0 for a in env.agents})
    assert env.render() is None
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 + SMALL["episode_len"]
    assert lines[-1].startswith("[uavlora] played slot 11: reward") and "slot 12/12" in lines[-1]


# ------------------------------------------------------------------ Gymnasium's seeding contract
def _episodes(env_factory, seeded_with: int, n_resets: int, steps: int, seed_actions: int = 0) -> list[np.ndarray]:
    """Observations of an env reset once with a seed, then `n_resets` times without one."""
    env = env_factory()
    rng = np.random.default_rng(seed_actions)
    out = []
    for k in range(1 + n_resets):
        obs, _ = env.reset(seed=seeded_with) if k == 0 else env.reset()
        out.append(_flat(obs))
        for _ in range(steps):
            action = _sample(env, rng)
            obs = env.step(action)[0]
            out.append(_flat(obs))
    return out


def _flat(obs) -> np.ndarray:
    if isinstance(obs, dict):
        return np.concatenate([np.ravel(obs[a]) for a in sorted(obs)])
    return np.ravel(obs).copy()


def _sample(env, rng):
    if isinstance(env, (UavLoraParallelEnv, UavLoraMultiAgentEnv)):
        arr = random_actions(env.scenario, 1, rng)[0]
        return {a: arr[i] for i, a in enumerate(env.possible_agents)}
    scenario = env.unwrapped.scenario
    if isinstance(env, UavLoraTeamVectorEnv):
        return random_actions(scenario, env.num_envs, rng)
    return random_actions(scenario, 1, rng)[0]


ENV_FACTORIES = {
    "parallel": lambda: UavLoraParallelEnv(SMALL),
    "multi_agent": lambda: UavLoraMultiAgentEnv({"scenario": SMALL}),
    "team": lambda: UavLoraTeamEnv(SMALL),
    "team_vector": lambda: UavLoraTeamVectorEnv(SMALL, num_envs=3),
    "gym_make": lambda: gymnasium.make("UavLora-v0", **SMALL),
}


@pytest.mark.parametrize("name", list(ENV_FACTORIES))
def test_unseeded_reset_continues_the_seeded_stream(name):
    make = ENV_FACTORIES[name]
    a = _episodes(make, 7, n_resets=3, steps=4)
    b = _episodes(make, 7, n_resets=3, steps=4)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    # a continuation, not a replay: the unseeded episodes differ from the seeded one and each other
    starts = [a[k * 5] for k in range(4)]
    assert all(not np.array_equal(starts[i], starts[j]) for i in range(4) for j in range(i))
    # and another seed continues differently
    c = _episodes(make, 8, n_resets=1, steps=0)
    assert not np.array_equal(a[5], c[1])


@pytest.mark.parametrize("n, lookahead", [(1, 0), (1, 32), (4, 0)])
def test_core_continuation_is_the_children_of_the_seed(n, lookahead):
    """After reset(seed=s), an unseeded reset gives scenario i the child i of SeedSequence(s):
    the same episodes the team vector env's autoresets play after a seeded reset."""
    cfg = make_cfg(**SMALL)
    core = BatchCore(cfg, n, lookahead=lookahead)
    seeded = core.reset(5).copy()
    again = core.reset().copy()
    ref = BatchCore(cfg, n)
    np.testing.assert_array_equal(ref.reset(list(np.random.SeedSequence(5).spawn(n))), again)
    np.testing.assert_array_equal(ref.reset(5), seeded)  # seeded resets unchanged: s + i


def test_seeded_reset_unchanged_by_earlier_unseeded_resets():
    core = BatchCore(make_cfg(**SMALL), 2)
    core.reset()
    core.reset()
    np.testing.assert_array_equal(core.reset(11), BatchCore(make_cfg(**SMALL), 2).reset(11))


def test_vector_env_unseeded_reset_after_autoresets_stays_deterministic():
    def run():
        env = UavLoraTeamVectorEnv(SMALL, num_envs=2)
        env.reset(seed=1)
        rng = np.random.default_rng(0)
        for _ in range(SMALL["episode_len"] + 3):  # crosses one autoreset
            env.step(random_actions(env.scenario, 2, rng))
        return env.reset()[0]

    np.testing.assert_array_equal(run(), run())


# ------------------------------------------------------------------ Gymnasium registry
def test_gymnasium_make_and_check_env():
    assert "UavLora-v0" in gymnasium.registry
    env = gymnasium.make("UavLora-v0", **SMALL)
    assert isinstance(env.unwrapped, UavLoraTeamEnv) and env.unwrapped.scenario.episode_len == 12
    check_env(env.unwrapped)
    # with a render mode, check_env also makes and checks one env per supported mode
    check_env(gymnasium.make("UavLora-v0", render_mode="rgb_array", **SMALL).unwrapped)
    frame = gymnasium.make("UavLora-v0", render_mode="rgb_array", **SMALL)
    frame.reset(seed=0)
    image = frame.render()
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3


def test_gymnasium_make_vec_gives_one_batch_core():
    vec = gymnasium.make_vec("UavLora-v0", num_envs=3, vectorization_mode="vector_entry_point", **SMALL)
    assert isinstance(vec, UavLoraTeamVectorEnv) and vec.num_envs == 3
    obs, _ = vec.reset(seed=4)
    assert obs.shape == (3, 2, vec.single_observation_space.shape[1])
    np.testing.assert_array_equal(obs[1], UavLoraTeamEnv(SMALL).reset(seed=5)[0])  # scenario i: seed s + i


def test_registration_is_idempotent():
    from uavlora_rllib.envs.registration import register_gymnasium_ids

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        register_gymnasium_ids()


def test_env_conventions_need_no_ray():
    """The PettingZoo factories and gymnasium.make (module-prefixed id) import neither Ray nor torch."""
    code = (
        "import sys, gymnasium\n"
        "e = gymnasium.make('uavlora_rllib:UavLora-v0', n_eds=10, n_uavs=2); e.reset(seed=0)\n"
        "from uavlora_rllib.envs import uavlora_v0\n"
        "a = uavlora_v0.env(n_eds=10); a.reset(seed=0)\n"
        "print(sorted(m for m in ('ray', 'torch') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
