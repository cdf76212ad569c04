"""Parse TOML into typed, validated, frozen dataclasses: once, at start-up.

Every error is a `ConfigError` whose message is one line naming the file and the dotted field,
e.g. `configs/rig.toml: loop.i_max_a: expected a number, got 'two'`.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from mrrig.errors import MrrigError
from mrrig.resources import resolve

T = TypeVar("T")


class ConfigError(MrrigError, ValueError):
    """A config file that cannot be used; the message is one line naming file and field."""


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file (found as `mrrig.resources.resolve` says), turning every failure into a
    one-line ConfigError."""
    p = resolve(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{p}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None


def parse(cls: type[T], data: Any, source: str, prefix: str = "") -> T:
    """Build dataclass `cls` from a TOML table, checking field names, types and `check()`."""
    where = prefix or "(top level)"
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: {where}: expected a table, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(
            f"{source}: {_join(prefix, unknown[0])}: unknown field "
            f"(known: {', '.join(sorted(fields))})"
        )
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key = _join(prefix, name)
        if name not in data:
            no_default = (
                f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
            )
            if no_default:
                raise ConfigError(f"{source}: {key}: missing required field")
            continue
        kwargs[name] = _convert(hints[name], data[name], source, key)
    obj = cls(**kwargs)
    check = getattr(obj, "check", None)
    if check is not None:
        try:
            check()
        except ValueError as exc:
            raise ConfigError(f"{source}: {_join(prefix, str(exc))}") from None
    return obj


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _convert(tp: Any, value: Any, source: str, key: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(arg, value, source, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0])
    if origin is typing.Literal:
        if value not in args:
            choices = ", ".join(repr(a) for a in args)
            raise ConfigError(f"{source}: {key}: expected one of {choices}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        return parse(tp, value, source, key)
    if origin is tuple:
        if not isinstance(value, list):
            raise ConfigError(f"{source}: {key}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, source, f"{key}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{source}: {key}: expected {len(args)} values, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(a, v, source, f"{key}[{i}]") for i, (a, v) in pairs)
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {key}: expected a table, got {value!r}")
        return dict(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{source}: {key}: expected a number, got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # an integer of hundreds of digits
            raise ConfigError(
                f"{source}: {key}: expected a number, got an integer of {len(str(abs(value)))} "
                "digits (beyond a float's range)"
            ) from None
        if not math.isfinite(number):  # TOML has nan and inf; no field means them
            raise ConfigError(f"{source}: {key}: expected a finite number, got {value!r}")
        return number
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {key}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key}: expected a string, got {value!r}")
        return _text(value, source, key)
    if tp is Path:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key}: expected a path string, got {value!r}")
        # relative to the config file where it is not in the working directory
        source_file = Path(source)
        base = source_file.parent if source_file.is_file() else None
        return resolve(_text(value, source, key), base)
    raise TypeError(f"unsupported config type {tp!r} for {key}")


def _text(value: str, source: str, key: str) -> str:
    """A string that a file name, a log line and a Zenoh payload can carry: no NUL character
    and no lone surrogate (JSON's "\\ud800"), which failed later as 'embedded null byte' or
    'surrogates not allowed' without naming the field."""
    if "\0" in value:
        raise ConfigError(f"{source}: {key}: contains a NUL character (\\u0000)")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError as exc:
        bad = value[exc.start]
        raise ConfigError(
            f"{source}: {key}: not valid text: a lone surrogate \\u{ord(bad):04x} at "
            f"character {exc.start + 1}"
        ) from None
    return value
