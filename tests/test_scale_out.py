"""Scale-out for real (slow): a sweep logging to an `mlflow server` on 127.0.0.1 and a sweep
through hydra/launcher=slurm on a one-node SLURM, each through its script under scripts/,
each ending with every child run FINISHED under one parent."""

import os
import shutil
import socket
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _script(name: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    import sys

    environment = {**os.environ, "PY": sys.executable, **(env or {})}
    return subprocess.run(
        ["bash", str(ROOT / "scripts" / name), *args],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=900,
    )


def _assert_all_finished(done: subprocess.CompletedProcess) -> None:
    assert done.returncode == 0, (done.stdout + done.stderr)[-3000:]
    assert "parent sweep" in done.stdout and ": FINISHED" in done.stdout
    assert "2 of 2 children FINISHED" in done.stdout


def test_a_sweep_logs_to_an_mlflow_tracking_server(tmp_path):
    port = _free_port()
    done = _script("tracking_server_sweep.sh", str(tmp_path), env={"PORT": str(port)})
    _assert_all_finished(done)
    assert f"http://127.0.0.1:{port}, experiment smoke" in done.stdout
    # Nothing went to a SQLite file beside the cache: the server holds the runs.
    assert not (tmp_path / "runs" / "mlflow.db").exists()
    assert (tmp_path / "server.db").exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="a one-node SLURM needs root (munged, slurmd)")
@pytest.mark.skipif(
    shutil.which("slurmctld") is None and shutil.which("apt-get") is None,
    reason="no slurm-wlm and no apt-get to install it",
)
def test_a_sweep_runs_through_slurm_and_shares_one_cache(tmp_path):
    runs = tmp_path / "runs"
    done = _script("slurm_sweep.sh", str(runs))
    _assert_all_finished(done)
    # The tasks ran as SLURM jobs (submitit's folders carry the job ids) and shared the cache:
    # the built-in BTF was generated once.
    tasks = [p.name for p in (runs / "hydra" / "multirun").glob("*/.submitit/*_*") if p.is_dir()]
    assert len(tasks) == 2 and all(name.replace("_", "").isdigit() for name in tasks), tasks
    logs = [p.read_text() for p in (runs / "hydra" / "multirun").glob("*/.submitit/*/*_log.out")]
    assert sum("generating the built-in synthetic BTF" in text for text in logs) == 1
