"""Shared fixtures (plain helpers are in ``helpers.py``): an empty MLflow store, and the
real Hydra config shrunk with experiment=smoke."""

from __future__ import annotations

import os

# Tests use tiny arrays: one thread per library is as fast, and far faster when the
# machine is busy (spin-waiting thread pools). Set before numpy/torch are imported; the
# command-line tests' subprocesses inherit it.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import shutil
from pathlib import Path

import pytest
from helpers import WIRING_STEPS, compose_config
from omegaconf import DictConfig

from pipeline.core.methods import register_schemas


@pytest.fixture(scope="session", autouse=True)
def _settings_schemas() -> None:
    """The structured configs the YAML files extend, for the tests that compose with
    Hydra's API themselves (``tests/helpers.compose_config`` registers them too)."""
    register_schemas()


@pytest.fixture(scope="session")
def _empty_mlflow_db(tmp_path_factory) -> Path:
    """An MLflow SQLite store with its schema, created once (creating one takes seconds)."""
    from pipeline.core.store import init_store

    folder = tmp_path_factory.mktemp("mlflow_template")
    init_store(folder, "Default")
    return folder / "mlflow.db"


@pytest.fixture
def mlflow_template(_empty_mlflow_db):
    """Copy the empty store into a runs folder: ``mlflow_template(runs_dir)``."""

    def copy(runs_dir: Path) -> None:
        runs_dir.mkdir(parents=True, exist_ok=True)
        shutil.copy(_empty_mlflow_db, runs_dir / "mlflow.db")

    return copy


@pytest.fixture(scope="session")
def shared_cache(tmp_path_factory) -> Path:
    """One stage cache for the pytest worker's smoke jobs. The cache is made to be shared
    (entries are keyed by their settings and inputs, published atomically, locked while
    computed), so a job whose stages another test already computed reads them: only the
    tests about computing or keeping entries need a cache of their own."""
    return tmp_path_factory.mktemp("shared_cache")


@pytest.fixture(scope="session")
def shared_data(tmp_path_factory) -> Path:
    """One folder for the worker's generated built-in BTFs (``paths.data``). The load
    stage's key holds the dataset's file times, so a dataset written again in each test's
    folder would miss every stage of :func:`shared_cache`; a generated dataset is
    published atomically and never rewritten with the same settings."""
    return tmp_path_factory.mktemp("shared_data")


@pytest.fixture
def smoke_cfg(tmp_path, mlflow_template, shared_cache, shared_data):
    """A factory: the smoke experiment writing its runs under a temporary ``paths.runs``,
    its stages into the worker's shared cache, its built-in BTF into the worker's shared
    data folder, trained for :data:`WIRING_STEPS` steps, unless the overrides name
    ``paths.cache``, ``paths.data`` or ``train.max_steps``."""
    mlflow_template(tmp_path / "runs")
    defaults = {
        "paths.cache": str(shared_cache),
        "paths.data": str(shared_data),
        "train.max_steps": str(WIRING_STEPS),
    }

    def make(*overrides: str) -> DictConfig:
        named = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
        if "train" in named:  # a train=<recipe> group brings its own length
            named.add("train.max_steps")
        unnamed = [f"{key}={value}" for key, value in defaults.items() if key not in named]
        return compose_config(
            "experiment=smoke", f"paths.runs={tmp_path / 'runs'}", *unnamed, *overrides
        )

    return make


@pytest.fixture
def own_cache(tmp_path) -> str:
    """The override that gives a smoke job a cache of its own (where ``paths.cache`` is by
    default), for the tests that check what was computed or stored."""
    return f"paths.cache={tmp_path / 'runs' / 'cache'}"


@pytest.fixture(autouse=True)
def _no_store_left_from_another_test(monkeypatch):
    """Each test starts with no MLflow store chosen and no run active: a test that stops a
    job midway (tests/test_signals.py) must not leave its store or run to the next one."""
    import mlflow

    while mlflow.active_run() is not None:
        mlflow.end_run()
    # The second: the store the pipeline itself chose (pipeline.core.store.use_store).
    for name in ("MLFLOW_TRACKING_URI", "PIPELINE_TRACKING_URI_SET_BY_PIPELINE"):
        monkeypatch.delenv(name, raising=False)
