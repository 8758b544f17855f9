"""The recipe rule: runs pool as seeds only when every setting that can change a number is
equal (pipeline.core.recipe), in every table that reports mean ± std."""

import logging
from fnmatch import fnmatchcase
from pathlib import Path

import mlflow
import pandas as pd
import pytest
from helpers import CONF_DIR, compose_config, recipe_tags

from pipeline.brdf_map import report as brdf_report
from pipeline.btf import tables
from pipeline.btf.render import report as render_report
from pipeline.core.recipe import NOT_RECIPE, left_out, recipe_id, render_recipe_id
from pipeline.core.run import flatten
from pipeline.core.store import init_store

EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))


def _changed(value):
    """Another value of the same kind (a null becomes a value)."""
    if value is None:
        return 1
    if isinstance(value, bool):
        return not value
    if isinstance(value, int | float):
        return value + 1
    if isinstance(value, list):
        return [*value, value[-1] if value else 1]
    return f"{value}_other"


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_setting_changes_the_recipe_or_is_on_the_documented_list(experiment):
    settings = flatten(compose_config(f"experiment={experiment}"))
    recipe, render = recipe_id(settings), render_recipe_id(settings)
    for key, value in settings.items():
        other = {**settings, key: _changed(value)}
        if left_out(key):
            assert recipe_id(other) == recipe, key
        else:
            assert recipe_id(other) != recipe, key
        # The render recipe holds the model's recipe and btf.render.* too.
        assert (render_recipe_id(other) != render) == (not left_out(key, render=True)), key


def test_every_entry_of_the_list_names_settings_that_exist():
    keys = set()
    for experiment in EXPERIMENTS:
        keys |= set(flatten(compose_config(f"experiment={experiment}")))
    for pattern in NOT_RECIPE:
        assert any(left_out(k) and fnmatchcase(k, pattern) for k in keys), pattern


# ----------------------------------------------------------------- never averaged


def _run(
    seed: int,
    value,
    metric: float,
    setting: str = "train.lr",
    render_lights="point",
    method: str = "clustered",
    k=8,
    truth: bool = False,
) -> dict:
    """One row as mlflow.search_runs returns it, with a job's recipe tags."""
    params = {
        "method.name": "btf",
        "model.name": method,
        "model.k": k,
        "seed": seed,
        "dataset.name": "synthetic",
        "dataset.root": None,
        "dataset.synthetic.material": "plain_weave",
        "btf.crop.size": 12,
        "train.epochs": 1,
        "train.precision": "float32",
        "model.texel_scale": "none",
        "model.target": "texel",
        "btf.render.lights": render_lights,
        setting: value,
    }
    row = {f"params.{k}": str(v) for k, v in params.items()}
    row.update({f"tags.{k}": v for k, v in recipe_tags(params).items()})
    row.update(
        {
            "run_id": f"r{seed}{value}{render_lights}",
            "status": "FINISHED",
            "metrics.rmse": metric,
            "metrics.n_directions": 81.0,
            "metrics.rmse_offgrid_model": metric,
            "metrics.rmse_without_texel_scale": metric,
            "metrics.rmse_with_texel_scale": metric,
            "tags.cache.render": f"c{seed}{value}{render_lights}",
            # One reference and one truth render per data and render set-up.
            "tags.cache.render_reference": f"ref-{render_lights}",
            "tags.cache.render_truth": f"truth-{render_lights}",
        }
    )
    for name in (
        "rmse_dark",
        "rmse_bright",
        "rmse_dark_spp4",
        "rmse_bright_spp4",
        "hf_ratio_dark_spp4",
        "hf_ratio_bright_spp4",
        "rmse_cloth_spp4",
    ):
        row[f"metrics.render_{name}"] = metric
        if truth:  # the built-in material: scored against its analytic truth too
            row[f"metrics.render_truth_{name}"] = metric
            row[f"metrics.render_reference_truth_{name}"] = 0.01
    return row


# A null against a value, and two values: never one cell with n = 2.
PAIRS = [(None, 0.5), (0.1, 0.5)]


def _cells(table: pd.DataFrame) -> list[str]:
    return [str(v) for v in table.to_numpy().ravel()]


@pytest.mark.parametrize(("first", "second"), PAIRS)
def test_btf_tables_never_average_two_recipes(first, second):
    runs = tables.label_runs(pd.DataFrame([_run(0, first, 0.1), _run(1, second, 0.2)]))
    assert runs["model"].nunique() == 2
    assert set(runs["model"]) == {f"k = 8 [train.lr={first}]", f"k = 8 [train.lr={second}]"}
    table2 = tables.table_rmse(runs)
    assert sorted(_cells(table2)) == ["0.1000 (n=1)", "0.2000 (n=1)"]
    for cell in _cells(tables.table_interpolation(runs)):
        assert "n=2" not in cell
    for metric in ("rmse_without_texel_scale", "rmse_with_texel_scale"):
        assert not any("n=2" in c for c in _cells(tables.table_rmse(runs, metric)))
    # The k verdict's families differ too: no block mixes the two recipes.
    assert runs["family"].nunique() == 2


@pytest.mark.parametrize("truth", [False, True])
@pytest.mark.parametrize(("first", "second"), PAIRS)
def test_render_tables_never_average_two_recipes(first, second, truth):
    rows = [_run(0, first, 0.1, truth=truth), _run(1, second, 0.2, truth=truth)]
    runs = render_report.scored_runs(
        render_report.rendered_runs(tables.label_runs(pd.DataFrame(rows), render=True))
    )
    assert runs["model"].nunique() >= 2
    for table in (
        render_report.table_crop(runs, "dark"),
        render_report.table_cloth(runs),
        render_report.table_graininess(runs),
    ):
        assert not any("n=2" in c for c in _cells(table)), table


def test_render_tables_never_average_two_render_setups_that_table2_pools():
    rows = [
        _run(0, 0.1, 0.1, render_lights="point"),
        _run(1, 0.1, 0.2, render_lights="directional"),
    ]
    assert tables.label_runs(pd.DataFrame(rows))["model"].nunique() == 1  # one model
    runs = render_report.scored_runs(
        render_report.rendered_runs(tables.label_runs(pd.DataFrame(rows), render=True))
    )
    assert set(runs["model"]) == {
        "k = 8 [btf.render.lights=point]",
        "k = 8 [btf.render.lights=directional]",
    }
    assert not any("n=2" in c for c in _cells(render_report.table_crop(runs, "dark")))


def test_seeds_of_one_recipe_pool():
    runs = tables.label_runs(pd.DataFrame([_run(0, 0.1, 0.1), _run(1, 0.1, 0.2)]))
    assert list(runs["model"].unique()) == ["k = 8"]
    assert _cells(tables.table_rmse(runs)) == ["0.1500 ± 0.0707 (n=2)"]


def test_brdf_table_never_averages_two_recipes():
    rows = []
    for seed, value in ((0, None), (1, 0.5)):
        params = {
            "method.name": "brdf_map",
            "seed": seed,
            "dataset.name": "synthetic_brdf",
            "dataset.root": None,
            "dataset.missing_above_deg": 60,
            "method.prior_strength": 1.0,
            "method.lobes": value,
        }
        row = {f"params.{k}": str(v) for k, v in params.items()}
        row.update({f"tags.{k}": v for k, v in recipe_tags(params).items()})
        row.update(
            {
                f"metrics.rmse_{where}{suffix}": 0.1 + seed
                for where in ("measured", "missing")
                for suffix in ("", "_noprior", "_as")
            }
        )
        rows.append(row)
    table = brdf_report.table_rmse(pd.DataFrame(rows))
    assert len(table) == 2 and not any("n=2" in c for c in _cells(table))


def test_runs_without_a_recipe_tag_are_left_out_with_one_warning(caplog):
    rows = [_run(0, 0.1, 0.1), _run(1, 0.1, 0.2)]
    del rows[1]["tags.recipe"]
    with caplog.at_level(logging.WARNING):
        runs = tables.label_runs(pd.DataFrame(rows))
    assert list(runs["seed"]) == [0]
    assert "1 of 2 runs carry no recipe tag" in caplog.text


# ----------------------------------------------------------------- end to end


def test_the_smoke_run_at_another_learning_rate_is_another_column(smoke_cfg, tmp_path):
    """``seed=0`` and ``seed=1 train.lr=0.5`` in one store: two labelled columns, never one
    cell of n = 2 (each column labelled by the rate it trained at)."""
    from pipeline.app import run_job
    from pipeline.tables import build_tables, default_settings

    run_job(smoke_cfg("seed=0"))
    run_job(smoke_cfg("seed=1", "train.lr=0.5"))
    runs_dir = Path(smoke_cfg().paths.runs)
    table = pd.read_csv(build_tables(runs_dir, default_settings()) / "table2_rmse.csv")
    assert {"k = 8 [train.lr=0.005]", "k = 8 [train.lr=0.5]"} <= set(table.columns)
    assert not any("n=2" in str(c) for c in table.to_numpy().ravel())


def test_a_store_of_untagged_runs_gives_empty_tables_and_says_why(
    tmp_path, mlflow_template, caplog
):
    from pipeline.tables import build_tables, default_settings

    mlflow_template(tmp_path)
    experiment_id = init_store(tmp_path, "btf")
    with mlflow.start_run(experiment_id=experiment_id):
        mlflow.log_params(
            {
                "method.name": "btf",
                "model.name": "clustered",
                "model.k": 8,
                "seed": 0,
                "dataset.name": "synthetic",
            }
        )
        mlflow.log_metrics({"rmse": 0.1})
    with caplog.at_level(logging.WARNING):
        out = build_tables(tmp_path, default_settings())
    assert "carry no recipe tag" in caplog.text
    assert "0.1000" not in (out / "summary.md").read_text()
