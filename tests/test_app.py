"""The whole job as ``python -m pipeline`` runs it, on the composed smoke config."""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from pipeline.app import run_job
from pipeline.core.errors import ConfigError, DataError
from pipeline.core.store import tracking_uri
from pipeline.data.images import read_exr


def _runs(cfg):
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    return client.search_runs([experiment.experiment_id])


def _cache_entries(cfg) -> list[Path]:
    root = Path(cfg.paths.cache)
    if not root.exists():
        return []
    return [p for p in root.glob("*/*") if not p.name.startswith(".")]


def test_smoke_run_logs_to_mlflow_and_second_run_computes_nothing(smoke_cfg, own_cache, caplog):
    cfg = smoke_cfg(own_cache)
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        rmse = run_job(cfg)
    first = [r.getMessage() for r in caplog.records if "stage" in r.getMessage()]
    assert any("computed" in m for m in first)
    assert 0 < rmse < 1
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        assert run_job(cfg) == pytest.approx(rmse)
    second = [r.getMessage() for r in caplog.records if "stage" in r.getMessage()]
    assert second and all(" hit " in m for m in second), second

    runs = _runs(cfg)
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    run = runs[0]
    assert run.data.params["model.name"] == "clustered"
    assert run.data.params["model.k"] == "8"
    assert run.data.params["seed"] == "0"
    assert run.data.params["dataset.name"] == "synthetic"
    for stage in ("load", "crop", "preprocess", "pca", "kmeans", "representatives", "train"):
        assert f"cache.{stage}" in run.data.tags
    assert "git.commit" in run.data.tags and "version.torch" in run.data.tags
    assert [
        a.path
        for a in MlflowClient(tracking_uri(cfg.paths.runs)).list_artifacts(
            run.info.run_id, "compressed"
        )
    ] == ["compressed/btf.safetensors"]
    for metric in ("rmse", "bytes_total", "compression_ratio", "rmse_mean_abrdf"):
        assert metric in run.data.metrics
    # The smoke run holds 4 lights out: rmse is over every direction, held-out ones too,
    # and lies between the trained and the held-out directions' RMSE.
    metrics = run.data.metrics
    low, high = sorted([metrics["rmse_train_dirs"], metrics["rmse_heldout_model"]])
    assert low < metrics["rmse"] < high and "rmse_all_dirs" not in metrics
    # The run page shows the description before the metrics: it leads with the result.
    assert run.data.tags["mlflow.note.content"].startswith(
        f"**Result:** `rmse` {metrics['rmse']:.4g}"
    )
    # The UI's runs table shows no metric unless asked: the shared view "results" asks.
    view = MlflowClient(tracking_uri(cfg.paths.runs)).get_experiment(run.info.experiment_id)
    state = json.loads(view.tags["mlflow.sharedViewState.results"])
    assert state["orderByKey"] == "metrics.`rmse`"
    assert "params.`model.name`" in state["selectedColumns"]
    assert metrics["rmse_ratio_to_mean_abrdf"] == pytest.approx(
        metrics["rmse"] / metrics["rmse_mean_abrdf"]
    )
    # The recipe tag is the same for another seed, not for another learning rate.
    assert len(run.data.tags["recipe"]) == 12
    # Unset settings are logged too: a null is a value that splits recipes.
    assert run.data.params["dataset.root"] == "None"
    # The loss is keyed by training step, as logged live (first run) and as replayed from
    # the cached model (second run), ending at the run's last step.
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    histories = [
        [(m.step, m.value) for m in client.get_metric_history(r.info.run_id, "loss")] for r in runs
    ]
    assert histories[0] == histories[1]
    assert histories[0][-1][0] == metrics["train_steps"] > len(histories[0]) - 1


def test_the_recipe_tag_ignores_the_seed_and_speed_settings_only(smoke_cfg):
    from pipeline.core.recipe import recipe_id
    from pipeline.core.run import flatten

    recipe = recipe_id(flatten(smoke_cfg()))
    assert recipe == recipe_id(flatten(smoke_cfg("seed=3", "train.threads=1")))
    assert recipe != recipe_id(flatten(smoke_cfg("train.lr=0.01")))


def test_changing_train_settings_reuses_the_data_stages(smoke_cfg, own_cache, caplog):
    run_job(smoke_cfg(own_cache))
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pipeline.core.cache"):
        run_job(smoke_cfg(own_cache, "train.max_steps=10", "model.k=4"))
    by_stage = {r.getMessage().split()[1]: r.getMessage() for r in caplog.records}
    for stage in ("load", "crop", "preprocess", "pca"):
        assert " hit " in by_stage[stage], by_stage[stage]
    for stage in ("kmeans", "train"):
        assert "computed" in by_stage[stage], by_stage[stage]


def _assert_failed_cleanly(cfg, error, match):
    with pytest.raises(error, match=match):
        run_job(cfg)
    runs = _runs(cfg)
    assert [r.info.status for r in runs] == ["FAILED"]
    return runs[0]


def test_missing_dataset_root_fails_cleanly(smoke_cfg, own_cache, tmp_path):
    missing = tmp_path / "no_such_dataset"
    cfg = smoke_cfg(own_cache, "dataset=ubo2003", f"dataset.root={missing}")
    _assert_failed_cleanly(cfg, DataError, str(missing))
    assert _cache_entries(cfg) == []


def test_crop_larger_than_texture_fails_cleanly(smoke_cfg, own_cache):
    cfg = smoke_cfg(own_cache, "btf.crop.size=17")
    _assert_failed_cleanly(cfg, ConfigError, "btf.crop.size=17")
    assert _cache_entries(cfg) == []  # refused from the images' size, before decoding them


def test_k_larger_than_texel_count_fails_cleanly(smoke_cfg, own_cache):
    """k against btf.crop.size²: refused before the job's run opens, no stage computed."""
    cfg = smoke_cfg(own_cache, "model.k=145")
    with pytest.raises(ConfigError, match="model.k=145 is larger than the number of texels M=144"):
        run_job(cfg)
    assert _cache_entries(cfg) == []


def test_corrupt_image_fails_cleanly_with_its_path(smoke_cfg, own_cache, tmp_path):
    from pipeline.btf.synthetic_dataset import write_synthetic_btf

    root = write_synthetic_btf(tmp_path / "ds", size=8, seed=0, views=[[0, 0], [15, 0]])
    victim = sorted(root.glob("*/*.jpg"))[5]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 2])
    cfg = smoke_cfg(
        own_cache,
        "dataset=ubo2003",
        f"dataset.root={root}",
        "dataset.views=null",
        "btf.crop.size=8",
    )
    _assert_failed_cleanly(cfg, DataError, victim.name)
    assert _cache_entries(cfg) == []


def test_pca_baseline_runs_through_the_app(smoke_cfg):
    cfg = smoke_cfg("model=pca", "model.n_components=3")
    rmse = run_job(cfg)
    run = _runs(cfg)[0]
    assert run.info.status == "FINISHED" and run.data.params["model.name"] == "pca"
    assert run.data.metrics["rmse"] == pytest.approx(rmse)
    assert rmse < run.data.metrics["rmse_mean_abrdf"]
    m, n = 144, 9 * 81
    assert run.data.metrics["bytes_total"] == 4 * (4 * 3 * n + m * 3)


def test_tables_draw_fig7_from_what_the_runs_logged_without_the_cache(smoke_cfg, own_cache):
    import shutil

    from pipeline.tables import build_tables

    cfg = smoke_cfg(own_cache)
    run_job(cfg)
    run_job(smoke_cfg(own_cache, "model=pca"))  # logs no Fig. 7 data: left out of the figure
    shutil.rmtree(cfg.paths.cache)  # the cache is a memo: the figure comes from the runs
    out = build_tables(cfg.paths.runs)
    pngs = sorted(p.name for p in out.glob("fig7_*.png"))
    assert pngs == ["fig7_synthetic_plain_weave_12__729.png"]
    # One EXR per pair and panel: reference + the one model, two direction pairs; the
    # model's panels are what the job drew and logged.
    exrs = sorted(out.glob("fig7_*.exr"))
    assert len(exrs) == 4
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    run = client.search_runs(
        [client.get_experiment_by_name(cfg.tracking.experiment).experiment_id],
        "params.`model.name` = 'clustered'",
    )[0]
    logged = Path(client.download_artifacts(run.info.run_id, "figures"))
    for exr in exrs:  # the job's file names its dataset without the crop's shape
        (mine,) = logged.glob("fig7_*" + exr.name[exr.name.index("_pair") :])
        tables, job = read_exr(exr), read_exr(mine)
        assert tables.keys() == job.keys()
        for channel in tables:
            np.testing.assert_array_equal(tables[channel], job[channel])


@pytest.mark.parametrize(
    "override, named", [("seed=-1", "seed=-1"), ("method.name=nope", "method.name='nope'")]
)
def test_bad_job_settings_are_refused_naming_the_setting(override, named):
    from helpers import compose_config

    with pytest.raises(ConfigError, match=re.escape(named)):
        run_job(compose_config("experiment=smoke", override))


def test_a_sweep_that_builds_tables_ends_with_a_short_verdict(
    tmp_path, mlflow_template, monkeypatch, capsys
):
    """The demo's last words: each model's RMSE against the mean-ABRDF baseline and its
    bytes, and where the tables are; not the tables themselves (no 'nan', no 'No finished
    ... run found' of the other methods). The parent run's description leads with it."""
    import mlflow
    from helpers import recipe_tags
    from omegaconf import OmegaConf

    import pipeline.tables
    from pipeline.app import print_sweep_result
    from pipeline.core.store import NOTE_TAG, init_store

    mlflow_template(tmp_path)
    experiment_id = init_store(tmp_path, "btf")
    client = MlflowClient(tracking_uri(tmp_path))
    parent = client.create_run(experiment_id, tags={NOTE_TAG: "**Hydra sweep**"}).info.run_id
    for model, k, rmse, total in (
        ("neural_btf", None, 0.031, 171_260),
        ("clustered", 128, 0.0524, 110_844),
        ("pca", None, 0.140, 110_000),
    ):
        params = {
            "method.name": "btf",
            "model.name": model,
            "model.k": k,
            "seed": 0,
            "dataset.name": "synthetic",
            "dataset.synthetic.material": "knit",
            "btf.crop.size": 48,
        }
        with mlflow.start_run(
            experiment_id=experiment_id, tags={"mlflow.parentRunId": parent, **recipe_tags(params)}
        ):
            mlflow.log_params(params)
            mlflow.log_metrics(
                {
                    "rmse": rmse,
                    "rmse_mean_abrdf": 0.1523,
                    "bytes_total": total,
                    "n_directions": 6561,
                    "n_components": 3,
                }
            )
    settings = pipeline.tables.default_settings()
    settings.fig7.enabled = False  # hand-made runs: no cached model to draw
    monkeypatch.setattr(pipeline.tables, "default_settings", lambda: settings)
    config = OmegaConf.create({"paths": {"runs": str(tmp_path)}, "tracking": {"experiment": "btf"}})

    print_sweep_result(config, tracking_uri(tmp_path), parent)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0] == f"Sweep finished: 3 jobs, MLflow experiment 'btf', parent run {parent}"
    assert lines[1] == (
        "synthetic:knit 48²×6561: RMSE (mean-ABRDF baseline 0.1523) and stored bytes"
    )
    assert lines[2:5] == [
        "  Neural BTF  0.0310  = 0.20 x baseline  171,260 B",
        "  k = 128     0.0524  = 0.34 x baseline  110,844 B",
        "  PCA c = 3   0.1400  = 0.92 x baseline  110,000 B  training "
        "failed (not below 0.9 x baseline)",
    ]
    assert lines[5] == (
        f"Tables: {tmp_path / 'tables' / 'summary.html'} (this experiment's: "
        f"{tmp_path / 'tables' / 'btf' / 'summary.html'})"
    )
    assert lines[6].startswith("In `mlflow ui`: http://127.0.0.1:5000/#/experiments/")
    assert lines[6].endswith("/runs?viewStateShareKey=results&workflowType=machine_learning")
    assert len(lines) == 7 and (tmp_path / "tables" / "btf" / "table2_rmse.md").is_file()
    note = client.get_run(parent).data.tags[NOTE_TAG]
    assert note.startswith("**Result**\n\n```\nsynthetic:knit 48²×6561")
    assert note.endswith("**Hydra sweep**")
