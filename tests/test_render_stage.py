"""The render stages of method A (pipeline/render/stage.py) and Fig. 8 / Tables 3-4."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers import compose_config
from mlflow.tracking import MlflowClient

from pipeline.core.errors import ConfigError
from pipeline.core.recipe import recipe_id
from pipeline.core.tracking import flatten, tracking_uri
from pipeline.render.stage import (
    choose_crops,
    compare,
    high_frequency_energy,
    render_settings,
    window_sums,
)


def test_window_sums_match_a_loop():
    values = np.random.default_rng(0).random((9, 7))
    sums = window_sums(values, 3)
    loop = np.array([[values[r : r + 3, c : c + 3].sum() for c in range(5)] for r in range(7)])
    np.testing.assert_allclose(sums, loop)


def test_crops_are_the_darkest_and_brightest_wholly_lit_windows():
    # Brightness grows to the right; the left columns are unlit (background or shadow), so
    # the darkest window must start right of them, not straddle them. Column 6 is a
    # silhouette: half its samples on cloth, and not darker than its right neighbours.
    image = np.tile(np.linspace(0.1, 1.0, 32, dtype=np.float32)[None, :, None], (24, 1, 3))
    image[:, :6] = 0
    image[20:, 28:] = 0  # a shadowed corner at the bright end
    coverage = (image[..., 0] > 0).astype(np.float32)
    coverage[:, 6] = 0.5
    crops = choose_crops(image, coverage, size=8)
    luminance = image[..., 0]
    windows = [(r, c) for r in range(0, 17, 2) for c in range(0, 25, 2)
               if coverage[r : r + 8, c : c + 8].min() == 1]
    means = {w: luminance[w[0] : w[0] + 8, w[1] : w[1] + 8].mean() for w in windows}
    assert crops["dark"] == list(min(means, key=means.get))
    assert crops["bright"] == list(max(means, key=means.get))
    assert crops["dark"][1] >= 7
    # A crop given in the settings is kept as given.
    given = choose_crops(image, coverage, 8, {"dark": [0, 10], "bright": None})
    assert given["dark"] == [0, 10]


def test_a_frame_without_lit_windows_is_refused_clearly():
    with pytest.raises(ValueError, match="crop_size"):
        choose_crops(np.ones((16, 16, 3), np.float32), np.full((16, 16), 0.9), size=4)


def test_comparison_of_a_render_with_itself_and_with_grain():
    rng = np.random.default_rng(1)
    reference = rng.random((32, 32, 3)).astype(np.float32) * 0.1 + 0.5
    crops = {"dark": [0, 0], "bright": [16, 16]}
    coverage = np.ones((32, 32), np.float32)
    same = compare(reference, reference, coverage, crops, 16)
    assert same["rmse_dark"] == same["rmse_bright"] == same["rmse_cloth"] == 0
    assert same["hf_ratio_dark"] == pytest.approx(1.0)
    grainy = reference + np.where(np.indices((32, 32)).sum(0) % 2, 0.05, -0.05)[..., None]
    found = compare(grainy.astype(np.float32), reference, coverage, crops, 16)
    assert found["rmse_dark"] == pytest.approx(0.05, rel=1e-4)
    # The cloth RMSE counts only pixels wholly on lit cloth.
    coverage[:, 16:] = 0.5
    grainy[:, 16:] += 1.0
    assert compare(grainy.astype(np.float32), reference, coverage, crops, 16)[
        "rmse_cloth"] == pytest.approx(0.05, rel=1e-4)
    assert found["hf_ratio_dark"] > 1.5
    # Smooth images have less high-frequency energy than grainy ones.
    assert high_frequency_energy(np.full((8, 8, 3), 0.3)) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("override, named", [
    ("btf.render.spp=[0]", "btf.render.spp"),
    ("btf.render.crop_size=64", "btf.render.crop_size"),
    ("btf.render.crops.dark=[14,14]", "btf.render.crops.dark"),
])
def test_bad_render_settings_name_the_setting(override, named):
    cfg = compose_config("experiment=render_smoke", override)
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        render_settings(cfg)


def test_render_settings_are_not_part_of_the_recipe():
    plain = compose_config("experiment=smoke", "dataset.views=null")
    rendered = compose_config("experiment=render_smoke")
    assert recipe_id(flatten(plain)) == recipe_id(flatten(rendered))


def test_a_rendering_job_logs_its_renders_and_the_tables_draw_fig8(tmp_path, mlflow_template):
    from pipeline.app import run_job
    from pipeline.tables import build_tables, default_settings

    runs_dir = tmp_path / "runs"
    mlflow_template(runs_dir)
    cfg = compose_config("experiment=render_smoke", f"paths.runs={runs_dir}")
    run_job(cfg)
    run_job(compose_config("experiment=render_smoke", f"paths.runs={runs_dir}", "method=pca",
                           "method.n_components=2"))

    client = MlflowClient(tracking_uri(runs_dir))
    experiment = client.get_experiment_by_name("render_smoke")
    pca, run = client.search_runs([experiment.experiment_id], order_by=["start_time DESC"])
    assert pca.data.params["method.name"] == "pca"
    assert pca.data.tags["cache.render_reference"] == run.data.tags["cache.render_reference"]
    assert np.isfinite(pca.data.metrics["render_rmse_bright"])
    for artifacts in (pca, run):  # every model's run keeps the same evaluation files
        logged = {a.path for a in client.list_artifacts(artifacts.info.run_id)}
        logged |= {a.path for a in client.list_artifacts(artifacts.info.run_id, "evaluate")}
        assert {"metrics.json", "evaluate/rmse_per_direction.npy"} <= logged
    metrics = run.data.metrics
    for name in ("render_rmse_dark", "render_rmse_bright", "render_rmse_dark_spp1",
                 "render_hf_ratio_bright_spp4", "render_seconds"):
        assert np.isfinite(metrics[name]), name
    assert metrics["render_rmse_dark"] == metrics["render_rmse_dark_spp4"]
    assert {"cache.render", "cache.render_reference"} <= set(run.data.tags)
    logged = {a.path for a in client.list_artifacts(run.info.run_id, "render")}
    assert {"render/model_spp4.png", "render/model_spp4.exr", "render/reference_spp4.png",
            "render/model_spp1.png", "render/crops.json"} <= logged

    settings = default_settings()
    settings.experiments = ["render_smoke"]
    out = build_tables(runs_dir, settings)
    for name in ("table3_render_dark.md", "table4_render_bright.md", "render_graininess.md",
                 "render_cloth.md"):
        assert (out / name).is_file(), name
    table3 = (out / "table3_render_dark.md").read_text()
    assert "k = 8" in table3 and "PCA c = 2" in table3
    cloth = pd.read_csv(out / "render_cloth.csv")
    assert sorted(cloth["spp"]) == [1, 4]  # one row per spp level of render_smoke
    top = cloth.loc[cloth["spp"] == 4, "k = 8"].item()
    assert top.startswith(f"{metrics['render_rmse_cloth']:.4f}")  # the run's own metric
    figures = sorted(out.glob("fig8_*.png"))
    assert [p.name.endswith("_crops_per_spp.png") for p in figures] == [False, True]
    assert all(p.stat().st_size > 0 for p in figures)
    assert len(list(out.glob("fig8_*.exr"))) == 3  # the reference and the two models


def test_the_render_benchmark_runs_each_material_on_the_same_rays(capsys):
    from pipeline.render.bench import main

    found = main(["--size", "16", "--spp", "1", "--crop", "4"])
    assert set(found) == {"lambertian", "measured", "neural"}
    assert len({stats.material_queries for stats in found.values()}) == 1
    assert "x lambertian" in capsys.readouterr().out
