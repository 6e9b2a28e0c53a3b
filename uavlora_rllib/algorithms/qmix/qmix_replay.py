"""Episode replay for recurrent value decomposition: whole, fixed-length episodes.

RLlib 2.60's multi-agent episode buffer cannot sample sequences for RNNs, so QMIX/VDN keep
their own ring buffer of |D| episodes (the paper: 32). Every episode of a scenario has the same
length T (truncation at episode_len, never termination), so one episode is one row:

  obs        [T+1, U, d]   o_0 .. o_T (o_T is the final observation after the last step)
  actions    [T, U]        per_uav: one joint action index per UAV
             [T, U, L]     per_device: the action vector of each UAV (L = action_len = 2 quota + 1)
  rewards    [T]
  state      [T+1, S]      s_0 .. s_T (s_T: final state, bootstrapped through at truncation)
  terminated []            True only if the env terminated (never in this project)

Sampling returns whole episodes, so every replayed sequence starts at an episode start and
the learner's GRU unroll starts from a zero hidden state: nothing can leak across episodes.
The buffer lives in the algorithm's driver process and is not part of checkpoints.
"""

from __future__ import annotations

import numpy as np
from ray.rllib.core.columns import Columns

from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE, TERMINATED


class EpisodeReplay:
    def __init__(
        self,
        capacity: int,
        episode_len: int,
        n_agents: int,
        obs_dim: int,
        state_dim: int,
        seed: int | None = None,
        action_len: int | None = None,
    ):
        """action_len: None stores one action per UAV (per_uav), an int a vector of that length (per_device)."""
        if capacity < 1:
            raise ValueError(f"capacity: must be >= 1, got {capacity}")
        c, t, u = capacity, episode_len, n_agents
        self.capacity, self.episode_len = c, t
        self.obs = np.zeros((c, t + 1, u, obs_dim), np.float32)
        self.actions = np.zeros((c, t, u) if action_len is None else (c, t, u, int(action_len)), np.int64)
        self.rewards = np.zeros((c, t), np.float32)
        self.state = np.zeros((c, t + 1, state_dim), np.float32)
        self.terminated = np.zeros(c, bool)
        self.size = 0
        self.next = 0
        self.added = 0  # episodes added over the lifetime
        self.rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs, actions, rewards, state, terminated: bool = False) -> None:
        obs, actions = np.asarray(obs, np.float32), np.asarray(actions, np.int64)
        rewards, state = np.asarray(rewards, np.float32), np.asarray(state, np.float32)
        t = self.episode_len
        if obs.shape != self.obs.shape[1:] or actions.shape != self.actions.shape[1:]:
            raise ValueError(
                f"episode: expected obs {self.obs.shape[1:]} and actions {self.actions.shape[1:]} "
                f"(whole episodes of {t} steps), got {obs.shape} and {actions.shape}"
            )
        if rewards.shape != (t,) or state.shape != self.state.shape[1:]:
            raise ValueError(
                f"episode: expected rewards ({t},) and state {self.state.shape[1:]}, got {rewards.shape}, {state.shape}"
            )
        i = self.next
        self.obs[i], self.actions[i], self.rewards[i], self.state[i] = obs, actions, rewards, state
        self.terminated[i] = bool(terminated)
        self.next = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.added += 1

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """batch_size whole episodes, uniformly (without replacement when the buffer allows)."""
        if self.size == 0:
            raise ValueError("replay: empty")
        idx = self.rng.choice(self.size, size=batch_size, replace=batch_size > self.size)
        return {
            Columns.OBS: self.obs[idx],
            Columns.ACTIONS: self.actions[idx],
            Columns.REWARDS: self.rewards[idx],
            GLOBAL_STATE: self.state[idx],
            TERMINATED: self.terminated[idx],
        }
