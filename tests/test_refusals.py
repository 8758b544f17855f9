"""A refusal is an answer: one line naming the setting, a non-zero exit, no traceback, no
stage computed for a setting that can be checked before the data is read, and no FAILED run
left without the error that ended it (pipeline/core/refusal.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import ROOT
from mlflow.tracking import MlflowClient

from pipeline.core.tracking import tracking_uri

# (experiment, override, what the one line must name); every one is refused before any
# job starts: no store, no cache.
BEFORE_ANY_JOB = [
    ("smoke", "btf.crop.szie=32", "did you mean btf.crop.size?"),
    ("smoke", "sed=3", "did you mean seed?"),
    ("brdf_smoke", "method.prior_strenght=0.1", "did you mean method.prior_strength?"),
    ("smoke", "method=nope", "choose from brdf_map, btf"),
    ("smoke", "train.lr=abc", "train.lr=abc"),
    ("smoke", "model.n_components=8", "model.n_components=8: no such setting"),
    ("smoke", "model.k=4,-1", "is a sweep: add -m"),
    ("smoke", "+btf.crop.szie=3", "did you mean btf.crop.size?"),
]
# Refused as the job starts (the run records why), before any stage.
AT_THE_JOB = [
    ("smoke", "threads=many", "threads='many' must be an integer >= 1"),
    ("smoke", "threads=0", "threads=0 must be an integer >= 1"),
    ("smoke", "model.k=0", "model.k=0 must be an integer >= 1"),
    ("smoke", "btf.network.encoder_channels=[]", "btf.network.encoder_channels"),
]


def _run(tmp_path, *arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "pipeline", *arguments, f"paths.runs={tmp_path / 'runs'}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _check_one_line(done: subprocess.CompletedProcess, named: str) -> None:
    output = done.stdout + done.stderr
    assert done.returncode == 2, output[-2000:]
    assert "Traceback" not in output and "HYDRA_FULL_ERROR" not in output, output[-2000:]
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and named in errors[0], done.stderr[-2000:]


@pytest.mark.parametrize(("experiment", "override", "named"), BEFORE_ANY_JOB)
def test_a_bad_command_line_is_one_line_before_any_job(tmp_path, experiment, override, named):
    done = _run(tmp_path, f"experiment={experiment}", override)
    _check_one_line(done, named)
    assert not (tmp_path / "runs").exists()  # no store, no cache, no data


@pytest.mark.parametrize(("experiment", "override", "named"), AT_THE_JOB)
def test_a_bad_value_is_one_line_and_its_run_says_why(tmp_path, experiment, override, named):
    done = _run(tmp_path, f"experiment={experiment}", override)
    _check_one_line(done, named)
    assert not list((tmp_path / "runs" / "cache").glob("*/*"))  # no stage computed
    if (tmp_path / "runs" / "mlflow.db").exists():  # a run was opened: it says why it failed
        client = MlflowClient(tracking_uri(tmp_path / "runs"))
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
        assert all(
            r.info.status == "FAILED" and named.split("=")[0] in r.data.tags["error"] for r in runs
        ), [(r.info.status, r.data.tags.get("error")) for r in runs]


def test_a_sweep_checks_every_job_before_the_first_runs(tmp_path):
    done = _run(tmp_path, "-m", "experiment=smoke", "model.k=4,-1")
    _check_one_line(done, "job #1")
    assert "model.k=-1 must be an integer >= 1" in done.stderr
    assert not list((tmp_path / "runs" / "cache").glob("*/*"))  # job #0 did not train


def test_a_setting_read_from_the_data_is_refused_naming_it(tmp_path):
    """The crop must fit the texture: known once the data's header is read."""
    done = _run(tmp_path, "experiment=smoke", "btf.crop.size=1000")
    _check_one_line(done, "btf.crop.size=1000")
    assert "Traceback" not in done.stdout + done.stderr


def test_debug_shows_the_traceback(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline",
            "experiment=smoke",
            "threads=0",
            f"paths.runs={tmp_path / 'runs'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        env={**__import__("os").environ, "PIPELINE_DEBUG": "1"},
    )
    assert done.returncode != 0 and "Traceback" in done.stdout + done.stderr
