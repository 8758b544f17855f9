"""Method C in the app (``experiment=fourier_smoke`` / ``fourier_pattern_smoke``).

MLflow runs, metrics, artifacts, cache reuse, real light-stack folders, errors, and the
Fig. 6 tables on hand-made runs.
"""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
import pytest
from helpers import CONF_DIR, SHARED, compose_config, recipe_tags
from hydra import compose, initialize_config_dir
from hydra.types import RunMode
from mlflow.tracking import MlflowClient

from pipeline.app import run_job
from pipeline.core.errors import ConfigError
from pipeline.core.store import tracking_uri
from pipeline.data.images import read_exr_channels
from pipeline.fourier import report as fourier_tables
from pipeline.fourier import segmentation
from pipeline.fourier.series import SOLVER_NAMES
from pipeline.fourier.settings import (
    COLOUR_SPACES,
    SOLVERS,
    FourierSettings,
    fourier_settings,
)
from pipeline.fourier.stack import shrink
from pipeline.fourier.synthetic import write_synthetic_stack

REAL = SHARED / "data/rti/neuralrti-example"


@pytest.fixture
def fourier_cfg(tmp_path, mlflow_template):
    runs = tmp_path / "runs"
    mlflow_template(runs)

    def make(*overrides: str, experiment: str = "fourier_smoke"):
        return compose_config(f"experiment={experiment}", f"paths.runs={runs}", *overrides)

    return make


def _runs(cfg):
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    return client, client.search_runs([experiment.experiment_id])


def _stage_messages(caplog) -> dict[str, str]:
    return {
        r.getMessage().split()[1]: r.getMessage()
        for r in caplog.records
        if r.getMessage().startswith("stage ")
    }


def _artifacts(client, run, folder) -> set[str]:
    return {Path(a.path).name for a in client.list_artifacts(run.info.run_id, folder)}


def test_smoke_run_logs_metrics_and_figures_and_reuses_the_cache(fourier_cfg, caplog):
    cfg = fourier_cfg()
    run_job(cfg)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(cfg)
    second = _stage_messages(caplog)
    assert len(second) == 7 and all(" hit " in m for m in second.values()), second
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(fourier_cfg("method.M=2", "method.lam=0.5"))  # one more point of a Fig. 6 sweep
    third = _stage_messages(caplog)
    assert sorted(s for s, m in third.items() if " hit " in m) == [
        "relight_baselines",
        "stack_data",
        "stack_normals",
        "stack_segmentation",
    ]
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(fourier_cfg("method.lam=0"))  # plain least squares: same cond(A) as M=3
    fourth = _stage_messages(caplog)
    assert " hit " in fourth["fourier_condition"] and " hit " not in fourth["fourier_fit"]

    client, runs = _runs(cfg)
    assert [r.info.status for r in runs] == ["FINISHED"] * 4
    assert runs[0].data.tags["fourier_solver"] == "svd"  # λ = 0: lstsq, not truncated
    run = runs[-1]  # the first
    assert run.data.tags["fourier_solver"] == "normal"
    metrics = run.data.metrics
    for model in ("fourier", "ptm", "hsh"):
        for split in ("heldout", "validation", "test"):
            name = f"rmse_{split}_{model}"
            assert 0 < metrics[name] < 0.05, (name, metrics[name])
    assert metrics["rmse_train_fourier"] < 0.05
    assert metrics["n_train_lights"] == 33 and metrics["n_heldout_lights"] == 4
    assert metrics["n_validation_lights"] == 2 and metrics["n_test_lights"] == 2
    # The backdrop's normal is the view: θs = θd there, so A is rank-deficient.
    assert 0 < metrics["frac_pixels_rank_deficient"] < 1
    assert metrics["cond_design_max"] >= metrics["cond_design_median"] > 1
    for name in ("paper", "kmeans"):
        for space in ("", "_rgb", "_chromaticity"):
            for scope in ("", "object_"):
                assert 0.5 < metrics[f"segmentation_accuracy_{scope}{name}{space}"] <= 1
        # rgb (the paper's colour space) is the default
        assert (
            metrics[f"segmentation_accuracy_{name}"] == metrics[f"segmentation_accuracy_{name}_rgb"]
        )
    assert metrics["segmentation_accuracy_object_paper_chromaticity"] >= 0.95
    # Flat normals = the view at every pixel: every A is singular, no cond(A) to report.
    run_job(fourier_cfg("dataset.normals=flat"))
    flat = _runs(cfg)[1][0].data.metrics
    assert flat["frac_pixels_rank_deficient"] == 1.0 and "cond_design_median" not in flat
    assert run.data.params["method.M"] == "3" and run.data.params["method.name"] == "fourier"
    assert run.data.tags["heldout_reference"] == "analytic"
    assert run.data.tags["mlflow.runName"].startswith("fourier M=3 lam=3.14 synthetic_stack")
    assert {f"cache.{s}" for s in ("stack_data", "fourier_fit", "relight_baselines")} <= set(
        run.data.tags
    )
    assert {"heldout.png", "normals.png", "segmentation.png"} <= _artifacts(client, run, "figures")
    # The fit is rebuilt from the cache key the run recorded.
    key = run.data.tags["cache.fourier_fit"]
    coeffs = np.load(Path(cfg.paths.cache) / "fourier_fit" / key / "coeffs.npy")
    assert coeffs.shape == (32, 32, 3, 8)


def test_pattern_smoke_quilts_renders_and_logs_png_and_exr(fourier_cfg):
    cfg = fourier_cfg(experiment="fourier_pattern_smoke")
    run_job(cfg)
    client, runs = _runs(cfg)
    (run,) = runs
    metrics = run.data.metrics
    assert metrics["seam_cost_quilting"] < metrics["seam_cost_random"]
    assert metrics["seconds_quilting"] > 0
    assert metrics["candidates_r1"] > 0 and metrics["candidates_r2"] > 0
    assert {"pattern.png", "pattern.exr", "weights.png", "quilting.png"} <= _artifacts(
        client, run, "pattern"
    )
    key = run.data.tags["cache.pattern_render"]
    folder = Path(cfg.paths.cache) / "pattern_render" / key
    exr = read_exr_channels(folder / "pattern" / "pattern.exr", ("R", "G", "B"))
    image = np.load(folder / "pattern.npy")
    assert exr.shape == image.shape == (48, 48, 3)
    np.testing.assert_allclose(exr, image, rtol=2e-3, atol=1e-4)  # half floats
    assert image.min() >= 0 and image.max() > 0.05
    np.testing.assert_allclose(np.load(folder / "weights.npy").sum(axis=0), 1.0, atol=1e-5)


def test_light_stack_folder_holds_out_every_kth_light_and_reads_a_normal_file(
    fourier_cfg, tmp_path
):
    root = tmp_path / "stack"
    write_synthetic_stack(
        root, size=24, seed=1, n_elevations=3, n_azimuths=9, azimuth_step_deg=10.0, n_heldout=2
    )
    cfg = fourier_cfg(
        "dataset=light_stack",
        f"dataset.root={root}",
        "dataset.holdout_every=3",
        f"dataset.normals={root / 'normals.npy'}",
        "dataset.downsample=2",
        "method.M=2",
    )
    run_job(cfg)
    _, (run,) = _runs(cfg)
    assert run.data.metrics["n_train_lights"] == 18 and run.data.metrics["n_heldout_lights"] == 9
    key = run.data.tags["cache.stack_normals"]
    normals = np.load(Path(cfg.paths.cache) / "stack_normals" / key / "normals.npy")
    assert normals.shape == (12, 12, 3)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)


@pytest.mark.skipif(not REAL.is_dir(), reason=f"the real RTI capture is not at {REAL}")
def test_real_capture_downsampled_with_photometric_normals(fourier_cfg):
    cfg = fourier_cfg(
        "dataset=light_stack",
        f"dataset.root={REAL}",
        "dataset.downsample=8",
        "dataset.crop=[0,0,392,400]",
        "method.M=5",
    )
    run_job(cfg)
    _, (run,) = _runs(cfg)
    metrics = run.data.metrics
    assert metrics["n_train_lights"] == 60 and metrics["n_heldout_lights"] == 12
    for name in ("rmse_heldout_fourier", "rmse_heldout_ptm", "rmse_heldout_hsh"):
        assert 0 < metrics[name] < 0.3, (name, metrics[name])
    assert "segmentation_accuracy_kmeans" not in metrics  # no ground truth
    assert run.data.tags["heldout_reference"] == "images"


@pytest.fixture(scope="module")
def tiny_btf(tmp_path_factory):
    """An 8 x 8 synthetic BTF in the UBO2003 layout (JPEG, as the real one), two views."""
    from pipeline.btf.synthetic_dataset import write_synthetic_btf

    root = tmp_path_factory.mktemp("btf") / "tiny"
    return write_synthetic_btf(root, size=8, format="ubo2003", views=[(0, 0), (30, 90)])


def test_btf_view_is_a_light_stack_with_its_view_in_eq4(fourier_cfg, tiny_btf):
    from pipeline.data.light_stack import load_btf_view
    from pipeline.fourier.series import fit_fourier

    cfg = fourier_cfg(
        "dataset=btf_view", f"dataset.root={tiny_btf}", "dataset.views=[[30,90]]", "method.M=2"
    )
    run_job(cfg)
    client, (run,) = _runs(cfg)
    metrics = run.data.metrics
    assert metrics["n_train_lights"] == 68 and metrics["n_heldout_lights"] == 13
    assert metrics["n_validation_lights"] == 7 and metrics["n_test_lights"] == 6
    assert 0 < metrics["rmse_test_fourier"] < 0.2
    assert "view=[30, 90]" in run.data.tags["mlflow.runName"]
    key = run.data.tags["cache.fourier_fit"]
    coeffs = np.load(Path(cfg.paths.cache) / "fourier_fit" / key / "coeffs.npy")
    # The fit used the folder's view v = (0, sin 30°, cos 30°), not (0, 0, 1).
    view = np.array([0.0, 0.5, np.sqrt(3) / 2])
    stack = load_btf_view(tiny_btf, "ubo2003", (30, 90))
    held = np.arange(81) % 6 == 5
    train, dirs = stack.images[~held], stack.light_dirs[~held]
    flat = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(
        coeffs, fit_fourier(train, dirs, flat, view=view, M=2), rtol=1e-5, atol=1e-6
    )
    assert np.abs(coeffs - fit_fourier(train, dirs, flat, M=2)).max() > 1e-3
    # Method A's preset with one view folder is the same light stack (same cache entries).
    run_job(
        fourier_cfg(
            "dataset=ubo2003", f"dataset.root={tiny_btf}", "dataset.views=[[30,90]]", "method.M=2"
        )
    )
    _, runs = _runs(cfg)
    assert runs[0].data.tags["cache.fourier_fit"] == key
    with pytest.raises(ConfigError, match=r"one view folder of a BTF.*got dataset.views=None"):
        run_job(fourier_cfg("dataset=ubo2003", f"dataset.root={tiny_btf}"))
    with pytest.raises(ConfigError, match="dataset=ubo2003 needs dataset.root"):
        run_job(fourier_cfg("dataset=ubo2003", "dataset.views=[[30,90]]"))


def test_light_stack_without_root_is_a_config_error(fourier_cfg):
    with pytest.raises(ConfigError, match="dataset=light_stack needs dataset.root"):
        run_job(fourier_cfg("dataset=light_stack"))


def test_too_few_lights_for_m_is_a_config_error(fourier_cfg):
    with pytest.raises(ConfigError, match=r"M=20 needs N >= 2M \+ 2 = 42 images, got N=33"):
        run_job(fourier_cfg("method.M=20"))


def test_the_settings_dataclass_is_the_one_source_of_the_fit_defaults():
    """method.M, lam, clamp_diffuse, solver: declared once (FourierSettings), typed in the
    composed config of both of method C's jobs; the YAML holds no second copy."""
    assert fourier_settings(compose_config("experiment=fourier")) == FourierSettings()
    for name in ("fourier", "fourier_pattern"):
        yaml = (CONF_DIR / "method" / f"{name}.yaml").read_text()
        for field in dataclasses.fields(FourierSettings):
            assert not re.search(rf"^{field.name}:", yaml, re.MULTILINE), (name, field.name)
    pattern = compose_config("experiment=fourier_pattern_smoke", "method.lam=0")
    assert fourier_settings(pattern) == FourierSettings(M=3, lam=0.0)
    # The maps of fourier.yaml and fourier_pattern.yaml, and the experiment's, all kept.
    assert pattern.method.segmentation.n_regions == 3 and pattern.method.quilting.block_size == 6
    for bad in ("method.lam=big", "method.M=1.5", "method.solvr=svd", "method.quilting.seed=1"):
        with pytest.raises(hydra.errors.ConfigCompositionException):
            compose_config("experiment=fourier_smoke", bad)
    # The allowed values declared with the settings are those the code takes.
    assert SOLVERS == SOLVER_NAMES and COLOUR_SPACES == segmentation.COLOUR_SPACES


def test_sweep_grid_is_fig6_and_fits_the_real_capture():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["experiment=fourier_sweep"], return_hydra_config=True)
    params = cfg.hydra.sweeper.params
    ms = [int(m) for m in str(params["method.M"]).split(",")]
    assert ms == [1, 2, 3, 5, 7, 10, 15]
    assert [float(x) for x in str(params["method.lam"]).split(",")] == [0, 0.5, 3.14, 10, 50]
    assert 2 * max(ms) + 2 <= 72 - 72 // 6  # the real capture's training lights
    assert cfg.hydra.mode == RunMode.MULTIRUN and cfg.method.name == "fourier"


def test_shrink_crops_then_box_averages():
    images = np.arange(2 * 4 * 6 * 1, dtype=np.float32).reshape(2, 4, 6, 1)
    out = shrink(images, [0, 2, 4, 4], 2)
    assert out.shape == (2, 2, 2, 1)
    np.testing.assert_allclose(out[0, :, :, 0], [[5.5, 7.5], [17.5, 19.5]])
    labels = np.array([[0, 0, 2, 2], [0, 1, 2, 2]])
    np.testing.assert_array_equal(shrink(labels, None, 2, labels=True), [[0, 2]])
    with pytest.raises(ConfigError, match="does not fit images of 4x6"):
        shrink(images, [1, 0, 4, 4], 1)


def _hand_made_runs() -> pd.DataFrame:
    rows = []
    for root, normals, offset in (("None", "given", 0.0), ("/data/rti/coin", "photometric", 0.05)):
        for M in (1, 5, 10):
            for lam in (0.0, 3.14):
                rms = offset + 0.01 + 0.001 * abs(M - 5) + (0.002 if lam == 0 else 0.0)
                # The test lights disagree with the validation lights at M = 10.
                test = rms + (0.01 if M == 10 else 0.0)
                rows.append(
                    {
                        "status": "FINISHED",
                        "start_time": pd.Timestamp("2026-01-01") + pd.Timedelta(len(rows), "s"),
                        "params.method.name": "fourier",
                        "params.dataset.name": "synthetic_stack"
                        if root == "None"
                        else "light_stack",
                        "params.dataset.root": root,
                        "params.dataset.normals": normals,
                        "params.dataset.crop": "None",
                        "params.dataset.downsample": "1",
                        "params.method.clamp_diffuse": "False",
                        "params.method.M": str(M),
                        "params.method.lam": str(lam),
                        "metrics.rmse_validation_fourier": rms,
                        "metrics.rmse_test_fourier": test,
                        "metrics.rmse_validation_ptm": offset + 0.02,
                        "metrics.rmse_test_ptm": offset + 0.021,
                        "metrics.rmse_validation_hsh": offset + 0.015,
                        "metrics.rmse_test_hsh": offset + 0.016,
                        "metrics.n_train_lights": 60.0,
                        "metrics.n_validation_lights": 6.0,
                        "metrics.n_test_lights": 6.0,
                        "metrics.cond_design_median": 10.0**M,
                        "metrics.cond_design_max": 10.0 ** (M + 1),
                        "metrics.frac_pixels_rank_deficient": 0.5,
                        "metrics.segmentation_accuracy_paper_rgb": 0.92,
                        "metrics.segmentation_accuracy_object_paper_rgb": 0.82,
                        "metrics.segmentation_accuracy_paper_chromaticity": 0.99,
                        "metrics.segmentation_accuracy_object_paper_chromaticity": 0.98,
                        "tags.fourier_solver": "svd" if lam == 0 else "normal",
                    }
                )
    for row in rows:  # the recipe tag a job logs (pipeline.core.run.job_run)
        params = {k[len("params.") :]: v for k, v in row.items() if k.startswith("params.")}
        row["tags.recipe"] = recipe_tags(params)["recipe"]
    runs = pd.DataFrame(rows)
    stale = runs.iloc[[0]].assign(start_time=pd.Timestamp("2025-01-01"))
    stale["metrics.rmse_validation_fourier"] = 99.0  # an older run of the same point: ignored
    # A run from before the validation/test split: left out.
    unsplit = runs.iloc[[1]].assign(**{"metrics.rmse_validation_fourier": np.nan})
    parent = pd.DataFrame([{"status": "FINISHED", "params.method.name": None}])
    other = runs.iloc[[0]].assign(**{"params.method.name": "brdf_map"})
    return pd.concat([stale, runs, unsplit, parent, other], ignore_index=True)


def test_fourier_tables_on_hand_made_runs(tmp_path):
    runs = fourier_tables.label_runs(_hand_made_runs())
    assert len(runs) == 1 + 12  # the stale run, then both setups' 6 points; not the unsplit
    assert sorted(runs["setup"].unique()) == [
        "coin, normals=photometric",
        "synthetic_stack, normals=given",
    ]
    synthetic = runs[runs["setup"] == "synthetic_stack, normals=given"]
    table = fourier_tables.fig6_table(synthetic)
    assert list(table.columns) == ["λ = 0", "λ = 3.14"]
    assert list(table.index) == [1, 5, 10, "PTM", "HSH"]
    assert table.loc[1, "λ = 0"] == pytest.approx(0.016)  # the latest run, not the stale one
    assert table.loc["PTM"].tolist() == pytest.approx([0.02, 0.02])
    test_table = fourier_tables.fig6_table(synthetic, "test")
    assert test_table.loc[10, "λ = 3.14"] == pytest.approx(0.025)
    assert test_table.loc["HSH"].tolist() == pytest.approx([0.016, 0.016])
    # Chosen on the validation lights, reported on the test lights.
    assert fourier_tables.best_point(synthetic) == (
        5,
        3.14,
        pytest.approx(0.01),
        pytest.approx(0.01),
    )
    summary = fourier_tables.summary_table(runs)
    coin = summary.loc["coin, normals=photometric"]
    assert coin["test: Fourier (M=10, λ=3.14)"] == pytest.approx(0.075)
    assert coin["validation: Fourier (chosen)"] == pytest.approx(0.06)
    assert coin["test: HSH"] == pytest.approx(0.066)
    assert coin["validation lights"] == 6 and coin["test lights"] == 6
    assert fourier_tables.solvers(synthetic) == (
        "λ = 0: SVD least squares (= np.linalg.lstsq); λ > 0: normal equations"
    )
    condition = fourier_tables.condition_table(synthetic)
    assert condition.loc[10, "cond(A) median"] == pytest.approx(1e10)
    segmentation = fourier_tables.segmentation_table(runs)
    rows = segmentation.loc["synthetic_stack, normals=given"]
    assert rows["colour space"].tolist() == ["rgb", "chromaticity"]
    assert rows["object pixels"].tolist() == pytest.approx([0.82, 0.98])

    sections = fourier_tables.sections(_hand_made_runs(), tmp_path)
    assert len(sections) == 1 + 2 * 4 + 1
    assert "M = 5, λ = 3.14" in sections[1] and "Solver: λ = 0: SVD" in sections[1]
    for stem in (
        "fourier_summary",
        "fig6_synthetic_stack_normals_given",
        "fig6_test_synthetic_stack_normals_given",
        "fourier_condition_synthetic_stack_normals_given",
        "fourier_segmentation",
    ):
        for suffix in (".md", ".csv", ".tex"):
            assert (tmp_path / f"{stem}{suffix}").is_file()
    assert (tmp_path / "fig6_coin_normals_photometric.png").stat().st_size > 1000
    empty = fourier_tables.sections(pd.DataFrame(), tmp_path)
    assert "No finished `method=fourier` run" in empty[0]
