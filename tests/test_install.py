"""The package works from a normal (not editable) install: its Hydra configs, the arms
sweeper and the C++ kernels' source ship inside it, so ``python -m pipeline`` runs from any
folder."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
from helpers import ROOT


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """``pip install --no-deps --target`` of this checkout: the package as a wheel installs
    it (the dependencies are this environment's)."""
    target = tmp_path_factory.mktemp("installed")
    # A copy of what the wheel is built from, so that setuptools' build/ lands there.
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    for name in ("pipeline", "hydra_plugins"):
        shutil.copytree(
            ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info")
        )
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    return target


def test_the_wheel_holds_the_configs_the_sweeper_and_the_kernels(installed):
    package = installed / "pipeline"
    assert (package / "conf" / "config.yaml").is_file()
    assert (package / "conf" / "model" / "clustered.yaml").is_file()
    assert (package / "btf" / "fast" / "kernels.cpp").is_file()
    assert (installed / "hydra_plugins" / "pipeline_sweeper" / "arms_sweeper.py").is_file()


@pytest.mark.slow
def test_the_smoke_job_runs_from_another_folder(installed, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(installed)}
    work = tmp_path / "elsewhere"
    work.mkdir()
    done = subprocess.run(
        [sys.executable, "-c", "import pipeline; print(pipeline.__file__)"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.stdout.strip().startswith(str(installed)), done.stdout + done.stderr
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline",
            "-m",
            "experiment=smoke",
            "model=pca",
            f"paths.runs={tmp_path / 'runs'}",
        ],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "pca s0: run" in done.stdout and "Launching 1 jobs" in done.stdout + done.stderr
