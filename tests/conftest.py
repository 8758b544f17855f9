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
from helpers import compose_config
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


@pytest.fixture
def smoke_cfg(tmp_path, mlflow_template):
    """A factory: the smoke experiment writing under a temporary ``paths.runs``."""
    mlflow_template(tmp_path / "runs")

    def make(*overrides: str) -> DictConfig:
        return compose_config("experiment=smoke", f"paths.runs={tmp_path / 'runs'}", *overrides)

    return make


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
