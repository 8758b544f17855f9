"""The MLflow store survives kills: atomic creation, damaged stores named, runs of dead
processes end FAILED at any start and at ``cache gc`` (SIGTERM: tests/test_signals.py;
leftover and foreign files: tests/test_store_leftovers.py)."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT, python_code
from mlflow.tracking import MlflowClient

from pipeline import cache as cache_command
from pipeline.core.cache import StageCache, save_arrays
from pipeline.core.errors import StoreError
from pipeline.core.process import process_alive
from pipeline.core.store import init_store, tracking_uri


def _dead_pid() -> int:
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(gone.stdout)


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


def test_runs_of_any_experiment_left_running_by_a_dead_process_are_marked_failed(
    tmp_path, mlflow_template
):
    mlflow_template(tmp_path)
    smoke = init_store(tmp_path, "smoke")
    client = MlflowClient(tracking_uri(tmp_path))
    host = socket.gethostname()
    dead = client.create_run(smoke, tags={"host": host, "pid": str(_dead_pid())})
    alive = client.create_run(smoke, tags={"host": host, "pid": str(os.getpid())})
    elsewhere = client.create_run(smoke, tags={"host": "another-node", "pid": "1"})
    untagged = client.create_run(smoke)
    pid_zero = client.create_run(smoke, tags={"host": host, "pid": "0"})  # no such process

    init_store(tmp_path, "fourier_smoke")  # the next start, of another experiment
    status = {
        r: client.get_run(r.info.run_id).info.status
        for r in (dead, alive, elsewhere, untagged, pid_zero)
    }
    assert status == {
        dead: "FAILED",
        alive: "RUNNING",
        elsewhere: "RUNNING",
        untagged: "RUNNING",
        pid_zero: "FAILED",
    }
    assert "gone" in client.get_run(dead.info.run_id).data.tags["ended_by"]


def test_a_zombie_is_not_alive():
    """A process that ended but that its parent has not collected yet (kill -9 of a job
    whose shell is busy) still answers os.kill(pid, 0): it is no less gone."""
    child = subprocess.Popen(["true"])
    # Wait for the exit without collecting it (WNOWAIT): the child stays a zombie until
    # child.wait() below; no polling, no timing.
    os.waitid(os.P_PID, child.pid, os.WEXITED | os.WNOWAIT)
    state = Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    assert state == "Z"
    os.kill(child.pid, 0)  # no error: the pid still exists
    assert not process_alive(child.pid)
    child.wait()
    assert not process_alive(child.pid)
    assert process_alive(os.getpid()) and not process_alive(0) and not process_alive(-1)


def _entry(cache: StageCache, stage: str, value: float):
    return cache.run(
        stage, "1", {"value": value}, {}, lambda folder: save_arrays(folder, x=np.full(4, value))
    )


def test_cache_gc_ends_dead_runs_and_no_longer_keeps_what_they_used(
    tmp_path, mlflow_template, monkeypatch, capsys
):
    """A run killed with kill -9 stays RUNNING; gc used to keep everything used since
    it started. gc marks it FAILED (dry_run=true only says so) and removes what no finished
    run uses."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    runs = tmp_path / "runs"
    mlflow_template(runs)
    client = MlflowClient(f"sqlite:///{runs / 'mlflow.db'}")
    experiment = client.create_experiment("smoke")
    cache = StageCache(runs / "cache")
    kept, unused = _entry(cache, "a", 1.0), _entry(cache, "b", 2.0)
    cache.release()  # as the job that made them does when it ends
    finished = client.create_run(experiment, tags={"cache.a": kept.key})
    client.set_terminated(finished.info.run_id, "FINISHED")
    killed = client.create_run(
        experiment, tags={"host": socket.gethostname(), "pid": str(_dead_pid())}
    )

    assert cache_command.main(["gc", "dry_run=true", f"paths.runs={runs}"]) == 0
    out = capsys.readouterr().out
    assert "would mark 1 RUNNING runs FAILED" in out and killed.info.run_id in out
    assert f"would remove {unused.path}" in out
    assert client.get_run(killed.info.run_id).info.status == "RUNNING"

    assert cache_command.main(["gc", f"paths.runs={runs}"]) == 0
    out = capsys.readouterr().out
    assert "marked 1 RUNNING runs FAILED" in out and "still RUNNING" not in out
    assert client.get_run(killed.info.run_id).info.status == "FAILED"
    assert kept.path.is_dir() and not unused.path.exists()


def test_a_tracking_server_chosen_by_the_user_stays_chosen(tmp_path, monkeypatch):
    """MLFLOW_TRACKING_URI (an `mlflow server`) wins over paths.runs, also after this
    process pointed MLflow at it (the sweep parent asks twice), and in its subprocesses;
    a SQLite store the pipeline chose itself never outlives its paths.runs."""
    from pipeline.core.store import use_store

    server = "http://127.0.0.1:5055"
    monkeypatch.delenv("PIPELINE_TRACKING_URI_SET_BY_PIPELINE", raising=False)  # restored after
    monkeypatch.setenv("MLFLOW_TRACKING_URI", server)
    assert use_store(tmp_path / "a") == server
    assert tracking_uri(tmp_path / "a") == server
    assert use_store(tmp_path / "b") == server

    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    first = use_store(tmp_path / "a", must_exist=False)
    assert first == f"sqlite:///{(tmp_path / 'a').resolve() / 'mlflow.db'}"
    assert tracking_uri(tmp_path / "b", must_exist=False) == (
        f"sqlite:///{(tmp_path / 'b').resolve() / 'mlflow.db'}"
    )


def test_a_folder_without_a_store_is_named_not_filled_with_an_empty_store(tmp_path, monkeypatch):
    """Reading a store that is not there (a relative paths.runs from another folder, a
    typo) is a StoreError naming the path; only a job's init_store creates one."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(
        StoreError,
        match=rf"no MLflow store at {tmp_path}/runs/mlflow.db "
        rf"\('runs' from {tmp_path}\)",
    ):
        tracking_uri("runs")
    assert not (tmp_path / "runs").exists()
    init_store("runs", "btf")  # a job's own run creates it
    assert tracking_uri("runs") == f"sqlite:///{tmp_path}/runs/mlflow.db"


def test_the_tables_command_refuses_a_runs_folder_without_a_store_in_one_line(tmp_path):
    missing = tmp_path / "nonexistent"
    done = subprocess.run(
        [sys.executable, "-m", "pipeline.tables", f"paths.runs={missing}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        f"error: no MLflow store at {missing}/mlflow.db: give the jobs' paths.runs, as an "
        "absolute path or from the folder they ran in"
    ]
    assert not missing.exists()  # no store, no tables, no Hydra folder


def test_each_experiment_gets_a_description_that_a_user_s_edit_replaces(tmp_path, mlflow_template):
    """The experiment's note (mlflow.note.content) says what its runs are and which
    metrics to read first; a job of another method extends it; an edited note stays."""
    from helpers import compose_config

    from pipeline.core.store import NOTE_TAG

    mlflow_template(tmp_path)
    cfg = compose_config("experiment=smoke", f"paths.runs={tmp_path}")
    experiment_id = init_store(tmp_path, "mixed", job=cfg)
    client = MlflowClient(tracking_uri(tmp_path))
    note = client.get_experiment(experiment_id).tags[NOTE_TAG]
    assert note.startswith("**Experiment `mixed`**: runs of Method A: Neural BTF")
    assert "Read first: `rmse`, `psnr_db`" in note and "tables.experiments=[mixed]" in note
    init_store(
        tmp_path, "mixed", job=compose_config("experiment=brdf_smoke", f"paths.runs={tmp_path}")
    )
    note = client.get_experiment(experiment_id).tags[NOTE_TAG]
    assert "Method A" in note and "(`method=brdf_map`)" in note and "`rmse_missing`" in note
    client.set_experiment_tag(experiment_id, NOTE_TAG, "my own words")
    init_store(tmp_path, "mixed", job=cfg)
    assert client.get_experiment(experiment_id).tags[NOTE_TAG] == "my own words"


def _readme_example() -> str:
    """The Python block of the README's "Using a trained model"."""
    readme = (ROOT / "README.md").read_text().split("## Using a trained model", 1)[1]
    lines = readme.split("From a script in any folder:", 1)[1].splitlines()[2:]
    block = []
    for line in lines:
        if line.strip() and not line.startswith("    "):
            break
        block.append(line[4:])
    return "\n".join(block).strip() + "\n"


def test_the_readme_example_from_another_folder_names_the_missing_store_or_finds_the_run(
    smoke_cfg, tmp_path
):
    """As written ("runs", relative) from a folder without a store: a StoreError naming
    the path it looked at, and no ./runs/mlflow.db made (MLflow used to make one, then
    fail with KeyError: 0). With the jobs' paths.runs: the clustered model answers."""
    from pipeline.app import run_job

    cfg = smoke_cfg("tracking.experiment=btf", "train.max_steps=10")  # the smoke's clustered
    run_job(cfg)
    code = _readme_example()
    assert 'pipeline.tracking_uri("runs")' in code and "model.predict" in code
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "as_written.py").write_text(code)
    (elsewhere / "with_paths_runs.py").write_text(
        code.replace('tracking_uri("runs")', f"tracking_uri({str(cfg.paths.runs)!r})")
    )
    probe = (
        "import runpy, sys\n"
        "try:\n    runpy.run_path('as_written.py')\n"
        "except Exception as error:\n    print(type(error).__name__, error)\n"
        "runpy.run_path('with_paths_runs.py')\n"
    )
    done = python_code(probe, elsewhere)
    assert done.returncode == 0, done.stderr[-3000:]
    first, *answer = done.stdout.strip().splitlines()
    assert first.startswith(f"StoreError no MLflow store at {elsewhere}/runs/mlflow.db")
    assert not (elsewhere / "runs").exists() and not (elsewhere / "mlflow.db").exists()
    assert answer[0].split() == ["R", "G", "B"] and len(answer) == 2
