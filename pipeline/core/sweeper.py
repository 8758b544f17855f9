"""A sweep composes exactly what was asked: an experiment's arms, crossed with its axes
and the command line, where the command line replaces what it names.

Hydra's basic sweeper crosses every axis with every other. An experiment's grid is often a
union instead (Neural BTF once, clustered at three k, PCA once), and a command line that
names a setting an experiment sweeps must replace that axis, not multiply it. So:

- ``hydra.sweeper.params``: axes crossed with everything (``seed: 0,1,2``), as Hydra's.
- ``hydra.sweeper.arms``: a list of arms, each a map of overrides whose values may be
  sweeps themselves (``{model: clustered, model.k: "500,1000,2000"}``); the jobs are the
  union over arms of each arm's grid, crossed with the axes.
- The command line's overrides apply to every job and replace the same key in the axes and
  in every arm. Where the command line chooses a config group that arms choose
  (``model=clustered``), only the arms that choose the same option are kept (none kept:
  one arm, the command line's); a line says which. Arms that differ only in what the
  command line replaced are one arm: the same job is never launched twice.

>>> expand([{"model": "a"}, {"model": "b", "k": "1,2"}], {"seed": "0,1"}, ["model=b"])
[['model=b', 'k=1', 'seed=0'], ['model=b', 'k=1', 'seed=1'], ['model=b', 'k=2', 'seed=0'], \
['model=b', 'k=2', 'seed=1']]
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Mapping, Sequence
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser

log = logging.getLogger(__name__)


def _parse(lines: Sequence[str]) -> list:
    return OverridesParser.create().parse_overrides(list(lines))


def _choices(override) -> list[str]:
    """``key=value`` lines of one override, a sweep giving one per value."""
    key = override.get_key_element()
    if override.is_sweep_override():
        return [f"{key}={value}" for value in override.sweep_string_iterator()]
    return [f"{key}={override.get_value_element_as_str()}"]


def _chooses_otherwise(given, arm) -> bool:
    """Whether the command line's ``given`` override picks another option of a config
    group (a key without a dot, ``model``) than the arm's override does."""
    if "." in given.get_key_element() or given.is_sweep_override():
        return False
    value = given.get_value_element_as_str()
    return value not in [line.split("=", 1)[1] for line in _choices(arm)]


def _lines(mapping: Mapping[str, Any] | None) -> list[str]:
    return [f"{key}={value}" for key, value in (mapping or {}).items()]


def expand(
    arms: Sequence[Mapping[str, Any]] | None,
    params: Mapping[str, Any] | None,
    arguments: Sequence[str],
    announce=None,
) -> list[list[str]]:
    """The jobs (each a list of ``key=value`` overrides) of ``arms`` x ``params`` with the
    command line ``arguments`` replacing what they name (see the module docstring)."""
    given = {o.get_key_element(): o for o in _parse(arguments)}
    distinct: dict[tuple, dict] = {}  # arms the command line made identical are one arm
    for arm in arms or [{}]:
        parsed = {o.get_key_element(): o for o in _parse(_lines(arm))}
        if not any(_chooses_otherwise(given[key], o) for key, o in parsed.items() if key in given):
            rest = {key: o for key, o in parsed.items() if key not in given}
            distinct.setdefault(tuple(o.input_line for o in rest.values()), rest)
    n_kept = len(distinct)  # an arm whose every key the command line replaced is still kept
    kept = list(distinct.values()) or [{}]
    if announce is not None and arms and n_kept < len(arms):
        chosen = [
            o.input_line for key, o in given.items() if "." not in key and not o.is_sweep_override()
        ]
        announce(
            f"{' '.join(chosen)} on the command line keeps "
            f"{n_kept} of the experiment's {len(arms)} arms"
        )
    swept = {o.get_key_element(): o for o in _parse(_lines(params))}
    axes = [o for key, o in swept.items() if key not in given]
    jobs = []
    for arm in kept:
        lists = [_choices(o) for o in given.values()]
        lists += [_choices(o) for o in arm.values()] + [_choices(o) for o in axes]
        jobs += [list(job) for job in itertools.product(*lists)]
    return jobs
