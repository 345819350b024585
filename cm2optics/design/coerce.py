"""Plain data ↔ dataclasses: the generic YAML edge of the design (type coercion with errors that
name the dotted field, unknown-field hints) and an atomic text write."""

from __future__ import annotations

import dataclasses
import difflib
import os
import tempfile
import types
import typing
from dataclasses import MISSING, fields
from enum import Enum
from pathlib import Path
from typing import Any, Union

from cm2optics.design.validation import DesignError

__all__ = ["dataclass_from_dict", "to_plain", "write_text_atomic"]


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder, then rename."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            stream.write(text)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def to_plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: to_plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, tuple):
        return [to_plain(v) for v in value]
    return value


def _type_name(tp: Any) -> str:
    if isinstance(tp, type):
        if issubclass(tp, Enum):
            return "one of " + ", ".join(repr(m.value) for m in tp)
        if dataclasses.is_dataclass(tp):
            return "a mapping of fields"
        return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(tp, tp.__name__)
    return str(tp)


def _coerce(tp: Any, value: Any, path: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(args[0], value, path)
    if origin is tuple:
        item_type = typing.get_args(tp)[0]
        if not isinstance(value, (list, tuple)):
            raise DesignError(path, value, f"must be a list of {_type_name(item_type)}")
        return tuple(_coerce(item_type, v, f"{path}[{i}]") for i, v in enumerate(value))
    if dataclasses.is_dataclass(tp):
        return dataclass_from_dict(tp, value, path)
    if isinstance(tp, type) and issubclass(tp, Enum):
        try:
            return tp(value)
        except ValueError:
            raise DesignError(path, value, f"must be {_type_name(tp)}") from None
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise DesignError(path, value, "must be a number")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise DesignError(path, value, "must be an integer")
        return value
    if tp is bool and not isinstance(value, bool):
        raise DesignError(path, value, "must be true or false")
    if tp is str and not isinstance(value, str):
        raise DesignError(path, value, "must be a string")
    return value


def dataclass_from_dict(cls: type, data: Any, path: str) -> Any:
    """``cls`` from a mapping of its fields; a field with a default may be left out (the
    optional ``as_built`` section and its fields), every other one must be given."""
    prefix = f"{path}." if path else ""
    if not isinstance(data, dict):
        raise DesignError(path or "<design>", data, "must be a mapping of fields")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in fields(cls)]
    for key in data:
        if key not in names:
            close = difflib.get_close_matches(str(key), names, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise DesignError(
                f"{prefix}{key}", data[key], f"unknown field{hint}; {cls.__name__} has: {', '.join(names)}"
            )
    optional = {f.name for f in fields(cls) if f.default is not MISSING or f.default_factory is not MISSING}
    for name in names:
        if name not in data and name not in optional:
            raise DesignError(f"{prefix}{name}", None, f"missing; expected {_type_name(hints[name])}")
    kwargs = {name: _coerce(hints[name], data[name], f"{prefix}{name}") for name in names if name in data}
    try:
        return cls(**kwargs)
    except DesignError as error:
        if error.field.startswith(prefix) and prefix:
            raise
        raise DesignError(f"{prefix}{error.field}", error.value, error.allowed) from None
