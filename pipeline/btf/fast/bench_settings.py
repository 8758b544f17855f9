"""The settings of ``python -m pipeline.bench``, given as ``key=value`` arguments like every
other command's (``paths.runs=...``), read without torch so that a bad argument is
answered at once, before the seconds torch takes to load.

>>> parse(["steps=5", "paths.runs=/tmp/runs", "mlflow=false"])
BenchSettings(steps=5, threads=None, device='cpu', runs='/tmp/runs', mlflow=False, paper_run=0, load_size=0)
>>> parse(["steps=0"])
Traceback (most recent call last):
...
pipeline.core.errors.ConfigError: steps=0 must be an integer >= 1
"""

from __future__ import annotations

import sys
import textwrap
from dataclasses import dataclass

import yaml

from pipeline.core.errors import ConfigError
from pipeline.core.settings import Integer, OneOf, check_settings

PROG = "python -m pipeline.bench"


@dataclass(frozen=True)
class BenchSettings:
    """The bench's settings; :data:`KEYS` describes each (``runs`` is ``paths.runs``)."""

    steps: int = 30
    threads: int | None = None
    device: str = "cpu"
    runs: str = "runs"
    mlflow: bool = True
    paper_run: int = 0
    load_size: int = 0


class _Text:
    """Any string (a path)."""

    def ok(self, value) -> bool:
        return isinstance(value, str) and value != ""

    def __str__(self) -> str:
        return "a non-empty string"


# Each key of the command line: its field, what it may be, and what it sets.
KEYS = {
    "steps": ("steps", Integer(1), "training steps per timing"),
    "threads": ("threads", Integer(1, optional=True), "CPU threads (null: all cores)"),
    "device": ("device", OneOf("cpu", "cuda"),
               "cpu: every figure, both training backends on the CPU; cuda: the training "
               "loops at the paper's batch on the GPU, per backend and precision (and "
               "paper_run, load_size when asked)"),
    "paths.runs": ("runs", _Text(), "the folder holding mlflow.db (and paper_run's outputs)"),
    "mlflow": ("mlflow", OneOf(True, False),
               "log the figures to MLflow (experiment bench under paths.runs)"),
    "paper_run": ("paper_run", Integer(0),
                  "also run paper-size jobs with this many training steps and report each "
                  "stage's time and peak RSS (0: not run)"),
    "load_size": ("load_size", Integer(0),
                  "also time loading a 6561-file UBO2003 folder of this texture size "
                  "(256 = the real datasets; 0: not run)"),
}


def _shown(value) -> str:
    """``value`` as it is written on the command line (YAML: null, true)."""
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def usage() -> str:
    defaults = BenchSettings()
    lines = [f"usage: {PROG} [key=value ...]", "",
             "Method A's training benchmark (pipeline/btf/fast/bench.py). Settings and "
             "their defaults:"]
    for key, (field, _, text) in KEYS.items():
        lines.append(f"  {key}={_shown(getattr(defaults, field))}")
        lines += textwrap.wrap(text, 88, initial_indent=" " * 6, subsequent_indent=" " * 6)
    lines.append("\nTimings are medians of interleaved rounds: compare them as ratios within "
                 "one run.")
    return "\n".join(lines)


def parse(argv: list[str]) -> BenchSettings:
    """:class:`BenchSettings` from ``key=value`` arguments (values read as YAML, as Hydra
    reads them: ``null``, ``true``, ``30``); raises :class:`ConfigError` naming a bad one."""
    given: dict = {}
    for argument in argv:
        key, equals, text = argument.partition("=")
        if not equals or key not in KEYS:
            raise ConfigError(f"{argument!r} is not a setting of the bench: give key=value "
                              f"with a key among {', '.join(KEYS)} (--help describes them)")
        try:
            given[key] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ConfigError(f"{key}={text!r} is not a value (YAML)") from None
    nested: dict = {}
    for key, value in given.items():  # check_settings reads dotted names from nested maps
        *parents, last = key.split(".")
        node = nested
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    check_settings(nested, {key: constraint for key, (_, constraint, _) in KEYS.items()})
    return BenchSettings(**{KEYS[key][0]: value for key, value in given.items()})


def parse_args(argv: list[str] | None = None) -> BenchSettings:
    """:func:`parse` for a command line: ``--help`` prints :func:`usage` and exits 0, a bad
    argument prints its error under the usage line and exits 2 (as argparse does)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help") for a in argv):
        print(usage())
        raise SystemExit(0)
    try:
        return parse(argv)
    except ConfigError as error:
        print(f"{usage().splitlines()[0]}\n{PROG}: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
