"""The render stages of method A (pipeline/btf/render/stage.py) and Fig. 8 / Tables 3-4:
scored against the analytic truth for the built-in material, against the measured
reference (every material clamped to the grid) for measured data."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest
from helpers import WIRING_STEPS, compose_config
from mlflow.tracking import MlflowClient

from pipeline.btf.methods import BTF
from pipeline.btf.render.stage import (
    choose_crops,
    compare,
    high_frequency_energy,
    scores,
    window_sums,
)
from pipeline.core.errors import ConfigError
from pipeline.core.recipe import recipe_id
from pipeline.core.run import flatten
from pipeline.core.store import tracking_uri
from pipeline.data.images import read_exr


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
    windows = [
        (r, c)
        for r in range(0, 17, 2)
        for c in range(0, 25, 2)
        if coverage[r : r + 8, c : c + 8].min() == 1
    ]
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
        "rmse_cloth"
    ] == pytest.approx(0.05, rel=1e-4)
    assert found["hf_ratio_dark"] > 1.5
    # Detail of the same amount in the wrong place: the ratio is blind, the HF RMSE is not.
    shifted = np.roll(reference, 1, axis=1)
    moved = compare(shifted, reference, np.ones((32, 32), np.float32), crops, 16)
    assert moved["hf_ratio_dark"] == pytest.approx(1.0, abs=0.1)
    assert moved["hf_rmse_dark"] > 0.5 * np.sqrt(high_frequency_energy(reference[:16, :16]))
    assert same["hf_rmse_dark"] == 0
    # Smooth images have less high-frequency energy than grainy ones.
    assert high_frequency_energy(np.full((8, 8, 3), 0.3)) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    "override, named",
    [
        ("btf.render.spp=[0]", "btf.render.spp"),
        ("btf.render.crop_size=64", "btf.render.crop_size"),
        ("btf.render.crops.dark=[14,14]", "btf.render.crops.dark"),
        ("btf.render.lights=sun", "btf.render.lights='sun' must be one of point"),
        ("btf.render.exposure=0", "btf.render.exposure=0.0 must be"),
        ("btf.render.crops.bright=[1]", "btf.render.crops.bright"),
    ],
)
def test_bad_render_settings_name_the_setting(override, named):
    """Refused at the door (before any stage runs), by the declared constraints or, for
    the crops against the frame, by render_settings."""
    cfg = compose_config("experiment=render_smoke", override)
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        BTF.check(cfg)


def test_render_settings_are_not_part_of_the_recipe():
    plain = compose_config("experiment=smoke", "dataset.views=null")
    rendered = compose_config("experiment=render_smoke")
    assert recipe_id(flatten(plain)) == recipe_id(flatten(rendered))


def test_scores_name_what_each_render_is_compared_with():
    rng = np.random.default_rng(2)
    model, reference, truth = (rng.random((16, 16, 3)).astype(np.float32) for _ in range(3))
    crops, coverage = {"dark": [0, 0], "bright": [8, 8]}, np.ones((16, 16), np.float32)
    found = scores(model, reference, coverage, crops, 8, truth)
    for prefix, (a, b) in {
        "render_": (model, reference),
        "render_truth_": (model, truth),
        "render_reference_truth_": (reference, truth),
    }.items():
        for name, value in compare(a, b, coverage, crops, 8).items():
            assert found[prefix + name] == value, prefix + name
    assert len(found) == 3 * 10  # 3 image metrics, 3 per crop (2 crops), the cloth RMSE
    assert set(scores(model, reference, coverage, crops, 8)) == {
        f"render_{name}" for name in compare(model, reference, coverage, crops, 8)
    }


def _hand_made_runs() -> pd.DataFrame:
    """Labelled rendered runs of two datasets: "built-in" with truth metrics (two seeds of
    one model, one reference render), "measured" without."""
    rows = []
    for dataset, truth, seed in (
        ("built-in", True, 0),
        ("built-in", True, 1),
        ("measured", False, 0),
    ):
        row = {
            "dataset": dataset,
            "model": "k = 8",
            "order": 8.0,
            "seed": seed,
            "run_id": f"{dataset}{seed}",
            "tags.cache.render_reference": f"ref-{dataset}",
            "tags.cache.render_truth": "truth" if truth else None,
            "metrics.render_rmse_dark": 0.1 + seed,
            "metrics.render_rmse_dark_spp4": 0.2,
            "metrics.render_beyond_grid_share_dark": 0.25 if truth else 0.0,
        }
        if truth:
            row.update(
                {
                    "metrics.render_truth_rmse_dark": 0.3 + seed,
                    "metrics.render_truth_rmse_dark_spp4": 0.4,
                    "metrics.render_reference_truth_rmse_dark": 0.05,
                    "metrics.render_reference_truth_rmse_dark_spp4": 0.06,
                }
            )
        rows.append(row)
    return pd.DataFrame(rows)


def test_each_dataset_is_scored_against_its_truth_if_it_has_one_else_the_reference():
    from pipeline.btf.render.report import REFERENCE, TRUTH, scored_runs, table_crop

    scored = scored_runs(_hand_made_runs())
    models = scored[scored["model"] == "k = 8"].set_index("run_id")
    assert list(models["scored against"]) == [TRUTH, TRUTH, REFERENCE]
    assert list(models["metrics.scored_rmse_dark"]) == [0.3, 1.3, 0.1]
    assert list(models["metrics.scored_rmse_dark_spp4"]) == [0.4, 0.4, 0.2]
    # One reference row for the built-in dataset (two runs share its render), none else.
    reference = scored[scored["model"] == REFERENCE]
    assert list(reference["dataset"]) == ["built-in"]
    assert list(reference["metrics.scored_rmse_dark"]) == [0.05]
    table = table_crop(scored, "dark")
    assert list(table.columns) == ["scored against", REFERENCE, "k = 8", "beyond grid"]
    assert table.loc["built-in", REFERENCE] == "0.0500 (n=1)"
    assert table.loc["measured", REFERENCE] == "–"
    assert table.loc["built-in", "k = 8"] == "0.8000 ± 0.7071 (n=2)"
    assert list(table["beyond grid"]) == ["25.0 %", "0.0 %"]


def test_a_rendering_job_logs_its_renders_and_the_tables_draw_fig8(
    tmp_path, mlflow_template, shared_data
):
    """The built-in material: the truth is rendered beside the reference, every run is
    scored against both, and the tables score against the truth."""
    from pipeline.app import run_job
    from pipeline.tables import build_tables, default_settings

    runs_dir = tmp_path / "runs"
    mlflow_template(runs_dir)
    paths = [f"paths.runs={runs_dir}", f"paths.data={shared_data}"]
    cfg = compose_config("experiment=render_smoke", *paths, f"train.max_steps={WIRING_STEPS}")
    run_job(cfg)
    run_job(compose_config("experiment=render_smoke", *paths, "model=pca", "model.n_components=2"))

    client = MlflowClient(tracking_uri(runs_dir))
    experiment = client.get_experiment_by_name("render_smoke")
    pca, run = client.search_runs([experiment.experiment_id], order_by=["start_time DESC"])
    assert pca.data.params["model.name"] == "pca"
    for stage in ("render_reference", "render_truth"):  # one reference and one truth
        assert pca.data.tags[f"cache.{stage}"] == run.data.tags[f"cache.{stage}"]
    assert np.isfinite(pca.data.metrics["render_rmse_bright"])
    for artifacts in (pca, run):  # every model's run keeps the same evaluation files
        logged = {a.path for a in client.list_artifacts(artifacts.info.run_id)}
        logged |= {a.path for a in client.list_artifacts(artifacts.info.run_id, "evaluate")}
        assert {"metrics.json", "evaluate/rmse_per_direction.npy"} <= logged
    metrics = run.data.metrics
    for name in (
        "render_rmse_dark",
        "render_rmse_bright",
        "render_rmse_dark_spp1",
        "render_hf_ratio_bright_spp4",
        "render_seconds",
        "render_truth_rmse_dark",
        "render_truth_rmse_cloth_spp1",
        "render_truth_hf_ratio_dark_spp4",
        "render_reference_truth_rmse_bright",
        "render_reference_truth_hf_ratio_dark",
    ):
        assert np.isfinite(metrics[name]), name
    assert metrics["render_rmse_dark"] == metrics["render_rmse_dark_spp4"]
    assert metrics["render_truth_rmse_cloth"] == metrics["render_truth_rmse_cloth_spp4"]
    for region in ("", "_dark", "_bright"):
        assert 0 <= metrics[f"render_beyond_grid_share{region}"] <= 1
    for name in ("render_reference_truth_rmse_cloth", "render_beyond_grid_share"):
        assert pca.data.metrics[name] == metrics[name]  # the same reference, truth and crops
    # The reference is near the truth (the data's JPEG rounding and the clamp), the model not.
    assert metrics["render_reference_truth_rmse_cloth"] < 0.05
    assert {"cache.render", "cache.render_reference", "cache.render_truth"} <= set(run.data.tags)
    logged = {a.path for a in client.list_artifacts(run.info.run_id, "render")}
    assert {
        "render/model_spp4.png",
        "render/model_spp4.exr",
        "render/reference_spp4.png",
        "render/truth_spp4.png",
        "render/model_spp1.png",
        "render/crops.json",
    } <= logged

    settings = default_settings()
    settings.experiments = ["render_smoke"]
    out = build_tables(runs_dir, settings)
    for name in (
        "table3_render_dark.md",
        "table4_render_bright.md",
        "render_graininess.md",
        "render_cloth.md",
    ):
        assert (out / name).is_file(), name
        text = (out / name).read_text()
        assert "against the analytic truth" in text and "measured reference" in text, name
        assert "against the measured reference" not in text, name
    table3 = (out / "table3_render_dark.md").read_text()
    assert "k = 8" in table3 and "PCA c = 2" in table3
    cloth = pd.read_csv(out / "render_cloth.csv")
    assert sorted(cloth["spp"]) == [1, 4]  # one row per spp level of render_smoke
    top = cloth.loc[cloth["spp"] == 4]
    assert top["k = 8"].item().startswith(f"{metrics['render_truth_rmse_cloth']:.4f}")
    assert (
        top["measured reference"]
        .item()
        .startswith(f"{metrics['render_reference_truth_rmse_cloth']:.4f}")
    )
    assert top["beyond grid"].item() == f"{100 * metrics['render_beyond_grid_share']:.1f} %"
    grain = pd.read_csv(out / "render_graininess.csv")
    assert set(grain["model"]) == {"measured reference", "k = 8", "PCA c = 2"}
    assert "dark: HF energy / truth" in grain
    assert grain["dark: HF RMSE"].notna().all()  # the detail in place, for every row
    figures = sorted(out.glob("fig8_*.png"))
    assert [p.name.endswith("_crops_per_spp.png") for p in figures] == [False, True]
    assert all(p.stat().st_size > 0 for p in figures)
    assert len(list(out.glob("fig8_*.exr"))) == 4  # the truth, the reference, two models
    # Fig. 8 comes from what the runs logged: with the cache gone the tables draw it alike.
    assert "render/fig8_data.npz" in logged
    before = {p.name: read_exr(p) for p in out.glob("fig8_*.exr")}
    shutil.rmtree(cfg.paths.cache)
    out = build_tables(runs_dir, settings)
    after = {p.name: read_exr(p) for p in out.glob("fig8_*.exr")}
    assert before.keys() == after.keys()
    for name, channels in before.items():
        for channel, pixels in channels.items():
            np.testing.assert_array_equal(pixels, after[name][channel])
    assert [p.name.endswith("_crops_per_spp.png") for p in sorted(out.glob("fig8_*.png"))] == [
        False,
        True,
    ]


def test_measured_data_is_scored_against_the_reference_with_every_material_clamped(
    tmp_path, mlflow_template
):
    """Data without a generator (a dataset folder): no truth; the model is queried at
    directions clamped onto the grid, and the tables say they score against the reference."""
    from pipeline.app import run_job
    from pipeline.btf.synthetic_dataset import write_synthetic_btf
    from pipeline.core.cache import StageCache
    from pipeline.tables import build_tables, default_settings

    runs_dir = tmp_path / "runs"
    mlflow_template(runs_dir)
    root = write_synthetic_btf(tmp_path / "WOOL", size=16)
    run_job(
        compose_config(
            "experiment=render_smoke",
            f"paths.runs={runs_dir}",
            "dataset=ubo2003",
            f"dataset.root={root}",
            "model=pca",
            "model.n_components=2",
        )
    )
    client = MlflowClient(tracking_uri(runs_dir))
    experiment = client.get_experiment_by_name("render_smoke")
    (run,) = client.search_runs([experiment.experiment_id])
    metrics = run.data.metrics
    assert not any(name.startswith(("render_truth", "render_reference_truth")) for name in metrics)
    assert "cache.render_truth" not in run.data.tags
    assert 0 <= metrics["render_beyond_grid_share"] <= 1
    entry = StageCache(runs_dir / "cache").lookup("render", run.data.tags["cache.render"])
    assert entry.manifest["summary"]["beyond_grid"] == "clamped to the grid"

    settings = default_settings()
    settings.experiments = ["render_smoke"]
    out = build_tables(runs_dir, settings)
    for name in ("table3_render_dark.md", "render_cloth.md", "render_graininess.md"):
        text = (out / name).read_text()
        assert "against the measured reference" in text, name
        assert "analytic truth" not in text, name
    assert "dark: HF energy / reference" in pd.read_csv(out / "render_graininess.csv")
    assert len(list(out.glob("fig8_*.exr"))) == 2  # the reference and the model


def test_the_render_benchmark_runs_each_material_on_the_same_rays(capsys):
    from benchmarks.render import main

    found = main(["size=16", "spp=1", "crop=4"])
    assert set(found) == {"lambertian", "measured", "neural", "truth", "beyond grid"}
    assert len({stats.material_queries for stats in found.values()}) == 1
    assert "x lambertian" in capsys.readouterr().out
