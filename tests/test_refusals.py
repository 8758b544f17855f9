"""A refusal is an answer: one line naming the setting, a non-zero exit, no traceback, no
stage computed for a setting that can be checked before the data is read, and no FAILED run
left without the error that ended it (pipeline/core/refusal.py)."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from helpers import check_one_line_refusal, pipeline_command
from mlflow.tracking import MlflowClient

from pipeline.core.errors import DataError
from pipeline.core.store import tracking_uri
from pipeline.data.brdf import UTIA_N_BYTES, read_utia_brdf, utia_directions, write_utia_brdf

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
    # Method C's fit is a structured config (pipeline.fourier.settings.FourierSettings).
    ("fourier_smoke", "method.lam=big", "method.lam=big"),
    ("fourier_smoke", "method.M=1.5", "method.M=1.5"),
    ("fourier_smoke", "method.lamm=1", "did you mean method.lam?"),
]
# Refused as the job starts (the run records why), before any stage.
AT_THE_JOB = [
    ("smoke", "threads=many", "threads='many' must be an integer >= 1"),
    ("smoke", "threads=0", "threads=0 must be an integer >= 1"),
    ("smoke", "model.k=0", "model.k=0 must be an integer >= 1"),
    ("smoke", "btf.network.encoder_channels=[]", "btf.network.encoder_channels"),
    ("brdf_smoke", "method.n_theta_cells=0", "method.n_theta_cells=0 must be an integer >= 1"),
    ("brdf_smoke", "method.rs_range=[0.5,0.2]", "method.rs_range=(0.5, 0.2) must be"),
    ("fourier_smoke", "method.M=-1", "method.M=-1 must be an integer >= 0"),
    ("fourier_smoke", "method.lam=-1", "method.lam=-1.0 must be a finite number >= 0"),
    ("fourier_smoke", "method.solver=qr", "method.solver='qr' must be one of auto, normal, svd"),
    ("fourier_smoke", "method.segmentation.n_init=0", "method.segmentation.n_init=0 must be"),
]


def _run(tmp_path, *arguments: str) -> subprocess.CompletedProcess:
    return pipeline_command(
        *arguments, f"paths.runs={tmp_path / 'runs'}", cwd=tmp_path, timeout=300
    )


@pytest.mark.parametrize(("experiment", "override", "named"), BEFORE_ANY_JOB)
def test_a_bad_command_line_is_one_line_before_any_job(tmp_path, experiment, override, named):
    done = _run(tmp_path, f"experiment={experiment}", override)
    check_one_line_refusal(done, named)
    assert not (tmp_path / "runs").exists()  # no store, no cache, no data


@pytest.mark.parametrize(("experiment", "override", "named"), AT_THE_JOB)
def test_a_bad_value_is_one_line_and_its_run_says_why(
    tmp_path, mlflow_template, experiment, override, named
):
    mlflow_template(tmp_path / "runs")  # the store exists: a job opens its run without creating it
    done = _run(tmp_path, f"experiment={experiment}", override)
    check_one_line_refusal(done, named)
    assert not list((tmp_path / "runs" / "cache").glob("*/*"))  # no stage computed
    client = MlflowClient(tracking_uri(tmp_path / "runs"))
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    assert all(  # a run that was opened says why it failed
        r.info.status == "FAILED" and named.split("=")[0] in r.data.tags["error"] for r in runs
    ), [(r.info.status, r.data.tags.get("error")) for r in runs]


def test_a_sweep_checks_every_job_before_the_first_runs(tmp_path):
    done = _run(tmp_path, "-m", "experiment=smoke", "model.k=4,-1")
    check_one_line_refusal(done, "job #1")
    assert "model.k=-1 must be an integer >= 1" in done.stderr
    assert not list((tmp_path / "runs" / "cache").glob("*/*"))  # job #0 did not train


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("btf.crop.size=1000", "btf.crop.size=1000"),  # the texture's size
        ("btf.interpolation.holdout_lights=100", "btf.interpolation.holdout_lights=100"),
    ],
)
def test_a_setting_read_from_the_data_is_refused_naming_it(
    tmp_path, mlflow_template, shared_data, override, named
):
    """Known once the data's header (or, for images, the load stage) is read: the crop must
    fit the texture, the held-out lights leave lights to train on. Nothing after the load
    stage is computed."""
    mlflow_template(tmp_path / "runs")
    done = _run(tmp_path, "experiment=smoke", f"paths.data={shared_data}", override)
    check_one_line_refusal(done, named)
    assert "Traceback" not in done.stdout + done.stderr
    stages = {p.parent.name for p in (tmp_path / "runs" / "cache").glob("*/*")}
    assert stages <= {"load"}, stages


def _utia_file_with_nan(path):
    """A UTIA BRDF file (the real layout, by the real writer) with one value made NaN."""
    light, view = utia_directions()
    write_utia_brdf(path, np.tile(0.1 + np.cos(light[:, :1]) * np.cos(view[:, :1]), 3))
    raw = np.fromfile(path, dtype="<f8")
    raw[1000] = np.nan
    raw.astype("<f8").tofile(path)
    assert path.stat().st_size == UTIA_N_BYTES
    return path


def test_a_utia_brdf_file_holding_nan_is_refused_naming_it(tmp_path):
    path = _utia_file_with_nan(tmp_path / "fabric139.bin")
    with pytest.raises(DataError, match=rf"{path} holds 1 non-finite values .*at byte 8000"):
        read_utia_brdf(path)


def test_a_bad_file_is_one_line_naming_it_and_its_run_says_why(tmp_path, mlflow_template):
    """A DataError (here a UTIA file holding NaN) ends the job as a refused setting does."""
    mlflow_template(tmp_path / "runs")
    path = _utia_file_with_nan(tmp_path / "fabric139.bin")
    done = _run(tmp_path, "experiment=brdf_smoke", "dataset=utia_brdf", f"dataset.root={path}")
    check_one_line_refusal(done, f"UTIA BRDF file {path} holds 1 non-finite values")
    client = MlflowClient(tracking_uri(tmp_path / "runs"))
    (run,) = client.search_runs([e.experiment_id for e in client.search_experiments()])
    assert run.info.status == "FAILED" and str(path) in run.data.tags["error"]
    assert not list((tmp_path / "runs" / "cache").glob("*/[!.]*"))  # no stage published


def test_debug_shows_the_traceback(tmp_path):
    done = pipeline_command(
        "experiment=smoke",
        "threads=0",
        f"paths.runs={tmp_path / 'runs'}",
        env={"PIPELINE_DEBUG": "1"},
        timeout=300,
    )
    assert done.returncode != 0 and "Traceback" in done.stdout + done.stderr


@pytest.mark.parametrize(
    ("override", "named"),
    [
        ("trian.lr=1", "trian.lr=1: no such setting (did you mean train.lr?)"),
        ("btf.crp.size=3", "btf.crp.size=3: no such setting (did you mean btf.crop.size?)"),
    ],
)
def test_a_misspelt_group_names_the_closest_whole_key(override, named):
    """Hydra fails at the first unknown part (``trian``); the closest key is looked for as
    the whole key was written."""
    from pipeline.core.errors import ConfigError
    from pipeline.core.methods import CONF_DIR
    from pipeline.core.refusal import check_command_line

    with pytest.raises(ConfigError) as refused:
        check_command_line(["experiment=smoke", override], CONF_DIR)
    assert str(refused.value) == named


def test_hydra_flags_and_their_values_are_not_read_as_overrides():
    """``--cfg job`` is a flag with its value (Hydra's parser says which flags take one);
    a bad setting after it is still refused, and ``--help`` asks for no composition."""
    from pipeline.core.errors import ConfigError
    from pipeline.core.methods import CONF_DIR
    from pipeline.core.refusal import check_command_line

    check_command_line(["--cfg", "job", "experiment=smoke"], CONF_DIR)
    check_command_line(["-c", "hydra", "-m", "experiment=smoke", "seed=0,1"], CONF_DIR)
    check_command_line(["--cfg=job", "-i", "config", "experiment=smoke"], CONF_DIR)
    check_command_line(["--help", "sed=3"], CONF_DIR)
    with pytest.raises(ConfigError, match="did you mean seed"):
        check_command_line(["--cfg", "job", "sed=3"], CONF_DIR)
