"""The mechanism behind :mod:`tivne.config`: dataclass fields that carry their allowed values, and
a base class that checks and converts them on construction (one mechanism for every section)."""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, ClassVar


class ConfigError(ValueError):
    """A setting outside its allowed values; ``str()`` is one line naming key, value and rule."""


def setting(
    default: Any,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """A dataclass field with its allowed range (``ge``/``gt``/``le``/``lt``) or ``choices``."""
    meta = {k: v for k, v in dict(ge=ge, gt=gt, le=le, lt=lt, choices=choices).items() if v is not None}
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def _describe(meta: dict[str, Any]) -> str:
    if "choices" in meta:
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    words = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    return " and ".join(f"{words[k]} {meta[k]}" for k in ("ge", "gt", "le", "lt") if k in meta)


def _coerce_scalar(kind: Any, value: Any) -> Any:
    """``value`` as ``kind`` (int, float, bool or str); raises TypeError when it is not one."""
    if kind is bool:
        if isinstance(value, bool):
            return value
        raise TypeError("a boolean (true/false)")
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
            raise TypeError("an integer")
        return int(value)
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError("a number")
        if not math.isfinite(value):
            raise TypeError("a finite number")
        return float(value)
    if kind is str:
        if not isinstance(value, str):
            raise TypeError("a string")
        return value
    return value


def _coerce(annotation: Any, value: Any) -> Any:
    """Check and convert a value against a field annotation (scalars, Optional, tuple[X, ...])."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return _coerce(inner[0], value)
    if origin in (tuple, list):
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
            raise TypeError("a list")
        return tuple(_coerce(args[0], v) for v in value)
    return _coerce_scalar(annotation, value)


def _check_range(value: Any, meta: dict[str, Any]) -> bool:
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if v is None:
            continue
        if "choices" in meta and v not in meta["choices"]:
            return False
        if "ge" in meta and not v >= meta["ge"]:
            return False
        if "gt" in meta and not v > meta["gt"]:
            return False
        if "le" in meta and not v <= meta["le"]:
            return False
        if "lt" in meta and not v < meta["lt"]:
            return False
    return True


@dataclass(frozen=True)
class Settings:
    """Base of every config section: checks and converts its fields on construction."""

    section: ClassVar[str] = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            key = f"{self.section}.{f.name}" if self.section else f.name
            try:
                value = _coerce(hints[f.name], value)
            except TypeError as exc:
                raise ConfigError(f"{key}={value!r}: must be {exc}" + (f" {_describe(f.metadata)}" if f.metadata else "")) from None
            if not _check_range(value, f.metadata):
                raise ConfigError(f"{key}={value!r}: must be {_describe(f.metadata)}")
            object.__setattr__(self, f.name, value)
        self.check()

    def check(self) -> None:
        """Rules that tie several fields together (override in a section)."""

    @classmethod
    def from_mapping(cls, values: dict[str, Any] | None) -> "Settings":
        """Build from a plain dict (a config node); unknown keys are an error naming the key."""
        values = dict(values or {})
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(f"{cls.section}.{unknown[0]}: unknown setting (known: {', '.join(sorted(names))})")
        return cls(**values)


def default_tree(sections: tuple[type[Settings], ...]) -> dict[str, Any]:
    """{section: {key: default}} of the given sections (a section-less class puts its keys at the
    top level): the base node the YAML presets override."""

    def plain(v: Any) -> Any:
        return list(v) if isinstance(v, tuple) else v

    tree: dict[str, Any] = {}
    for cls in sections:
        values = {f.name: plain(getattr(cls(), f.name)) for f in dataclasses.fields(cls)}
        if cls.section:
            tree[cls.section] = values
        else:
            tree.update(values)
    return tree
