"""Scenario defaults (docs/model.md#scenario) and bad input: every boundary raises ConfigError or
ActionError (both ValueError) with a message that names the offending field or agent."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.envs.multi_agent import UavLoraMultiAgentEnv, UavLoraParallelEnv
from uavlora_rllib.sim.actions import ActionError, per_device_action_len
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig, flatten


# ------------------------------------------------------------------ defaults
def test_defaults_are_spec_md_table():
    c = ScenarioConfig()
    assert (c.area_m, c.altitude_m, c.n_eds, c.n_uavs) == (1000.0, 90.0, 10, 2)
    assert (c.carrier_hz, c.speed_of_light_mps) == (868e6, 3e8)
    assert (c.los_a, c.los_b, c.eta_los_db, c.eta_nlos_db) == (4.88, 0.43, 0.1, 21.0)
    assert c.noise_dbm == -120.0
    assert c.tp_dbm == (2.0, 5.0, 8.0, 11.0, 14.0)
    assert c.sf_set == (7, 8, 9, 10, 11, 12)
    assert c.bw_khz == (125, 250, 500)
    assert (c.interference, c.rate_model, c.association, c.action_mode) == ("paper", "shannon", "greedy", "per_uav")
    assert c.comm_range_m == 600.0
    assert c.episode_len == 150
    m = c.mobility
    assert (m.memory, m.sigma, m.dt_s, m.v_max_mps) == (0.85, 0.5, 0.5, 1.0)
    assert (m.mean_velocity_init_mps, m.mean_resample_prob) == (0.005, 0.01)
    h = c.hover
    assert (h.n_rotors, h.weight_n, h.air_density, h.solidity) == (4, 20.0, 1.168, 0.045)
    assert (h.disc_area_m2, h.thrust_coef, h.drag_coef, h.induced_factor) == (0.214, 0.001195, 0.011, 0.11)
    assert dataclasses.astuple(c.reward_weights) == (4e-4, 5.0, 1.0, -1e-2)
    assert c.n_joint_actions == 90


def test_w1_follows_the_rate_model_unless_set():
    """reward.w1 null: the paper's 4e-4 under the Shannon rate, 0.1 under the LoRa PHY rate (EE ~230x
    smaller there, docs/model.md#metrics-and-reward); a set w1 wins, and a copy with another rate re-resolves."""
    shannon = ScenarioConfig()
    phy = shannon.replace(rate_model="lora_phy")
    assert shannon.reward.w1 is None and shannon.reward_weights.w1 == 4e-4
    assert phy.reward_weights.w1 == 0.1 and dataclasses.astuple(phy.reward_weights)[1:] == (5.0, 1.0, -1e-2)
    assert phy.replace(reward={"w1": 4e-4}).reward_weights.w1 == 4e-4
    assert ScenarioConfig.from_dict({"rate_model": "lora_phy", "reward": {"w1": 0}}).reward_weights.w1 == 0.0
    assert ScenarioConfig.from_dict(phy.to_dict()).reward_weights.w1 == 0.1  # round trip keeps it null


@pytest.mark.parametrize("v,u", [(10, 2), (20, 4), (40, 6), (60, 8), (100, 8), (7, 3)])
def test_quota_default_is_ceil_1_5_v_over_u(v, u):
    assert ScenarioConfig(n_eds=v, n_uavs=u).quota == math.ceil(1.5 * v / u)
    assert ScenarioConfig(n_eds=v, n_uavs=u, max_eds_per_uav=3).quota == 3


def test_round_trip_and_replace():
    c = ScenarioConfig.from_dict({"n_eds": 20, "mobility": {"sigma": 1.0}, "sf_set": [12, 7]})
    assert c.sf_set == (7, 12)  # sorted
    assert c.mobility.sigma == 1.0 and c.mobility.memory == 0.85  # nested partial update keeps defaults
    assert ScenarioConfig.from_dict(c.to_dict()) == c
    r = c.replace(mobility={"memory": 0.5})
    assert (r.mobility.memory, r.mobility.sigma, r.n_eds) == (0.5, 1.0, 20)
    assert flatten(c)["scenario.mobility.sigma"] == 1.0 and flatten(c)["scenario.quota"] == 15
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.n_eds = 3  # type: ignore[misc]


def test_error_types_are_value_errors():
    assert issubclass(ConfigError, ValueError)
    assert issubclass(ActionError, ValueError)


# ------------------------------------------------------------------ bad scenario input
@pytest.mark.parametrize(
    "data,pattern",
    [
        ({"n_edz": 3}, r"^scenario\.n_edz: unknown field; allowed: .*\bn_eds\b"),
        ({"mobility": {"speed": 1}}, r"^scenario\.mobility\.speed: unknown field; allowed: .*\bv_max_mps\b"),
        ({"reward": {"w5": 1.0}}, r"^scenario\.reward\.w5: unknown field; allowed: w1, w2, w3, w4"),
        ({"n_eds": -5}, r"^scenario\.n_eds: .*greater than or equal to 1.*-5"),
        ({"n_eds": 0}, r"^scenario\.n_eds: "),
        ({"n_eds": "ten"}, r"^scenario\.n_eds: .*integer"),
        ({"n_uavs": 0}, r"^scenario\.n_uavs: "),
        ({"max_eds_per_uav": 0}, r"^scenario\.max_eds_per_uav: "),
        ({"comm_range_m": -1.0}, r"^scenario\.comm_range_m: "),
        ({"sf_set": [6, 7]}, r"^scenario\.sf_set: must be distinct values from \[7, 8, 9, 10, 11, 12\]"),
        ({"sf_set": [7, 13]}, r"^scenario\.sf_set: "),
        ({"sf_set": [7, 7]}, r"^scenario\.sf_set: must be distinct"),
        ({"sf_set": []}, r"^scenario\.sf_set: "),
        ({"bw_khz": [125, 200]}, r"^scenario\.bw_khz: must be distinct values from \[125, 250, 500\]"),
        ({"tp_dbm": [2.0, 50.0]}, r"^scenario\.tp_dbm: .*\[-30, 30\]"),
        ({"interference": "full"}, r"^scenario\.interference: .*'paper'.*'cross_gain'.*'full'"),
        ({"rate_model": "exact"}, r"^scenario\.rate_model: .*'shannon'.*'lora_phy'"),
        ({"association": "random"}, r"^scenario\.association: .*'greedy'.*'optimal'"),
        ({"action_mode": "joint"}, r"^scenario\.action_mode: .*'per_uav'.*'per_device'"),
        ({"mobility": {"memory": 1.5}}, r"^scenario\.mobility\.memory: .*less than or equal to 1"),
        ({"mobility": {"dt_s": 0}}, r"^scenario\.mobility\.dt_s: "),
        ({"mobility": {"mean_resample_prob": -0.1}}, r"^scenario\.mobility\.mean_resample_prob: "),
        ({"hover": {"n_rotors": 0}}, r"^scenario\.hover\.n_rotors: "),
        ({"lora_coding_rate": 5}, r"^scenario\.lora_coding_rate: "),
        ({"episode_len": 0}, r"^scenario\.episode_len: "),
        ({"action_mode": "per_device", "n_eds": 100, "n_uavs": 1}, r"max_eds_per_uav <= 64"),
    ],
)
def test_bad_scenario_fields_name_the_field(data, pattern):
    with pytest.raises(ConfigError, match=pattern):
        ScenarioConfig.from_dict(data)


def test_several_errors_are_reported_together():
    with pytest.raises(ConfigError) as info:
        ScenarioConfig.from_dict({"n_eds": -1, "interference": "x", "foo": 1})
    msg = str(info.value)
    assert "scenario.n_eds" in msg and "scenario.interference" in msg and "scenario.foo" in msg


# ------------------------------------------------------------------ strict numbers, bounded physics
@pytest.mark.parametrize(
    "data,pattern",
    [
        ({"n_eds": True}, r"^scenario\.n_eds: expected an integer in \[1, 10000\], got True \(bool\)$"),
        ({"episode_len": "150"}, r"^scenario\.episode_len: expected an integer .*got '150' \(str\)$"),
        ({"area_m": "1e3"}, r"^scenario\.area_m: expected a number in \[1, 1e\+07\], got '1e3' \(str\)$"),
        ({"area_m": False}, r"^scenario\.area_m: expected a number"),
        ({"altitude_m": math.inf}, r"^scenario\.altitude_m: expected a finite number in \[1, 10000\], got inf$"),
        ({"noise_dbm": -math.inf}, r"^scenario\.noise_dbm: expected a finite number"),
        (
            {"reward": {"w2": math.nan}},
            r"^scenario\.reward\.w2: expected a finite number in \[-1e\+06, 1e\+06\], got nan$",
        ),
        ({"hover": {"n_rotors": True}}, r"^scenario\.hover\.n_rotors: expected an integer"),
        ({"tp_dbm": [2, math.nan]}, r"^scenario\.tp_dbm\.1: expected a finite number, got nan$"),
        ({"sf_set": [7, True]}, r"^scenario\.sf_set\.1: expected an integer, got True"),
        ({"max_eds_per_uav": 10**30}, r"^scenario\.max_eds_per_uav: expected an integer in \[1, 10000\]"),
        ({"area_m": 10**400}, r"^scenario\.area_m: expected a finite number .*\(401 characters\)$"),
        ({"hover": {"thrust_coef": 1e-320}}, r"^scenario\.hover\.thrust_coef: .*greater than or equal to 0.000001"),
        ({"mobility": {"v_max_mps": 1e300}}, r"^scenario\.mobility\.v_max_mps: .*less than or equal to 1000"),
    ],
)
def test_numbers_are_strict_and_bounded(data, pattern):
    with pytest.raises(ConfigError, match=pattern):
        ScenarioConfig.from_dict(data)


def test_ints_are_fine_for_floats_and_none_for_optionals():
    cfg = ScenarioConfig.from_dict({"area_m": 800, "tp_dbm": [2, 14], "max_eds_per_uav": None, "reward": {"w1": 0}})
    assert cfg.area_m == 800.0 and cfg.tp_dbm == (2.0, 14.0) and cfg.reward.w1 == 0.0


def test_every_physical_parameter_is_bounded_and_documented():
    """The finite box the simulator is tested on (tests/test_scenario_properties.py) is the one
    the validator enforces: every float field has both bounds and says them in its description."""
    from uavlora_rllib.sim.scenario import HoverConfig, MobilityConfig, RewardWeights

    for cls in (ScenarioConfig, MobilityConfig, HoverConfig, RewardWeights):
        for name, info in cls.__pydantic_fields__.items():
            if info.annotation is not float:
                continue
            lows = [m for m in info.metadata if hasattr(m, "ge") or hasattr(m, "gt")]
            highs = [m for m in info.metadata if hasattr(m, "le") or hasattr(m, "lt")]
            assert lows and highs, f"{cls.__name__}.{name} is not bounded on both sides"
            assert info.description and any(c in info.description for c in "[("), f"{cls.__name__}.{name}: no range"


def test_a_field_may_document_non_finite_values():
    """The strict-number guard lets a field opt in to inf (allow_inf_nan=True), and only it."""
    from pydantic import Field
    from pydantic.dataclasses import dataclass

    from uavlora_rllib.config_errors import build

    @dataclass(config={"extra": "forbid"})
    class Knobs:
        clip: float = Field(1.0, allow_inf_nan=True, description="inf: no clipping")
        lr: float = 1e-3

    assert build(Knobs, {"clip": math.inf}, "k").clip == math.inf
    with pytest.raises(ConfigError, match=r"^k\.lr: expected a finite number, got inf$"):
        build(Knobs, {"lr": math.inf}, "k")
    with pytest.raises(ConfigError, match=r"^k\.clip: expected a number, got True"):
        build(Knobs, {"clip": True}, "k")


@pytest.mark.parametrize("value", [1, 0, "yes", "false"])
def test_bools_are_strict_too(value):
    from pydantic import Field
    from pydantic.dataclasses import dataclass

    from uavlora_rllib.config_errors import build

    @dataclass(config={"extra": "forbid"})
    class Flags:
        share: bool = True
        n: int | float = Field(1, gt=0)

    assert build(Flags, {"share": False, "n": 2.5}, "f") == Flags(False, 2.5)
    with pytest.raises(ConfigError, match=r"^f\.share: expected true or false, got "):
        build(Flags, {"share": value}, "f")
    with pytest.raises(ConfigError, match=r"^f\.n: expected a number in \(0, inf\), got True"):
        build(Flags, {"n": True}, "f")


def test_bad_input_at_every_entry_point():
    with pytest.raises(ConfigError, match=r"^scenario: expected a mapping, got list"):
        ScenarioConfig.from_dict([("n_eds", 3)])
    with pytest.raises(ConfigError, match=r"^cfg\.n_edz: unknown field"):
        ScenarioConfig.from_dict({"n_edz": 1}, prefix="cfg")
    with pytest.raises(ConfigError, match=r"scenario\.n_eds: "):
        ScenarioConfig().replace(n_eds=-3)
    with pytest.raises(ConfigError, match=r"scenario\.n_edz: unknown field"):
        UavLoraParallelEnv({"n_edz": 3})
    with pytest.raises(ConfigError, match=r"scenario\.sf_set: "):
        UavLoraMultiAgentEnv({"scenario": {"sf_set": [5]}})
    with pytest.raises(ConfigError, match=r"^scenario: expected a ScenarioConfig or a mapping of its fields, got int"):
        UavLoraParallelEnv(42)  # type: ignore[arg-type]


# ------------------------------------------------------------------ bad actions
@pytest.fixture(params=["parallel", "rllib"])
def env_factory(request):
    def make(**fields):
        env = UavLoraParallelEnv(fields) if request.param == "parallel" else UavLoraMultiAgentEnv({"scenario": fields})
        env.reset(seed=0)
        return env

    return make


@pytest.mark.parametrize(
    "actions,pattern",
    [
        ({"uav_0": 90, "uav_1": 0}, r"action of uav_0 .*: 90 is outside \[0, 90\)"),
        ({"uav_0": 0, "uav_1": -1}, r"action of uav_1 .*: -1 is outside \[0, 90\)"),
        ({"uav_0": 0}, r"missing \['uav_1'\]"),
        ({"uav_0": 0, "uav_1": 0, "uav_7": 0}, r"unknown \['uav_7'\]"),
        ({"uav_0": np.array([1, 2]), "uav_1": 0}, r"action of uav_0: expected one integer.*shape \(2,\)"),
        ({"uav_0": 0, "uav_1": 3.5}, r"action of uav_1: expected one integer.*non-integer"),
        ({"uav_0": "7", "uav_1": 0}, r"action of uav_0: expected one integer"),
    ],
)
def test_bad_per_uav_actions(env_factory, actions, pattern):
    env = env_factory()
    with pytest.raises(ActionError, match=pattern):
        env.step(actions)


def test_per_uav_accepts_numpy_scalars_and_integral_floats(env_factory):
    env = env_factory()
    env.step({"uav_0": np.int64(89), "uav_1": np.array([3])})
    env.step({"uav_0": np.float32(5.0), "uav_1": np.uint8(0)})


def test_bad_per_device_actions(env_factory):
    env = env_factory(action_mode="per_device")
    length = per_device_action_len(env.scenario)  # 2 * 8 + 1 = 17
    assert length == 17
    good = np.zeros(length, dtype=np.int64)
    too_big_sf = good.copy()
    too_big_sf[4] = 6  # slot 2's SF index; 6 SFs -> [0, 6)
    with pytest.raises(ActionError, match=r"action of uav_1 .*: 6 is outside \[0, 6\)"):
        env.step({"uav_0": good, "uav_1": too_big_sf})
    too_big_tp = good.copy()
    too_big_tp[1] = 5  # slot 0's TP index; 5 TPs
    with pytest.raises(ActionError, match=r"action of uav_0 .*: 5 is outside \[0, 5\)"):
        env.step({"uav_0": too_big_tp, "uav_1": good})
    too_big_bw = good.copy()
    too_big_bw[-1] = 3  # the gateway's BW index; 3 BWs
    with pytest.raises(ActionError, match=r"action of uav_0 .*: 3 is outside \[0, 3\)"):
        env.step({"uav_0": too_big_bw, "uav_1": good})
    with pytest.raises(ActionError, match=r"action of uav_1 .*: -2 is outside"):
        env.step({"uav_0": good, "uav_1": np.r_[good[:-1], -2]})
    with pytest.raises(ActionError, match=r"action of uav_0: expected 17 integers .*shape \(16,\)"):
        env.step({"uav_0": good[:-1], "uav_1": good})
    with pytest.raises(ActionError, match=r"action of uav_1: expected 17 integers"):
        env.step({"uav_0": good, "uav_1": 3})
    with pytest.raises(ActionError, match=r"missing \['uav_0'\]"):
        env.step({"uav_1": good})
    env.step({"uav_0": good, "uav_1": good})  # the env is still usable after rejected actions


def test_bad_actions_on_the_batch_core():
    cfg = ScenarioConfig()
    core = BatchCore(cfg, 3)
    with pytest.raises(RuntimeError, match="reset"):
        core.step(np.zeros((3, 2), dtype=np.int64))
    core.reset(0)
    with pytest.raises(ActionError, match=r"actions: expected shape \(3, 2\), got \(2, 3\)"):
        core.step(np.zeros((2, 3), dtype=np.int64))
    with pytest.raises(ActionError, match=r"actions: expected integers, got dtype float64"):
        core.step(np.zeros((3, 2)))
    bad = np.zeros((3, 2), dtype=np.int64)
    bad[2, 1] = 90
    with pytest.raises(ActionError, match=r"action of uav_1 \(scenario 2\): 90 is outside \[0, 90\)"):
        core.step(bad)
    with pytest.raises(ValueError, match="n_envs"):
        BatchCore(cfg, 0)
    with pytest.raises(ValueError, match=r"seed: expected 3 seeds, got 2"):
        core.reset([1, 2])
    core.step(np.zeros((3, 2), dtype=np.int64))  # still usable
