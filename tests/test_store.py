"""The MLflow store survives kills: atomic creation, damaged stores named, orphans and
SIGTERM end FAILED."""

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from pipeline.core.errors import StoreError
from pipeline.core.tracking import init_store, tracking_uri

ROOT = Path(__file__).resolve().parents[1]


def test_a_half_made_store_from_a_killed_creation_is_never_used(tmp_path):
    # A process killed while MLflow built its tables leaves only its partial file.
    (tmp_path / ".mlflow.db.partial-12345").write_bytes(b"SQLite format 3\x00 half")
    experiment_id = init_store(tmp_path, "btf")
    client = MlflowClient(tracking_uri(tmp_path))
    assert client.get_experiment(experiment_id).name == "btf"
    assert not list(tmp_path.glob(f".mlflow.db.partial-{os.getpid()}"))


def test_a_damaged_store_is_named_in_the_error(tmp_path):
    (tmp_path / "mlflow.db").write_bytes(b"this is not a database" * 100)
    with pytest.raises(StoreError, match=str(tmp_path / "mlflow.db")):
        init_store(tmp_path, "btf")


def test_runs_left_running_by_a_dead_process_are_marked_failed(tmp_path, mlflow_template):
    mlflow_template(tmp_path)
    experiment_id = init_store(tmp_path, "btf")
    client = MlflowClient(tracking_uri(tmp_path))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    host = socket.gethostname()
    dead = client.create_run(experiment_id, tags={"host": host, "pid": gone.stdout.strip()})
    alive = client.create_run(experiment_id, tags={"host": host, "pid": str(os.getpid())})
    elsewhere = client.create_run(experiment_id, tags={"host": "another-node", "pid": "1"})

    init_store(tmp_path, "btf")  # the next job's start
    status = {r: client.get_run(r.info.run_id).info.status for r in (dead, alive, elsewhere)}
    assert status == {dead: "FAILED", alive: "RUNNING", elsewhere: "RUNNING"}
    assert "gone" in client.get_run(dead.info.run_id).data.tags["ended_by"]


def test_sigterm_ends_the_run_failed_and_leaves_no_temporary_folder(tmp_path, mlflow_template):
    runs = tmp_path / "runs"
    mlflow_template(runs)
    job = subprocess.Popen(
        [sys.executable, "-m", "pipeline", "experiment=smoke", f"paths.runs={runs}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for line in job.stdout:  # wait until a stage is computing (Hydra logs to stdout)
            if "generating the built-in synthetic BTF" in line or "stage " in line:
                break
        time.sleep(1.0)
        job.send_signal(signal.SIGTERM)
        job.communicate(timeout=300)  # reads the rest, so the job never blocks on the pipe
    finally:
        job.kill()
        job.wait()
    assert job.returncode != 0
    client = MlflowClient(tracking_uri(runs))
    found = client.search_runs([client.get_experiment_by_name("smoke").experiment_id])
    assert [r.info.status for r in found] == ["FAILED"]
    assert not list((runs / "cache").glob("*/.tmp-*"))
    assert not list((runs / "data").glob(".*partial*"))


def test_a_tracking_server_chosen_by_the_user_stays_chosen(tmp_path, monkeypatch):
    """MLFLOW_TRACKING_URI (an `mlflow server`) wins over paths.runs, also after this
    process pointed MLflow at it (the sweep parent asks twice), and in its subprocesses;
    a SQLite store the pipeline chose itself never outlives its paths.runs."""
    from pipeline.core.tracking import use_store

    server = "http://127.0.0.1:5055"
    monkeypatch.delenv("PIPELINE_TRACKING_URI_SET_BY_PIPELINE", raising=False)  # restored after
    monkeypatch.setenv("MLFLOW_TRACKING_URI", server)
    assert use_store(tmp_path / "a") == server
    assert tracking_uri(tmp_path / "a") == server
    assert use_store(tmp_path / "b") == server

    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    first = use_store(tmp_path / "a")
    assert first == f"sqlite:///{(tmp_path / 'a').resolve() / 'mlflow.db'}"
    assert tracking_uri(tmp_path / "b") == f"sqlite:///{(tmp_path / 'b').resolve() / 'mlflow.db'}"
