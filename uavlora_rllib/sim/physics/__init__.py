"""The paper's system model, one pure vectorised function per equation.

Every function broadcasts over leading batch dimensions. The simulator core, the
environments, the baselines and the analysis all call these functions; no equation is
written anywhere else. Equation labels, e.g. Eq. (gm), are those of the paper (Ahmed et al.,
VTC2026-Spring), each restated in docs/model.md; where the project decides something the paper
leaves open (docs/model.md#decisions), the docstring says so.

The modules, in the order the equations are applied:

- `arrays`: gathers, per-group sums, clipping, unit and dB conversions;
- `channel`: UAV positions, distances, and the ground-to-air channel, Eqs. (plos), (a2g_pl);
- `radio`: LoRa SNR thresholds, SNR, SINR (Eq. sinr) and bit rate (Eq. shannon);
- `reward_terms`: hover power (Eq. hover), energy efficiency (Eq. sys_ee), success rate,
  margin score, total power and the reward (Eq. reward);
- `slot`: one slot end to end (`Tables`, `slot_metrics`, `slot_metrics_shared`).

Callers use this package's namespace (`physics.slot_metrics`); the names below are its API.
"""

from uavlora_rllib.sim.physics.arrays import (
    CLIP_MIN,
    DB_FLOOR,
    at_least,
    at_serving,
    clip,
    db_threshold_lin,
    db_to_lin,
    dbm_to_w,
    group_count,
    group_sum,
    lin_to_db,
)
from uavlora_rllib.sim.physics.channel import (
    channel_gain,
    channel_gain_sq,
    elevation_deg,
    gain_decreases_with_distance,
    horizontal_distance_sq,
    horizontal_distance_sq_to,
    los_probability,
    path_loss_db,
    uav_positions,
)
from uavlora_rllib.sim.physics.radio import (
    lora_phy_bit_rate,
    rate_bps,
    sinr_cross_gain,
    sinr_paper,
    snr,
    snr_threshold_db,
)
from uavlora_rllib.sim.physics.reward_terms import (
    energy_efficiency,
    hover_power_w,
    margin_score,
    reward,
    success_rate,
    total_power_w,
)
from uavlora_rllib.sim.physics.slot import (
    SLOT_METRICS,
    SharedAllocation,
    SharedAllocationTable,
    Tables,
    allocation_values,
    shared_allocation,
    slot_metrics,
    slot_metrics_shared,
)

__all__ = [
    "CLIP_MIN",
    "DB_FLOOR",
    "SLOT_METRICS",
    "SharedAllocation",
    "SharedAllocationTable",
    "Tables",
    "allocation_values",
    "at_least",
    "at_serving",
    "channel_gain",
    "channel_gain_sq",
    "clip",
    "db_to_lin",
    "dbm_to_w",
    "elevation_deg",
    "energy_efficiency",
    "gain_decreases_with_distance",
    "group_count",
    "group_sum",
    "horizontal_distance_sq",
    "horizontal_distance_sq_to",
    "hover_power_w",
    "db_threshold_lin",
    "lin_to_db",
    "los_probability",
    "margin_score",
    "path_loss_db",
    "lora_phy_bit_rate",
    "rate_bps",
    "reward",
    "shared_allocation",
    "sinr_cross_gain",
    "sinr_paper",
    "slot_metrics",
    "slot_metrics_shared",
    "snr",
    "snr_threshold_db",
    "success_rate",
    "total_power_w",
    "uav_positions",
]
