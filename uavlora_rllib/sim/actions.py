"""The agents' actions: their spaces, their checks, and the per-ED allocations they imply.

Two action modes (docs/model.md):
- per_uav: one joint index per UAV, shared by all the EDs it serves,
  index = (sf_idx * n_tp + tp_idx) * n_bw + bw_idx, in [0, n_sf n_tp n_bw);
- per_device: per UAV a vector of length 2 quota + 1: (SF, TP) for each of its quota rows
  (the EDs it serves, in the order of its observation, `Links.slot_of_ed`), then one BW.
"""

from __future__ import annotations

import numpy as np

from uavlora_rllib.sim import physics
from uavlora_rllib.sim.links import Links
from uavlora_rllib.sim.scenario import ScenarioConfig

# per_uav mode: EDs in a batch above which per-UAV table look-ups followed by per-ED gathers
# beat one per-ED look-up in the joint-action decoding table (fewer NumPy calls below it)
PER_UAV_GATHER_MIN = 4096


class ActionError(ValueError):
    """An action outside its space; the message names the agent and the allowed range."""


def as_integers(value: np.ndarray, label: str, what: str) -> np.ndarray:
    """`value` as integers: whole-valued floats (a policy's output) are cast; other floats raise ActionError
    naming `label` (a cast would truncate them silently); range and shape are check_range's."""
    if value.dtype.kind != "f":
        return value
    if not (np.isfinite(value).all() and (value == np.round(value)).all()):
        raise ActionError(f"{label}: expected {what}, got non-integer values {value.tolist()}")
    return value.astype(np.int64)


def per_device_action_len(cfg: ScenarioConfig) -> int:
    return 2 * cfg.quota + 1


def decode_joint_action(a: np.ndarray, cfg: ScenarioConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """per_uav index -> (sf_idx, tp_idx, bw_idx); index = (sf_idx * n_tp + tp_idx) * n_bw + bw_idx."""
    a = np.asarray(a)
    return a // (cfg.n_tp * cfg.n_bw), (a // cfg.n_bw) % cfg.n_tp, a % cfg.n_bw


def encode_joint_action(sf_idx, tp_idx, bw_idx, cfg: ScenarioConfig) -> np.ndarray:
    return (np.asarray(sf_idx) * cfg.n_tp + np.asarray(tp_idx)) * cfg.n_bw + np.asarray(bw_idx)


def check_range(actions: np.ndarray, shape: tuple[int, ...], high) -> None:
    """ActionError unless `actions` is an integer array of `shape` with 0 <= a < high
    (`high` a scalar, or an array broadcast to `shape`)."""
    if actions.shape != shape:
        raise ActionError(f"actions: expected shape {shape}, got {actions.shape}")
    if actions.dtype.kind not in "iu":  # signed or unsigned integers
        raise ActionError(f"actions: expected integers, got dtype {actions.dtype}")
    if np.isscalar(high) and actions.size:
        if actions.size <= 64:  # small: Python's min/max on a list beat two NumPy reductions
            values = actions.ravel().tolist()
            if 0 <= min(values) and max(values) < high:
                return
        elif 0 <= actions.min() and actions.max() < high:
            return
    bad = (actions < 0) | (actions >= high)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        limit = int(np.broadcast_to(high, shape)[idx])  # (a scalar high broadcasts to itself)
        raise ActionError(f"action of uav_{idx[1]} (scenario {idx[0]}): {int(actions[idx])} is outside [0, {limit})")


class ActionDecoder:
    """Checks the actions of N scenarios and decodes them into per-ED allocations [N, V]
    (sf_idx, tp_idx, bw_idx), or into the values the scoring needs, through tables of every
    joint action built once."""

    def __init__(self, cfg: ScenarioConfig, n_envs: int, tables: physics.Tables):
        self.cfg = cfg
        self.n = n_envs
        env_idx = np.arange(n_envs)
        self._env_idx_col = env_idx[:, None]
        self.act_base = (env_idx * cfg.n_uavs)[:, None]  # flat index of (e, 0) in an [N, U] array
        self.n_joint = cfg.n_joint_actions
        self.per_uav_shape = (n_envs, cfg.n_uavs)
        self._per_device_highs = np.array([cfg.n_sf, cfg.n_tp] * cfg.quota + [cfg.n_bw])
        # per_uav action index -> (sf_idx, tp_idx, bw_idx), one row per joint action
        self.joint_table = np.stack(decode_joint_action(np.arange(cfg.n_joint_actions), cfg), axis=-1).astype(np.int64)
        # per_uav action index -> its SF index and (P_W, W_Hz, rho_thr), for per_uav_values
        sf_a, tp_a, bw_a = self.joint_table.T
        self._action_values = (sf_a.copy(), *physics.allocation_values(sf_a, tp_a, bw_a, tables))

    def check_per_uav(self, actions: np.ndarray) -> np.ndarray:
        """per_uav actions [N, U] as an array, checked (ActionError otherwise)."""
        actions = np.asarray(actions)
        check_range(actions, self.per_uav_shape, self.n_joint)
        return actions

    def allocations(self, actions: np.ndarray, links: Links) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-ED (sf_idx, tp_idx, bw_idx) [N, V] implied by the agents' actions this slot."""
        cfg = self.cfg
        actions = np.asarray(actions)
        if cfg.action_mode == "per_uav":
            check_range(actions, self.per_uav_shape, self.n_joint)
            idx = links.serving_idx + self.act_base  # flat index of each ED's serving UAV in [N, U]
            if idx.size <= PER_UAV_GATHER_MIN:  # small: one lookup in the decoding table
                alloc = self.joint_table[actions.reshape(-1).take(idx)]  # [N, V, 3]
                return alloc[..., 0], alloc[..., 1], alloc[..., 2]
            sf, tp, bw = decode_joint_action(actions, cfg)  # [N, U] each, then 3 contiguous gathers
            return sf.reshape(-1).take(idx), tp.reshape(-1).take(idx), bw.reshape(-1).take(idx)
        check_range(actions, (self.n, cfg.n_uavs, per_device_action_len(cfg)), self._per_device_highs)
        slot = np.maximum(links.slot_of_ed, 0)
        per_uav = actions[self._env_idx_col, links.serving_idx]  # [N, V, length]
        sf = np.take_along_axis(per_uav, (2 * slot)[..., None], axis=-1)[..., 0]
        tp = np.take_along_axis(per_uav, (2 * slot + 1)[..., None], axis=-1)[..., 0]
        return sf, tp, per_uav[..., -1]

    def per_uav_values(self, actions: np.ndarray, links: Links) -> tuple[np.ndarray, tuple, tuple]:
        """per_uav mode, large batches: each ED's SF index and (P_W, W_Hz, rho_thr) gathered
        from its serving UAV's values ([N, U]: U table look-ups per scenario instead of V),
        and (actions, flat serving-UAV index), from which previous_allocation gets the TP and
        BW indices when it is asked."""
        actions = self.check_per_uav(actions)
        idx = links.serving_idx + self.act_base  # flat index of each ED's serving UAV in [N, U]
        sf, *values = (table.take(actions).reshape(-1).take(idx) for table in self._action_values)
        return sf, tuple(values), (actions.copy(), idx)  # (a copy: the caller may reuse its array)

    def previous_allocation(self, parts: tuple) -> np.ndarray:
        """[N, V, 3] (sf_idx, tp_idx, bw_idx) from what the scoring kept of a slot: (sf, tp, bw,
        (actions, flat serving index) or None, associated or None when all were). per_uav
        slots keep the actions and are decoded only here (tp None; sf too when shared)."""
        sf, tp, bw, actions_idx, assoc = parts
        if tp is None:  # per_uav: decoded from the actions only now
            actions, idx = actions_idx
            sf_u, tp_u, bw_u = decode_joint_action(actions, self.cfg)
            tp, bw = tp_u.reshape(-1).take(idx), bw_u.reshape(-1).take(idx)
            if sf is None:
                sf = sf_u.reshape(-1).take(idx)
        prev = np.stack((sf, tp, bw), axis=-1)
        if assoc is not None:
            prev[~assoc] = -1
        return prev
