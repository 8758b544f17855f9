"""A refusal is one line, no traceback: :func:`check_command_line` composes the command line
as Hydra will (each sweep at its first value) before any job starts, and turns Hydra's error
into one line naming the setting and, for a misspelt key, the closest real one.
``PIPELINE_DEBUG=1`` shows tracebacks.
"""

from __future__ import annotations

import difflib
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from pipeline.core.errors import ConfigError

DEBUG = "PIPELINE_DEBUG"


def debugging() -> bool:
    return os.environ.get(DEBUG, "") not in ("", "0")


def refuse(error: BaseException, status: int = 2) -> NoReturn:
    """Print ``error: <message>`` on one line to stderr and exit with ``status``."""
    message = " ".join(str(error).split())
    print(f"error: {message}", file=sys.stderr, flush=True)
    raise SystemExit(status)


def first_values(overrides: Sequence[str]) -> list[str]:
    """The command line with each sweep (``k=1,2``, ``range(3)``) at its first value."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    lines = []
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        if override.is_sweep_override():
            key = override.input_line.split("=", 1)[0]
            lines.append(f"{key}={next(iter(override.sweep_string_iterator()))}")
        else:
            lines.append(override.input_line)
    return lines


def check_command_line(argv: Sequence[str], conf_dir: Path, config_name: str = "config") -> None:
    """Compose ``argv``'s overrides as Hydra will; raise :class:`ConfigError` in one line
    naming the bad override (and the closest setting to a misspelt key)."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    overrides, config_name = _hydra_arguments(argv, config_name)
    if overrides is None:  # --help, --version, a bad flag: Hydra answers it
        return
    try:
        lines = first_values(overrides)
    except HydraException as error:
        raise ConfigError(_first_line(error)) from None
    from pipeline.core.settings import check_added_keys

    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=lines, return_hydra_config=True)
            # A key added with + that no code reads (Hydra adds it without a word).
            job = OmegaConf.masked_copy(cfg, [key for key in cfg if key != "hydra"])
            check_added_keys(
                job, lines, conf_dir, compose=lambda given: compose(config_name, given)
            )
    except (HydraException, OmegaConfBaseException) as error:
        raise ConfigError(explain(error, lines, conf_dir, config_name)) from None
    multirun = {"-m", "--multirun"} & set(argv) or str(cfg.hydra.mode) == "RunMode.MULTIRUN"
    sweeps = [line for line, given in zip(lines, overrides, strict=True) if line != given]
    if sweeps and not multirun:
        raise ConfigError(
            f"{overrides[lines.index(sweeps[0])]} is a sweep: add -m (or give one value)"
        )


# Hydra's flags that take a value, which is not an override (its parser, in a private
# module, says so: hydra._internal.utils.get_args_parser); --info's value is optional.
_VALUED = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn"}
_VALUED |= {"--config-dir", "-cd", "--experimental-rerun"}
_INFO = {"--info", "-i"}
_INFO_VALUES = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
_NO_COMPOSE = {"-h", "--help", "--hydra-help", "--version", "-sc", "--shell-completion"}


def _hydra_arguments(argv: Sequence[str], config_name: str) -> tuple[list[str] | None, str]:
    """The overrides of a Hydra command line (flags and their values, as in ``--cfg job``,
    left out) and the config it composes; None where it asks for no composition."""
    overrides, given = [], list(argv)
    while given:
        flag = given.pop(0)
        name, has_value, value = flag.partition("=")
        if name in _NO_COMPOSE:
            return None, config_name
        if name in _VALUED and not has_value and given:
            value = given.pop(0)
        elif name in _INFO and not has_value and given and given[0] in _INFO_VALUES:
            given.pop(0)
        if name in ("--config-name", "-cn"):
            config_name = value
        if not flag.startswith("-"):
            overrides.append(flag)
    return overrides, config_name


def explain(error: BaseException, lines: Sequence[str], conf_dir: Path, config_name: str) -> str:
    """One line for Hydra's composition ``error`` of the overrides ``lines``."""
    text = f"{error} {error.__cause__ or ''}"
    key = _failed_key(text)
    if "Could not find" in text or "Could not load" in text:
        found = re.search(r"Could not (?:find|load) '([^']+)'", text)
        name = found.group(1) if found else "?"
        options = re.findall(r"^\s+(\S+)$", str(error), flags=re.M)
        choose = f" (choose from {', '.join(options)})" if options else ""
        return f"{name}: no such config{choose}"
    if key and (
        "not in struct" in text or "Could not override" in text or "Could not append" in text
    ):
        return f"{_given(lines, key)}: no such setting{_closest(key, lines, conf_dir, config_name)}"
    if key:
        return f"{_given(lines, key)}: {_first_line(error.__cause__ or error)}"
    return _first_line(error)


def _failed_key(text: str) -> str | None:
    for pattern in (
        r"full_key: (\S+)",
        r"Could not override '([^']+)'",
        r"Could not append to config\. An item is already at '([^']+)'",
        r"[Kk]ey '([^']+)' (?:is )?not in struct",
    ):
        found = re.search(pattern, text)
        if found:
            return found.group(1)
    return None


def _given(lines: Sequence[str], key: str) -> str:
    """The override that set ``key`` (or a setting under it) as the user wrote it, else
    the key."""
    for line in lines:
        written = line.lstrip("+~").split("=", 1)[0]
        if written == key or written.startswith(f"{key}."):
            return line
    return key


def _closest(key: str, lines: Sequence[str], conf_dir: Path, config_name: str) -> str:
    """`` (did you mean KEY?)`` among the settings the config has without the override
    that failed at ``key``, compared as it was written (``trian.lr``, not ``trian``)."""
    from hydra import compose, initialize_config_dir

    from pipeline.core.settings import leaf_keys

    failed = _given(lines, key)
    key = failed.lstrip("+~").split("=", 1)[0]
    others = [line for line in lines if line != failed]
    try:
        with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
            cfg = compose(config_name=config_name, overrides=others)
    except Exception:  # another bad override: name the closest without its help
        return ""
    found = difflib.get_close_matches(key, leaf_keys(cfg), n=1, cutoff=0.6)
    return f" (did you mean {found[0]}?)" if found else ""


def _first_line(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__
