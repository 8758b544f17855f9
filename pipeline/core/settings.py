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

import copy
import dataclasses
import difflib
import functools
import math
import sys
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

if typing.TYPE_CHECKING:  # omegaconf is imported where used: training code imports this
    from omegaconf import DictConfig  # module, and runs where no Hydra is installed (a GPU)

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
        if isinstance(value, bool) or not isinstance(value, int):
            return False
        return (self.low is None or value >= self.low) and (self.high is None or value <= self.high)

    def __str__(self) -> str:
        low = f">= {self.low}" if self.low is not None else ""
        high = f"<= {self.high}" if self.high is not None else ""
        return _described("an integer", low, high, self.optional)


@dataclass(frozen=True)
class Real:
    """A finite number (not a bool, not a string) above ``low`` (or at it when
    ``closed``) and at most ``high`` (below it unless ``high_closed``); None too when
    ``optional``."""

    low: float | None = None
    closed: bool = True
    optional: bool = False
    high: float | None = None
    high_closed: bool = True

    def ok(self, value) -> bool:
        if value is None:
            return self.optional
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if not math.isfinite(value):
            return False
        if self.high is not None and (
            value > self.high or (value == self.high and not self.high_closed)
        ):
            return False
        return self.low is None or value > self.low or (self.closed and value == self.low)

    def __str__(self) -> str:
        low = "" if self.low is None else f"{'>=' if self.closed else '>'} {self.low:g}"
        high = "" if self.high is None else f"{'<=' if self.high_closed else '<'} {self.high:g}"
        return _described("a finite number", low, high, self.optional)


def _described(noun: str, low: str, high: str, optional: bool) -> str:
    """``noun`` with its bounds (empty when none) and `` or null`` when ``optional``."""
    text = " and ".join(b for b in (low, high) if b)
    return f"{noun} {text}".rstrip() + (" or null" if optional else "")


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

    item: Integer | Real | OneOf | Either
    length: int | None = None
    at_least: int = 0

    def ok(self, value) -> bool:
        return (
            isinstance(value, list | tuple)
            and (self.length is None or len(value) == self.length)
            and len(value) >= self.at_least
            and all(self.item.ok(v) for v in value)
        )

    def __str__(self) -> str:
        count = f"at least {self.at_least} " if self.at_least else ""
        if self.length is not None:
            count = f"{self.length} "
        return f"a list of {count}items, each {self.item}"


@dataclass(frozen=True)
class Either:
    """A value that one of the given constraints allows (``Either(OneOf(-1), Integer(1))``:
    -1 for "none", or a count)."""

    choices: tuple

    def __init__(self, *choices):
        if not choices:
            raise TypeError("Either needs at least one constraint")
        object.__setattr__(self, "choices", choices)

    def ok(self, value) -> bool:
        return any(choice.ok(value) for choice in self.choices)

    def __str__(self) -> str:
        return " or ".join(str(choice) for choice in self.choices)


Constraint = Integer | Real | OneOf | ListOf | Either


def check_settings(cfg: Mapping | DictConfig, constraints: Mapping[str, Constraint]) -> None:
    """Raise :class:`ConfigError` naming the first setting (dotted name) whose value breaks
    its constraint; settings absent from ``cfg`` are not checked."""
    omegaconf = sys.modules.get("omegaconf")  # a DictConfig means it is loaded
    if omegaconf is not None and isinstance(cfg, omegaconf.DictConfig):
        cfg = omegaconf.OmegaConf.to_container(cfg, resolve=True)
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
    """Check a dataclass's fields against the constraint each declares (:func:`setting`),
    else against its annotation (``int``, ``float``, ``str``, ``bool``, ``X | None``: an
    ``int`` refuses 1.5, True and NaN). Raises :class:`ConfigError` naming ``prefix.field``."""
    hints = typing.get_type_hints(type(settings))
    for field in dataclasses.fields(settings):
        value = getattr(settings, field.name)
        constraint = field.metadata.get("constraint") or _constraint_of(hints[field.name])
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


def schema(settings_class: type, class_name: str | None = None, **extra: object) -> type:
    """A Hydra structured config with the fields and defaults of ``settings_class`` (a
    mutable copy: the frozen settings dataclass stays the one source of defaults).

    ``extra`` adds fields the config group holds besides (name: default; a dict default
    becomes an open ``dict[str, Any]`` field), or gives a field another default in the
    config, which may then be null.
    """
    hints = typing.get_type_hints(settings_class)
    fields = []
    for f in dataclasses.fields(settings_class):
        if f.name in extra:  # the config's own default, e.g. null for "the method's"
            value = extra.pop(f.name)
            fields.append((f.name, hints[f.name] | None, dataclasses.field(default=value)))
            continue
        default = (
            dataclasses.field(default_factory=f.default_factory)
            if f.default is dataclasses.MISSING
            else dataclasses.field(default=f.default)
        )
        fields.append((f.name, hints[f.name], default))
    for key, value in extra.items():
        if isinstance(value, dict):
            copy = dataclasses.field(default_factory=functools.partial(dict, value))
            fields.append((key, dict[str, typing.Any], copy))
        else:
            fields.append((key, type(value) if value is not None else typing.Any, value))
    return dataclasses.make_dataclass(class_name or f"{settings_class.__name__}Schema", fields)


def check_added_keys(
    cfg: DictConfig,
    overrides: list[str],
    conf_dir: Path,
    open_maps: tuple[str, ...] = ("tracking.tags",),
    compose=None,
) -> None:
    """Refuse a setting added with ``+key=value`` (or ``++``) that the config does not have.

    Hydra adds ``+btf.crop.szie=32`` as a new key that no code reads. Adding is allowed for
    config groups (``+experiment=...``) and under ``open_maps``; ``++key`` is refused when
    the config composed without it (``compose(overrides)``) lacks the key. The error names
    the closest setting.
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    parsed = OverridesParser.create().parse_overrides(overrides)
    base = None
    for override in parsed:
        if not (override.is_add() or override.is_force_add()):
            continue
        key = override.key_or_group
        if "/" in key or (conf_dir / key.replace(".", "/")).is_dir():
            continue  # a config group, e.g. +experiment=smoke
        if any(key == m or key.startswith(m + ".") for m in open_maps):
            continue
        if override.is_force_add() and compose is not None:
            if base is None:
                base = compose([o.input_line for o in parsed if not o.is_force_add()])
            if OmegaConf.select(base, key, default=_ABSENT) is not _ABSENT:
                continue  # ++ on a real setting: a plain change
        known = [k for k in leaf_keys(cfg) if k != key]
        close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]}?" if close else ""
        raise ConfigError(
            f"+{key}: no such setting{hint} (a + adds a new key that no code "
            f"reads; only {', '.join(open_maps)} take new keys)"
        )


_ABSENT = object()


def leaf_keys(cfg: DictConfig, prefix: str = "") -> list[str]:
    """Every key of ``cfg``, dotted, its maps' included."""
    from omegaconf import DictConfig

    keys = []
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        keys.append(name)
        if isinstance(value, DictConfig):
            keys += leaf_keys(value, name + ".")
    return keys


# A setting's role (field metadata "role"): what its value can change. Cache keys and
# recipes hold the RESULT settings.
RESULT = "result"  # can change a number in a table
SPEED = "speed"  # changes how fast the same numbers are computed (up to float sums)
LOG = "log"  # changes what is logged or drawn, not the model
ROLES = (RESULT, SPEED, LOG)


def setting(
    default,
    constraint: Constraint | None = None,
    *,
    role: str = RESULT,
    help: str = "",
    added: bool = False,
):
    """A dataclass field with its role, its allowed values and one line of help.

    ``added``: the setting came after results existed, its default what the code did
    before; at its default it is left out of cache keys, recipes and logged parameters
    (:func:`at_added_default`), so those results stay the same model.
    """
    if role not in ROLES:
        raise ValueError(f"role={role!r} must be one of {', '.join(ROLES)}")
    if added and isinstance(default, list | dict):
        raise ValueError("an added setting needs a plain default, compared as it is")
    metadata = {"role": role, "constraint": constraint, "help": help, "added": added}
    if isinstance(default, list | dict) or dataclasses.is_dataclass(default):  # nested settings
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def roles(settings_class: type, prefix: str) -> dict[str, str]:
    """``{"prefix.field": role}`` of a dataclass whose fields are :func:`setting` s;
    raises ``TypeError`` naming a field declared without a role."""
    found = {}
    for f in dataclasses.fields(settings_class):
        if "role" not in f.metadata:
            raise TypeError(
                f"{settings_class.__name__}.{f.name} has no role: declare it "
                f"with pipeline.core.settings.setting(..., role=...)"
            )
        found[f"{prefix}.{f.name}"] = f.metadata["role"]
    return found


def added_defaults(settings_class: type, prefix: str) -> dict[str, object]:
    """``{"prefix.field": default}`` of the fields declared ``added`` (:func:`setting`)."""
    return {
        f"{prefix}.{f.name}": f.default
        for f in dataclasses.fields(settings_class)
        if f.metadata.get("added")
    }


def at_added_default(settings_class: type, prefix: str, values: Mapping) -> list[str]:
    """The ``added`` settings (dotted names) whose value in the nested ``values`` (a config
    holding ``prefix``) is their default, or which it lacks: left out of keys and recipes."""
    return [
        key
        for key, default in added_defaults(settings_class, prefix).items()
        if _select(values, key, default) == default
    ]


def constraints(settings_class: type, prefix: str) -> dict[str, Constraint]:
    """``{"prefix.field": constraint}`` of the :func:`setting` fields that declare one."""
    return {
        f"{prefix}.{f.name}": f.metadata["constraint"]
        for f in dataclasses.fields(settings_class)
        if f.metadata.get("constraint") is not None
    }
