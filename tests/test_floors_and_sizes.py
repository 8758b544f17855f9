"""Numbers read from the data: the data-vs-truth floor, the stored types of Table 1, and
the per-texel scale's bytes compared at equal size."""

import mlflow
import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from pipeline.app import run_job
from pipeline.btf import tables
from pipeline.btf.models import MODELS
from pipeline.btf.stages import data_truth_rmse
from pipeline.core.store import tracking_uri


def _runs(cfg):
    client = MlflowClient(tracking_uri(cfg.paths.runs))
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    return client.search_runs([experiment.experiment_id], order_by=["attributes.start_time"])


def test_the_floor_in_chunks_equals_the_floor_at_once():
    rng = np.random.default_rng(0)
    truth = rng.random((6, 10, 3))
    data = truth + rng.normal(0, 0.01, truth.shape)
    directions = rng.random((10, 4))
    column = {tuple(d): i for i, d in enumerate(directions)}

    def truth_of(queries):
        return truth[:, [column[tuple(q)] for q in queries]]

    expected = np.sqrt(np.mean((data - truth) ** 2)) / 0.5
    assert data_truth_rmse(data, directions, truth_of, 0.5, chunk=3) == pytest.approx(expected)
    assert data_truth_rmse(truth, directions, truth_of, 0.5) == 0.0


def test_a_built_in_run_logs_its_floor_lossless_data_below_jpeg(smoke_cfg):
    """The JPEG layout's floor is above the PNG layout's (8-bit rounding only), both > 0
    and both far below the model's error."""
    floors = {}
    for ext in ("jpg", "png"):
        run_job(smoke_cfg(f"dataset.synthetic.ext={ext}", "train.max_steps=-1"))  # trained
        metrics = _runs(smoke_cfg())[-1].data.metrics
        floors[ext] = metrics["rmse_data_vs_truth"]
        assert 0 < floors[ext] < metrics["rmse"]
    # 8-bit rounding alone: at most half a step of 1/255 in the encoded value.
    assert floors["png"] < floors["jpg"]
    assert floors["png"] < 0.5 / 255 * 4  # gamma 2.2's slope is below 4 where values matter


def test_table1_reads_the_stored_types(smoke_cfg):
    run_job(smoke_cfg("btf.sizes.weight_dtype=float16"))
    run_job(smoke_cfg("model=pca"))
    clustered, pca = _runs(smoke_cfg())
    assert clustered.data.tags["stored_as.decoder"] == "float16"
    assert clustered.data.tags["stored_as.latents"] == "float16"
    assert clustered.data.tags["stored_as.list"] == "int32"
    assert pca.data.tags["stored_as.decoder"] == pca.data.params["model.dtype"]


def test_pca_at_a_budget_below_one_component_runs_one_and_says_so(smoke_cfg, caplog):
    """The main job's PCA arm at many directions (a UBO2014 file's 22,801): the bytes of a
    small clustered model hold no component, so it runs the smallest PCA model, one
    component, warns and tags the run; its bytes_total is what it really stores."""
    from pipeline.btf.linear import pca_bytes

    run_job(
        smoke_cfg(
            "dataset.views=null", "model=pca", "model.match_clustered_k=1", "model.dtype=float32"
        )
    )
    run = _runs(smoke_cfg())[-1]
    m, n = int(run.data.metrics["n_texels"]), int(run.data.metrics["n_directions"])
    assert run.data.metrics["n_components"] == 1
    assert run.data.metrics["bytes_total"] == pca_bytes(1, m, n, "float32")
    assert "cannot hold one float32 component" in run.data.tags["over_budget"]
    assert "PCA runs with 1 component, over the budget" in caplog.text
    # The tables label it so (not "bytes of k = 1", a budget it does not meet).
    cfg = smoke_cfg()
    mlflow.set_tracking_uri(tracking_uri(cfg.paths.runs))
    runs = mlflow.search_runs(experiment_names=[cfg.tracking.experiment])
    assert set(tables.label_runs(runs)["model"]) == {"PCA c = 1 (over budget)"}


def test_a_pca_within_its_budget_is_not_labelled_over_it():
    column = MODELS["pca"].column
    assert column({"metrics.n_components": 3.0, "tags.over_budget": float("nan")}) == "PCA c = 3"
    assert column({"metrics.n_components": 3.0}) == "PCA c = 3"


def _row(model: str, k, total: int, rmse: float, seed=0, scaled=None, unscaled=None) -> dict:
    return {
        "dataset": "d",
        "model": model,
        "family": "clustered" if k else "",
        "k": k if k else float("nan"),
        "order": k or 0,
        "params.method.name": "btf",
        "params.model.name": "clustered" if k else "neural_btf",
        "seed": seed,
        "params.btf.sizes.extra_dtype": "float32",
        "metrics.n_texels": 100.0,
        "metrics.bytes_decoder": 1000,
        "metrics.bytes_latents": total - 1000 - 400 * bool(k),
        "metrics.bytes_list": 400 * bool(k),
        "metrics.bytes_extra": 0,
        "metrics.bytes_total": total,
        "metrics.bytes_original": 10**6,
        "metrics.rmse": rmse,
        "metrics.rmse_with_texel_scale": scaled,
        "metrics.rmse_without_texel_scale": unscaled,
        "tags.stored_as.decoder": "float32",
        "tags.stored_as.latents": "float32",
        "tags.stored_as.list": "int32" if k else None,
    }


def test_the_scale_gets_its_bytes_and_is_compared_at_the_nearest_size():
    runs = pd.DataFrame(
        [
            _row("k = 8", 8, 1500, 0.10, scaled=0.08, unscaled=0.10),
            _row("k = 16", 16, 1900, 0.07, scaled=0.06, unscaled=0.07),
            _row("Neural BTF", None, 5000, 0.05),
        ]
    )
    sizes = tables.table_sizes(runs)
    assert list(sizes["model"]) == [
        "Neural BTF",
        "k = 8",
        "k = 8 + per-texel scale",
        "k = 16",
        "k = 16 + per-texel scale",
    ]
    scaled = sizes.set_index("model").loc["k = 8 + per-texel scale"]
    assert scaled["per-texel scale [B]"] == 400 and scaled["total [B]"] == 1900
    assert scaled["stored as"] == (
        "decoder float32, latents float32, list int32, per-texel scale float32"
    )
    grain = tables.table_graininess(runs).set_index("model")
    # k = 8 with its scale (1900 B) against k = 16 without (1900 B): the same bytes.
    assert grain.loc["k = 8", "bytes with scale"] == 1900
    assert grain.loc["k = 8", "nearest in bytes, no scale"] == "k = 16"
    assert grain.loc["k = 8", "its RMSE"] == "0.0700 (n=1)"
    assert grain.loc["k = 16", "nearest in bytes, no scale"] == "k = 8"


def test_table2_shows_the_floor_for_built_in_data_only():
    runs = pd.DataFrame(
        [
            {
                "dataset": "synthetic",
                "model": "k = 8",
                "order": 8,
                "metrics.rmse": 0.1,
                "metrics.rmse_data_vs_truth": 0.0078,
            },
            {
                "dataset": "wool",
                "model": "k = 8",
                "order": 8,
                "metrics.rmse": 0.2,
                "metrics.rmse_data_vs_truth": np.nan,
            },
        ]
    )
    table = tables.with_truth_floor(tables.table_rmse(runs), runs)
    assert list(table.columns) == ["data vs truth", "k = 8"]
    assert table.loc["synthetic", "data vs truth"] == "0.0078"
    assert table.loc["wool", "data vs truth"] == "–"
