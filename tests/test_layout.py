"""The project's shape: every experiment composes, a stage runs only with its code
version, and the examples in the docstrings run. (What importing does:
``test_import_effects.py``; how modules import each other: ``test_imports.py``.)
"""

from __future__ import annotations

import doctest
import importlib
import io
import re

import pytest
from helpers import CONF_DIR, compose_config, hydra_compose
from helpers import PIPELINE_MODULES as MODULES
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

from pipeline.core.sweeper import expand

# ------------------------------------------------------------------ experiments compose

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
METHOD_A = {"btf"}


def _sweep_points(experiment: str) -> list[list[str]]:
    """The experiment alone, then each value of each of its sweep's axes alone, then each
    job of each of its arms (pipeline.core.sweeper)."""
    cfg = compose_config(f"experiment={experiment}", return_hydra_config=True)
    params = OmegaConf.select(cfg, "hydra.sweeper.params") or {}
    parser = OverridesParser.create()
    points = [[]]
    for key, values in params.items():
        override = parser.parse_override(f"{key}={values}")
        points += [[f"{key}={value}"] for value in override.sweep_string_iterator()]
    arms = OmegaConf.select(cfg, "hydra.sweeper.arms")
    arms = OmegaConf.to_container(arms) if arms else []
    return points + expand(arms, None, [])


def test_the_tests_set_folders_as_a_hydra_override_does(tmp_path):
    """compose_config sets plain ``paths.*`` folders on a copy of a composed config: the
    result equals Hydra's compose with the same overrides, interpolations resolved."""
    overrides = (
        "experiment=render_smoke",
        "model=pca",
        f"paths.runs={tmp_path / 'runs'}",
        f"paths.data={tmp_path / 'data'}",
    )
    ours = compose_config(*overrides)
    assert ours.paths.data == str(tmp_path / "data")
    hydras = hydra_compose(overrides)
    assert OmegaConf.to_container(ours, resolve=True) == OmegaConf.to_container(
        hydras, resolve=True
    )


def test_experiments_are_found():
    assert {"default", "smoke", "brdf_map", "fourier"} <= set(EXPERIMENTS)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_composes_with_its_methods_settings_only(experiment):
    """Each experiment (and each point of its sweep) composes with the real config;
    method A's settings (``btf.*``, ``train.*``) are there for A and absent from B and C."""
    for point in _sweep_points(experiment):
        cfg = compose_config(f"experiment={experiment}", *point)
        where = f"experiment={experiment} {' '.join(point)}".strip()
        if cfg.method.name in METHOD_A:
            assert isinstance(OmegaConf.select(cfg, "btf.crop.size"), int), where
            assert "train" in cfg, where
        else:
            assert {"btf", "train", "model"} & set(cfg) == set(), where
        OmegaConf.to_container(cfg, resolve=True)  # every interpolation resolves


# ------------------------------------------------------------------------ command line


def test_a_stage_runs_only_with_its_code_version(tmp_path):
    """An unknown stage (no ``version=``) is an error, not version "1"; nothing runs."""
    from pipeline.core.cache import StageCache
    from pipeline.core.stage import Context

    ctx = Context(OmegaConf.create({}), StageCache(tmp_path / "cache"))
    calls = []

    def compute(folder):
        calls.append(folder)

    with pytest.raises(TypeError):
        ctx.run("new_stage", {}, {}, compute)
    for version in (None, "", 1):
        with pytest.raises(TypeError, match="version"):
            ctx.run("new_stage", {}, {}, compute, version=version)
    assert calls == [] and ctx.keys == {}
    assert not (tmp_path / "cache").exists()
    entry = ctx.run("new_stage", {}, {}, compute, version="1")
    assert len(calls) == 1 and ctx.keys == {"new_stage": entry.key}


# --------------------------------------------------------------------------- doctests

# Modules with examples, found by reading the files (only these are imported here).
EXAMPLES = sorted(
    name for name, path in MODULES.items() if re.search(r"^\s*>>> ", path.read_text(), re.MULTILINE)
)
# The examples in these must run (not all be skipped).
MUST_RUN = {"pipeline.btf.synthetic", "pipeline.fourier.series", "pipeline.fourier.quilting"}
# Examples that fail because of a mistake in pipeline/ (reported; strict: remove the
# entry once fixed).
BROKEN_EXAMPLES: dict[str, str] = {}


def test_examples_are_found():
    assert MUST_RUN <= set(EXAMPLES)


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=pytest.mark.xfail(reason=BROKEN_EXAMPLES[name], strict=True))
        if name in BROKEN_EXAMPLES
        else name
        for name in EXAMPLES
    ],
)
def test_docstring_examples(name):
    """The ``>>>`` examples of the module run and print what they show (doctest, with
    pytest's default ELLIPSIS; ``pytest --doctest-modules pipeline`` runs the same)."""
    module = importlib.import_module(name)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    report = io.StringIO()
    for test in doctest.DocTestFinder().find(module, name):
        runner.run(test, out=report.write)
    results = runner.summarize(verbose=False)
    assert results.failed == 0, report.getvalue()
    if name in MUST_RUN:
        assert results.attempted > 0
