"""Command lines of ``key=value`` settings, read before torch or MLflow is imported, so that
a bad argument is answered at once, naming it and, for a misspelt key, the closest real one.

A command describes its settings in one table, key -> ``(field, constraint, help)``: the
field of its settings dataclass that the key sets, what the value may be (a constraint of
:mod:`pipeline.core.settings`, or :class:`Text`) and its ``--help`` line. Values are read as
YAML 1.2, as Hydra reads them: ``null``, ``true``, ``30``, ``[0,0,100,100]`` (``1:30`` stays
a string, ``on``/``yes`` are no booleans).

>>> from pipeline.core.settings import Integer
>>> keys = {"steps": ("steps", Integer(1), "training steps")}
>>> read(["steps=5"], keys)
{'steps': 5}
>>> read(["step=5"], keys)
Traceback (most recent call last):
...
pipeline.core.errors.ConfigError: 'step=5' is not a setting (did you mean steps?): ...
"""

from __future__ import annotations

import difflib
import re
import sys
import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import yaml

from pipeline.core.errors import ConfigError
from pipeline.core.settings import check_settings


class _Yaml12Loader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2's booleans, integers and floats (PyYAML has only
    YAML 1.1, which reads ``1:30`` as 90 and ``on``/``yes`` as true)."""


_Yaml12Loader.yaml_implicit_resolvers = {
    first: [
        (tag, regexp)
        for tag, regexp in resolvers
        if tag not in ("tag:yaml.org,2002:bool", "tag:yaml.org,2002:int", "tag:yaml.org,2002:float")
    ]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
for _tag, _pattern, _first in (
    ("bool", r"^(?:true|True|TRUE|false|False|FALSE)$", "tTfF"),
    ("int", r"^[-+]?[0-9]+$", "-+0123456789"),
    (
        "float",
        r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
        r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$",
        "-+0123456789.",
    ),
):
    _Yaml12Loader.add_implicit_resolver(
        f"tag:yaml.org,2002:{_tag}", re.compile(_pattern), list(_first)
    )


def read_value(text: str):
    """One command-line value as YAML 1.2 reads it."""
    return yaml.load(text, Loader=_Yaml12Loader)  # a SafeLoader: no arbitrary objects


@dataclass(frozen=True)
class Text:
    """A non-empty string (a path, a name); None too when ``optional``."""

    optional: bool = False

    def ok(self, value) -> bool:
        return (isinstance(value, str) and value != "") or (value is None and self.optional)

    def __str__(self) -> str:
        return "a non-empty string" + (" or null" if self.optional else "")


def closest(word: str, choices: Sequence[str]) -> str:
    """`` (did you mean KEY?)`` for the choice nearest ``word`` (``--dry-run`` read as
    ``dry_run``; ``runs`` matches ``paths.runs``), or ``""`` when none is near."""
    names = {choice.rsplit(".", 1)[-1]: choice for choice in choices} | {c: c for c in choices}
    found = difflib.get_close_matches(word.lstrip("-").replace("-", "_"), list(names), n=1)
    return f" (did you mean {names[found[0]]}?)" if found else ""


def read(argv: Sequence[str], keys: Mapping[str, tuple], command: str = "") -> dict:
    """``{field: value}`` of the ``key=value`` arguments ``argv``, each checked against its
    key's constraint; raises :class:`ConfigError` naming the first bad argument
    (``command``, say ``"the bench"``, completes "is not a setting of ...")."""
    given: dict = {}
    for argument in argv:
        key, equals, text = argument.partition("=")
        if not equals and key in keys:
            raise ConfigError(f"{key} needs a value: give {key}=VALUE")
        if not equals or key not in keys:
            of = f" of {command}" if command else ""
            raise ConfigError(
                f"{argument!r} is not a setting{of}{closest(key, list(keys))}: "
                f"give key=value with a key among {', '.join(keys)} "
                f"(--help describes them)"
            )
        if key in given:
            raise ConfigError(f"{key} is given twice")
        try:
            given[key] = read_value(text)
        except yaml.YAMLError:
            raise ConfigError(f"{key}={text!r} is not a value (YAML)") from None
    nested: dict = {}
    for key, value in given.items():  # check_settings reads dotted names from nested maps
        *parents, last = key.split(".")
        node = nested
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    check_settings(nested, {key: keys[key][1] for key in given})
    return {keys[key][0]: value for key, value in given.items()}


def parse(argv: Sequence[str], keys: Mapping[str, tuple], settings_class: type, command: str = ""):
    """``settings_class`` (a dataclass) from ``argv`` (:func:`read`)."""
    return settings_class(**read(argv, keys, command))


def command_of(argv: Sequence[str], commands: Sequence[str]) -> tuple[str, list[str]]:
    """The command that ``argv``'s first word names, and the words after it; raises
    :class:`ConfigError` when it is not one of ``commands``."""
    if not argv or "=" in argv[0]:
        raise ConfigError(f"no command: give one of {', '.join(commands)} first")
    if argv[0] not in commands:
        raise ConfigError(
            f"unknown command {argv[0]!r}{closest(argv[0], commands)}; "
            f"commands: {', '.join(commands)}"
        )
    return argv[0], list(argv[1:])


def shown(value) -> str:
    """``value`` as it is written on the command line (``null``, ``true``, ``[0,0,1,1]``)."""
    if isinstance(value, list | tuple):
        return "[" + ",".join(shown(item) for item in value) + "]"
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def usage(
    prog: str,
    keys: Mapping[str, tuple],
    defaults,
    summary: str,
    synopsis: str = "[key=value ...]",
    notes: str = "",
) -> str:
    """The ``--help`` text: the usage line, ``summary``, each key with its default (from
    ``defaults``, an instance of the settings dataclass) and help, then ``notes``."""
    lines = [f"usage: {prog} {synopsis}", "", summary]
    for key, (field, _, text) in keys.items():
        lines.append(f"  {key}={shown(getattr(defaults, field))}")
        lines += textwrap.wrap(text, 88, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return "\n".join(lines + ([f"\n{notes}"] if notes else []))


def parse_args(
    prog: str, parse: Callable[[list[str]], object], usage: str, argv: Sequence[str] | None = None
):
    """``parse(argv)`` (``sys.argv[1:]`` by default): ``-h``/``--help`` prints ``usage`` and
    exits 0; a :class:`ConfigError` prints ``PROG: error: ...`` on stderr and exits 2."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print(usage)
        raise SystemExit(0)
    try:
        return parse(argv)
    except ConfigError as error:
        print(f"{prog}: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


@dataclass(frozen=True)
class Command:
    """One command's command line: its ``prog``, key table, settings dataclass, ``--help``
    summary and ``what`` (:func:`read`'s ``command``). A command whose parsing does more
    passes its own ``parse`` to :meth:`parse_args`."""

    prog: str
    keys: Mapping[str, tuple]
    settings: type
    summary: str
    what: str = ""
    synopsis: str = "[key=value ...]"
    notes: str = ""

    def usage(self) -> str:
        """The ``--help`` text (:func:`usage`)."""
        return usage(self.prog, self.keys, self.settings(), self.summary, self.synopsis, self.notes)

    def parse(self, argv: Sequence[str]):
        """The settings from ``key=value`` arguments (:func:`parse`)."""
        return parse(argv, self.keys, self.settings, self.what)

    def parse_args(
        self, argv: Sequence[str] | None = None, parser: Callable[[list[str]], object] | None = None
    ):
        """``parser`` (by default :meth:`parse`) for a command line (:func:`parse_args`)."""
        return parse_args(self.prog, parser or self.parse, self.usage(), argv)
