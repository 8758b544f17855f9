"""Method B's report: RMSE of the MAP reconstruction against its two baselines, per setup.

A *setup* is one BRDF (the built-in synthetic one with its generator's kind, or a file)
with its missing-angle cutoff and the prior strength w_u; runs of one setup that differ
only in the seed are pooled (mean ± std, n). Columns: the method, the same fit without the
prior (w_u = 0) and Ashikhmin-Shirley least squares, on the measured samples and, where
the truth is known, on the missing ones.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.core.report import param, runs_of, write_table

MODELS = (("MAP", ""), ("no prior", "_noprior"), ("Ashikhmin-Shirley", "_as"))


def _setup(runs: pd.DataFrame) -> pd.Series:
    root = param(runs, "dataset.root").map(lambda r: r.rstrip("/").split("/")[-1])
    name = param(runs, "dataset.name", "?")
    kind = param(runs, "dataset.synthetic.kind", "")
    source = np.where(root != "None", name + ":" + root,
                      np.where(kind != "", name + " (" + kind + ")", name))
    cutoff = param(runs, "dataset.missing_above_deg")
    return pd.Series(source, index=runs.index) + np.where(
        cutoff != "None", ", missing above " + cutoff + "°", ", complete")


def table_rmse(runs: pd.DataFrame) -> pd.DataFrame:
    """Rows (setup, w_u); columns '<model>, measured' and '<model>, missing' as
    'mean ± std (n=…)' over seeds."""
    runs = runs.assign(setup=_setup(runs), w_u=param(runs, "method.prior_strength"))
    rows = {}
    for (setup, w_u), group in runs.groupby(["setup", "w_u"], sort=True):
        row = {}
        for label, suffix in MODELS:
            for where in ("measured", "missing"):
                values = pd.to_numeric(group.get(f"metrics.rmse_{where}{suffix}"),
                                       errors="coerce")
                values = values.dropna() if values is not None else pd.Series(dtype=float)
                if not values.empty:
                    std = f" ± {values.std():.4f}" if len(values) > 1 else ""
                    row[f"{label}, {where}"] = f"{values.mean():.4f}{std} (n={len(values)})"
        rows[(setup, w_u)] = row
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index = pd.MultiIndex.from_tuples(table.index, names=["setup", "w_u"])
    return table


def sections(runs: pd.DataFrame, out: Path, settings=None) -> list[str]:
    """Method B's sections (its runs picked out of ``runs``), tables written into ``out``."""
    runs = runs_of(runs, ["brdf_map"])
    if runs.empty or "metrics.rmse_measured" not in runs:
        return ["## Method B (MAP BRDF)\n\nNo finished `method=brdf_map` run found: "
                "`python -m pipeline experiment=brdf_map`.\n"]
    table = table_rmse(runs[runs["metrics.rmse_measured"].notna()])
    return [write_table(
        table.reset_index(), out, "brdf_map_rmse",
        "Method B: RMSE of the reconstructed BRDF (MAP, without the prior, Ashikhmin-Shirley)",
        "measured: on the samples the fit saw (light and view above the horizon); missing: "
        "on the removed samples against the truth (the synthetic generator's BRDF, or the "
        "removed measured values). n = runs pooled (seeds of one setup and w_u).")]
