"""Method C in the app (``experiment=fourier_smoke`` / ``fourier_pattern_smoke``).

MLflow runs, metrics, artifacts, cache reuse, real light-stack folders, errors, and the
Fig. 6 tables on hand-made runs.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import CONF_DIR, SHARED, compose_config
from hydra import compose, initialize_config_dir
from hydra.types import RunMode
from mlflow.tracking import MlflowClient

from pipeline.app import run_job
from pipeline.core.errors import ConfigError
from pipeline.core.tracking import tracking_uri
from pipeline.data.images import read_exr_channels
from pipeline.fourier import report as fourier_tables
from pipeline.fourier.runner import shrink
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
    assert len(second) == 6 and all(" hit " in m for m in second.values()), second
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

    client, runs = _runs(cfg)
    assert [r.info.status for r in runs] == ["FINISHED"] * 3
    run = runs[-1]  # the first
    metrics = run.data.metrics
    for name in ("rmse_heldout_fourier", "rmse_heldout_ptm", "rmse_heldout_hsh"):
        assert 0 < metrics[name] < 0.05, (name, metrics[name])
    assert metrics["rmse_train_fourier"] < 0.05
    assert metrics["n_train_lights"] == 33 and metrics["n_heldout_lights"] == 4
    assert metrics["segmentation_accuracy_paper"] >= 0.95
    assert metrics["segmentation_accuracy_kmeans"] >= 0.95
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


def test_light_stack_without_root_is_a_config_error(fourier_cfg):
    with pytest.raises(ConfigError, match="dataset=light_stack needs dataset.root"):
        run_job(fourier_cfg("dataset=light_stack"))


def test_too_few_lights_for_m_is_a_config_error(fourier_cfg):
    with pytest.raises(ConfigError, match=r"M=20 needs N >= 2M \+ 2 = 42 images, got N=33"):
        run_job(fourier_cfg("method.M=20"))


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
                        "metrics.rmse_heldout_fourier": rms,
                        "metrics.rmse_heldout_ptm": offset + 0.02,
                        "metrics.rmse_heldout_hsh": offset + 0.015,
                        "metrics.n_train_lights": 60.0,
                        "metrics.n_heldout_lights": 12.0,
                    }
                )
    runs = pd.DataFrame(rows)
    stale = runs.iloc[[0]].assign(start_time=pd.Timestamp("2025-01-01"))
    stale["metrics.rmse_heldout_fourier"] = 99.0  # an older run of the same point: ignored
    parent = pd.DataFrame([{"status": "FINISHED", "params.method.name": None}])
    other = runs.iloc[[0]].assign(**{"params.method.name": "brdf_map"})
    return pd.concat([stale, runs, parent, other], ignore_index=True)


def test_fourier_tables_on_hand_made_runs(tmp_path):
    runs = fourier_tables.label_runs(_hand_made_runs())
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
    assert fourier_tables.best_point(synthetic) == (5, 3.14, pytest.approx(0.01))
    summary = fourier_tables.summary_table(runs)
    assert summary.loc["coin, normals=photometric", "Fourier (M=10, λ=3.14)"] == pytest.approx(
        0.065
    )
    assert summary.loc["coin, normals=photometric", "HSH"] == pytest.approx(0.065)

    sections = fourier_tables.sections(_hand_made_runs(), tmp_path)
    assert len(sections) == 1 + 2 * 2
    assert "M = 5, λ = 3.14" in sections[1]
    for stem in ("fourier_summary", "fig6_synthetic_stack_normals_given"):
        for suffix in (".md", ".csv", ".tex"):
            assert (tmp_path / f"{stem}{suffix}").is_file()
    assert (tmp_path / "fig6_coin_normals_photometric.png").stat().st_size > 1000
    empty = fourier_tables.sections(pd.DataFrame(), tmp_path)
    assert "No finished `method=fourier` run" in empty[0]
