"""Method B in the app (``experiment=brdf_smoke``): MLflow run, metrics, figures, cache, errors."""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import hydra.errors
import mlflow
import numpy as np
import pytest
from helpers import CONF_DIR, compose_config
from mlflow.tracking import MlflowClient

from pipeline.app import run_job
from pipeline.brdf_map.runner import em_settings, load_reconstruction, merl_lookup
from pipeline.brdf_map.settings import MicrofacetEMSettings
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.store import tracking_uri
from pipeline.data.brdf import (
    MeasuredBRDF,
    half_diff_to_directions,
    read_utia_brdf,
    utia_directions,
)

FIGURES = {
    "distribution.png",
    "slices.png",
    "spheres_raw.png",
    "spheres_reconstruction.png",
    "spheres_noprior.png",
    "spheres_as.png",
    "spheres_truth.png",
    "objective.png",
}


@pytest.fixture
def brdf_cfg(tmp_path, mlflow_template):
    runs = tmp_path / "runs"
    mlflow_template(runs)

    def make(*overrides: str):
        return compose_config("experiment=brdf_smoke", f"paths.runs={runs}", *overrides)

    return make


def _runs(cfg):
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    return client, client.search_runs([experiment.experiment_id])


def test_smoke_run_logs_metrics_figures_and_second_run_hits_the_cache(brdf_cfg, caplog):
    cfg = brdf_cfg()
    run_job(cfg)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(cfg)
    second = [r.getMessage() for r in caplog.records if "stage" in r.getMessage()]
    assert len(second) == 4 and all(" hit " in m for m in second), second
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(brdf_cfg("method.prior_strength=0.5"))  # w_u: only the fit and evaluation
    third = {r.getMessage().split()[1]: r.getMessage() for r in caplog.records}
    assert [s for s, m in third.items() if " hit " in m] == ["brdf_data", "brdf_baselines"]

    client, runs = _runs(cfg)
    assert [r.info.status for r in runs] == ["FINISHED"] * 3
    run = runs[-1]  # the first
    metrics = run.data.metrics
    for name in ("rmse_measured", "rmse_missing", "rmse_missing_noprior", "rmse_missing_as"):
        assert 0 < metrics[name] < 1, (name, metrics[name])
    assert metrics["n_parameters"] == 3 + 12 + 16 + 4 + 3 + 1
    assert metrics["n_missing"] == 82944 - 57600  # the theta = 75 deg rings
    objective = client.get_metric_history(run.info.run_id, "objective")
    assert len(objective) == metrics["em_iterations"] > 1
    assert sorted(m.step for m in objective) == list(range(len(objective)))
    assert run.data.params["method.name"] == "brdf_map"
    assert {f"cache.brdf_{s}" for s in ("data", "fit", "baselines", "evaluate")} <= set(
        run.data.tags
    )
    figures = {Path(a.path).name for a in client.list_artifacts(run.info.run_id, "figures")}
    assert FIGURES <= figures

    # The logged parameters alone rebuild the BRDF; it matches the complete UTIA export.
    fit_dir = mlflow.artifacts.download_artifacts(
        run_id=run.info.run_id, artifact_path="fit", tracking_uri=tracking_uri(cfg.paths.runs)
    )
    fit = load_reconstruction(fit_dir)
    exported = read_utia_brdf(Path(fit_dir) / "reconstruction_utia.bin")
    assert exported.measured.all()  # the grazing part is filled
    light, view = utia_directions()
    rows = np.arange(0, light.shape[0], 997)
    np.testing.assert_allclose(
        fit.evaluate(light[rows], view[rows]), exported.reflectance[rows], rtol=1e-12
    )
    off_grid = fit.evaluate(np.array([[1.45, 0.3]]), np.array([[1.4, 2.0]]))
    assert off_grid.shape == (1, 3) and np.all(np.isfinite(off_grid))


def test_wrong_size_utia_file_fails_with_its_name(brdf_cfg, tmp_path):
    bad = tmp_path / "truncated_fabric.bin"
    bad.write_bytes(b"\0" * 1000)
    cfg = brdf_cfg("dataset=utia_brdf", f"dataset.root={bad}")
    with pytest.raises(DataError, match="truncated_fabric.bin has 1000 bytes"):
        run_job(cfg)
    _, runs = _runs(cfg)
    assert [r.info.status for r in runs] == ["FAILED"]
    assert not list(Path(cfg.paths.cache).glob("brdf_data/[!.]*"))


def test_real_dataset_without_root_is_a_config_error(brdf_cfg):
    with pytest.raises(ConfigError, match="dataset=merl needs dataset.root"):
        run_job(brdf_cfg("dataset=merl"))


def test_the_settings_dataclass_is_the_one_source_of_the_em_defaults():
    assert em_settings(compose_config("experiment=brdf_map")) == MicrofacetEMSettings()
    yaml = (CONF_DIR / "method" / "brdf_map.yaml").read_text()
    for field in dataclasses.fields(MicrofacetEMSettings):  # no second copy of a default
        assert not re.search(rf"^{field.name}:", yaml, re.MULTILINE), field.name
    changed = em_settings(compose_config("experiment=brdf_map", "method.prior_strength=0.2"))
    assert changed == dataclasses.replace(MicrofacetEMSettings(), prior_strength=0.2)
    # The structured config checks names and types as Hydra composes.
    for bad in ("method.n_gaussians=3", "method.prior_strength=abc", "method.n_rs=2.5"):
        with pytest.raises(hydra.errors.ConfigCompositionException):
            compose_config("experiment=brdf_map", bad)


def test_merl_lookup_maps_table_directions_back_to_their_entries():
    i_h, i_d, i_p = np.meshgrid([3, 40, 85], [1, 30, 70], [0, 45, 90, 179], indexing="ij")
    i_h, i_d, i_p = i_h.ravel(), i_d.ravel(), i_p.ravel()
    half_diff = np.stack(
        [(i_h / 90.0) ** 2 * np.pi / 2, i_d * np.pi / 180, i_p * np.pi / 180], axis=-1
    )
    light, view = half_diff_to_directions(half_diff)
    above = (light[:, 0] < np.pi / 2) & (view[:, 0] < np.pi / 2)
    n = 90 * 90 * 180
    table = MeasuredBRDF(
        np.repeat(np.arange(n, dtype=float)[:, None], 3, axis=1),
        np.zeros((n, 2)),
        np.zeros((n, 2)),
        np.arange(n) % 2 == 0,  # every odd entry missing
    )
    found = merl_lookup(table)(light[above], view[above])[:, 0]
    index = (i_p + 180 * (i_d + 90 * i_h))[above]
    expected = np.where(index % 2 == 0, index, np.nan)
    np.testing.assert_array_equal(found, expected)
