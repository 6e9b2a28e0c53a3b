"""One error type for bad user input, and the helper that turns pydantic's errors into it.

Every boundary (scenario dicts, grid YAMLs, CLI flags) raises `ConfigError` with a message
that names the offending field by its dotted path and says what is allowed, so a user never
has to read a traceback from deep inside the simulator or RLlib.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any, Mapping

import pydantic


class ConfigError(ValueError):
    """Invalid user input; the message names the field path and the allowed values."""


def _fields_at(root: type | None, loc: tuple[Any, ...]) -> list[str] | None:
    """Field names of the (nested) dataclass that holds the field at `loc`."""
    cls = root
    for part in loc[:-1]:
        if cls is None or not dataclasses.is_dataclass(cls):
            return None
        hints = typing.get_type_hints(cls)
        cls = hints.get(str(part))
    if cls is None or not dataclasses.is_dataclass(cls):
        return None
    return sorted(f.name for f in dataclasses.fields(cls))


def _describe(err: Mapping[str, Any], prefix: str, root: type | None) -> str:
    loc = tuple(err.get("loc", ()))
    path = ".".join(str(p) for p in (prefix, *loc) if p != "")
    kind = err.get("type", "")
    if kind in ("unexpected_keyword_argument", "extra_forbidden"):
        names = _fields_at(root, loc)
        hint = f"; allowed: {', '.join(names)}" if names else ""
        return f"{path}: unknown field{hint}"
    if kind in ("missing", "missing_argument"):
        return f"{path}: required field is missing"
    msg = str(err.get("msg", "invalid value")).removeprefix("Value error, ")
    if kind == "value_error":  # our validators already quote the value
        return f"{path}: {msg}"
    return f"{path}: {msg} (got {err.get('input')!r})"


def from_validation_error(exc: pydantic.ValidationError, prefix: str, root: type | None = None) -> ConfigError:
    """Convert a pydantic ValidationError into one ConfigError listing every problem."""
    return ConfigError("; ".join(_describe(e, prefix, root) for e in exc.errors()))


def build(cls: type, data: Mapping[str, Any] | None, prefix: str) -> Any:
    """Construct pydantic dataclass `cls` from a mapping, raising ConfigError on bad input."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{prefix}: expected a mapping, got {type(data).__name__} {data!r}")
    try:
        return cls(**dict(data))
    except pydantic.ValidationError as exc:
        raise from_validation_error(exc, prefix, root=cls) from None
    except TypeError as exc:  # e.g. a keyword the constructor does not take
        names = ", ".join(sorted(f.name for f in dataclasses.fields(cls)))
        raise ConfigError(f"{prefix}: {exc}; allowed: {names}") from None
