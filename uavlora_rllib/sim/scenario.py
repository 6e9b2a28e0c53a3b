"""The scenario: every parameter of the paper's system model, typed, with SPEC.md's defaults.

Units are in the field names (``_m``, ``_hz``, ``_dbm``, ``_db``, ``_s``, ``_mps``, ``_n``).
A `ScenarioConfig` is validated once, when it is built (directly or with `from_dict`), and is
immutable afterwards; the simulator, the environments, the baselines and the analysis all
read the same object.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Literal, Mapping

import pydantic
from pydantic import Field, field_validator, model_validator
from pydantic.dataclasses import dataclass

from uavlora_rllib.config_errors import build

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


@dataclass(config=_STRICT)
class MobilityConfig:
    """Gauss-Markov ED mobility, the paper's Eq. (gm), with SPEC.md's decisions."""

    memory: float = Field(0.85, ge=0.0, le=1.0)  # eth, temporal correlation of the velocity
    sigma: float = Field(0.5, ge=0.0)  # sigma-hat, randomness of the velocity (m/s)
    dt_s: float = Field(0.5, gt=0.0)  # slot duration Delta t
    v_max_mps: float = Field(1.0, gt=0.0)  # speed clip
    mean_velocity_init_mps: float = 0.005  # v-bar on each axis at reset (the table's 0.005)
    mean_resample_prob: float = Field(0.01, ge=0.0, le=1.0)  # per-step chance to re-draw v-bar


@dataclass(config=_STRICT)
class HoverConfig:
    """Multirotor hover power, the paper's Eq. (hover), Gong et al.'s parameter set."""

    n_rotors: int = Field(4, ge=1)
    weight_n: float = Field(20.0, gt=0.0)  # total weight; per-rotor W_r = weight_n / n_rotors
    air_density: float = Field(1.168, gt=0.0)  # kg/m^3
    solidity: float = Field(0.045, gt=0.0)
    disc_area_m2: float = Field(0.214, gt=0.0)
    thrust_coef: float = Field(0.001195, gt=0.0)
    drag_coef: float = Field(0.011, ge=0.0)
    induced_factor: float = Field(0.11, ge=0.0)


@dataclass(config=_STRICT)
class RewardWeights:
    """r = w1 EE_sys + w2 Xi + w3 beta - |w4| P_total (SPEC.md: the w4 term is always a penalty)."""

    w1: float = 4e-4
    w2: float = 5.0
    w3: float = 1.0
    w4: float = -1e-2


@dataclass(config=_STRICT)
class ScenarioConfig:
    """Every parameter of the system model. Defaults: SPEC.md's scenario table."""

    n_eds: int = Field(10, ge=1, le=10_000)
    n_uavs: int = Field(2, ge=1, le=64)
    area_m: float = Field(1000.0, gt=0.0)
    altitude_m: float = Field(90.0, gt=0.0)
    comm_range_m: float = Field(600.0, gt=0.0)
    max_eds_per_uav: int | None = Field(None, ge=1)  # Lambda_max; None -> ceil(1.5 V / U)
    carrier_hz: float = Field(868e6, gt=0.0)
    speed_of_light_mps: float = Field(3e8, gt=0.0)
    los_a: float = 4.88  # Al-Hourani 'a' (vartheta), elevation in degrees
    los_b: float = 0.43  # Al-Hourani 'b' (lambda)
    eta_los_db: float = 0.1
    eta_nlos_db: float = 21.0
    noise_dbm: float = -120.0
    tp_dbm: tuple[float, ...] = (2.0, 5.0, 8.0, 11.0, 14.0)
    sf_set: tuple[int, ...] = (7, 8, 9, 10, 11, 12)
    bw_khz: tuple[int, ...] = (125, 250, 500)
    interference: Literal["paper", "cross_gain"] = "paper"
    rate_model: Literal["shannon", "lora_phy"] = "shannon"
    lora_coding_rate: int = Field(1, ge=1, le=4)  # CR in 4/(4+CR), used by rate_model=lora_phy
    association: Literal["greedy", "optimal"] = "greedy"
    action_mode: Literal["per_uav", "per_device"] = "per_uav"
    episode_len: int = Field(150, ge=1)
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
    def _check_quota(self) -> "ScenarioConfig":
        if self.action_mode == "per_device" and self.quota > 64:
            raise ValueError(
                f"action_mode per_device needs max_eds_per_uav <= 64 (action slots), got quota {self.quota}"
            )
        return self

    # ---- derived quantities (read-only; never stored twice) ----
    @property
    def quota(self) -> int:
        """Lambda_max: max EDs per UAV (SPEC.md: ceil(1.5 V / U) unless set)."""
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

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def replace(self, **changes: Any) -> "ScenarioConfig":
        """A validated copy with some fields changed (nested groups as dicts or objects)."""
        merged = self.to_dict()
        for key, value in changes.items():
            if dataclasses.is_dataclass(value):
                value = dataclasses.asdict(value)
            if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
                merged[key] = {**merged[key], **value}
            else:
                merged[key] = value
        return ScenarioConfig.from_dict(merged)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None, prefix: str = "scenario") -> "ScenarioConfig":
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
