"""Settings checked at the door, declaratively: each setting's allowed values in one table
that a single validator reads (as scikit-learn's ``_parameter_constraints``), so that a
bad value is refused before any stage runs, with a message naming it and what it may be.

>>> check_settings({"k": 8}, {"k": Integer(1)})
>>> check_settings({"k": True}, {"k": Integer(1)})
Traceback (most recent call last):
...
pipeline.core.errors.ConfigError: k=True must be an integer >= 1
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from pipeline.core.errors import ConfigError


@dataclass(frozen=True)
class Integer:
    """An integer (not a bool, not 1.5) in [low, high]; None too when ``optional``."""

    low: int | None = None
    high: int | None = None
    optional: bool = False

    def ok(self, value) -> bool:
        if value is None:
            return self.optional
        return (isinstance(value, int) and not isinstance(value, bool)
                and (self.low is None or value >= self.low)
                and (self.high is None or value <= self.high))

    def __str__(self) -> str:
        bounds = [f">= {self.low}" if self.low is not None else "",
                  f"<= {self.high}" if self.high is not None else ""]
        text = " and ".join(b for b in bounds if b)
        return f"an integer {text}".rstrip() + (" or null" if self.optional else "")


@dataclass(frozen=True)
class Real:
    """A finite number (not a bool, not a string) above ``low`` (or at it when
    ``closed``); None too when ``optional``."""

    low: float | None = None
    closed: bool = True
    optional: bool = False

    def ok(self, value) -> bool:
        if value is None:
            return self.optional
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if not math.isfinite(value):
            return False
        return self.low is None or value > self.low or (self.closed and value == self.low)

    def __str__(self) -> str:
        bound = "" if self.low is None else f" {'>=' if self.closed else '>'} {self.low:g}"
        return f"a finite number{bound}" + (" or null" if self.optional else "")


@dataclass(frozen=True)
class OneOf:
    """One of the given values."""

    values: tuple

    def __init__(self, *values):
        object.__setattr__(self, "values", values)

    def ok(self, value) -> bool:
        return any(value == v and type(value) is type(v) for v in self.values)

    def __str__(self) -> str:
        return "one of " + ", ".join("null" if v is None else str(v) for v in self.values)


@dataclass(frozen=True)
class ListOf:
    """A list whose items each satisfy ``item``, of ``length`` items when given."""

    item: Integer | Real | OneOf
    length: int | None = None

    def ok(self, value) -> bool:
        return (isinstance(value, list | tuple)
                and (self.length is None or len(value) == self.length)
                and all(self.item.ok(v) for v in value))

    def __str__(self) -> str:
        count = f"{self.length} " if self.length is not None else ""
        return f"a list of {count}items, each {self.item}"


Constraint = Integer | Real | OneOf | ListOf


def check_settings(cfg: Mapping | DictConfig, constraints: Mapping[str, Constraint]) -> None:
    """Raise :class:`ConfigError` naming the first setting (dotted name) whose value breaks
    its constraint; settings absent from ``cfg`` are not checked."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    missing = object()
    for name, constraint in constraints.items():
        value = _select(cfg, name, missing)
        if value is not missing and not constraint.ok(value):
            raise ConfigError(f"{name}={value!r} must be {constraint}")


def _select(cfg: Mapping, name: str, default):
    node = cfg
    for part in name.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def check_fields(settings, prefix: str) -> None:
    """Check a dataclass's fields against their annotations (``int``, ``float``, ``str``,
    ``bool``, ``X | None``): an ``int`` field refuses 1.5, True and NaN, a ``float`` field
    refuses strings and non-finite values. Raises :class:`ConfigError` naming
    ``prefix.field``."""
    hints = typing.get_type_hints(type(settings))
    for field in dataclasses.fields(settings):
        value = getattr(settings, field.name)
        constraint = _constraint_of(hints[field.name])
        if constraint is not None and not constraint.ok(value):
            raise ConfigError(f"{prefix}.{field.name}={value!r} must be {constraint}")


def _constraint_of(hint) -> Constraint | None:
    args = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
    optional = type(None) in args
    kinds = [a for a in args if a is not type(None)]
    if kinds == [int]:
        return Integer(optional=optional)
    if kinds == [float]:
        return Real(optional=optional)
    if kinds == [bool]:
        return OneOf(True, False, *([None] if optional else []))
    if kinds == [str]:
        return _String(optional)
    return None


@dataclass(frozen=True)
class _String:
    optional: bool = False

    def ok(self, value) -> bool:
        return isinstance(value, str) or (value is None and self.optional)

    def __str__(self) -> str:
        return "a string" + (" or null" if self.optional else "")
