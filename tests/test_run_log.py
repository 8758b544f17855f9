"""The run logger on a stage's context (pipeline.core.run_log): outside a run it does
nothing and needs no store; inside one it logs what it is given; no stage asks MLflow."""

from __future__ import annotations

import re
from pathlib import Path

import mlflow
import numpy as np
from mlflow.tracking import MlflowClient

from pipeline.core.run_log import NO_RUN, RunLog
from pipeline.core.store import init_store

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline"


def _everything(log: RunLog, tmp_path: Path) -> None:
    (tmp_path / "folder").mkdir(exist_ok=True)
    (tmp_path / "folder" / "a.txt").write_text("a")
    (tmp_path / "b.txt").write_text("b")
    log.metric("m", 1.5, step=2)
    log.metrics({"n": 2.0, "o": 3.0})
    log.series("curve", [(0, 4.0), (5, 3.0), (9, 2.5)])
    log.tags({"t": "v"})
    log.file(tmp_path / "b.txt", "files")
    log.files({"renamed.txt": tmp_path / "b.txt"}, "named")
    log.folder(tmp_path / "folder", "tree")
    log.json({"x": 1}, "x.json")


def test_no_run_logs_nothing_and_opens_no_store(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # MLflow's default store would appear here
    assert mlflow.active_run() is None
    _everything(NO_RUN, tmp_path)
    assert mlflow.active_run() is None
    assert not list(tmp_path.glob("mlflow.db")) and not (tmp_path / "mlruns").exists()


def test_a_run_log_logs_metrics_series_tags_and_files(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv("PIPELINE_TRACKING_URI_SET_BY_PIPELINE", raising=False)
    experiment = init_store(tmp_path / "runs", "run_log")
    with mlflow.start_run(experiment_id=experiment) as run:
        _everything(RunLog(on=True), tmp_path)
    client = MlflowClient()
    data = client.get_run(run.info.run_id).data
    assert data.metrics == {"m": 1.5, "n": 2.0, "o": 3.0, "curve": 2.5}
    history = client.get_metric_history(run.info.run_id, "curve")
    assert [(m.step, m.value) for m in history] == [(0, 4.0), (5, 3.0), (9, 2.5)]
    assert data.tags["t"] == "v"
    names = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert names == {"files", "named", "tree", "x.json"}
    assert [a.path for a in client.list_artifacts(run.info.run_id, "named")] == [
        "named/renamed.txt"
    ]
    local = Path(mlflow.artifacts.download_artifacts(run_id=run.info.run_id, dst_path=tmp_path))
    assert (local / "tree" / "a.txt").read_text() == "a"
    assert (local / "x.json").read_text().replace(" ", "").replace("\n", "") == '{"x":1}'
    assert np.isclose(client.get_metric_history(run.info.run_id, "m")[0].step, 2)


def test_stages_log_through_the_context_only():
    """Only the job's run (core/run.py), the run logger and the commands call MLflow's
    logging functions or ask for the active run (the benchmarks, which make their own runs,
    are outside the package)."""
    allowed = {
        "core/run.py",
        "core/run_log.py",
        "core/store.py",
        "core/sweep_run.py",
        "app.py",
        "tables.py",
        "btf/export.py",  # the pyfunc model, logged only when ctx.log is on
    }
    calls = re.compile(r"mlflow\.(active_run|log_\w+|set_tags?)\(|\.log_batch\(")
    found = [
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if str(path.relative_to(PACKAGE)) not in allowed and calls.search(path.read_text())
    ]
    assert found == []
