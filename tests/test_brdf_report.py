"""Method B's report on hand-made runs: the RMSE table, the prior study and its figure."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from helpers import recipe_tags

from pipeline.brdf_map.report import prior_study_table, sections, study_runs, table_rmse


def _run(kind, cutoff, w_u, missing, noprior, as_, seed=0, method="brdf_map", split=True):
    row = {
        "params.method.name": method,
        "params.dataset.name": "synthetic_brdf",
        "params.dataset.root": "None",
        "params.dataset.synthetic.kind": kind,
        "params.dataset.missing_above_deg": str(cutoff),
        "params.method.prior_strength": str(w_u),
        "params.seed": str(seed),
        "metrics.rmse_measured": 0.01,
        "metrics.rmse_measured_noprior": 0.01,
        "metrics.rmse_measured_as": 0.05,
        "metrics.rmse_missing": missing,
        "metrics.rmse_missing_noprior": noprior,
        "metrics.rmse_missing_as": as_,
        "metrics.n_missing": 1000,
    }
    if split:  # near the mirror: 10 x the whole; off it: half the whole
        for part, factor in (("near_mirror", 10.0), ("off_mirror", 0.5)):
            row[f"metrics.rmse_missing_{part}"] = factor * missing
            row[f"metrics.rmse_missing_{part}_noprior"] = factor * noprior
            row[f"metrics.rmse_missing_{part}_as"] = factor * as_
        row["metrics.n_missing_near_mirror"], row["metrics.n_missing_off_mirror"] = 100, 900
    params = {k[len("params.") :]: v for k, v in row.items() if k.startswith("params.")}
    row["tags.recipe"] = recipe_tags(params)["recipe"]  # as a job logs it
    return row


@pytest.fixture
def runs():
    rows = []
    # separable, cutoff 30: the prior helps (0.20 -> 0.15 at w_u = 0.5), hurts at 2.
    for w_u, value in ((0, 0.20), (0.05, 0.18), (0.5, 0.15), (2, 0.25)):
        rows.append(_run("separable", 30, w_u, value, 0.20, 0.40))
    # beckmann, cutoff 60: two seeds pooled; the prior hurts at every strength.
    for seed, shift in ((0, -0.01), (1, 0.01)):
        for w_u, value in ((0, 0.10), (0.5, 0.11), (2, 0.12)):
            rows.append(_run("beckmann", 60, w_u, value + shift, 0.10 + shift, 0.30, seed))
    rows.append(_run("beckmann", 45, 0.05, 0.3, 0.3, 0.3))  # one w_u only: not in the study
    rows.append(_run("separable", 30, 0.5, 9.0, 9.0, 9.0, method="fourier"))  # not method B
    return pd.DataFrame(rows)


def test_prior_study_table_by_hand(runs):
    table = prior_study_table(runs[runs["params.method.name"] == "brdf_map"])
    assert list(table.index) == [
        ("synthetic_brdf (beckmann)", "60"),
        ("synthetic_brdf (separable)", "30"),
    ]
    assert list(table.columns) == [
        "samples",
        "w_u = 0",
        "w_u = 0.05",
        "w_u = 0.5",
        "w_u = 2",
        "no prior",
        "Ashikhmin-Shirley",
        "best w_u > 0",
        "change vs no prior (%)",
    ]
    separable = table.loc[("synthetic_brdf (separable)", "30")]
    assert separable["w_u = 0.5"] == pytest.approx(0.15)
    assert separable["best w_u > 0"] == 0.5
    assert separable["change vs no prior (%)"] == pytest.approx(-25.0)
    assert separable["Ashikhmin-Shirley"] == pytest.approx(0.40)
    beckmann = table.loc[("synthetic_brdf (beckmann)", "60")]
    assert beckmann["w_u = 2"] == pytest.approx(0.12)  # mean of 0.11 and 0.13
    assert np.isnan(beckmann["w_u = 0.05"])  # not run at that strength
    assert beckmann["change vs no prior (%)"] == pytest.approx(10.0)  # the prior hurts


def test_prior_study_split_uses_the_split_metrics(runs):
    near = prior_study_table(
        runs[runs["params.method.name"] == "brdf_map"], "rmse_missing_near_mirror"
    )
    assert near.loc[("synthetic_brdf (separable)", "30"), "w_u = 0.5"] == pytest.approx(1.5)
    assert near.loc[("synthetic_brdf (separable)", "30"), "no prior"] == pytest.approx(2.0)
    assert near["samples"].tolist() == [100, 100]


def test_prior_study_is_empty_without_a_sweep_over_w_u(runs):
    single = runs[runs["params.method.prior_strength"] == "0.05"]
    assert study_runs(single).empty
    assert prior_study_table(single).empty
    # Runs logged before the split have no near/off-mirror metrics: no split table.
    old = pd.DataFrame([_run("beckmann", 60, w, 0.1, 0.1, 0.3, split=False) for w in (0, 2)])
    assert prior_study_table(old, "rmse_missing_off_mirror").empty
    assert not prior_study_table(old).empty


def test_table_rmse_pools_seeds(runs):
    table = table_rmse(runs[runs["params.method.name"] == "brdf_map"])
    cell = table.loc[("synthetic_brdf (beckmann), missing above 60°", "2"), "MAP, missing"]
    assert cell == "0.1200 ± 0.0141 (n=2)"


def test_table_rmse_never_pools_runs_of_different_recipes(runs):
    b = runs[runs["params.method.name"] == "brdf_map"].copy()
    b["params.method.em_iterations"] = "50"
    other = b[b["params.dataset.missing_above_deg"] == "60"].assign(
        **{"params.method.em_iterations": "5", "metrics.rmse_missing": 0.5, "params.seed": "2"}
    )
    table = table_rmse(pd.concat([b, other], ignore_index=True))
    setup = "synthetic_brdf (beckmann), missing above 60°"
    assert table.loc[(f"{setup} [method.em_iterations=50]", "2"), "MAP, missing"] == (
        "0.1200 ± 0.0141 (n=2)"
    )
    assert table.loc[(f"{setup} [method.em_iterations=5]", "2"), "MAP, missing"] == (
        "0.5000 ± 0.0000 (n=2)"
    )
    # Where every run shares its recipe, the row keeps its plain name.
    assert ("synthetic_brdf (separable), missing above 30°", "0.5") in table.index


def test_sections_write_the_tables_and_the_figure(runs, tmp_path):
    text = "\n".join(sections(runs, tmp_path))
    assert "Method B prior study: RMSE on all missing samples" in text
    assert "near the mirror direction" in text and "off the mirror direction" in text
    assert "![Method B prior study" in text
    for stem in (
        "brdf_map_rmse",
        "brdf_prior_study_rmse_missing",
        "brdf_prior_study_rmse_missing_near_mirror",
    ):
        assert (tmp_path / f"{stem}.md").is_file() and (tmp_path / f"{stem}.csv").is_file()
    assert (tmp_path / "brdf_prior_study.png").stat().st_size > 10_000
    csv = pd.read_csv(tmp_path / "brdf_prior_study_rmse_missing.csv")
    assert csv["BRDF"].tolist() == ["synthetic_brdf (beckmann)", "synthetic_brdf (separable)"]
    assert csv["w_u = 0.5"].tolist() == [0.11, 0.15]
    assert csv["change vs no prior (%)"].tolist() == [10.0, -25.0]


def test_sections_without_brdf_runs(tmp_path):
    text = "\n".join(sections(pd.DataFrame(), tmp_path))
    assert "No finished `method=brdf_map` run" in text
