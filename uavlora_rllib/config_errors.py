"""One error type for bad user input, and the helper that turns pydantic's errors into it.

Every boundary (scenario dicts, grid YAMLs, CLI flags) raises `ConfigError` with a message
that names the offending field by its dotted path and says what is allowed, so a user never
has to read a traceback from deep inside the simulator or RLlib.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from typing import Annotated, Any

import annotated_types
import pydantic


class ConfigError(ValueError):
    """Invalid user input; the message names the field path and the allowed values."""


def exception_line(exc: BaseException) -> str:
    """`Type: message` on one line, for an error raised by user code (a plugin) that is reported, not shown
    as a traceback."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split()) or '(no message)'}"


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


# --------------------------------------------------------------------------- strict numbers
# pydantic's lax mode turns `true` into 1, "3" into 3 and 0 into false, and accepts NaN and
# inf. User input (YAML, CLI) goes through `build`, which refuses all of these for every number
# (and bool) field of the class it builds, in nested groups, lists, tuples and dict values
# too, before pydantic sees the data; ints beyond int64 are refused as well. A field that
# documents non-finite values opts in with `Field(allow_inf_nan=True)`. This covers every
# class built through `build` (scenario, grid, resources, each algorithm's hyperparameters)
# without each class having to remember a strict flag.


INT64_MAX = 2**63 - 1


def _show(value: Any) -> str:
    """repr of a value, shortened (a 400-digit integer is not worth a terminal screen)."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:20]}...{text[-8:]} ({len(text)} characters)"


def _describe_range(metadata: list[Any]) -> str:
    """' in [lo, hi]' style text from pydantic's constraint metadata (Ge/Gt/Le/Lt)."""
    low = high = None
    for m in metadata:
        for item in getattr(m, "metadata", None) or [m]:  # a FieldInfo nested in Annotated
            if isinstance(item, annotated_types.Ge):
                low = f"[{item.ge:g}"
            elif isinstance(item, annotated_types.Gt):
                low = f"({item.gt:g}"
            elif isinstance(item, annotated_types.Le):
                high = f"{item.le:g}]"
            elif isinstance(item, annotated_types.Lt):
                high = f"{item.lt:g})"
    if low is None and high is None:
        return ""
    return f" in {low or '(-inf'}, {high or 'inf)'}"


def _allows_non_finite(metadata: list[Any]) -> bool:
    for m in metadata:
        for item in getattr(m, "metadata", None) or [m]:
            if isinstance(item, pydantic.AllowInfNan) and item.allow_inf_nan:
                return True
    return False


def _scalar_problems(hint: Any, value: Any, path: str, metadata: list[Any]) -> list[str]:
    """Problems of `value` against the type `hint` that pydantic's lax mode would let through."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Annotated:
        return _scalar_problems(args[0], value, path, [*metadata, *args[1:]])
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return []
        options = [a for a in args if a is not type(None)]
        if len(options) > 1 and set(options) <= {int, float}:  # int | float: a number
            options = [float]
        return _scalar_problems(options[0], value, path, metadata) if len(options) == 1 else []
    if hint is bool and not isinstance(value, bool):  # lax mode reads 0, 1, "yes", "off"... as bools
        return [f"{path}: expected true or false, got {_show(value)} ({type(value).__name__})"]
    if hint is float or hint is int:
        kind = "a number" if hint is float else "an integer"
        allowed = f"{kind}{_describe_range(metadata)}"
        if isinstance(value, (bool, str)) or not isinstance(value, (int, float)):
            return [f"{path}: expected {allowed}, got {_show(value)} ({type(value).__name__})"]
        if hint is int and isinstance(value, int) and not -INT64_MAX - 1 <= value <= INT64_MAX:
            # beyond what NumPy, torch and Ray hold (and an unbounded field would pass it on)
            return [f"{path}: expected {allowed} within the 64-bit range, got {_show(value)}"]
        if hint is float and not _allows_non_finite(metadata):
            try:
                finite = math.isfinite(float(value))
            except OverflowError:
                finite = False
            if not finite:
                return [f"{path}: expected a finite number{_describe_range(metadata)}, got {_show(value)}"]
        return []
    if origin in (list, tuple, set, frozenset) and isinstance(value, (list, tuple)):
        if origin is tuple and not (len(args) == 2 and args[1] is Ellipsis):
            pairs = list(zip(args, value))
        else:
            pairs = [(args[0] if args else Any, v) for v in value]
        return [p for i, (h, v) in enumerate(pairs) for p in _scalar_problems(h, v, f"{path}.{i}", [])]
    if origin is dict and isinstance(value, Mapping) and len(args) == 2:
        return [p for k, v in value.items() for p in _scalar_problems(args[1], v, f"{path}.{k}", [])]
    if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, Mapping):
        return number_problems(hint, value, path)
    return []  # str, Literal, Any, ...: pydantic's own checks are strict enough


def number_problems(cls: type, data: Mapping[str, Any], prefix: str) -> list[str]:
    """Every bool/str given for a number, and every NaN/inf not documented, in `data` for `cls`."""
    fields = getattr(cls, "__pydantic_fields__", None)
    if fields is None:
        return []
    out = []
    for key, value in data.items():
        info = fields.get(key) if isinstance(key, str) else None
        if info is not None:
            path = f"{prefix}.{key}" if prefix else str(key)
            out += _scalar_problems(info.annotation, value, path, list(info.metadata))
    return out


def build(cls: type, data: Mapping[str, Any] | None, prefix: str) -> Any:
    """Construct pydantic dataclass `cls` from a mapping, raising ConfigError on bad input
    (strict numbers: see `number_problems`)."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{prefix}: expected a mapping, got {type(data).__name__} {data!r}")
    where = prefix or "<top level>"
    not_names = [k for k in data if not isinstance(k, str)]
    if not_names:  # YAML reads `5:` as an int key, which no field is named
        names = ", ".join(sorted(f.name for f in dataclasses.fields(cls)))
        raise ConfigError(f"{where}: {not_names[0]!r} is not a field name; allowed: {names}")
    problems = number_problems(cls, data, prefix)
    if problems:
        raise ConfigError("; ".join(problems))
    try:
        return cls(**dict(data))
    except pydantic.ValidationError as exc:
        raise from_validation_error(exc, prefix, root=cls) from None
    except TypeError as exc:  # e.g. a keyword the constructor does not take
        names = ", ".join(sorted(f.name for f in dataclasses.fields(cls)))
        raise ConfigError(f"{where}: {exc}; allowed: {names}") from None
