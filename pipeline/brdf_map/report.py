"""Method B's report: RMSE of the MAP reconstruction against its two baselines, and the
prior study (when does the Dirichlet prior on u help?).

A *setup* is one BRDF (the built-in synthetic one with its generator's kind, or a file)
with its missing-angle cutoff and the prior strength w_u; runs of one setup that differ
only in the seed are pooled (mean ± std, n). Columns: the method, the same fit without the
prior (w_u = 0) and Ashikhmin-Shirley least squares, on the measured samples and, where
the truth is known, on the missing ones.

The prior study (``experiment=brdf_prior_study``) is every (BRDF, cutoff) fitted at two or
more w_u: the missing-region RMSE across w_u next to both baselines, also split near the
mirror direction (theta_h below ``runner.NEAR_MIRROR_DEG``) and off it, and a figure of the
missing-region RMSE against w_u, one line per cutoff, one panel per BRDF.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.brdf_map.runner import NEAR_MIRROR_DEG
from pipeline.core.recipe import recipe_suffixes, with_recipe
from pipeline.core.report import param, runs_of, save_figure, write_table

MODELS = (("MAP", ""), ("no prior", "_noprior"), ("Ashikhmin-Shirley", "_as"))
# The missing-region RMSE and its split at theta_h = NEAR_MIRROR_DEG (runner.py).
STUDY_METRICS = (
    ("rmse_missing", "all missing samples"),
    ("rmse_missing_off_mirror", "the missing samples off the mirror direction"),
    ("rmse_missing_near_mirror", "the missing samples near the mirror direction"),
)


def _source(runs: pd.DataFrame) -> pd.Series:
    """The BRDF of each run: 'name:file', or 'name (kind)' for the built-in one."""
    root = param(runs, "dataset.root").map(lambda r: r.rstrip("/").split("/")[-1])
    name = param(runs, "dataset.name", "?")
    kind = param(runs, "dataset.synthetic.kind", "")
    source = np.where(
        root != "None", name + ":" + root, np.where(kind != "", name + " (" + kind + ")", name)
    )
    return pd.Series(source, index=runs.index)


def _setup(runs: pd.DataFrame) -> pd.Series:
    cutoff = param(runs, "dataset.missing_above_deg")
    return _source(runs) + np.where(
        cutoff != "None", ", missing above " + cutoff + "°", ", complete"
    )


def _labelled(runs: pd.DataFrame) -> pd.DataFrame:
    """Runs with numeric columns ``cutoff`` (NaN = complete) and ``w_u``, and ``source``:
    the BRDF, with the settings in which its runs differ beyond the study's two axes (a
    study pools seeds of one recipe only)."""
    runs = runs.assign(source=_source(runs))
    axes = ["method.prior_strength", "dataset.missing_above_deg"]
    return runs.assign(
        source=runs["source"] + recipe_suffixes(runs, ["source"], ignore=axes),
        cutoff=pd.to_numeric(param(runs, "dataset.missing_above_deg"), errors="coerce"),
        w_u=pd.to_numeric(param(runs, "method.prior_strength"), errors="coerce"),
    )


def _metric(runs: pd.DataFrame, name: str) -> pd.Series:
    return pd.to_numeric(
        runs.get(f"metrics.{name}", pd.Series(np.nan, index=runs.index)), errors="coerce"
    )


def table_rmse(runs: pd.DataFrame) -> pd.DataFrame:
    """Rows (setup, w_u); columns '<model>, measured' and '<model>, missing' as
    'mean ± std (n=…)' over seeds (runs whose recipes differ are never pooled)."""
    runs = runs.assign(setup=_setup(runs), w_u=param(runs, "method.prior_strength"))
    # Runs are seeds of one fit only when their recipes match: others get their own row,
    # labelled by the settings in which they differ.
    runs = runs.assign(setup=runs["setup"] + recipe_suffixes(runs, ["setup", "w_u"]))
    rows = {}
    for (setup, w_u), group in runs.groupby(["setup", "w_u"], sort=True):
        row = {}
        for label, suffix in MODELS:
            for where in ("measured", "missing"):
                values = pd.to_numeric(group.get(f"metrics.rmse_{where}{suffix}"), errors="coerce")
                values = values.dropna() if values is not None else pd.Series(dtype=float)
                if not values.empty:
                    std = f" ± {values.std():.4f}" if len(values) > 1 else ""
                    row[f"{label}, {where}"] = f"{values.mean():.4f}{std} (n={len(values)})"
        rows[(setup, w_u)] = row
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index = pd.MultiIndex.from_tuples(table.index, names=["setup", "w_u"])
    return table


def study_runs(runs: pd.DataFrame, metric: str = "rmse_missing") -> pd.DataFrame:
    """The runs of the prior study: labelled (:func:`_labelled`), with ``metric`` known,
    of (BRDF, cutoff) pairs fitted at two or more prior strengths."""
    runs = _labelled(runs)
    runs = runs[_metric(runs, metric).notna() & runs["w_u"].notna()]
    keys = ["source", runs["cutoff"].fillna(-1.0)]
    n_strengths = runs.groupby(keys)["w_u"].transform("nunique")
    return runs[n_strengths >= 2]


def _w_label(w_u: float) -> str:
    return f"w_u = {w_u:g}"


def prior_study_table(runs: pd.DataFrame, metric: str = "rmse_missing") -> pd.DataFrame:
    """The missing-region error of the prior study, one row per (BRDF, cutoff).

    Parameters
    ----------
    runs : DataFrame
        Runs as ``mlflow.search_runs`` returns them (``params.*``, ``metrics.*``).
    metric : str
        ``rmse_missing`` or one of its parts (``STUDY_METRICS``); the baselines' columns
        are the same metric with the suffixes ``_noprior`` and ``_as``.

    Returns
    -------
    DataFrame
        Index (BRDF, missing above °); columns the number of samples the metric covers,
        the method at each w_u (mean over seeds), 'no prior', 'Ashikhmin-Shirley', the
        best w_u and its change against no prior in percent (negative = the prior helps).
        Empty when there is no study.
    """
    runs = study_runs(runs, metric)
    if runs.empty:
        return pd.DataFrame()
    counted = "n_missing" + metric[len("rmse_missing") :]  # samples behind the metric
    runs = runs.assign(
        value=_metric(runs, metric),
        noprior=_metric(runs, f"{metric}_noprior"),
        ashikhmin_shirley=_metric(runs, f"{metric}_as"),
        n_samples=_metric(runs, counted),
    )
    rows = {}
    for (source, cutoff), group in runs.groupby(["source", runs["cutoff"].fillna(-1.0)]):
        by_w = group.groupby("w_u")["value"].mean().sort_index()
        row = {"samples": group["n_samples"].max()}
        row.update({_w_label(w): value for w, value in by_w.items()})
        noprior = group["noprior"].mean()
        row["no prior"] = noprior
        row["Ashikhmin-Shirley"] = group["ashikhmin_shirley"].mean()
        best = by_w[by_w.index > 0]
        if not best.empty and noprior > 0:
            row["best w_u > 0"] = best.idxmin()
            row["change vs no prior (%)"] = 100.0 * (best.min() - noprior) / noprior
        label = "complete" if cutoff < 0 else f"{cutoff:g}"
        rows[(source, label)] = row
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index = pd.MultiIndex.from_tuples(table.index, names=["BRDF", "missing above (°)"])
    strengths = sorted(runs["w_u"].unique())
    baselines = ("no prior", "Ashikhmin-Shirley", "best w_u > 0", "change vs no prior (%)")
    return table[["samples", *map(_w_label, strengths), *(c for c in baselines if c in table)]]


def plot_prior_study(runs: pd.DataFrame, path: Path) -> Path:
    """Missing-region RMSE against w_u, one line per cutoff (Ashikhmin-Shirley dashed in
    the same colour), one column of panels per BRDF; further rows off and near the mirror
    direction when that split was logged."""
    from matplotlib.figure import Figure

    runs = study_runs(runs)
    metrics = [m for m, _ in STUDY_METRICS if _metric(runs, m).notna().any()]
    sources = sorted(runs["source"].unique())
    strengths = np.sort(runs["w_u"].unique())
    positive = strengths[strengths > 0]
    fig = Figure(figsize=(4.4 * len(sources), 3.2 * len(metrics)), constrained_layout=True)
    axes = fig.subplots(len(metrics), len(sources), squeeze=False)
    for row, metric in enumerate(metrics):
        for col, source in enumerate(sources):
            ax = axes[row, col]
            group = runs[runs["source"] == source]
            group = group.assign(value=_metric(group, metric), base=_metric(group, f"{metric}_as"))
            for cutoff, lines in group.groupby(group["cutoff"].fillna(-1.0)):
                curve = lines.groupby("w_u")["value"].mean().sort_index()
                label = "complete" if cutoff < 0 else f"missing above {cutoff:g}°"
                (line,) = ax.plot(curve.index, curve.values, marker="o", label=label)
                if lines["base"].notna().any():
                    ax.axhline(lines["base"].mean(), color=line.get_color(), ls="--", lw=0.8)
            ax.plot([], [], color="grey", ls="--", lw=0.8, label="Ashikhmin-Shirley")
            ax.set_xscale("symlog", linthresh=float(positive.min()) if positive.size else 1.0)
            ax.set_xticks(strengths, [f"{w:g}" for w in strengths])
            ax.minorticks_off()
            ax.set_xlabel("prior strength w_u (0 = no prior)")
            ax.set_ylabel("RMSE", fontsize=8)
            ax.set_title(f"{source}: {dict(STUDY_METRICS)[metric]}", fontsize=8)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
    save_figure(fig, path)
    return path


def sections(runs: pd.DataFrame, out: Path, settings=None) -> list[str]:
    """Method B's sections (its runs picked out of ``runs``), tables written into ``out``."""
    out = Path(out)
    runs = runs_of(runs, ["brdf_map"])
    if runs.empty or "metrics.rmse_measured" not in runs:
        return [
            "## Method B (MAP BRDF)\n\nNo finished `method=brdf_map` run found: "
            "`python -m pipeline experiment=brdf_map`.\n"
        ]
    runs = with_recipe(runs[runs["metrics.rmse_measured"].notna()])
    sections = [
        write_table(
            table_rmse(runs).reset_index(),
            out,
            "brdf_map_rmse",
            "Method B: RMSE of the reconstructed BRDF (MAP, without the prior, Ashikhmin-Shirley)",
            "measured: on the samples the fit saw (light and view above the horizon); missing: "
            "on the removed samples against the truth (the synthetic generator's BRDF, or the "
            "removed measured values). n = runs pooled (seeds of one setup and w_u).",
        )
    ]
    for metric, where in STUDY_METRICS:
        table = prior_study_table(runs, metric)
        if table.empty:
            continue
        counts = study_runs(runs, metric).groupby(["source", "cutoff", "w_u"]).size()
        low, high = counts.min(), counts.max()
        pooled = f"{low}" if low == high else f"{low}-{high}"
        extra = ""
        if metric != "rmse_missing":
            extra = (
                f" The split is at θh = {NEAR_MIRROR_DEG:g}° (the half vector's polar angle): "
                "near the mirror direction, the missing samples are the mirror pairs with light "
                "and view both beyond the cutoff: few samples (the 'samples' column) with large "
                "values and errors; their share of the squared error on all missing samples is "
                "samples x RMSE² against the other part's."
            )
        table = table.round(4).astype({"samples": "Int64"})
        if "change vs no prior (%)" in table:
            table["change vs no prior (%)"] = table["change vs no prior (%)"].round(1) + 0.0
        sections.append(
            write_table(
                table.reset_index(),
                out,
                f"brdf_prior_study_{metric}",
                f"Method B prior study: RMSE on {where}",
                "Rows: the BRDF and the light/view polar angle above which its samples are "
                "missing (the UTIA grid measures 0, 15, ..., 75°: 60 removes the 75° rings, "
                "15 leaves 0 and 15° only). Columns: the MAP fit at each prior strength w_u "
                "(w_u = 0 is the no-prior fit, the 'no prior' column computed as the baseline), "
                "then Ashikhmin-Shirley; best w_u > 0 and its change are chosen against the "
                "truth (an oracle, for reading the table, not a tuning rule). "
                f"Runs pooled per cell: {pooled}." + extra,
            )
        )
    if not study_runs(runs).empty:
        plot = plot_prior_study(runs, out / "brdf_prior_study.png")
        sections.append(f"![Method B prior study: missing-region RMSE against w_u]({plot.name})\n")
    return sections
