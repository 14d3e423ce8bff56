"""Configuration files: a tree of frozen dataclasses read from one TOML file.

A configuration type is a frozen dataclass whose fields are tables (frozen dataclasses
again) or values: ``bool``, ``int``, ``float``, ``str``, ``None`` and unions and tuples
of them. :func:`read_config` reads a TOML file into one, :func:`config_from_dict` builds
one from nested dicts (TOML / JSON shape), :func:`config_to_dict` and
:func:`config_to_toml` write one back; a configuration survives the round trip.

Rules, the same for every configuration:

- Every table and key is optional (the dataclass defaults); unknown ones are rejected.
- Types are checked, never guessed: ``2.5`` or ``true`` is not an integer, ``1`` is not
  ``true``, ``"3"`` is not a number. An integer is taken where a number is expected
  (``tile_size_m = 50`` reads as ``50.0``); a TOML array becomes a tuple.
- TOML has no null: where a field admits ``None``, the string ``"none"`` (any case)
  stands for it, and ``None`` is written back as ``"none"``.
- Value checks (ranges, choices) are the dataclasses' own ``__post_init__``, which raise
  :class:`~semantic3d.core.errors.ConfigError` as ``key: expected ..., found ...``; the
  loader puts the file and table in front. Values built in Python get the same checks.

Every problem of a file is reported at once, one line each, in the form
``model.toml: [forest] max_depth: expected a positive integer or "none", found -3``.

Type checking is pydantic's (v2, strict JSON-mode validation of the dataclasses
themselves: no model classes, no pydantic import until a file is read). pydantic is
already the validation library of the server; its errors carry the location, type and
input of every problem, which is what the messages above are built from.
"""

from __future__ import annotations

import dataclasses
import datetime
import functools
import json
import math
import tomllib
import types
import typing
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from semantic3d.core.errors import ConfigError

if TYPE_CHECKING:
    from pydantic import TypeAdapter

__all__ = [
    "NONE_TEXT",
    "ConfigError",
    "config_from_dict",
    "config_to_dict",
    "config_to_toml",
    "read_config",
]

ConfigT = TypeVar("ConfigT")

NONE_TEXT = "none"
"""How ``None`` is spelled in a configuration file (TOML has no null)."""

_Path = tuple[str | int, ...]
_DATES = (datetime.datetime, datetime.date, datetime.time)


def read_config(path: str | Path, config_type: type[ConfigT]) -> ConfigT:
    """Read the TOML file ``path`` into a ``config_type``.

    Raises:
        ConfigError: the file cannot be read, is not TOML, or does not describe a
            ``config_type``; the message names the file, table and key of every problem.
    """
    path = Path(path)
    try:
        with path.open("rb") as stream:
            data = tomllib.load(stream)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the configuration: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return config_from_dict(data, config_type, source=str(path))


def config_from_dict(
    data: Mapping[str, Any], config_type: type[ConfigT], *, source: str = "config"
) -> ConfigT:
    """Build a ``config_type`` from nested dicts (the shape of TOML or JSON).

    ``source`` names the origin in error messages (a file name).
    """
    if not (isinstance(config_type, type) and dataclasses.is_dataclass(config_type)):
        raise TypeError(f"config_type: expected a dataclass, found {config_type!r}")
    # Dates and times parse as TOML but are no configuration value: reported here, and
    # handed to the validator as null so that every other problem is found too.
    dated = [(path, value) for path, value in _dates(data, ()) if _is_field(config_type, path)]
    problems = [
        f"{_where(config_type, path)}: expected {_describe(_type_at(config_type, path))}, "
        f"found {_toml_value(value)}"
        for path, value in dated
    ]
    from pydantic import ValidationError

    document = json.dumps(_nones_to_null(data, config_type), default=_date_as_null)
    try:
        config = _adapter(config_type).validate_json(document, strict=True, extra="forbid")
    except ValidationError as exc:
        problems += _problems(exc, config_type, data, skip={path for path, _ in dated})
    if problems:
        raise ConfigError("\n".join(f"{source}: {problem}" for problem in problems))
    return config


def config_to_dict(config: Any) -> dict[str, Any]:
    """``config`` as nested dicts: tables as dicts, tuples as lists, ``None`` as ``"none"``."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"config: expected a dataclass instance, found {config!r}")
    return {field.name: _plain(getattr(config, field.name)) for field in dataclasses.fields(config)}


def config_to_toml(config: Any) -> str:
    """``config`` as TOML text that :func:`read_config` reads back to an equal value."""
    lines: list[str] = []
    _write_table(config_to_dict(config), (), lines)
    return "\n".join(lines).lstrip("\n") + "\n"


@functools.cache
def _adapter(config_type: type[ConfigT]) -> TypeAdapter[ConfigT]:
    from pydantic import TypeAdapter

    return TypeAdapter(config_type)


def _problems(
    exc: Any, config_type: type, data: Mapping[str, Any], *, skip: set[_Path]
) -> list[str]:
    """One line per problem of a pydantic ``ValidationError``: unknown keys grouped by
    table, the errors of a union's members merged into one line per value."""
    lines: dict[tuple[str, _Path], str] = {}
    unknown: dict[_Path, list[str]] = {}
    for error in exc.errors():
        path = _known_prefix(config_type, tuple(error["loc"]))
        kind = error["type"]
        if kind in ("unexpected_keyword_argument", "extra_forbidden"):
            table = path[:-1]
            lines.setdefault(("unknown", table), "")  # keeps the order of first appearance
            unknown.setdefault(table, []).append(str(path[-1]))
        elif path in skip:
            continue
        elif kind == "value_error":  # a dataclass's own check (``__post_init__``)
            cause = error.get("ctx", {}).get("error")
            message = str(cause) if cause is not None else error["msg"]
            where = _where(config_type, path)
            lines["value", path] = f"{where} {message}" if where else message
        else:
            expected = _describe(_type_at(config_type, path))
            where = _where(config_type, path)
            if kind == "missing":
                lines["type", path] = f"{where}: missing, expected {expected}"
            else:
                found = _toml_value(_value_at(data, path))
                lines["type", path] = f"{where}: expected {expected}, found {found}"
    for table, keys in unknown.items():
        known = sorted(f.name for f in dataclasses.fields(_type_at(config_type, table)))
        what = f"unknown key(s) {sorted(keys)}" if table else f"unknown section(s) {sorted(keys)}"
        where = _where(config_type, table)
        message = f"{what}: expected some of {known}"
        lines["unknown", table] = f"{where}: {message}" if where else message
    return list(lines.values())


def _where(config_type: type, path: _Path) -> str:
    """``[forest]`` for a table, ``[forest] max_depth`` for a key, ``[grid_search]
    max_depth[2]`` for a list item, ``seed`` for a key outside any table."""
    tables: list[str] = []
    for depth in range(1, len(path) + 1):
        if not dataclasses.is_dataclass(_unwrap(_type_at(config_type, path[:depth]))):
            break
        tables.append(str(path[depth - 1]))
    rest = path[len(tables) :]
    key = "".join(f"[{p}]" if isinstance(p, int) else str(p) for p in rest)
    if not tables:
        return key
    head = f"[{'.'.join(tables)}]"
    return f"{head} {key}" if key else head


def _is_field(config_type: type, path: _Path) -> bool:
    return _type_at(config_type, path) is not Any


def _unwrap(tp: Any) -> Any:
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _members(tp: Any) -> tuple[Any, ...]:
    tp = _unwrap(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return tuple(_unwrap(m) for m in typing.get_args(tp))
    return (tp,)


def _element(tp: Any) -> Any | None:
    """``X`` for ``tuple[X, ...]``; None for anything else."""
    tp = _unwrap(tp)
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis:
        return args[0]
    return None


def _hints(table: type) -> dict[str, Any]:
    return typing.get_type_hints(table)


def _known_prefix(config_type: type, loc: _Path) -> _Path:
    """The part of a pydantic location that names tables, keys and list items (what
    follows is a union member's tag), plus an unknown key itself."""
    tp: Any = config_type
    for depth, part in enumerate(loc):
        if isinstance(part, str) and dataclasses.is_dataclass(tp):
            hints = _hints(tp)  # type: ignore[arg-type]
            if part not in hints:
                return loc[: depth + 1]
            tp = hints[part]
        elif isinstance(part, int) and _element(tp) is not None:
            tp = _element(tp)
        else:
            return loc[:depth]
        tp = _unwrap(tp)
    return loc


def _type_at(config_type: type, path: _Path) -> Any:
    tp: Any = config_type
    for part in path:
        tp = _unwrap(tp)
        if isinstance(part, str) and dataclasses.is_dataclass(tp):
            tp = _hints(tp).get(part, Any)  # type: ignore[arg-type]
        elif isinstance(part, int) and _element(tp) is not None:
            tp = _element(tp)
        else:
            return Any
    return tp


def _value_at(data: Any, path: _Path) -> Any:
    for part in path:
        data = data[part]
    return data


def _describe(tp: Any) -> str:
    """What a value of type ``tp`` looks like in a file: ``an integer or "none"``."""
    parts: list[str] = []
    members = _members(tp)
    for member in members:
        if member is bool:
            text = "true or false"
        elif member is int:
            text = "a number" if float in members else "an integer"
        elif member is float:
            text = "a number"
        elif member is str:
            text = "a string"
        elif member is type(None) or member is None:
            text = f'"{NONE_TEXT}"'
        elif _element(member) is not None or member is tuple:
            text = "a list"
        elif dataclasses.is_dataclass(member):
            text = "a table"
        else:
            text = "a value"
        if text not in parts:
            parts.append(text)
    return parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " or " + parts[-1]


def _admits_none(tp: Any) -> bool:
    return any(m is type(None) or m is None for m in _members(tp))


def _nones_to_null(value: Any, tp: Any) -> Any:
    """``value`` with ``"none"`` replaced by None wherever its field admits None."""
    if isinstance(value, str) and value.lower() == NONE_TEXT and _admits_none(tp):
        return None
    for member in _members(tp):
        if isinstance(value, Mapping) and dataclasses.is_dataclass(member):
            hints = _hints(member)  # type: ignore[arg-type]
            return {k: _nones_to_null(v, hints.get(k, Any)) for k, v in value.items()}
        element = _element(member)
        if isinstance(value, list | tuple) and element is not None:
            return [_nones_to_null(v, element) for v in value]
    return value


def _dates(value: Any, path: _Path) -> Iterator[tuple[_Path, Any]]:
    """Dates and times in TOML data: no configuration value is one."""
    if isinstance(value, _DATES):
        yield path, value
    elif isinstance(value, Mapping):
        for key, item in value.items():
            yield from _dates(item, (*path, key))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _dates(item, (*path, index))


def _date_as_null(value: Any) -> None:
    if not isinstance(value, _DATES):
        raise TypeError(f"data: expected TOML values, found {value!r}")


def _plain(value: Any) -> Any:
    if value is None:
        return NONE_TEXT
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return config_to_dict(value)
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def _toml_value(value: Any) -> str:
    """``value`` as TOML writes it (strings quoted and escaped, ``true``, ``[1, 2]``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(float(value))  # shortest round trip; inf, -inf and 1e-05 are TOML as written
    if isinstance(value, str):
        # JSON escapes are TOML escapes; TOML also wants DEL escaped.
        return json.dumps(value, ensure_ascii=False).replace("\x7f", "\\u007F")
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        items = ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{" + items + "}"
    if isinstance(value, _DATES):
        return value.isoformat()
    return repr(value)


def _toml_key(key: str) -> str:
    bare = bool(key) and all(c.isascii() and (c.isalnum() or c in "-_") for c in key)
    return key if bare else _toml_value(key)


def _write_table(table: dict[str, Any], path: tuple[str, ...], lines: list[str]) -> None:
    subtables = {k: v for k, v in table.items() if isinstance(v, dict)}
    if path and (len(subtables) < len(table) or not subtables):
        lines += ["", f"[{'.'.join(_toml_key(p) for p in path)}]"]
    for key, value in table.items():
        if key not in subtables:
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
    for key, value in subtables.items():
        _write_table(value, (*path, key), lines)
