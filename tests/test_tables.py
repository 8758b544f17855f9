"""`python -m pipeline.tables` on a few hand-made MLflow runs with known numbers."""

import re
import warnings

import mlflow
import pandas as pd
import pytest
from helpers import recipe_tags
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from pipeline.core.store import init_store, tracking_uri
from pipeline.tables import build_tables, default_settings

# (method, k, seed, rmse): k = 500 is clearly worse than k = 1000 beyond the seed spread.
RUNS = [
    ("neural_btf", None, 0, 0.0200),
    ("neural_btf", None, 1, 0.0210),
    ("clustered", 500, 0, 0.0300),
    ("clustered", 500, 1, 0.0302),
    ("clustered", 500, 2, 0.0304),
    ("clustered", 1000, 0, 0.0250),
    ("clustered", 1000, 1, 0.0252),
    ("clustered", 1000, 2, 0.0254),
]


@pytest.fixture(autouse=True)
def _store(tmp_path, mlflow_template):
    mlflow_template(tmp_path)


def _log_runs(
    runs_dir,
    rows,
    experiment="btf",
    failed=False,
    evaluate_key=None,
    epochs=16,
    curve=(),
    precision=None,
):
    experiment_id = init_store(runs_dir, experiment)
    for method, k, seed, rmse in rows:
        m = 10_000
        latents = (k or m) * 8 * 4
        listing = m * 4 if k else 0
        params = {
            "method.name": "btf",
            "model.name": method,
            "model.k": k,
            "seed": seed,
            "dataset.name": "synthetic",
            "dataset.root": None,
            "dataset.synthetic.material": "plain_weave",
            "model.texel_scale": "none",
            "model.target": "texel",
            "train.epochs": epochs,
            "train.precision": precision or "float32",
        }
        tags = {
            "cache.evaluate": evaluate_key or f"{method}-{k}-{seed}-{rmse}-{precision}",
            **recipe_tags(params),
        }
        with mlflow.start_run(experiment_id=experiment_id, tags=tags) as run:
            mlflow.log_params(params)
            for step, seconds, value in curve:
                mlflow.log_metrics({"curve_rmse": value, "curve_seconds": seconds}, step=step)
            mlflow.log_metrics(
                {
                    "rmse": rmse,
                    "bytes_decoder": 97_532,
                    "bytes_latents": latents,
                    "bytes_list": listing,
                    "bytes_extra": 0,
                    "bytes_total": 97_532 + latents + listing,
                    "bytes_original": 787_320_000,
                    "compression_ratio": 787_320_000 / (97_532 + latents + listing),
                    "rmse_offgrid_model": rmse * 2,
                    "rmse_offgrid_linear": 0.01,
                }
            )
            if failed:
                mlflow.end_run(status="FAILED")
        assert run.info.run_id


def _log_run(experiment_id, params: dict, metrics: dict, tags: dict) -> None:
    """One finished run with these settings, as a job logs them (recipe tags included)."""
    with mlflow.start_run(experiment_id=experiment_id, tags={**tags, **recipe_tags(params)}):
        mlflow.log_params(params)
        mlflow.log_metrics(metrics)


@pytest.fixture
def settings():
    s = default_settings()
    s.fig7.enabled = False  # the hand-made runs have no cached models to draw
    return s


def test_tables_from_hand_made_runs(tmp_path, settings):
    _log_runs(tmp_path, RUNS)
    _log_runs(tmp_path, [("clustered", 2000, 0, 0.9)], failed=True)  # ignored: FAILED
    out = build_tables(tmp_path, settings)

    sizes = pd.read_csv(out / "table1_sizes.csv").set_index("model")
    assert list(sizes.index) == ["Neural BTF", "k = 500", "k = 1000"]
    assert sizes.loc["Neural BTF", "latents [B]"] == 320_000
    assert sizes.loc["k = 500", "total [B]"] == 153_532
    assert sizes.loc["k = 1000", "list [B]"] == 40_000
    assert sizes.loc["Neural BTF", "ratio (exact)"] == "1:1885.7"
    assert sizes.loc["Neural BTF", "ratio (paper)"] == "1:1885"  # 751 MB / 408 KB
    assert sizes.loc["k = 500", "ratio (paper)"] == "1:5127"  # the paper's 1:5127
    assert sizes.loc["k = 1000", "ratio (paper)"] == "1:4633"

    # What the disk holds, MLflow holds: a run of the experiment "tables" with the outputs,
    # and that run is never read back as a result by the next `python -m pipeline.tables`.
    client = MlflowClient(tracking_uri(tmp_path))
    logged = client.search_runs([client.get_experiment_by_name("tables").experiment_id])
    assert len(logged) == 1 and logged[0].info.status == "FINISHED"
    names = {a.path for a in client.list_artifacts(logged[0].info.run_id, "tables")}
    assert {"tables/summary.md", "tables/table1_sizes.md", "tables/k_verdict.csv"} <= names
    build_tables(tmp_path, settings)
    assert pd.read_csv(out / "table1_sizes.csv").shape == (3, sizes.shape[1] + 1)

    rmse = pd.read_csv(out / "table2_rmse.csv").set_index("dataset")
    assert rmse.loc["synthetic:plain_weave", "Neural BTF"] == "0.0205 ± 0.0007 (n=2)"
    assert rmse.loc["synthetic:plain_weave", "k = 500"] == "0.0302 ± 0.0002 (n=3)"
    assert rmse.loc["synthetic:plain_weave", "k = 1000"] == "0.0252 ± 0.0002 (n=3)"
    assert "k = 2000" not in rmse.columns

    verdict = pd.read_csv(out / "k_verdict.csv")
    assert verdict.loc[0, "verdict"].startswith("k changes the RMSE beyond seed noise")
    assert "lowest mean at k = 1000" in verdict.loc[0, "verdict"]

    summary = (out / "summary.md").read_text()
    assert "synthetic:plain_weave: no run of k = 2000" in summary
    assert "synthetic: Neural BTF has" not in summary  # two seeds: nothing to report
    for stem in ("table1_sizes", "table2_rmse", "interpolation", "k_verdict"):
        for ext in ("md", "csv", "tex"):
            assert (out / f"{stem}.{ext}").is_file()
    assert "\\begin{table}" in (out / "table2_rmse.tex").read_text()
    # The paper's Table 2 stands beside ours, in the same files and in the summary.
    published = pd.read_csv(out / "table2_paper.csv").set_index("dataset")
    assert published.loc["fabric02", "k = 500"] == 0.0212
    assert " 0.0200 |" in (out / "table2_paper.md").read_text()  # as published, 4 digits
    assert "The paper's Table 2, beside ours" in summary


def test_verdict_finds_no_effect_when_k_is_within_seed_noise(tmp_path, settings):
    noisy = [("clustered", 500, s, r) for s, r in enumerate([0.030, 0.026, 0.034])]
    noisy += [("clustered", 1000, s, r) for s, r in enumerate([0.031, 0.027, 0.033])]
    _log_runs(tmp_path, noisy)
    verdict = pd.read_csv(build_tables(tmp_path, settings) / "k_verdict.csv")
    assert verdict.loc[0, "verdict"].startswith("no evidence")


def test_one_seed_per_k_says_what_is_missing(tmp_path, settings):
    _log_runs(tmp_path, [("clustered", 500, 0, 0.03), ("clustered", 1000, 0, 0.03)])
    out = build_tables(tmp_path, settings)
    assert "not enough runs" in pd.read_csv(out / "k_verdict.csv").loc[0, "verdict"]
    assert "k = 500 has 1 seed" in (out / "summary.md").read_text()


def test_filters_select_experiments(tmp_path, settings):
    _log_runs(tmp_path, RUNS[:2], experiment="a")
    _log_runs(tmp_path, RUNS[2:4], experiment="b")
    settings = OmegaConf.merge(settings, {"experiments": ["b"]})
    rmse = pd.read_csv(build_tables(tmp_path, settings) / "table2_rmse.csv")
    assert list(rmse.columns) == ["dataset", "k = 500"]


def test_no_runs_says_so(tmp_path, settings):
    out = build_tables(tmp_path, settings)
    assert "No finished run in the store" in (out / "summary.md").read_text()


def test_a_rerun_of_the_same_job_is_not_another_seed(tmp_path, settings):
    _log_runs(tmp_path, [("clustered", 500, 0, 0.03), ("clustered", 500, 1, 0.04)])
    _log_runs(tmp_path, [("clustered", 500, 0, 0.03)])  # same stages, all cache hits
    rmse = pd.read_csv(build_tables(tmp_path, settings) / "table2_rmse.csv")
    assert rmse.loc[0, "k = 500"] == "0.0350 ± 0.0071 (n=2)"


def test_different_crops_of_one_source_are_different_datasets(tmp_path, settings):
    experiment_id = init_store(tmp_path, "btf")
    for crop, n, rmse, key in ((12, 729, 0.16, "btf.crop.size"), (48, 6561, 0.03, "btf.crop.size")):
        _log_run(
            experiment_id,
            {
                "method.name": "btf",
                "model.name": "clustered",
                "model.k": 8,
                "seed": 0,
                "dataset.name": "synthetic",
                key: crop,
                "dataset.synthetic.material": "plain_weave",
            },
            {"rmse": rmse, "n_directions": n},
            {"cache.evaluate": str(crop)},
        )
    rmse = pd.read_csv(build_tables(tmp_path, settings) / "table2_rmse.csv")
    assert dict(zip(rmse["dataset"], rmse["k = 8"], strict=True)) == {
        "synthetic:plain_weave 12²×729": "0.1600 (n=1)",
        "synthetic:plain_weave 48²×6561": "0.0300 (n=1)",
    }


def test_a_longer_run_is_its_own_model_and_its_curve_is_drawn(tmp_path, settings):
    _log_runs(tmp_path, RUNS)
    _log_runs(
        tmp_path,
        [("neural_btf", None, 0, 0.019)],
        epochs=64,
        curve=[(0, 0.0, 0.2), (100, 60.0, 0.05), (200, 120.0, 0.02)],
    )
    out = build_tables(tmp_path, settings)
    rmse = pd.read_csv(out / "table2_rmse.csv").set_index("dataset")
    assert (
        rmse.loc["synthetic:plain_weave", "Neural BTF"] == "0.0205 ± 0.0007 (n=2)"
    )  # not mixed in
    assert rmse.loc["synthetic:plain_weave", "Neural BTF (64 epochs)"] == "0.0190 (n=1)"
    points = pd.read_csv(out / "training_curves.csv")
    assert list(points["step"]) == [0, 100, 200]
    assert list(points["seconds"]) == [0.0, 60.0, 120.0]
    assert set(points["model"]) == {"Neural BTF (64 epochs)"}
    assert (out / "training_curves_0.png").is_file()
    assert "Training: RMSE versus time" in (out / "summary.md").read_text()


def test_a_bfloat16_run_is_its_own_model_not_another_seed(tmp_path, settings):
    _log_runs(tmp_path, RUNS[:1])
    _log_runs(tmp_path, RUNS[1:2], precision="float32")
    _log_runs(tmp_path, [("neural_btf", None, 0, 0.0230)], precision="bfloat16")
    rmse = pd.read_csv(build_tables(tmp_path, settings) / "table2_rmse.csv").set_index("dataset")
    assert rmse.loc["synthetic:plain_weave", "Neural BTF"] == "0.0205 ± 0.0007 (n=2)"
    assert rmse.loc["synthetic:plain_weave", "Neural BTF (bfloat16)"] == "0.0230 (n=1)"


def test_convergence_compares_each_run_with_the_same_model_and_seed_trained_longest(
    tmp_path, settings
):
    _log_runs(tmp_path, RUNS, curve=[(0, 0.0, 0.2), (100, 60.0, 0.03)])  # 16 epochs
    _log_runs(
        tmp_path,
        [("neural_btf", None, 0, 0.0195), ("clustered", 1000, 0, 0.0200)],
        epochs=64,
        curve=[(0, 0.0, 0.2), (100, 60.0, 0.03), (400, 240.0, 0.02)],
    )
    out = build_tables(tmp_path, settings)
    assert (out / "training_curves_0.png").is_file()  # with the models' 5 % lines
    table = pd.read_csv(out / "convergence.csv")
    # Only seed 0 of Neural BTF and k = 1000 has a longer run beside it; k = 500 has none.
    assert list(
        zip(table["model"], table["seed"], table["epochs"], table["reference epochs"], strict=True)
    ) == [("Neural BTF", 0, 16, 64), ("k = 1000", 0, 16, 64)]
    # 0.0200 / 0.0195 - 1 = +2.6 %, within 5 %; 0.0250 / 0.0200 - 1 = +25.0 %, not.
    assert list(table["excess"]) == ["+2.6 %", "+25.0 %"]
    assert list(table["within 5 %"]) == [True, False]
    assert list(table["length ratio"]) == [4, 4]
    assert "Converged?" in (out / "summary.md").read_text()


def test_no_convergence_table_without_runs_of_different_lengths(tmp_path, settings):
    _log_runs(tmp_path, RUNS)
    out = build_tables(tmp_path, settings)
    assert not (out / "convergence.csv").exists()


def test_runs_near_the_mean_abrdf_baseline_are_flagged(tmp_path, settings):
    experiment_id = init_store(tmp_path, "btf")
    for seed, rmse in ((0, 0.03), (1, 0.14)):  # against a baseline of 0.15
        _log_run(
            experiment_id,
            {
                "method.name": "btf",
                "model.name": "neural_btf",
                "model.k": None,
                "seed": seed,
                "dataset.name": "synthetic",
            },
            {"rmse": rmse, "rmse_mean_abrdf": 0.15},
            {"cache.evaluate": str(seed)},
        )
    out = build_tables(tmp_path, settings)
    failed = pd.read_csv(out / "failed_runs.csv")
    assert list(failed["seed"]) == [1] and failed.loc[0, "ratio"] == 0.93
    assert "did not beat the trivial baseline" in (out / "summary.md").read_text()


def test_a_failed_training_warns_and_reports_its_ratio(caplog):
    from pipeline.btf.runner import check_against_baseline
    from pipeline.core.run_log import NO_RUN

    good = {"rmse": 0.03, "rmse_mean_abrdf": 0.15}
    check_against_baseline(NO_RUN, good)
    assert good["rmse_ratio_to_mean_abrdf"] == pytest.approx(0.2) and not caplog.records
    bad = {"rmse": 0.16, "rmse_mean_abrdf": 0.15}
    check_against_baseline(NO_RUN, bad)
    assert "training failed" in caplog.text and "1.07 x the mean-ABRDF baseline" in caplog.text


def test_runs_of_two_recipes_are_never_averaged_as_seeds(tmp_path, settings):
    """SGD and Adam runs of one model at the same epochs: two columns, labelled by what
    differs; the threads setting (speed only) does not split them."""
    experiment_id = init_store(tmp_path, "btf")
    for seed, optimizer, threads, rmse in (
        (0, "sgd", 1, 0.05),
        (1, "sgd", 2, 0.07),
        (0, "adam", 1, 0.02),
        (1, "adam", 2, 0.04),
    ):
        _log_run(
            experiment_id,
            {
                "method.name": "btf",
                "model.name": "clustered",
                "model.k": 500,
                "seed": seed,
                "dataset.name": "synthetic",
                "train.epochs": 16,
                "train.optimizer": optimizer,
                "train.threads": threads,
            },
            {"rmse": rmse},
            {"cache.evaluate": f"{optimizer}{seed}"},
        )
    rmse = pd.read_csv(build_tables(tmp_path, settings) / "table2_rmse.csv")
    assert rmse.loc[0, "k = 500 (adam)"] == "0.0300 ± 0.0141 (n=2)"
    assert rmse.loc[0, "k = 500 (sgd)"] == "0.0600 ± 0.0141 (n=2)"
    assert "k = 500" not in rmse.columns


def test_table2_names_each_columns_learning_rate(tmp_path, settings):
    experiment_id = init_store(tmp_path, "btf")
    for method, k, train_lr, method_lr in (
        ("neural_btf", None, "None", 0.05),
        ("clustered", 500, 0.05, 0.08),
    ):
        _log_run(
            experiment_id,
            {
                "method.name": "btf",
                "model.name": method,
                "model.k": k,
                "seed": 0,
                "dataset.name": "synthetic",
                "train.lr": train_lr,
                "model.lr": method_lr,
            },
            {"rmse": 0.03},
            {"cache.evaluate": method},
        )
    text = (build_tables(tmp_path, settings) / "table2_rmse.md").read_text()
    assert "Learning rates: Neural BTF: 0.05; k = 500: 0.05." in text


def test_experiments_or_a_filter_that_match_nothing_are_refused_and_nothing_is_rewritten(
    tmp_path, settings
):
    from pipeline.core.errors import ConfigError

    _log_runs(tmp_path, RUNS)
    out = build_tables(tmp_path, settings)
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    typo = OmegaConf.merge(settings, {"experiments": ["btff"]})
    with pytest.raises(ConfigError, match=r"\['btff'\] not in the store .*'btf'"):
        build_tables(tmp_path, typo)
    nothing = OmegaConf.merge(settings, {"filter": "tags.note = 'none'"})
    with pytest.raises(ConfigError, match="matches none of the 8 runs"):
        build_tables(tmp_path, nothing)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before


def test_a_new_set_of_tables_leaves_no_file_of_the_old_one(tmp_path, settings):
    _log_runs(tmp_path, RUNS)
    out = build_tables(tmp_path, settings)
    (out / "stale_table.md").write_text("from an earlier run")
    build_tables(tmp_path, settings)
    assert not (out / "stale_table.md").exists() and (out / "table2_rmse.md").is_file()
    assert [p.name for p in tmp_path.iterdir() if "tables." in p.name] == []  # no temporaries


def test_the_summary_page_shows_its_tables_and_figures_in_one_file(tmp_path, settings):
    import base64
    import re

    _log_runs(tmp_path, RUNS)
    out = build_tables(tmp_path, settings)
    assert "![rmse_vs_k](rmse_vs_k.png)" in (out / "summary.md").read_text()
    html = (out / "summary.html").read_text()
    assert "<table>" in html and 'src="rmse_vs_k.png"' not in html
    [png] = re.findall(r'alt="rmse_vs_k" src="data:image/png;base64,([^"]+)"', html)
    assert base64.b64decode(png) == (out / "rmse_vs_k.png").read_bytes()


def test_rmse_versus_k_says_so_when_it_has_nothing_to_draw(tmp_path):
    """A store of PCA runs alone: no empty figure (and no matplotlib warning), a line."""
    from pipeline.btf.report import plot_rmse_vs_k

    runs = pd.DataFrame(
        {
            "dataset": ["d"],
            "params.method.name": "btf",
            "params.model.name": ["pca"],
            "family": ["f"],
            "model": ["PCA"],
            "k": [128],
            "metrics.rmse": [0.1],
        }
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        section = plot_rmse_vs_k(runs, tmp_path)
    assert "No clustered or Neural BTF run" in section
    assert not (tmp_path / "rmse_vs_k.png").exists()


def _log_btf(experiment_id, model: str, seed: int, metrics: dict, **settings) -> None:
    """One finished method-A run on the smoke's data (12 x 12 crop) with these settings."""
    params = {
        "method.name": "btf",
        "model.name": model,
        "seed": seed,
        "dataset.name": "synthetic",
        "dataset.synthetic.material": "plain_weave",
        "btf.crop.size": 12,
        "train.epochs": 6,
        **settings,
    }
    key = f"{model}-{seed}-{sorted(settings.items())}"
    _log_run(experiment_id, params, {"n_directions": 729, **metrics}, {"cache.evaluate": key})


def test_a_table_holds_one_experiment_and_names_what_differs_in_words(tmp_path, settings):
    """Smoke, demo and rate-distortion runs in one store: a section and a folder per
    experiment; a column per recipe, labelled by the fewest settings that tell it apart,
    in words (a smoke run against a run differing in five correlated settings: one)."""
    smoke = init_store(tmp_path, "smoke")
    for seed in (0, 1):
        _log_btf(smoke, "clustered", seed, {"rmse": 0.05 + seed / 1000}, **{"model.k": 8})
    rate = init_store(tmp_path, "rate_distortion_smoke")
    for latent in (2, 8):
        for dtype in ("float32", "float16"):
            _log_btf(
                rate,
                "neural_btf",
                0,
                {"rmse": 0.1 / latent},
                **{"btf.network.latent": latent, "btf.sizes.weight_dtype": dtype},
            )
    # Another Neural BTF recipe in five settings at once (a longer, held-out demo run).
    _log_btf(
        rate,
        "neural_btf",
        0,
        {"rmse": 0.02},
        **{
            "btf.network.latent": 8,
            "btf.sizes.weight_dtype": "float32",
            "btf.interpolation.holdout_lights": 6,
            "train.lr": 0.01,
            "train.optimizer": "sgd",
            "train.batch_size": 64,
            "train.max_steps": 500,
        },
    )
    out = build_tables(tmp_path, settings)

    assert out == tmp_path / "tables"
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["rate_distortion_smoke", "smoke"]
    assert list(pd.read_csv(out / "smoke" / "table2_rmse.csv").columns) == ["dataset", "k = 8"]
    columns = list(pd.read_csv(out / "rate_distortion_smoke" / "table2_rmse.csv").columns)
    assert columns == [
        "dataset",
        "Neural BTF (latent 2, float16)",
        "Neural BTF (latent 2, float32)",
        "Neural BTF (latent 8, float16)",
        "Neural BTF (latent 8, float32)",
        "Neural BTF (latent 8, float32, 6 lights held out)",
    ]
    recipes = pd.read_csv(out / "rate_distortion_smoke" / "table2_columns.csv")
    five = recipes.loc[recipes["model"].str.contains("held out"), "differs in"].iloc[0]
    assert "train.lr=0.01" in five and "btf.interpolation.holdout_lights=6" in five
    summary = (out / "summary.md").read_text()
    assert "# Experiment `smoke`: 2 finished jobs" in summary
    assert "# Experiment `rate_distortion_smoke`: 5 finished jobs" in summary
    assert "](smoke/rmse_vs_k.png)" in summary  # figures linked into their folder
    assert "No finished" not in summary
    assert not re.search(r"recipe [0-9a-f]{6}|\+\d+ more", summary)  # no hashes, no walls


def test_the_graininess_table_compares_rmse_over_the_same_directions(tmp_path, settings):
    """Table 2's RMSE and the logged scaled/unscaled RMSEs are all over every direction
    (held-out lights too): the graininess table shows the same number as Table 2."""
    experiment_id = init_store(tmp_path, "btf")
    for k, every in ((128, 0.05251), (256, 0.04100)):
        _log_btf(
            experiment_id,
            "clustered",
            0,
            {
                "rmse": every,
                "rmse_train_dirs": every - 0.0001,
                "rmse_without_texel_scale": every,
                "rmse_with_texel_scale": every - 0.005,
                "bytes_total": 100_000 + k,
                "bytes_extra": 0,
                "n_texels": 144,
            },
            **{"model.k": k, "btf.interpolation.holdout_lights": 6},
        )
    out = build_tables(tmp_path, settings)
    rmse = pd.read_csv(out / "table2_rmse.csv")
    assert rmse.loc[0, "k = 128"] == "0.0525 (n=1)"
    grain = pd.read_csv(out / "graininess.csv").set_index("model")
    assert grain.loc["k = 128", "without scale"] == "0.0525 (n=1)"
    assert grain.loc["k = 128", "nearest in bytes, no scale"] == "k = 256"
    assert grain.loc["k = 128", "its RMSE"] == "0.0410 (n=1)"


def test_a_model_that_stores_its_scale_lists_its_bytes_without_and_with_it(tmp_path, settings):
    """A +scale run's bytes_total holds the scale (144 texels x float16 = 288 B): the
    'bytes' column is without it, 'bytes with scale' with it, never the same number; the
    nearest unscaled model is of the same recipe but k and scale."""
    experiment_id = init_store(tmp_path, "btf")
    common = {"btf.sizes.weight_dtype": "float32", "btf.sizes.list_dtype": "uint16"}
    for k, scale, extra in ((4, "lstsq", 288), (4, "none", 0), (16, "none", 0)):
        rmse = 0.15 - k / 1000 - (0.01 if extra else 0)
        _log_btf(
            experiment_id,
            "clustered",
            0,
            {
                "rmse": rmse,
                "rmse_without_texel_scale": 0.15 - k / 1000,
                "rmse_with_texel_scale": 0.14 - k / 1000,
                "bytes_extra": extra,
                "bytes_total": 97_948 + 96 * (k > 4) * 4 + extra,
                "n_texels": 144,
            },
            **common,
            **{
                "model.k": k,
                "model.texel_scale": scale,
                "btf.sizes.extra_dtype": "float16" if extra else "float32",
            },
        )
    grain = pd.read_csv(build_tables(tmp_path, settings) / "graininess.csv").set_index("model")
    assert grain.loc["k = 4 +scale", "bytes"] == 97_948
    assert grain.loc["k = 4 +scale", "bytes with scale"] == 97_948 + 288
    assert grain.loc["k = 4 +scale", "nearest in bytes, no scale"] == "k = 16"
    assert grain.loc["k = 4", "bytes with scale"] == 97_948 + 4 * 144  # float32 when unstored


def test_a_hash_names_a_column_only_where_no_logged_setting_tells_it_apart():
    from pipeline.btf.tables import recipe_labels

    runs = pd.DataFrame(
        {
            "dataset": "d",
            "model": "k = 8",
            "params.train.lr": ["0.1", "0.1", "0.2"],
            "params.btf.crop.size": ["12", "12", "48"],
            "tags.recipe": ["aaaaaa1", "bbbbbb2", "cccccc3"],
        }
    )
    assert list(recipe_labels(runs, ["dataset", "model"])) == [
        " (12² crop) recipe aaaaaa",
        " (12² crop) recipe bbbbbb",
        " (48² crop)",
    ]
    alike = runs.assign(**{"params.btf.crop.size": "12"})  # no setting differs at all
    assert list(recipe_labels(alike.iloc[:2], ["dataset", "model"])) == [
        " recipe aaaaaa",
        " recipe bbbbbb",
    ]
