"""The part of the hyperparameter convention (common/config.py) that needs neither Ray nor torch:
the field types and checks the algorithms' typed configs share, and their listing. The typed configs
themselves live in each algorithm's `hparams.py`, so that a grid's validation, `tune --dry-run` and
`--list-hparams` read them without importing RLlib (registry.spec)."""

from __future__ import annotations

import typing
from typing import Annotated, Any, Literal

from pydantic import Field

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.sim.scenario import ScenarioConfig

# Upper bounds of the size and count hyperparameters: far above any use, and low enough that a typo (10**9)
# is refused when the grid loads instead of failing an allocation inside a trial.
MAX_WIDTH = 8192  # units of one layer
MAX_EPISODES = 100_000  # episodes in a batch or a replay
MAX_UPDATES = 100_000  # epochs, minibatches, updates or critic steps per iteration; n-step and sequence length in slots
MAX_UPDATE_COUNT = 10**9  # updates over a whole run
MAX_ENV_STEPS = 10**12  # env steps of a run, as stop.env_steps


def check_actor_heads(share_actor: bool, actor_agent_heads: bool, path: str) -> None:
    """Per-UAV output heads sit on a shared actor; with one actor per UAV they have nothing to add."""
    if actor_agent_heads and not share_actor:
        raise ConfigError(
            f"{path}.actor_agent_heads: true needs share_actor: true (one actor per UAV already has "
            "its own output layer); allowed: false, or share_actor: true"
        )


# The per_device actor's output (common/per_ed_actor.py), one field type for every actor-critic learner
ActorHeadsName = Literal["flat", "per_slot", "shared"]
ActorHeads = Annotated[
    ActorHeadsName,
    Field(
        description="per_device actor output: 'flat' (one output layer for every branch) | 'per_slot' (a head "
        "per ED slot reading that ED's own observation row) | 'shared' (one such head for all slots, + the "
        "slot's one-hot) (docs/model.md#mappo-and-ippo-per-device)"
    ),
]


# MAPPO's and IPPO's `actor_heads` when the grid leaves it null: per-ED heads in per_device mode, where an
# ED's (SF, TP) must follow its own row and the flat actor stays near the best constant
# (docs/model.md#mappo-and-ippo-per-device), and the flat actor in per_uav mode, which has no per-ED actions.
DEFAULT_ACTOR_HEADS = {"per_device": "shared", "per_uav": "flat"}


def resolve_actor_heads(actor_heads: str | None, per_device: bool) -> str:
    """`actor_heads` as set, or its action mode's default (DEFAULT_ACTOR_HEADS) when null."""
    if actor_heads is not None:
        return actor_heads
    return DEFAULT_ACTOR_HEADS["per_device" if per_device else "per_uav"]


def check_per_ed_heads(actor_heads: str | None, actor_agent_heads: bool, scenario: ScenarioConfig, path: str) -> None:
    """Per-ED heads act per ED, and replace the output layer that per-UAV heads would add to.
    A null `actor_heads` takes its action mode's default, so it passes here unless per-UAV heads
    are asked for in per_device mode."""
    if actor_heads is None:
        if actor_agent_heads and scenario.action_mode == "per_device":
            raise ConfigError(
                f"{path}.actor_agent_heads: true needs actor_heads: flat in per_device mode (the default there is "
                "'shared', per-ED heads); allowed: false, or actor_heads: flat"
            )
        return
    if actor_heads != "flat" and scenario.action_mode != "per_device":
        raise ConfigError(
            f"{path}.actor_heads: {actor_heads!r} needs action_mode per_device (per-ED heads act per ED); "
            "allowed with per_uav: 'flat'"
        )
    if actor_heads != "flat" and actor_agent_heads:
        raise ConfigError(
            f"{path}.actor_agent_heads: true only with actor_heads 'flat'; allowed: false, or actor_heads: flat"
        )


def type_name(ann: Any) -> str:
    """A field's type as written in Python (`tuple[int, ...]`), its constraints (Annotated metadata) left out:
    the field's description states them."""
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if origin is Annotated:
        return type_name(args[0])
    if isinstance(ann, type) and not args:
        return ann.__name__
    if origin is tuple and args:
        return "tuple[" + ", ".join("..." if a is Ellipsis else type_name(a) for a in args) + "]"
    return str(ann).replace("typing.", "")


def describe_hparams(cls: type[Any]) -> str:
    """One block per field: name, type and default, then its description (--list-hparams)."""
    lines = []
    for name, info in cls.__pydantic_fields__.items():  # pydantic's FieldInfo of each field, in order
        lines.append(f"{name} ({type_name(info.annotation)}, default {info.default!r})")
        lines.append(f"    {info.description or '(no description)'}")
    return "\n".join(lines)
