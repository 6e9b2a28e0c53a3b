"""The scenario: every parameter of the paper's system model, typed, with the defaults of docs/model.md#scenario.

Units are in the field names (``_m``, ``_hz``, ``_dbm``, ``_db``, ``_s``, ``_mps``, ``_n``).
A `ScenarioConfig` is validated once, when it is built (directly or with `from_dict`), and is
immutable afterwards; the simulator, the environments, the baselines and the analysis all
read the same object.

Every physical parameter is bounded (the `Field` bounds below, documented in each field's
description) to a box in which the model's arithmetic (docs/model.md) stays finite in
float64 and the observations stay finite in float32 at every corner: e.g. the path loss stays
below ~450 dB (G >= 1e-45), the noise power above 1e-23 W, the hover power in (1e-7, 1e21) W,
and a reward weight of at most 1e6 times the largest EE_sys (~1e18 bit/J) stays far below
float64's 1.8e308. tests/test_scenario_properties.py steps random configs of this box, its
corners included, and checks that observations, rewards and infos are finite. Input from YAML
or the CLI (`from_dict`) takes numbers strictly: no bool or string for a number, no NaN or inf.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Any, ClassVar, Literal

import pydantic
from pydantic import Field, field_validator, model_validator
from pydantic.dataclasses import dataclass

from uavlora_rllib.config_errors import build

# Most scenarios one BatchCore steps at once (an env runner's num_envs_per_env_runner, a vector env's num_envs):
# far above any use, and below an allocation from a typo.
MAX_ENVS = 100_000

# The paper's Table "SNR rho_thr(Psi, W) in dB" (Yu et al., IEEE Access 2020): SF -> BW(kHz) -> dB.
SNR_THRESHOLD_TABLE_DB: dict[int, dict[int, float]] = {
    7: {125: -7.5, 250: -9.0, 500: -11.0},
    8: {125: -10.0, 250: -12.0, 500: -13.8},
    9: {125: -12.5, 250: -14.5, 500: -16.5},
    10: {125: -15.0, 250: -17.0, 500: -19.0},
    11: {125: -18.0, 250: -20.0, 500: -21.8},
    12: {125: -21.0, 250: -23.0, 500: -25.0},
}
KNOWN_SFS = tuple(sorted(SNR_THRESHOLD_TABLE_DB))
KNOWN_BWS_KHZ = (125, 250, 500)

_STRICT = pydantic.ConfigDict(extra="forbid", frozen=True)

# reward.w1 when it is null, per rate model, sized in per_device mode (docs/model.md#metrics-and-reward): there
# the LoRa PHY rates give ~1/240 of the Shannon EE, where 4e-4 would leave the EE term below the success and margin
# terms and learners would maximise those instead (robust SFs at high TP); 0.1 restores the paper's balance there.
DEFAULT_W1: dict[str, float] = {"shannon": 4e-4, "lora_phy": 0.1}


@dataclass(config=_STRICT)
class MobilityConfig:
    """Gauss-Markov ED mobility, the paper's Eq. (gm), with the decisions of docs/model.md#mobility."""

    memory: float = Field(default=0.85, ge=0.0, le=1.0, description="eth, temporal correlation of the velocity, [0, 1]")
    sigma: float = Field(
        default=0.5, ge=0.0, le=1e3, description="sigma-hat, randomness of the velocity (m/s), [0, 1e3]"
    )
    dt_s: float = Field(default=0.5, gt=0.0, le=3600.0, description="slot duration Delta t (s), (0, 3600]")
    v_max_mps: float = Field(default=1.0, gt=0.0, le=1e3, description="speed clip (m/s), (0, 1e3]")
    mean_velocity_init_mps: float = Field(
        default=0.005, ge=-1e3, le=1e3, description="v-bar on each axis at reset (m/s; the table's 0.005), [-1e3, 1e3]"
    )
    mean_resample_prob: float = Field(
        default=0.01, ge=0.0, le=1.0, description="per-step chance to re-draw v-bar, [0, 1]"
    )


@dataclass(config=_STRICT)
class HoverConfig:
    """Multirotor hover power, the paper's Eq. (hover), Gong et al.'s parameter set."""

    # Lower bounds are positive minima, not "> 0": the formula takes rho^-1/2, A^-1/2 and
    # C_T^-3/2, which overflow for denormal inputs.
    n_rotors: int = Field(default=4, ge=1, le=16, description="rotors n, [1, 16]")
    weight_n: float = Field(
        default=20.0, ge=1e-3, le=1e5, description="total weight (N); per-rotor W_r = weight_n / n_rotors, [1e-3, 1e5]"
    )
    air_density: float = Field(default=1.168, ge=1e-3, le=10.0, description="rho (kg/m^3), [1e-3, 10]")
    solidity: float = Field(default=0.045, ge=1e-4, le=1.0, description="rotor solidity s, [1e-4, 1]")
    disc_area_m2: float = Field(default=0.214, ge=1e-4, le=100.0, description="rotor disc area A (m^2), [1e-4, 100]")
    thrust_coef: float = Field(default=0.001195, ge=1e-6, le=1.0, description="thrust coefficient C_T, [1e-6, 1]")
    drag_coef: float = Field(default=0.011, ge=0.0, le=1.0, description="profile drag coefficient delta, [0, 1]")
    induced_factor: float = Field(default=0.11, ge=0.0, le=10.0, description="induced power correction k, [0, 10]")


@dataclass(config=_STRICT)
class RewardWeights:
    """r = w1 EE_sys + w2 Xi + w3 beta - |w4| P_total (docs/model.md#metrics-and-reward: the w4 term is always a penalty)."""

    # |w| <= 1e6: times the largest EE_sys of the scenario box (~1e18) still finite
    w1: float | None = Field(
        default=None,
        ge=-1e6,
        le=1e6,
        description="weight of EE_sys, [-1e6, 1e6]; null: the rate model's (DEFAULT_W1: 4e-4 Shannon, the paper's; "
        "0.1 LoRa PHY) (docs/model.md#metrics-and-reward)",
    )
    w2: float = Field(default=5.0, ge=-1e6, le=1e6, description="weight of the success rate Xi, [-1e6, 1e6]")
    w3: float = Field(default=1.0, ge=-1e6, le=1e6, description="weight of the SNR-margin score beta, [-1e6, 1e6]")
    w4: float = Field(
        default=-1e-2, ge=-1e6, le=1e6, description="weight of P_total (always a penalty: |w4|), [-1e6, 1e6]"
    )


@dataclass(config=_STRICT)
class ScenarioConfig:
    """Every parameter of the system model. Defaults: docs/model.md#scenario."""

    # constants that change the numbers a trial's slot computes but not how many: a calibration record
    # measured with other values of these prices a trial (experiment/calibration.py, Store.nearest).
    # Not the geometry (which EDs each UAV hears), the LoS/NLoS constants (which pick the link stage:
    # physics/links.py), mobility (its resampling draws) or anything a baseline's search loops on.
    SPEED_NEUTRAL: ClassVar[frozenset[str]] = frozenset(
        {"carrier_hz", "speed_of_light_mps", "noise_dbm", "hover", "reward"}
    )

    n_eds: int = Field(default=10, ge=1, le=10_000, description="V, end devices, [1, 10000]")
    n_uavs: int = Field(default=2, ge=1, le=64, description="U, UAV gateways, [1, 64]")
    area_m: float = Field(default=1000.0, ge=1.0, le=1e7, description="side L of the square area (m), [1, 1e7]")
    altitude_m: float = Field(default=90.0, ge=1.0, le=1e4, description="UAV altitude h (m), [1, 1e4]")
    comm_range_m: float = Field(default=600.0, ge=0.01, le=1e7, description="R_comm, horizontal range (m), [0.01, 1e7]")
    max_eds_per_uav: int | None = Field(
        default=None, ge=1, le=10_000, description="Lambda_max, [1, 10000]; None -> ceil(1.5 V / U)"
    )
    carrier_hz: float = Field(default=868e6, ge=1e6, le=1e11, description="carrier frequency f (Hz), [1e6, 1e11]")
    speed_of_light_mps: float = Field(
        default=3e8, ge=1e6, le=1e9, description="c in the free-space term (m/s), [1e6, 1e9]"
    )
    los_a: float = Field(
        default=4.88, ge=0.0, le=100.0, description="Al-Hourani 'a' (vartheta), elevation in degrees, [0, 100]"
    )
    los_b: float = Field(default=0.43, ge=0.0, le=5.0, description="Al-Hourani 'b' (lambda), [0, 5]")
    eta_los_db: float = Field(default=0.1, ge=0.0, le=150.0, description="excess loss in LoS (dB), [0, 150]")
    eta_nlos_db: float = Field(default=21.0, ge=0.0, le=150.0, description="excess loss in NLoS (dB), [0, 150]")
    noise_dbm: float = Field(default=-120.0, ge=-200.0, le=30.0, description="noise power sigma^2 (dBm), [-200, 30]")
    tp_dbm: tuple[float, ...] = (2.0, 5.0, 8.0, 11.0, 14.0)  # distinct, each in [-30, 30] dBm
    sf_set: tuple[int, ...] = (7, 8, 9, 10, 11, 12)
    bw_khz: tuple[int, ...] = (125, 250, 500)
    interference: Literal["paper", "cross_gain"] = "paper"
    rate_model: Literal["shannon", "lora_phy"] = "shannon"
    lora_coding_rate: int = Field(default=1, ge=1, le=4)  # CR in 4/(4+CR), used by rate_model=lora_phy
    association: Literal["greedy", "optimal"] = "greedy"
    action_mode: Literal["per_uav", "per_device"] = "per_uav"
    episode_len: int = Field(default=150, ge=1, le=1_000_000, description="T, slots per episode, [1, 1e6]")
    mobility: MobilityConfig = dataclasses.field(default_factory=MobilityConfig)
    hover: HoverConfig = dataclasses.field(default_factory=HoverConfig)
    reward: RewardWeights = dataclasses.field(default_factory=RewardWeights)

    @field_validator("sf_set")
    @classmethod
    def _check_sfs(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        bad = [s for s in v if s not in KNOWN_SFS]
        if bad or not v or len(set(v)) != len(v):
            raise ValueError(f"must be distinct values from {list(KNOWN_SFS)}, got {list(v)}")
        return tuple(sorted(v))

    @field_validator("bw_khz")
    @classmethod
    def _check_bws(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        bad = [b for b in v if b not in KNOWN_BWS_KHZ]
        if bad or not v or len(set(v)) != len(v):
            raise ValueError(f"must be distinct values from {list(KNOWN_BWS_KHZ)}, got {list(v)}")
        return tuple(sorted(v))

    @field_validator("tp_dbm")
    @classmethod
    def _check_tps(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v or len(set(v)) != len(v) or not all(math.isfinite(x) and -30 <= x <= 30 for x in v):
            raise ValueError(f"must be distinct finite dBm values in [-30, 30], got {list(v)}")
        return tuple(sorted(v))

    @model_validator(mode="after")
    def _check_quota(self) -> ScenarioConfig:
        if self.action_mode == "per_device" and self.quota > 64:
            raise ValueError(
                f"action_mode per_device needs max_eds_per_uav <= 64 (action slots), got quota {self.quota}"
            )
        return self

    # ---- derived quantities (read-only; never stored twice) ----
    @property
    def quota(self) -> int:
        """Lambda_max: max EDs per UAV (docs/model.md#association: ceil(1.5 V / U) unless set)."""
        if self.max_eds_per_uav is not None:
            return self.max_eds_per_uav
        return math.ceil(1.5 * self.n_eds / self.n_uavs)

    @property
    def n_sf(self) -> int:
        return len(self.sf_set)

    @property
    def n_tp(self) -> int:
        return len(self.tp_dbm)

    @property
    def n_bw(self) -> int:
        return len(self.bw_khz)

    @property
    def n_joint_actions(self) -> int:
        """Size of the per_uav action: one (SF, TP, BW) triple, 90 with the paper's sets."""
        return self.n_sf * self.n_tp * self.n_bw

    @functools.cached_property
    def reward_weights(self) -> RewardWeights:
        """The reward's weights as the env applies them: a null w1 is the rate model's DEFAULT_W1
        (resolved once per config: every slot's reward reads it)."""
        if self.reward.w1 is not None:
            return self.reward
        return dataclasses.replace(self.reward, w1=DEFAULT_W1[self.rate_model])

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> ScenarioConfig:
        """A validated copy with some fields changed (nested groups as dicts or objects)."""
        merged = self.to_dict()
        for key, value in changes.items():
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                value = dataclasses.asdict(value)
            if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        return ScenarioConfig.from_dict(merged)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, prefix: str = "scenario") -> ScenarioConfig:
        """Build from a plain mapping (a YAML section); raises ConfigError naming the bad field."""
        return build(cls, data, prefix)


def flatten(cfg: ScenarioConfig, prefix: str = "scenario") -> dict[str, Any]:
    """Dotted key -> scalar, for MLflow params and trial tables."""
    out: dict[str, Any] = {}

    def walk(obj: Any, path: str) -> None:
        if isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, f"{path}.{k}")
        else:
            out[path] = list(obj) if isinstance(obj, tuple) else obj

    walk(cfg.to_dict(), prefix)
    out[f"{prefix}.quota"] = cfg.quota
    return out


def off_defaults(cfg: ScenarioConfig, shown: tuple[str, ...] = ()) -> list[str]:
    """`cfg`'s settings off ScenarioConfig's defaults (the paper's scenario) at its own V and U, as
    `name=value` in field order, leaving out the `shown` ones (V and U always): what makes a result
    another scenario's than the paper's."""
    skip = {f"scenario.{k}" for k in ("n_eds", "n_uavs", "quota", *shown)}
    ours, paper = flatten(cfg), flatten(ScenarioConfig(n_eds=cfg.n_eds, n_uavs=cfg.n_uavs))
    return [f"{k[len('scenario.') :]}={v}" for k, v in ours.items() if k not in skip and v != paper.get(k)]
