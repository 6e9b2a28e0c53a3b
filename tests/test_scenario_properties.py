"""Property test: every scenario the validator accepts steps to finite numbers.

Random configs are drawn from the whole box `ScenarioConfig` allows (docs/model.md's ranges,
the Field bounds of sim/scenario.py), each physical parameter at its lower bound, its upper
bound, its default or anywhere in between, so the corners are tried on purpose. Each config is
stepped through both environments (PettingZoo and RLlib) and the cheap baselines, and the
observations, global state, rewards and every info must be finite. Floating-point overflow,
invalid operations and divisions by zero are errors here (underflow to 0 is legitimate: a
gain of 1e-45 is a real, tiny gain).
"""

from __future__ import annotations

import math

import numpy as np
from conftest import random_actions
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uavlora_rllib.baselines.policies import make_baseline
from uavlora_rllib.envs.multi_agent import STATE_KEY, UavLoraMultiAgentEnv, UavLoraParallelEnv
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import HoverConfig, MobilityConfig, RewardWeights, ScenarioConfig


def _bounds(cls: type, name: str) -> tuple[float, float]:
    """(lower, upper) bound of a numeric field, from its pydantic constraints."""
    low, high = -math.inf, math.inf
    for m in cls.__pydantic_fields__[name].metadata:
        if hasattr(m, "gt"):  # the smallest value above an exclusive bound is its extreme
            low = math.nextafter(m.gt, math.inf)
        low = getattr(m, "ge", low)
        if hasattr(m, "lt"):
            high = math.nextafter(m.lt, -math.inf)
        high = getattr(m, "le", high)
    return low, high


def _value(cls: type, name: str, default: float):
    """A strategy over the field's range: its ends and its default, or any finite value in between."""
    low, high = _bounds(cls, name)
    assert math.isfinite(low) and math.isfinite(high), f"{cls.__name__}.{name} must be bounded"
    if isinstance(default, int) and not isinstance(default, bool):
        return st.sampled_from([int(low), int(high), default]) | st.integers(int(low), int(high))
    return st.sampled_from([low, high, default]) | st.floats(low, high, allow_nan=False, allow_infinity=False)


PHYSICAL = (
    "area_m",
    "altitude_m",
    "comm_range_m",
    "carrier_hz",
    "speed_of_light_mps",
    "los_a",
    "los_b",
    "eta_los_db",
    "eta_nlos_db",
    "noise_dbm",
)


@st.composite
def scenarios(draw) -> ScenarioConfig:
    default = ScenarioConfig()
    fields = {name: draw(_value(ScenarioConfig, name, getattr(default, name))) for name in PHYSICAL}
    groups = {
        "mobility": (MobilityConfig, MobilityConfig()),
        "hover": (HoverConfig, HoverConfig()),
        "reward": (RewardWeights, RewardWeights()),
    }
    for key, (cls, obj) in groups.items():
        fields[key] = {f: draw(_value(cls, f, getattr(obj, f))) for f in cls.__pydantic_fields__ if draw(st.booleans())}
    tp = draw(st.lists(st.sampled_from([-30.0, -10.0, 0.0, 14.0, 30.0]), min_size=1, max_size=3, unique=True))
    fields.update(
        n_eds=draw(st.integers(1, 8)),
        n_uavs=draw(st.integers(1, 3)),
        tp_dbm=tp,
        sf_set=draw(st.lists(st.sampled_from([7, 9, 12]), min_size=1, max_size=3, unique=True)),
        bw_khz=draw(st.lists(st.sampled_from([125, 250, 500]), min_size=1, max_size=3, unique=True)),
        interference=draw(st.sampled_from(["paper", "cross_gain"])),
        rate_model=draw(st.sampled_from(["shannon", "lora_phy"])),
        association=draw(st.sampled_from(["greedy", "optimal"])),
        action_mode=draw(st.sampled_from(["per_uav", "per_device"])),
        max_eds_per_uav=draw(st.none() | st.integers(1, 6)),
        episode_len=3,
    )
    return ScenarioConfig.from_dict(fields)


def _finite_infos(infos: dict) -> None:
    for agent, info in infos.items():
        for key, value in info.items():
            assert np.isfinite(np.asarray(value, dtype=np.float64)).all(), (agent, key, value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cfg=scenarios(), seed=st.integers(0, 2**32 - 1))
def test_valid_scenarios_step_to_finite_values(cfg, seed):
    rng = np.random.default_rng(seed)
    with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):
        core = BatchCore(cfg, 2)
        core.reset(seed)
        for _ in range(cfg.episode_len):
            res = core.step(random_actions(cfg, 2, rng))
            assert np.isfinite(res.obs).all() and np.isfinite(core.state()).all()
            assert np.isfinite(res.reward).all()
            for key, value in res.metrics.items():
                assert np.isfinite(value).all(), key

        pz = UavLoraParallelEnv(cfg)
        obs, _ = pz.reset(seed=seed)
        while pz.agents:
            assert all(np.isfinite(o).all() for o in obs.values())
            acts = random_actions(cfg, 1, rng)[0]
            obs, rew, _, _, infos = pz.step(dict(zip(pz.agents, acts)))
            assert all(math.isfinite(r) for r in rew.values())
            _finite_infos(infos)
            assert np.isfinite(pz.state()).all()

        env = UavLoraMultiAgentEnv({"scenario": cfg.to_dict()})
        obs, infos = env.reset(seed=seed)
        for _ in range(cfg.episode_len):
            acts = random_actions(cfg, 1, rng)[0]
            obs, rew, _, truncs, infos = env.step(dict(zip(env.possible_agents, acts)))
            assert all(np.isfinite(o).all() for o in obs.values())
            assert all(math.isfinite(r) for r in rew.values())
            _finite_infos({a: {k: v for k, v in i.items() if k != STATE_KEY} for a, i in infos.items()})
            assert all(np.isfinite(i[STATE_KEY]).all() for i in infos.values())
        assert truncs["__all__"]

        for name in ("random", "fixed", "adr"):
            policy = make_baseline(name, cfg, seed=0)
            core.reset(seed)
            policy.reset(core)
            res = core.step(policy.act(core))
            assert np.isfinite(res.reward).all(), name
