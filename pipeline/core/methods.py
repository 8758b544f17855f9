"""The method registry: what the job and the tables command know of a method.

A method is one :class:`Method` object that its package exports, named by its config file
``conf/method/<name>.yaml`` (``spec: <module>:<attribute>``); neither the job nor the tables
command names a method (``docs/design.md``, "Adding a method"). A :class:`Method` lives in
a light module whose functions import the heavy ones when called, so registering it costs
no torch import.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from pipeline.core.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # shipped inside the package


@dataclass(frozen=True)
class Method:
    """One method as the job and the tables command see it.

    name : ``method.name`` of its config file.
    paper : the letter of PAPERS.md it reproduces; orders the report's sections.
    run : ``(ctx) -> dict[str, float]``: the job's chain on a
        :class:`pipeline.core.stage.Context`, returning its metrics.
    description : the run's note in the MLflow UI: what it computed, how to read it.
    headline : the metrics printed at the end of a job (and returned to sweepers: the
        first one that exists).
    reports : modules whose ``sections(runs, out, settings) -> list[str]`` write the
        method's tables and figures for ``python -m pipeline.tables`` (once per module).
    figures : ``(cfg, cache_keys, out) -> list[Path]`` drawing the figures of a finished
        job into ``out`` (logged under ``figures/``), or None.
    prepare : ``(cfg) -> None`` called before anything else of the job
        (process-wide state that must be set before torch loads), or None.
    run_name : ``(cfg) -> str``, the MLflow run's name; None: ``"<name> s<seed>"``.
    unused : ``(cfg) -> list[str]``, flattened settings this job does not read (e.g. the
        method's learning rate when ``train.lr`` replaces it): not logged, not in the recipe.
    schemas : Hydra structured configs to register before composing, as
        ``(group, name, dataclass)``: the one source of a settings group's defaults,
        which the YAML files extend (``defaults: [/<group>/<name>@_here_, _self_]``).
    check : ``(cfg) -> None`` raising :class:`ConfigError` for a bad setting, called for
        every job of a sweep before the first runs, and by the job itself (not by a
        library call of the method's runner); or None.
    settings : ``(prefix, dataclass)`` pairs whose fields declare their roles
        (:func:`pipeline.core.settings.setting`): the recipe leaves out what is not a result.
    """

    name: str
    paper: str
    run: Callable[[Any], dict[str, float]]
    description: str
    headline: tuple[str, ...] = ("rmse",)
    reports: tuple[str, ...] = ()
    figures: Callable[[DictConfig, dict, Path], list[Path]] | None = None
    prepare: Callable[[DictConfig], None] | None = None
    run_name: Callable[[DictConfig], str] | None = None
    unused: Callable[[DictConfig], list[str]] | None = None
    schemas: tuple[tuple[str, str, type], ...] = ()
    settings: tuple[tuple[str, type], ...] = ()
    check: Callable[[DictConfig], None] | None = None

    def roles(self) -> dict[str, str]:
        """``{"prefix.field": role}`` of :attr:`settings`."""
        from pipeline.core.settings import roles

        return {
            key: role for prefix, cls in self.settings for key, role in roles(cls, prefix).items()
        }

    def left_out(self, cfg: DictConfig) -> list[str]:
        """The settings :attr:`unused` names for this job, and the settings declared
        ``added`` that are at their default (:func:`pipeline.core.settings.setting`)."""
        from pipeline.core.settings import added_defaults, at_added_default, roles

        added = {key for prefix, cls in self.settings for key in at_added_default(cls, prefix, cfg)}
        # A name another class under the same prefix (another model) declares plainly stays.
        plain = {
            key
            for prefix, cls in self.settings
            for key in roles(cls, prefix)
            if key not in added_defaults(cls, prefix)
        }
        return (self.unused(cfg) if self.unused else []) + sorted(added - plain)

    def name_run(self, cfg: DictConfig) -> str:
        return self.run_name(cfg) if self.run_name else f"{self.name} s{cfg.seed}"


def resolve(reference: str) -> Any:
    """The object a ``module:name`` (or ``module``) reference names."""
    module_name, _, attribute = reference.partition(":")
    try:
        module = importlib.import_module(module_name)
        return getattr(module, attribute) if attribute else module
    except (ImportError, AttributeError) as error:
        raise ConfigError(f"cannot import {reference!r}: {error}") from error


def method_of(cfg: DictConfig) -> Method:
    """The :class:`Method` the composed config's ``method.spec`` names."""
    spec = cfg.method.get("spec")
    if not spec:
        raise ConfigError(
            f"method {cfg.method.get('name')!r} has no 'spec' naming its "
            "Method object (conf/method/<name>.yaml: spec: <module>:<name>)"
        )
    method = resolve(spec)
    if not isinstance(method, Method):
        raise ConfigError(f"method.spec={spec!r} is a {type(method).__name__}, not a Method")
    if method.name != cfg.method.name:
        raise ConfigError(
            f"method.spec={spec!r} is method {method.name!r}, but method.name={cfg.method.name!r}"
        )
    return method


def registered(conf_dirs: Iterable[Path] = (CONF_DIR,)) -> list[Method]:
    """Every method a ``conf/method/*.yaml`` names, in the order of PAPERS.md."""
    methods = {}
    for conf_dir in conf_dirs:
        for path in sorted(Path(conf_dir, "method").glob("*.yaml")):
            spec = OmegaConf.load(path).get("spec")
            if spec:
                method = resolve(spec)
                methods.setdefault(method.name, method)
    return sorted(methods.values(), key=lambda m: m.paper)


def reports(methods: Iterable[Method]) -> list[Any]:
    """The distinct report modules of ``methods``, in their order."""
    names = list(dict.fromkeys(name for m in methods for name in m.reports))
    return [resolve(name) for name in names]


def register_schemas(conf_dirs: Iterable[Path] = (CONF_DIR,)) -> None:
    """Put every registered method's structured configs in Hydra's ConfigStore, which a
    YAML file extending them needs before Hydra composes."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for method in registered(conf_dirs):
        for group, name, schema in method.schemas:
            store.store(group=group, name=name, node=schema)
