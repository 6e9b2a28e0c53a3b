"""The team view's Gymnasium ids, registered by `import uavlora_rllib` (docs/model.md#environments).

    import gymnasium, uavlora_rllib
    env = gymnasium.make("UavLora-v0", n_eds=60, n_uavs=2)
    vec = gymnasium.make_vec("UavLora-v0", num_envs=16, vectorization_mode="vector_entry_point", n_eds=60)

Only the ids and entry-point strings live here: the env modules load when an env is made.
"""

from __future__ import annotations

import gymnasium

GYM_IDS = {"UavLora-v0": ("uavlora_rllib.envs.team:gym_env", "uavlora_rllib.envs.team:gym_vector_env")}


def register_gymnasium_ids() -> None:
    """Register each id once per process (a second import of the package changes nothing)."""
    for env_id, (entry_point, vector_entry_point) in GYM_IDS.items():
        if env_id not in gymnasium.registry:
            # no max_episode_steps: the env truncates itself after episode_len slots
            gymnasium.register(id=env_id, entry_point=entry_point, vector_entry_point=vector_entry_point)
