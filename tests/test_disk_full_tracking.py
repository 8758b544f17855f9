"""A full disk while MLflow creates or writes its store is one error naming the store
(``mlflow.db``) and the space left, and the run ends FAILED, or is left RUNNING for the
next start to mark FAILED when the store cannot take even that: with the store's writes
made to fail as SQLite fails on a full disk, and on a real small tmpfs where this machine
lets a test mount one (tests/test_disk_full.py does the same for the other writers)."""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path

import mlflow
import pytest
import sqlalchemy
from helpers import ROOT, check_one_line_refusal, compose_config, pipeline_command
from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore
from mlflow.tracking import MlflowClient

from pipeline.core import files, store
from pipeline.core.errors import DataError
from pipeline.core.run import job_run
from pipeline.core.store import ENDED_BY_TAG, ERROR_TAG, init_store, tracking_uri

FREE = 24 << 10
FULL = "database or disk is full"  # SQLite's SQLITE_FULL, all a full disk says to MLflow


def _sqlite_full(*args, **kwargs):
    """Fail as MLflow's SQLAlchemy store does on a full disk."""
    raise sqlalchemy.exc.OperationalError("INSERT INTO ...", {}, sqlite3.OperationalError(FULL))


def _status(runs: Path, run_id: str):
    return MlflowClient(tracking_uri(runs)).get_run(run_id)


@contextlib.contextmanager
def _small_disk(folder: Path, size: str):
    """``folder`` on a fresh tmpfs of ``size``; the test is skipped where none mounts."""
    folder.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command here; the patched tests cover it")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or done.returncode})")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "--lazy", str(folder)], capture_output=True)


def _pipeline(tmp_path: Path, *arguments: str, script: str | None = None, env=None):
    """``python -m pipeline`` (or ``script`` run before it) with the job's cache, data and
    Hydra folders in ``tmp_path``: only the store is on the small disk."""
    outside = [
        f"paths.cache={tmp_path / 'cache'}",
        f"paths.data={tmp_path / 'data'}",
        f"hydra.run.dir={tmp_path / 'hydra'}",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
    ]
    if script is None:
        return pipeline_command(*arguments, *outside)
    return subprocess.run(
        [sys.executable, script, *arguments, *outside],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


# ----------------------------------------------------------------- creating the store


def test_a_store_created_on_a_full_disk_is_named_with_the_space_left(tmp_path, monkeypatch):
    monkeypatch.setattr(mlflow.store.db.utils, "_initialize_tables", _sqlite_full)
    monkeypatch.setattr(files, "free_bytes", lambda path: FREE)
    runs = tmp_path / "runs"
    with pytest.raises(DataError) as caught:
        init_store(runs, "fourier_smoke")
    assert str(caught.value) == (
        f"no space left for {runs / 'mlflow.db'}: 24.0 KiB free in {runs}; {store.STORE_FULL_HINT}"
    )
    assert [p.name for p in runs.iterdir()] == [".mlflow.lock"]  # no store, no partial one


@pytest.mark.parametrize(
    "sweep", [pytest.param(False, marks=pytest.mark.slow), True], ids=["job", "sweep"]
)
def test_a_store_created_on_a_full_tmpfs_is_one_line(tmp_path, sweep):
    """A 256 KiB disk: MLflow's empty store takes about 1 MiB. A sweep's launcher creates
    the store first (its parent run's callback), and is refused alike."""
    with _small_disk(tmp_path / "disk", "256k") as disk:
        runs = disk / "runs"
        done = _pipeline(
            tmp_path, *(["-m"] if sweep else []), "experiment=fourier_smoke", f"paths.runs={runs}"
        )
        check_one_line_refusal(done, f"no space left for {runs / 'mlflow.db'}: ")
        # The space the partial store took is given back before it is measured.
        assert f" {files.human(shutil.disk_usage(disk).free)} free in {runs};" in done.stderr
        assert sorted(p.name for p in runs.iterdir()) == [".mlflow.lock"]
        assert not (tmp_path / "cache").exists()  # no stage ran


# ----------------------------------------------------------------- during a run


def test_a_full_disk_during_a_run_is_named_and_the_run_ends_failed(tmp_path, mlflow_template):
    """The store takes the run's end but not its metrics (a few pages were still free)."""
    runs = tmp_path / "runs"
    mlflow_template(runs)
    cfg = compose_config("experiment=fourier_smoke", f"paths.runs={runs}")
    with pytest.raises(DataError) as caught, pytest.MonkeyPatch.context() as patch:
        with job_run(cfg) as run:
            patch.setattr(SqlAlchemyStore, "log_metric", _sqlite_full)
            mlflow.log_metric("loss", 0.5)
    message = str(caught.value)
    assert message.startswith(f"no space left for {runs / 'mlflow.db'}: "), message
    assert message.endswith(f"; its run {run.info.run_id} ended FAILED"), message
    ended = _status(runs, run.info.run_id)
    assert ended.info.status == "FAILED"
    assert ended.data.tags[ERROR_TAG].startswith(f"no space left for {runs / 'mlflow.db'}: ")
    assert mlflow.active_run() is None


def test_a_run_the_full_store_cannot_end_is_marked_failed_at_the_next_start(
    tmp_path, mlflow_template, monkeypatch
):
    runs = tmp_path / "runs"
    mlflow_template(runs)
    cfg = compose_config("experiment=fourier_smoke", f"paths.runs={runs}")
    with pytest.raises(DataError) as caught, pytest.MonkeyPatch.context() as full:
        with job_run(cfg) as run:
            for write in ("log_metric", "log_batch", "set_tag", "update_run_info"):
                full.setattr(SqlAlchemyStore, write, _sqlite_full)
            mlflow.log_metric("loss", 0.5)
    assert str(caught.value).endswith(
        f"; its run {run.info.run_id} is left RUNNING: the next start marks it FAILED"
    )
    assert mlflow.active_run() is None
    assert _status(runs, run.info.run_id).info.status == "RUNNING"
    # Space freed, and the job's process gone (as it is once the command has exited).
    monkeypatch.setattr(store, "process_alive", lambda pid: False)
    init_store(runs, "fourier_smoke")
    ended = _status(runs, run.info.run_id)
    assert ended.info.status == "FAILED" and ended.data.tags[ENDED_BY_TAG].startswith("its process")


# Fills the disk as the job logs its results, then runs the command (argv as given).
FILL_AT_THE_RESULTS = """
import os, runpy, shutil, sys
from pathlib import Path

from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

disk, log_batch = Path(os.environ["FILL_DISK"]), SqlAlchemyStore.log_batch


def filled_first(self, run_id, metrics=(), *args, **kwargs):
    if metrics and not (disk / "filler").exists():
        (disk / "filler").write_bytes(bytes(shutil.disk_usage(disk).free))
    return log_batch(self, run_id, metrics, *args, **kwargs)


SqlAlchemyStore.log_batch = filled_first
sys.argv = ["pipeline", *sys.argv[1:]]
runpy.run_module("pipeline", run_name="__main__", alter_sys=True)
"""


@pytest.mark.slow
def test_a_tmpfs_that_fills_during_a_run_is_one_line_and_the_run_ends_failed(tmp_path):
    """The real thing: SQLite meets the full disk as the job logs its metrics, and cannot
    write the run's end either; after space is freed, the next start marks it FAILED."""
    script = tmp_path / "fill_at_the_results.py"
    script.write_text(FILL_AT_THE_RESULTS)
    with _small_disk(tmp_path / "disk", "4m") as disk:
        runs = disk / "runs"
        env = {**__import__("os").environ, "FILL_DISK": str(disk)}
        done = _pipeline(
            tmp_path, "experiment=fourier_smoke", f"paths.runs={runs}", script=str(script), env=env
        )
        check_one_line_refusal(done, f"no space left for {runs / 'mlflow.db'}: 0 B free in {runs};")
        (error,) = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
        run_id = error.split("its run ")[1].split()[0]
        (disk / "filler").unlink()
        init_store(runs, "fourier_smoke")  # the next start
        assert _status(runs, run_id).info.status == "FAILED"
